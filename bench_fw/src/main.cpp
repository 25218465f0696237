// The stage controller's main program: the protocol loop on the Arduino core (setup/loop).
//
// Modules: system (machine state, realtime execution, waits), serial (UART0 + realtime bytes),
// protocol (line collection and parsing), planner (trapezoid blocks and the queue), stepper
// (Timer1 step ISR, Timer3 acceleration tick, limit inputs), settings (EEPROM), homing, report.
// PROTOCOL.md documents the wire protocol.
#include <Arduino.h>
#include <avr/pgmspace.h>

#include "codes.h"
#include "config.h"
#include "planner.h"
#include "protocol.h"
#include "serial.h"
#include "settings.h"
#include "stepper.h"
#include "system.h"

ParserState parser_state;
static LineCollector collector;
static int32_t planned[N_AXIS];  // steps: where the last queued block ends

static void sync_planned_position() {
  if (!stepper_busy()) stepper_get_position(planned);
}

static Status execute_move(const Command &cmd) {
  sync_planned_position();
  float target[N_AXIS];
  for (uint8_t k = 0; k < N_AXIS; k++) {
    float here = static_cast<float>(planned[k]) / settings.steps_per_unit[k];
    if (!cmd.has_axis[k]) target[k] = here;
    else target[k] = cmd.absolute ? cmd.axis[k] : here + cmd.axis[k];
  }
  Block b;
  bool zero_length;
  Status s = plan_move(settings, planned, target, cmd.feed, b, &zero_length);
  if (s != STATUS_OK || zero_length) return s;
  // Queue full: hold this line's reply until the stepper frees a slot (the host's flow control).
  while (block_queue.full()) {
    protocol_execute_realtime();
    if (sys.abort || sys.state == STATE_ALARM) return STATUS_SYSTEM_GC_LOCK;
    idle_sleep();
  }
  uint8_t sreg = SREG;
  cli();
  if (rt_exec & EXEC_RESET) {  // a Ctrl-X arrived: queue nothing, start nothing
    SREG = sreg;
    return STATUS_SYSTEM_GC_LOCK;
  }
  block_queue.push(b);
  SREG = sreg;
  for (uint8_t k = 0; k < N_AXIS; k++) planned[k] = units_to_steps(settings, k, target[k]);
  if (sys.state == STATE_IDLE) sys.state = STATE_RUN;
  stepper_wake();
  return STATUS_OK;
}

static bool machine_busy() {
  return sys.state == STATE_RUN || sys.state == STATE_HOLD || sys.state == STATE_HOME;
}

static Status execute_line(const char *line) {
  if (line[0] == 0) return STATUS_OK;  // empty line: Grbl answers ok (used to sync)
  Command cmd;
  Status s = parse_line(line, parser_state, cmd);
  if (s != STATUS_OK) return s;
  switch (cmd.kind) {
    case CMD_EMPTY:
      if (sys.state == STATE_ALARM) return STATUS_SYSTEM_GC_LOCK;
      break;
    case CMD_MOVE:
      if (sys.state == STATE_ALARM) return STATUS_SYSTEM_GC_LOCK;
      s = execute_move(cmd);
      if (s != STATUS_OK) return s;
      break;
    case CMD_DWELL:
      if (sys.state == STATE_ALARM) return STATUS_SYSTEM_GC_LOCK;
      // G4 waits for the moves before it, then dwells (its ok means "done", like Grbl's).
      if (!wait_motion_done() || !wait_ms(static_cast<uint32_t>(cmd.dwell_s * 1000.0f + 0.5f)))
        return STATUS_SYSTEM_GC_LOCK;
      break;
    case CMD_SYS_HELP: report_help(); return STATUS_OK;
    case CMD_SYS_INFO: report_info(); return STATUS_OK;
    case CMD_SYS_STATE: report_parser_state(); return STATUS_OK;
    case CMD_SYS_SETTINGS:
      if (machine_busy()) return STATUS_IDLE_ERROR;
      report_settings();
      return STATUS_OK;
    case CMD_SYS_SET:
      if (machine_busy()) return STATUS_IDLE_ERROR;
      s = settings_set(settings, cmd.setting, cmd.value);
      stepper_apply_settings();
      return s;
    case CMD_SYS_RESTORE:
      if (machine_busy()) return STATUS_IDLE_ERROR;
      settings_defaults(settings);
      settings_save(settings);
      stepper_apply_settings();
      return STATUS_OK;
    case CMD_SYS_UNLOCK:
      if (machine_busy()) return STATUS_IDLE_ERROR;
      if (sys.state == STATE_ALARM) {
        sys.state = STATE_IDLE;
        sys.alarm = 0;
        serial_print_P(PSTR("[MSG:Caution: Unlocked]\r\n"));
      }
      return STATUS_OK;
    case CMD_SYS_HOME:
      if (!settings.homing_enable) return STATUS_SETTING_DISABLED;
      if (machine_busy()) return STATUS_IDLE_ERROR;
      return homing_cycle();
  }
  parser_state = cmd.next;  // the line was carried out: keep its modal state
  return STATUS_OK;
}

static void soft_reset() {
  uint8_t sreg = SREG;
  cli();
  bool in_motion = (rt_exec & EXEC_RESET_IN_MOTION) != 0;
  rt_exec = 0;
  SREG = sreg;
  in_motion |= stepper_abort();
  stepper_set_homing(false);
  serial_reset_rx();
  collector.reset();
  parser_state_reset(parser_state);
  uint8_t alarm = 0;
  if (sys.state == STATE_HOME) alarm = ALARM_HOMING_FAIL_RESET;
  else if (in_motion) alarm = ALARM_ABORT_CYCLE;
  if (alarm) {
    report_alarm(alarm);
    sys.state = STATE_ALARM;
    sys.alarm = alarm;
  } else if (sys.state != STATE_ALARM) {
    sys.state = STATE_IDLE;
  }
  sys.abort = false;
  report_banner();
  if (sys.state == STATE_ALARM) report_unlock_message();
}

void setup() {
  serial_init();
  bool valid = settings_load(settings);
  stepper_init();
  parser_state_reset(parser_state);
  sys.abort = false;
  sys.alarm = 0;
  // Like Grbl: with homing enabled the position is unknown at power-up, so G-code is locked
  // until $H (or $X).
  sys.state = settings.homing_enable ? STATE_ALARM : STATE_IDLE;
  report_banner();
  if (!valid) serial_print_P(PSTR("[MSG:EEPROM settings invalid: defaults restored]\r\n"));
  if (sys.state == STATE_ALARM) report_unlock_message();
}

void loop() {
  protocol_execute_realtime();
  if (sys.abort) {
    soft_reset();
    return;
  }
  uint16_t c = serial_read();
  if (c == SERIAL_NO_DATA) {
    idle_sleep();
    return;
  }
  if (c == SERIAL_DAMAGE_MARK) {
    collector.mark_overflow();
    return;
  }
  LineEvent ev = collector.feed(static_cast<char>(c));
  if (ev == LINE_OVERFLOW) {
    report_status_code(STATUS_OVERFLOW);
  } else if (ev == LINE_READY) {
    Status s = execute_line(collector.line());
    if (!sys.abort) report_status_code(s);  // a reset abandons the line: the banner says so
  }
}
