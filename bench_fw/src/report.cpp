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

void report_status() {
  serial_write('<');
  switch (sys.state) {
    case STATE_IDLE: serial_print_P(PSTR("Idle")); break;
    case STATE_RUN: serial_print_P(PSTR("Run")); break;
    case STATE_HOLD: serial_print_P(stepper_hold_complete() ? PSTR("Hold:0") : PSTR("Hold:1")); break;
    case STATE_HOME: serial_print_P(PSTR("Home")); break;
    case STATE_ALARM: serial_print_P(PSTR("Alarm")); break;
  }
  int32_t pos[N_AXIS];
  stepper_get_position(pos);
  serial_print_P(PSTR("|MPos:"));
  for (uint8_t k = 0; k < N_AXIS; k++) {
    if (k) serial_write(',');
    serial_print_float3(static_cast<float>(pos[k]) / settings.steps_per_unit[k]);
  }
  serial_print_P(PSTR("|FS:"));
  serial_print_uint(static_cast<uint32_t>(parser_state.feed));
  serial_print_P(PSTR(",0"));
  uint8_t lim = limits_read();
  if (lim) {
    serial_print_P(PSTR("|Pn:"));
    for (uint8_t k = 0; k < N_AXIS; k++)
      if (lim & (1 << k)) serial_write(static_cast<uint8_t>(AXIS_LETTERS[k]));
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
  serial_print_P(PSTR("[GC:G"));
  serial_print_uint(parser_state.motion == MOTION_RAPID ? 0 : 1);
  serial_print_P(parser_state.absolute ? PSTR(" G90") : PSTR(" G91"));
  serial_print_P(PSTR(" G21 G94 F"));
  serial_print_uint(static_cast<uint32_t>(parser_state.feed));
  serial_write(']');
  print_nl();
}

void report_help() {
  serial_print_P(PSTR("[HLP:$$ $N=val $H $X $I $G $RST=$ ? ! ~ ctrl-x]\r\n"));
}

void report_info() {
  serial_print_P(PSTR("[VER:1.1h.aimbench-" FW_VERSION ":]\r\n[OPT:H," ));
  serial_print_uint(BLOCK_BUFFER_SIZE - 1);
  serial_write(',');
  serial_print_uint(UART_RX_BUFFER_SIZE);
  serial_print_P(PSTR(",AXES:" AXIS_LETTERS "]\r\n"));
}
