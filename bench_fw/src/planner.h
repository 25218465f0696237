// The planner: turns a target in machine units into a block of steps with a trapezoidal speed
// profile, and queues blocks for the stepper. Pure C++, unit-tested on the host.
//
// Every block starts and ends at rest (no look-ahead between blocks): the bench makes
// point-to-point moves and must stand still at each measurement position anyway.
#ifndef BENCH_PLANNER_H
#define BENCH_PLANNER_H

#include <stdint.h>
#include "codes.h"
#include "config.h"
#include "protocol.h"
#include "settings.h"

// Homing blocks stop on a limit input instead of running to the end.
enum BlockMode : uint8_t {
  BLOCK_NORMAL = 0,
  BLOCK_STOP_ON_TRIGGER,   // homing seek: stop at the step that makes the axis' switch read hit
  BLOCK_STOP_ON_RELEASE,   // homing locate: stop at the step that makes it read released
};

struct Block {
  uint32_t steps[N_AXIS];      // step count per axis (absolute value)
  uint8_t dir_negative_mask;   // bit per axis: moves toward negative
  uint32_t step_event_count;   // max(steps): the dominant axis steps at every event
  float nominal_rate;          // steps/s of the dominant axis at cruise
  float accel;                 // steps/s^2 of the dominant axis
  float start_rate;            // steps/s at the first and last step
  BlockMode mode;
  uint8_t homing_axis;         // for the homing modes
};

// Plans a move from `from` to `target` (both in steps). feed_units_per_min == 0 means rapid (G0):
// each axis' max rate. The speed and acceleration along the path are the largest that keep every
// axis within its own $11x and $12x. Returns STATUS_TRAVEL_EXCEEDED if soft limits are on and the
// target lies outside the travel (then `out` is untouched: no move).
// *zero_length is set when the target is the current position (nothing to queue).
Status plan_move(const Settings &s, const int32_t from[N_AXIS], const int32_t target[N_AXIS],
                 float feed_units_per_min, Block &out, bool *zero_length);

// The travel of an axis in steps: [0, $13x] when it homes toward min, [-$13x, 0] otherwise.
void travel_range(const Settings &s, uint8_t axis, int32_t *lo, int32_t *hi);
bool within_travel(const Settings &s, const int32_t target[N_AXIS]);

// A number as written (mantissa x 10^exponent) in steps of `axis`, computed in integers: the
// nearest step, half a step away from zero. False if it lies beyond +-2^30 steps.
bool decimal_to_steps(const Settings &s, uint8_t axis, const Decimal &units, int32_t *steps);
// The same from a float (homing distances, tests): lroundf(units x steps/unit).
int32_t units_to_steps(const Settings &s, uint8_t axis, float units);
// A position in thousandths of a unit, for reports: round(steps / steps-per-unit x 1000), in
// integers (half away from zero), so MPos shows each step exactly as far as 3 decimals can.
int32_t steps_to_milli(const Settings &s, uint8_t axis, int32_t steps);

// Time (s) of a trapezoidal profile over `distance` at `rate` and `accel`, starting and ending at
// rest: the reference the benchmark and the tests compare the real moves against.
float trapezoid_time(float distance, float rate, float accel);

// A fixed ring of blocks between the protocol (producer) and the stepper ISR (consumer).
class BlockQueue {
 public:
  BlockQueue() { clear(); }
  void clear() { head_ = tail_ = 0; }
  bool empty() const { return head_ == tail_; }
  bool full() const { return next(head_) == tail_; }
  uint8_t count() const { return static_cast<uint8_t>((head_ + BLOCK_BUFFER_SIZE - tail_) % BLOCK_BUFFER_SIZE); }
  // Producer side.
  bool push(const Block &b);
  // Consumer side: the oldest block, or null.
  Block *peek() { return empty() ? nullptr : &blocks_[tail_]; }
  void pop() { if (!empty()) tail_ = next(tail_); }

 private:
  static uint8_t next(uint8_t i) { return static_cast<uint8_t>((i + 1) % BLOCK_BUFFER_SIZE); }
  Block blocks_[BLOCK_BUFFER_SIZE];
  volatile uint8_t head_;
  volatile uint8_t tail_;
};

#endif
