// Planner: step conversion, soft limits, and the per-block rates of a trapezoidal profile.
#include "planner.h"

#include <math.h>

int32_t units_to_steps(const Settings &s, uint8_t axis, float units) {
  return static_cast<int32_t>(lroundf(units * s.steps_per_unit[axis]));
}

static int64_t pow10_64(uint8_t n) {
  int64_t p = 1;
  while (n--) p *= 10;
  return p;
}

// round(num / den) for den > 0, half away from zero.
static int64_t div_round(int64_t num, int64_t den) {
  return num >= 0 ? (num + den / 2) / den : -((-num + den / 2) / den);
}

bool decimal_to_steps(const Settings &s, uint8_t axis, const Decimal &units, int32_t *steps) {
  const int64_t kLimit = 1L << 30;
  // steps = mantissa x 10^exponent x spu_milli / 1000
  int64_t num = static_cast<int64_t>(units.mantissa) * s.spu_milli[axis];
  int8_t shift = static_cast<int8_t>(units.exponent - 3);
  int64_t v;
  if (shift >= 0) {
    // Multiplying only grows |num|: refuse what is already out of range (no int64 overflow).
    v = num;
    for (int8_t e = 0; e < shift; e++) {
      if (v > kLimit || v < -kLimit) return false;
      v *= 10;
    }
  } else {
    v = div_round(num, pow10_64(static_cast<uint8_t>(-shift)));
  }
  if (v > kLimit || v < -kLimit) return false;
  *steps = static_cast<int32_t>(v);
  return true;
}

int32_t steps_to_milli(const Settings &s, uint8_t axis, int32_t steps) {
  return static_cast<int32_t>(div_round(static_cast<int64_t>(steps) * 1000000, s.spu_milli[axis]));
}

void travel_range(const Settings &s, uint8_t axis, int32_t *lo, int32_t *hi) {
  if (s.homing_dir_mask & (1 << axis)) {
    *lo = 0;
    *hi = s.travel_steps[axis];
  } else {
    *lo = -s.travel_steps[axis];
    *hi = 0;
  }
}

bool within_travel(const Settings &s, const int32_t target[N_AXIS]) {
  for (uint8_t k = 0; k < N_AXIS; k++) {
    int32_t lo, hi;
    travel_range(s, k, &lo, &hi);
    if (target[k] < lo || target[k] > hi) return false;
  }
  return true;
}

Status plan_move(const Settings &s, const int32_t from[N_AXIS], const int32_t target[N_AXIS],
                 float feed, Block &out, bool *zero_length) {
  *zero_length = false;
  if (s.soft_limits && !within_travel(s, target)) return STATUS_TRAVEL_EXCEEDED;
  Block b;
  b.dir_negative_mask = 0;
  b.step_event_count = 0;
  b.mode = BLOCK_NORMAL;
  b.homing_axis = 0;
  float delta[N_AXIS];
  float length_sq = 0.0f;
  for (uint8_t k = 0; k < N_AXIS; k++) {
    int32_t d = target[k] - from[k];
    if (d < 0) b.dir_negative_mask |= static_cast<uint8_t>(1 << k);
    b.steps[k] = static_cast<uint32_t>(d < 0 ? -d : d);
    if (b.steps[k] > b.step_event_count) b.step_event_count = b.steps[k];
    delta[k] = static_cast<float>(b.steps[k]) / s.steps_per_unit[k];  // units actually moved
    length_sq += delta[k] * delta[k];
  }
  if (b.step_event_count == 0) {
    *zero_length = true;
    return STATUS_OK;
  }
  // Speed and acceleration along the path (units/min, units/s^2): the largest values for which
  // no axis exceeds its own limit, as Grbl limits them.
  float length = sqrtf(length_sq);
  float rate = 1e30f, accel = 1e30f;
  for (uint8_t k = 0; k < N_AXIS; k++) {
    if (b.steps[k] == 0) continue;
    float unit = delta[k] / length;
    rate = fminf(rate, s.max_rate[k] / unit);
    accel = fminf(accel, s.accel[k] / unit);
  }
  if (feed > 0.0f) rate = fminf(rate, feed);
  // Convert to dominant-axis steps per second.
  float steps_per_length = static_cast<float>(b.step_event_count) / length;
  b.nominal_rate = fminf(rate / 60.0f * steps_per_length, MAX_STEP_RATE);
  if (b.nominal_rate < MIN_STEP_RATE) b.nominal_rate = MIN_STEP_RATE;
  b.accel = accel * steps_per_length;
  // The speed half a step after a standing start under constant acceleration, sqrt(2 a 0.5):
  // the first and last step intervals, so a move neither crawls at its ends nor jumps to speed,
  // and its duration stays within a few % of the ideal trapezoid from rest even for short moves.
  b.start_rate = fmaxf(sqrtf(b.accel), MIN_STEP_RATE);
  if (b.start_rate > b.nominal_rate) b.start_rate = b.nominal_rate;
  out = b;
  return STATUS_OK;
}

float trapezoid_time(float distance, float rate, float accel) {
  if (distance <= 0.0f) return 0.0f;
  float ramp = rate * rate / accel;  // distance spent accelerating plus decelerating
  if (distance >= ramp) return distance / rate + rate / accel;
  return 2.0f * sqrtf(distance / accel);
}

bool BlockQueue::push(const Block &b) {
  if (full()) return false;
  blocks_[head_] = b;
  head_ = next(head_);
  return true;
}
