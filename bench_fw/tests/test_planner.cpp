// Planner: step rounding, soft limits, per-axis rate/acceleration limits along a combined path,
// the trapezoid reference time, and the block queue.
#include "check.h"
#include "planner.h"

static Settings defaults() {
  Settings s;
  settings_defaults(s);
  return s;
}

// plan_move with a target in units (rounded by units_to_steps), as most cases read best.
static Status plan_units(const Settings &s, const int32_t from[N_AXIS], const float units[N_AXIS],
                         float feed, Block &b, bool *zero) {
  int32_t target[N_AXIS];
  for (uint8_t k = 0; k < N_AXIS; k++) target[k] = units_to_steps(s, k, units[k]);
  return plan_move(s, from, target, feed, b, zero);
}

static Decimal dec(const char *text) {
  Decimal d{0, 0};
  uint8_t i = 0;
  read_decimal(text, &i, &d);
  return d;
}

TEST(planner_single_axis_rates) {
  Settings s = defaults();
  int32_t from[N_AXIS] = {0, 0};
  float target[N_AXIS] = {10.0f, 0.0f};
  Block b;
  bool zero;
  CHECK_EQ(plan_units(s, from, target, 0.0f, b, &zero), STATUS_OK);
  CHECK(!zero);
  CHECK_EQ(b.steps[AXIS_X], 4000);
  CHECK_EQ(b.steps[AXIS_A], 0);
  CHECK_EQ(b.step_event_count, 4000);
  CHECK_EQ(b.dir_negative_mask, 0);
  CHECK_NEAR(b.nominal_rate, 600.0 / 60 * 400, 0.5);   // 10 mm/s = 4000 steps/s
  CHECK_NEAR(b.accel, 50.0 * 400, 1.0);               // 20000 steps/s^2
  CHECK_NEAR(b.start_rate, std::sqrt(20000.0), 0.5);
  // G1 feed below the max rate wins; above it the max rate does.
  CHECK_EQ(plan_units(s, from, target, 120.0f, b, &zero), STATUS_OK);
  CHECK_NEAR(b.nominal_rate, 2.0 * 400, 0.5);
  CHECK_EQ(plan_units(s, from, target, 5000.0f, b, &zero), STATUS_OK);
  CHECK_NEAR(b.nominal_rate, 4000.0, 0.5);
}

TEST(planner_rotary_axis_and_direction) {
  Settings s = defaults();
  int32_t from[N_AXIS] = {0, 24000};   // A at 30 deg
  float target[N_AXIS] = {0.0f, 20.0f};
  Block b;
  bool zero;
  CHECK_EQ(plan_units(s, from, target, 0.0f, b, &zero), STATUS_OK);
  CHECK_EQ(b.steps[AXIS_A], 8000);
  CHECK_EQ(b.dir_negative_mask, 1 << AXIS_A);
  CHECK_NEAR(b.nominal_rate, 20.0 * 800, 1.0);   // 16000 steps/s
  CHECK_NEAR(b.accel, 40.0 * 800, 1.0);
}

TEST(planner_combined_move_respects_every_axis) {
  Settings s = defaults();
  int32_t from[N_AXIS] = {0, 0};
  // 3 mm and 4 deg: path length 5 (mixed units, as Grbl does).
  float target[N_AXIS] = {3.0f, 4.0f};
  Block b;
  bool zero;
  CHECK_EQ(plan_units(s, from, target, 0.0f, b, &zero), STATUS_OK);
  CHECK_EQ(b.steps[AXIS_X], 1200);
  CHECK_EQ(b.steps[AXIS_A], 3200);
  CHECK_EQ(b.step_event_count, 3200);
  // Path rate limited by X: 600 / (3/5) = 1000 units/min; A would allow 1200 / (4/5) = 1500.
  double path_rate = 1000.0 / 60.0;
  double x_rate = path_rate * 3.0 / 5.0, a_rate = path_rate * 4.0 / 5.0;
  CHECK(x_rate <= 10.0 + 1e-6 && a_rate <= 20.0 + 1e-6);
  CHECK_NEAR(b.nominal_rate, path_rate * 3200 / 5.0, 1.0);
  // Acceleration limited by A: 40 / (4/5) = 50 units/s^2; X allows 50 / (3/5) = 83.3.
  CHECK_NEAR(b.accel, 50.0 * 3200 / 5.0, 1.0);
}

TEST(planner_rounding_and_zero_length) {
  Settings s = defaults();
  int32_t from[N_AXIS] = {0, 0};
  float target[N_AXIS] = {0.0012f, 0.0f};   // 0.48 steps -> 0
  Block b;
  bool zero;
  CHECK_EQ(plan_units(s, from, target, 0.0f, b, &zero), STATUS_OK);
  CHECK(zero);
  target[0] = 0.0013f;   // 0.52 steps -> 1
  CHECK_EQ(plan_units(s, from, target, 0.0f, b, &zero), STATUS_OK);
  CHECK(!zero);
  CHECK_EQ(b.steps[AXIS_X], 1);
  CHECK_EQ(units_to_steps(s, AXIS_A, -12.3456f), -9876);
  CHECK_EQ(units_to_steps(s, AXIS_X, 50.0f), 20000);
}

TEST(decimal_to_steps_is_exact) {
  Settings s = defaults();
  int32_t v = 0;
  // Single precision moved these by a step (issue: A60.000624 refused, X65.818749 one step off):
  // 60.000624 x 800 = 48000.4992 and 65.818749 x 400 = 26327.4996 round down.
  CHECK(decimal_to_steps(s, AXIS_A, dec("60.000624"), &v) && v == 48000);
  CHECK(decimal_to_steps(s, AXIS_X, dec("65.818749"), &v) && v == 26327);
  CHECK(decimal_to_steps(s, AXIS_X, dec("65.81875"), &v) && v == 26328);    // a tie: away from 0
  CHECK(decimal_to_steps(s, AXIS_X, dec("-65.81875"), &v) && v == -26328);
  CHECK(decimal_to_steps(s, AXIS_A, dec("-12.3456"), &v) && v == -9876);
  CHECK(decimal_to_steps(s, AXIS_X, dec("0.00125"), &v) && v == 1);         // 0.5 step
  CHECK(decimal_to_steps(s, AXIS_X, dec("0.0012"), &v) && v == 0);
  CHECK(decimal_to_steps(s, AXIS_X, dec("123456789012"), &v) == false);    // beyond 2^30 steps
  CHECK(decimal_to_steps(s, AXIS_X, dec("0"), &v) && v == 0);
  // A fractional steps/unit is used to its three decimals: 78.74 x 10 = 787.4.
  s.steps_per_unit[AXIS_X] = 78.74f;
  settings_derive(s);
  CHECK(decimal_to_steps(s, AXIS_X, dec("10"), &v) && v == 787);
  // Reports: steps back to thousandths, exactly.
  s = defaults();
  CHECK_EQ(steps_to_milli(s, AXIS_X, 26327), 65818);   // 65.8175 -> 65.818 (half away)
  CHECK_EQ(steps_to_milli(s, AXIS_X, -26327), -65818);
  CHECK_EQ(steps_to_milli(s, AXIS_A, 48000), 60000);
}

TEST(planner_soft_limits_in_steps) {
  Settings s = defaults();
  int32_t from[N_AXIS] = {0, 0};
  Block b;
  bool zero;
  int32_t end[N_AXIS] = {40000, 48000};   // exactly the ends of travel: allowed
  CHECK_EQ(plan_move(s, from, end, 0.0f, b, &zero), STATUS_OK);
  int32_t past[N_AXIS] = {40000, 48001};
  CHECK_EQ(plan_move(s, from, past, 0.0f, b, &zero), STATUS_TRAVEL_EXCEEDED);
}

TEST(planner_soft_limits) {
  Settings s = defaults();
  int32_t from[N_AXIS] = {0, 0};
  Block b;
  b.step_event_count = 12345;
  bool zero;
  float inside[N_AXIS] = {100.0f, 60.0f};
  CHECK_EQ(plan_units(s, from, inside, 0.0f, b, &zero), STATUS_OK);
  float over[N_AXIS] = {100.01f, 0.0f};
  Block untouched;
  untouched.step_event_count = 777;
  CHECK_EQ(plan_units(s, from, over, 0.0f, untouched, &zero), STATUS_TRAVEL_EXCEEDED);
  CHECK_EQ(untouched.step_event_count, 777);
  float under[N_AXIS] = {0.0f, -0.01f};
  CHECK_EQ(plan_units(s, from, under, 0.0f, b, &zero), STATUS_TRAVEL_EXCEEDED);
  // Homing toward max puts the travel at [-travel, 0].
  s.homing_dir_mask = 0;
  float neg[N_AXIS] = {-100.0f, -60.0f};
  CHECK_EQ(plan_units(s, from, neg, 0.0f, b, &zero), STATUS_OK);
  CHECK_EQ(plan_units(s, from, inside, 0.0f, b, &zero), STATUS_TRAVEL_EXCEEDED);
  // Soft limits off: anything goes.
  s.soft_limits = 0;
  CHECK_EQ(plan_units(s, from, over, 0.0f, b, &zero), STATUS_OK);
}

TEST(trapezoid_reference_time) {
  // 20 deg at 20 deg/s, 40 deg/s^2: ramps take 0.5 s each over 5 deg each; 10 deg cruise 0.5 s.
  CHECK_NEAR(trapezoid_time(20.0f, 20.0f, 40.0f), 1.5, 1e-6);
  // 1 deg never reaches full speed: triangle, 2 sqrt(d/a).
  CHECK_NEAR(trapezoid_time(1.0f, 20.0f, 40.0f), 2.0 * std::sqrt(1.0 / 40.0), 1e-6);
  // Continuity at the boundary d = v^2/a.
  CHECK_NEAR(trapezoid_time(10.0f, 20.0f, 40.0f), 1.0, 1e-6);
  CHECK_NEAR(trapezoid_time(0.0f, 20.0f, 40.0f), 0.0, 0);
}

TEST(block_queue_ring) {
  BlockQueue q;
  Block b{};
  CHECK(q.empty());
  int pushed = 0;
  while (q.push(b)) pushed++;
  CHECK_EQ(pushed, BLOCK_BUFFER_SIZE - 1);
  CHECK(q.full());
  CHECK_EQ(q.count(), BLOCK_BUFFER_SIZE - 1);
  q.pop();
  CHECK(!q.full());
  CHECK(q.push(b));
  q.clear();
  CHECK(q.empty() && q.peek() == nullptr);
}
