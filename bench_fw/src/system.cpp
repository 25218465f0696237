// The machine state and the waits that run realtime: shared by the protocol loop (main.cpp) and
// homing (homing.cpp), so that neither calls into the other.
#include <Arduino.h>
#include <avr/sleep.h>

#include "codes.h"
#include "config.h"
#include "serial.h"
#include "settings.h"
#include "stepper.h"
#include "system.h"

System sys;
static uint32_t idle_since_ms = 0;
static bool idle_timing = false;

void system_alarm(uint8_t code) {
  stepper_abort();
  sys.state = STATE_ALARM;
  sys.alarm = code;
  report_alarm(code);
  report_unlock_message();
}

void protocol_execute_realtime() {
  uint8_t sreg = SREG;
  cli();
  uint8_t rt = rt_exec;
  rt_exec = static_cast<uint8_t>(rt & (EXEC_RESET | EXEC_RESET_IN_MOTION));  // reset is the loop's
  SREG = sreg;
  if (rt & EXEC_RESET) {
    sys.abort = true;
    return;
  }
  uint8_t alarm = stepper_take_alarm();
  if (alarm) system_alarm(alarm);
  if ((rt & EXEC_FEED_HOLD) && sys.state == STATE_RUN) {
    stepper_hold();
    sys.state = STATE_HOLD;
  }
  // Like Grbl: a jog cancel, or a feed hold while jogging, decelerates to a stop and drops the
  // rest of the jogs; the position is kept (the motors never lost a step).
  if ((rt & (EXEC_JOG_CANCEL | EXEC_FEED_HOLD)) && sys.state == STATE_JOG && !sys.jog_cancel) {
    stepper_hold();
    sys.jog_cancel = true;
  }
  if (sys.jog_cancel && (stepper_hold_complete() || !stepper_running())) {
    stepper_abort();
    sys.jog_cancel = false;
    sys.state = STATE_IDLE;
  }
  if ((rt & EXEC_CYCLE_START) && sys.state == STATE_HOLD) {
    stepper_resume();
    sys.state = STATE_RUN;
  }
  if ((sys.state == STATE_RUN || sys.state == STATE_JOG) && !stepper_busy()) {
    sys.state = STATE_IDLE;
    sys.jog_cancel = false;
  }
  if (rt & EXEC_STATUS_REPORT) report_status();

  // $1: release the drivers after the steppers have been idle this long (255 = never).
  if (stepper_busy()) {
    idle_timing = false;
  } else if (!idle_timing) {
    idle_timing = true;
    idle_since_ms = millis();
  } else if (settings.idle_delay_ms != 255 && millis() - idle_since_ms >= settings.idle_delay_ms) {
    stepper_enable(false);
  }
}

// Idle sleep until the next interrupt (a received byte, a step, the 1 kHz tick, millis()), when
// nothing is waiting in the receive buffer or the realtime flags. Timers and the UART keep
// running in idle mode, so nothing is delayed by more than an interrupt's latency. On the board
// it saves a little power; in simavr it lets the simulator skip the idle cycles instead of
// interpreting a busy loop, which keeps the simulation in real time on a loaded host.
void idle_sleep() {
  cli();
  if (rt_exec == 0 && !serial_available()) {
    set_sleep_mode(SLEEP_MODE_IDLE);
    sleep_enable();
    sei();  // the instruction after sei runs before any interrupt: no wake-up is lost
    sleep_cpu();
    sleep_disable();
  } else {
    sei();
  }
}

bool wait_motion_done() {
  while (stepper_busy()) {
    protocol_execute_realtime();
    if (sys.abort || sys.state == STATE_ALARM) return false;
    idle_sleep();
  }
  protocol_execute_realtime();
  return !sys.abort;
}

bool wait_ms(uint32_t ms) {
  uint32_t start = millis();
  while (millis() - start < ms) {
    protocol_execute_realtime();
    if (sys.abort || sys.state == STATE_ALARM) return false;
    idle_sleep();
  }
  return true;
}
