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

// Where the next move starts: the last queued target, or the machine position when nothing is
// queued (check mode keeps its own, the parser's, position).
static void sync_planned_position() {
  if (sys.state != STATE_CHECK && !stepper_busy()) stepper_get_position(planned);
}

// The target of a move or jog in steps: each axis word turned into steps exactly (integer
// arithmetic on the number as written), absolute or added to where the last queued block ends.
static Status target_steps(const Command &cmd, int32_t target[N_AXIS]) {
  for (uint8_t k = 0; k < N_AXIS; k++) {
    target[k] = planned[k];
    if (!cmd.has_axis[k]) continue;
    int32_t v;
    if (!decimal_to_steps(settings, k, cmd.axis_dec[k], &v)) return STATUS_BAD_NUMBER_FORMAT;
    target[k] = cmd.absolute ? v : planned[k] + v;
  }
  return STATUS_OK;
}

static Status execute_move(const Command &cmd, bool jog) {
  sync_planned_position();
  int32_t target[N_AXIS];
  Status s = target_steps(cmd, target);
  if (s != STATUS_OK) return s;
  Block b;
  bool zero_length;
  s = plan_move(settings, planned, target, cmd.feed, b, &zero_length);
  if (s != STATUS_OK || zero_length) return s;
  if (sys.state == STATE_CHECK) {  // checked, and followed in the parser only: nothing moves
    for (uint8_t k = 0; k < N_AXIS; k++) planned[k] = target[k];
    return STATUS_OK;
  }
  // Queue full: hold this line's reply until the stepper frees a slot (the host's flow control).
  while (block_queue.full()) {
    protocol_execute_realtime();
    if (sys.abort || sys.state == STATE_ALARM) return STATUS_SYSTEM_GC_LOCK;
    idle_sleep();
  }
  sync_planned_position();  // a cancelled jog dropped the queue: start from where it stopped
  uint8_t sreg = SREG;
  cli();
  if (rt_exec & EXEC_RESET) {  // a Ctrl-X arrived: queue nothing, start nothing
    SREG = sreg;
    return STATUS_SYSTEM_GC_LOCK;
  }
  block_queue.push(b);
  SREG = sreg;
  for (uint8_t k = 0; k < N_AXIS; k++) planned[k] = target[k];
  if (sys.state == STATE_IDLE) sys.state = jog ? STATE_JOG : STATE_RUN;
  stepper_wake();
  return STATUS_OK;
}

static bool machine_busy() {
  return sys.state == STATE_RUN || sys.state == STATE_HOLD || sys.state == STATE_HOME ||
         sys.state == STATE_JOG;
}

// Grbl's rule for the '$' commands that need the machine at rest: Idle or Alarm only.
static bool idle_or_alarm() { return sys.state == STATE_IDLE || sys.state == STATE_ALARM; }

// G-code lines are locked in Alarm (home or unlock first) and while a jog moves, as in Grbl.
static bool gcode_locked() { return sys.state == STATE_ALARM || sys.state == STATE_JOG; }

static Status toggle_check_mode() {
  if (sys.state == STATE_CHECK) {
    // Like Grbl: leaving check mode resets, so the parser's position is the machine's again.
    report_message(PSTR("Disabled"));
    sys.reset_after_reply = true;
    return STATUS_OK;
  }
  if (sys.state != STATE_IDLE) return STATUS_IDLE_ERROR;
  sys.state = STATE_CHECK;
  report_message(PSTR("Enabled"));
  return STATUS_OK;
}

static Status execute_line(const char *line) {
  if (line[0] == 0) return STATUS_OK;  // empty line: Grbl answers ok (used to sync)
  Command cmd;
  Status s = parse_line(line, parser_state, cmd);
  if (s != STATUS_OK) return s;
  switch (cmd.kind) {
    case CMD_EMPTY:
      if (gcode_locked()) return STATUS_SYSTEM_GC_LOCK;
      break;
    case CMD_MOVE:
      if (gcode_locked()) return STATUS_SYSTEM_GC_LOCK;
      s = execute_move(cmd, false);
      if (s != STATUS_OK) return s;
      break;
    case CMD_JOG:
      if (sys.state != STATE_IDLE && sys.state != STATE_JOG) return STATUS_IDLE_ERROR;
      return execute_move(cmd, true);  // a jog keeps the modal state as it was
    case CMD_DWELL:
      if (gcode_locked()) return STATUS_SYSTEM_GC_LOCK;
      if (sys.state == STATE_CHECK) break;  // check mode does not wait
      // G4 waits for the moves before it, then dwells (its ok means "done", like Grbl's).
      if (!wait_motion_done() || !wait_ms(static_cast<uint32_t>(cmd.dwell_s * 1000.0f + 0.5f)))
        return STATUS_SYSTEM_GC_LOCK;
      break;
    case CMD_SYS_HELP: report_help(); return STATUS_OK;
    case CMD_SYS_STATE: report_parser_state(); return STATUS_OK;
    case CMD_SYS_CHECK: return toggle_check_mode();
    case CMD_SYS_INFO:
      if (!idle_or_alarm()) return STATUS_IDLE_ERROR;
      report_info();
      return STATUS_OK;
    case CMD_SYS_PARAMS:
      if (!idle_or_alarm()) return STATUS_IDLE_ERROR;
      report_ngc_parameters();
      return STATUS_OK;
    case CMD_SYS_STARTUP:
      if (!idle_or_alarm()) return STATUS_IDLE_ERROR;
      report_startup_lines();
      return STATUS_OK;
    case CMD_SYS_SETTINGS:
      if (machine_busy()) return STATUS_IDLE_ERROR;
      report_settings();
      return STATUS_OK;
    case CMD_SYS_SET:
      if (!idle_or_alarm()) return STATUS_IDLE_ERROR;
      s = settings_set(settings, cmd.setting, cmd.value);
      stepper_apply_settings();
      return s;
    case CMD_SYS_RESTORE:
      if (!idle_or_alarm()) return STATUS_IDLE_ERROR;
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
      if (!idle_or_alarm()) return STATUS_IDLE_ERROR;
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
  sys.jog_cancel = false;
  sys.reset_after_reply = false;
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
  sys.jog_cancel = false;
  sys.reset_after_reply = false;
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
    if (sys.reset_after_reply) sys.abort = true;
  }
}
