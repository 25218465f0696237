// Homing cycle ($H): for each axis in turn, X then A:
//   1. seek toward the homing end at $25 until the switch reads hit (fail: ALARM:9 after 1.5 x
//      travel);
//   2. after $26 ms, creep back at $24 until it reads released (fail: ALARM:8 after 5 x $27);
//   3. pull off $27 at $25 and call that position 0.
// Hard limits are ignored meanwhile (the switches are driven into on purpose).
#include "codes.h"
#include "config.h"
#include "planner.h"
#include "settings.h"
#include "stepper.h"
#include "system.h"

// Runs one single-axis block; returns 1 if it ended on its switch condition, 0 if it ran out
// of distance, -1 if a reset or an alarm ended it.
static int8_t run_block(uint8_t axis, float distance, float rate, BlockMode mode) {
  Settings s = settings;
  s.soft_limits = 0;  // homing starts from an unknown position
  int32_t from[N_AXIS];
  stepper_get_position(from);
  int32_t target[N_AXIS];
  for (uint8_t k = 0; k < N_AXIS; k++) target[k] = from[k];
  target[axis] += units_to_steps(s, axis, distance);
  Block b;
  bool zero;
  if (plan_move(s, from, target, rate, b, &zero) != STATUS_OK || zero) return 0;
  b.mode = mode;
  b.homing_axis = axis;
  block_queue.push(b);
  stepper_wake();
  if (!wait_motion_done()) return -1;
  return (mode != BLOCK_NORMAL && stepper_stopped_by_switch()) ? 1 : 0;
}

static Status fail(uint8_t alarm) {
  stepper_set_homing(false);
  system_alarm(alarm);
  return STATUS_SYSTEM_GC_LOCK;
}

Status homing_cycle() {
  sys.state = STATE_HOME;
  stepper_set_homing(true);
  for (uint8_t axis = 0; axis < N_AXIS; axis++) {
    float toward = (settings.homing_dir_mask & (1 << axis)) ? -1.0f : 1.0f;
    float pulloff = settings.homing_pulloff;
    float locate = 5.0f * pulloff;
    if (locate < 1.0f) locate = 1.0f;
    int8_t r = run_block(axis, toward * 1.5f * settings.max_travel[axis], settings.homing_seek,
                         BLOCK_STOP_ON_TRIGGER);
    if (r < 0) return STATUS_SYSTEM_GC_LOCK;
    if (r == 0) return fail(ALARM_HOMING_FAIL_APPROACH);
    if (!wait_ms(settings.homing_debounce_ms)) return STATUS_SYSTEM_GC_LOCK;
    r = run_block(axis, -toward * locate, settings.homing_feed, BLOCK_STOP_ON_RELEASE);
    if (r < 0) return STATUS_SYSTEM_GC_LOCK;
    if (r == 0) return fail(ALARM_HOMING_FAIL_PULLOFF);
    if (!wait_ms(settings.homing_debounce_ms)) return STATUS_SYSTEM_GC_LOCK;
    if (run_block(axis, -toward * pulloff, settings.homing_seek, BLOCK_NORMAL) < 0)
      return STATUS_SYSTEM_GC_LOCK;
    stepper_set_position(axis, 0);
  }
  stepper_set_homing(false);
  sys.state = STATE_IDLE;
  sys.alarm = 0;
  return STATUS_OK;
}
