// Machine state shared by the protocol loop, the reports and homing; system.cpp defines the
// state and the waits, report.cpp the reports, homing.cpp the homing cycle.
#ifndef BENCH_SYSTEM_H
#define BENCH_SYSTEM_H

#include <stdint.h>
#include "codes.h"

enum MachineState : uint8_t {
  STATE_IDLE = 0,
  STATE_RUN,
  STATE_HOLD,    // reported Hold:1 while decelerating, Hold:0 at rest
  STATE_HOME,
  STATE_ALARM,
  STATE_JOG,     // a $J= jog is moving
  STATE_CHECK,   // $C check mode: lines are checked, nothing moves
};

struct System {
  MachineState state;
  bool abort;       // Ctrl-X seen: unwind every wait and re-initialise
  uint8_t alarm;    // the alarm that put us in STATE_ALARM (0 = "homing required" at power-up)
  bool jog_cancel;  // a jog is decelerating to be dropped (0x85, or a feed hold while jogging)
  bool reset_after_reply;  // soft-reset once this line's reply is out ($C leaving check mode)
};

extern System sys;

// Acts on realtime requests and events: status report, hold, resume, reset, alarms raised by the
// step interrupt, end of motion. Called from the main loop and from every wait.
void protocol_execute_realtime();
// Reports.
void report_status();
void report_alarm(uint8_t code);
void report_status_code(Status s);
void report_settings();
void report_parser_state();
void report_help();
void report_info();
void report_ngc_parameters();
void report_startup_lines();
void report_message(const char *progmem_text);
void report_banner();
void report_unlock_message();
// Raises an alarm from the main loop: stops motion, prints ALARM:N, locks G-code.
void system_alarm(uint8_t code);
// Homing cycle ($H). Returns STATUS_OK, or STATUS_SYSTEM_GC_LOCK if an alarm/reset ended it.
Status homing_cycle();
// Waits (running realtime) until all queued motion has finished. False if aborted.
bool wait_motion_done();
// Waits `ms` milliseconds running realtime. False if aborted.
bool wait_ms(uint32_t ms);
// Sleeps until the next interrupt when no byte or realtime request is waiting.
void idle_sleep();

#endif
