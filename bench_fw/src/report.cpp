// Everything the firmware prints. Constant text lives in flash (PSTR) to spare the 8 KB of RAM.
#include <avr/pgmspace.h>

#include "config.h"
#include "planner.h"
#include "protocol.h"
#include "serial.h"
#include "settings.h"
#include "stepper.h"
#include "system.h"

extern ParserState parser_state;

static void print_nl() { serial_print_P(PSTR("\r\n")); }

void report_status_code(Status s) {
  if (s == STATUS_OK) {
    serial_print_P(PSTR("ok\r\n"));
  } else {
    serial_print_P(PSTR("error:"));
    serial_print_uint(s);
    print_nl();
  }
}

void report_alarm(uint8_t code) {
  serial_print_P(PSTR("ALARM:"));
  serial_print_uint(code);
  print_nl();
}

void report_banner() {
  print_nl();
  serial_print_P(PSTR(FW_BANNER));
  print_nl();
}

void report_unlock_message() { serial_print_P(PSTR("[MSG:'$H'|'$X' to unlock]\r\n")); }

// The three report slots X, Y, Z: the linear stage in X, the rotary stage in Y, Z unused (0).
static void print_slots(const int32_t milli[N_AXIS]) {
  serial_print_milli(milli[AXIS_X]);
  serial_write(',');
  serial_print_milli(milli[AXIS_A]);
  serial_print_P(PSTR(",0.000"));
}

static void print_zero_slots() { serial_print_P(PSTR("0.000,0.000,0.000")); }

void report_status() {
  serial_write('<');
  switch (sys.state) {
    case STATE_IDLE: serial_print_P(PSTR("Idle")); break;
    case STATE_RUN: serial_print_P(PSTR("Run")); break;
    case STATE_HOLD: serial_print_P(stepper_hold_complete() ? PSTR("Hold:0") : PSTR("Hold:1")); break;
    case STATE_HOME: serial_print_P(PSTR("Home")); break;
    case STATE_ALARM: serial_print_P(PSTR("Alarm")); break;
    case STATE_JOG: serial_print_P(PSTR("Jog")); break;
    case STATE_CHECK: serial_print_P(PSTR("Check")); break;
  }
  int32_t pos[N_AXIS], milli[N_AXIS];
  stepper_get_position(pos);
  for (uint8_t k = 0; k < N_AXIS; k++) milli[k] = steps_to_milli(settings, k, pos[k]);
  serial_print_P(PSTR("|MPos:"));
  print_slots(milli);
  serial_print_P(PSTR("|FS:"));
  serial_print_uint(static_cast<uint32_t>(parser_state.feed));
  serial_print_P(PSTR(",0"));
  uint8_t lim = limits_read();
  if (lim) {
    serial_print_P(PSTR("|Pn:"));  // by report slot, as Grbl names its limit pins
    if (lim & (1 << AXIS_X)) serial_write('X');
    if (lim & (1 << AXIS_A)) serial_write(AXIS_A_SLOT_LETTER);
  }
  serial_write('>');
  print_nl();
}

void report_settings() {
  const uint16_t *numbers;
  uint8_t count = settings_numbers(numbers);
  for (uint8_t i = 0; i < count; i++) {
    float v;
    settings_get(settings, numbers[i], v);
    serial_write('$');
    serial_print_uint(numbers[i]);
    serial_write('=');
    if (settings_is_integer(numbers[i])) serial_print_uint(static_cast<uint32_t>(v));
    else serial_print_float3(v);
    print_nl();
  }
}

void report_parser_state() {
  // Grbl 1.1's full list of modal groups, so senders that parse it find every field; the ones
  // this firmware has no choice in are fixed (G54 G17 G21 G94 M5 M9 T0 S0).
  serial_print_P(PSTR("[GC:G"));
  serial_print_uint(parser_state.motion == MOTION_RAPID ? 0 : 1);
  serial_print_P(PSTR(" G54 G17 G21"));
  serial_print_P(parser_state.absolute ? PSTR(" G90") : PSTR(" G91"));
  serial_print_P(PSTR(" G94 M5 M9 T0 F"));
  serial_print_uint(static_cast<uint32_t>(parser_state.feed));
  serial_print_P(PSTR(" S0]"));
  print_nl();
}

void report_ngc_parameters() {
  // No work coordinate systems, offsets, tool lengths or probe here: all zero, as on a fresh
  // Grbl, so work positions equal machine positions.
  static const char kNames[] PROGMEM = "54\0" "55\0" "56\0" "57\0" "58\0" "59\0" "28\0" "30\0" "92";
  for (uint8_t i = 0; i < 9; i++) {
    serial_print_P(PSTR("[G"));
    serial_print_P(kNames + 3 * i);
    serial_write(':');
    print_zero_slots();
    serial_write(']');
    print_nl();
  }
  serial_print_P(PSTR("[TLO:0.000]\r\n[PRB:"));
  print_zero_slots();
  serial_print_P(PSTR(":0]\r\n"));
}

void report_startup_lines() {
  // Grbl's two startup lines, both empty: storing one ($N0=...) is not supported (error:3).
  serial_print_P(PSTR("$N0=\r\n$N1=\r\n"));
}

void report_message(const char *text) {
  serial_print_P(PSTR("[MSG:"));
  serial_print_P(text);
  serial_write(']');
  print_nl();
}

void report_help() {
  serial_print_P(PSTR("[HLP:$$ $# $G $I $N $x=val $J=line $C $X $H $RST=$ ~ ! ? ctrl-x]\r\n"));
}

void report_info() {
  // [OPT:] in Grbl's form (option letters: none of Grbl's apply; planner blocks; RX buffer),
  // then the axes: [AXS:count:letters], the linear X and the rotary A (reported in slot Y).
  serial_print_P(PSTR("[VER:1.1h.aimbench-" FW_VERSION ":]\r\n[OPT:,"));
  serial_print_uint(BLOCK_BUFFER_SIZE - 1);
  serial_write(',');
  serial_print_uint(UART_RX_BUFFER_SIZE);
  serial_print_P(PSTR("]\r\n[AXS:2:" AXIS_LETTERS "]\r\n"));
}
