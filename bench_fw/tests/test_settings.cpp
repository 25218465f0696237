// Settings: defaults equal the bench's fixed numbers, validation of $N=value, EEPROM round trip.
#include <cstring>

#include "check.h"
#include "nvm_host.h"
#include "settings.h"

TEST(settings_defaults_are_the_bench) {
  Settings s;
  settings_defaults(s);
  float v;
  struct { uint16_t n; float v; } expect[] = {
      {100, 400}, {101, 800}, {110, 600}, {111, 1200}, {120, 50}, {121, 40},
      {130, 100}, {131, 60}, {20, 1}, {21, 1}, {22, 1}, {23, 3}, {27, 1},
  };
  for (auto &e : expect) {
    CHECK(settings_get(s, e.n, v));
    CHECK_NEAR(v, e.v, 0);
  }
  CHECK(!settings_get(s, 102, v));
  CHECK(!settings_get(s, 6, v));
}

TEST(settings_load_blank_and_round_trip) {
  nvm_erase();
  Settings s;
  CHECK(!settings_load(s));         // blank EEPROM: defaults, written back
  float v;
  CHECK(settings_get(s, 100, v) && v == 400.0f);
  Settings again;
  CHECK(settings_load(again));      // now valid
  CHECK_EQ(settings_set(s, 110, 450.0f), STATUS_OK);
  CHECK(settings_load(again));
  CHECK(settings_get(again, 110, v) && v == 450.0f);
  // A flipped bit is caught by the checksum: defaults again.
  nvm_image[5] ^= 0x10;
  CHECK(!settings_load(again));
  CHECK(settings_get(again, 110, v) && v == 600.0f);
}

TEST(settings_validation) {
  nvm_erase();
  Settings s;
  settings_defaults(s);
  CHECK_EQ(settings_set(s, 102, 1.0f), STATUS_INVALID_STATEMENT);
  CHECK_EQ(settings_set(s, 7, 1.0f), STATUS_INVALID_STATEMENT);
  CHECK_EQ(settings_set(s, 100, -1.0f), STATUS_NEGATIVE_VALUE);
  CHECK_EQ(settings_set(s, 100, 0.0f), STATUS_BAD_NUMBER_FORMAT);
  CHECK_EQ(settings_set(s, 0, 2.0f), STATUS_SETTING_STEP_PULSE_MIN);
  CHECK_EQ(settings_set(s, 0, 10.0f), STATUS_OK);
  CHECK_EQ(settings_set(s, 1, 256.0f), STATUS_BAD_NUMBER_FORMAT);
  CHECK_EQ(settings_set(s, 1, 1.5f), STATUS_BAD_NUMBER_FORMAT);
  // 800 steps/deg * 1600 deg/min = 21.3 kHz: more than the ISR can make (MAX_STEP_RATE).
  CHECK_EQ(settings_set(s, 111, 1600.0f), STATUS_MAX_STEP_RATE_EXCEEDED);
  CHECK_EQ(settings_set(s, 101, 1100.0f), STATUS_MAX_STEP_RATE_EXCEEDED);
  CHECK_EQ(settings_set(s, 111, 1500.0f), STATUS_OK);              // 20 kHz: the limit itself
  CHECK_EQ(settings_set(s, 0, 50.0f), STATUS_MAX_STEP_RATE_EXCEEDED);  // 80 us a step: 12.5 kHz
  CHECK_EQ(settings_set(s, 111, 1200.0f), STATUS_OK);
  float v;
  CHECK(settings_get(s, 111, v) && v == 1200.0f);   // refused: unchanged
  // Soft limits need homing; turning homing off turns soft limits off.
  CHECK_EQ(settings_set(s, 22, 0.0f), STATUS_OK);
  CHECK(settings_get(s, 20, v) && v == 0.0f);
  CHECK_EQ(settings_set(s, 20, 1.0f), STATUS_SOFT_LIMIT_ERROR);
  CHECK_EQ(settings_set(s, 22, 1.0f), STATUS_OK);
  CHECK_EQ(settings_set(s, 20, 1.0f), STATUS_OK);
  CHECK_EQ(settings_set(s, 26, 300.0f), STATUS_OK);
  CHECK_EQ(settings_set(s, 27, 0.5f), STATUS_OK);
  CHECK_EQ(settings_set(s, 24, 0.0f), STATUS_BAD_NUMBER_FORMAT);
}

TEST(settings_ranges) {
  // Every value that would overflow a step count, or that the hardware cannot do, is refused and
  // changes nothing ($130=5368709 was accepted and then every move failed with error:15).
  nvm_erase();
  Settings s;
  settings_defaults(s);
  float v;
  struct { uint16_t n; float value; Status s; } cases[] = {
      {130, 5368709.0f, STATUS_BAD_NUMBER_FORMAT},   // 2.1e9 steps: beyond the step counter
      {131, 1e7f, STATUS_BAD_NUMBER_FORMAT},
      {130, 41943.05f, STATUS_BAD_NUMBER_FORMAT},    // 2^24 steps and a bit at 400 steps/mm
      {130, 41943.0f, STATUS_OK},
      {130, 100.0f, STATUS_OK},
      {100, 20000.0f, STATUS_BAD_NUMBER_FORMAT},     // above 10000 steps/unit
      {100, 0.0001f, STATUS_BAD_NUMBER_FORMAT},      // below 0.001 steps/unit
      {110, 1.0f, STATUS_BAD_NUMBER_FORMAT},         // 6.7 steps/s: slower than the timer can
      {120, 2e6f, STATUS_BAD_NUMBER_FORMAT},
      {2, 8.0f, STATUS_BAD_NUMBER_FORMAT},           // masks: a bit per X Y Z slot
      {3, 7.0f, STATUS_OK},
      {3, 0.0f, STATUS_OK},
      {4, 2.0f, STATUS_BAD_NUMBER_FORMAT},           // switches: 0 or 1
      {21, 2.0f, STATUS_BAD_NUMBER_FORMAT},
      {23, 9.0f, STATUS_BAD_NUMBER_FORMAT},
      {24, 2e6f, STATUS_BAD_NUMBER_FORMAT},
      {27, 5000.0f, STATUS_BAD_NUMBER_FORMAT},
      {26, 65536.0f, STATUS_BAD_NUMBER_FORMAT},
  };
  for (auto &c : cases) {
    Settings before = s;
    Status got = settings_set(s, c.n, c.value);
    if (got != c.s) std::printf("  $%u=%g\n", c.n, c.value);
    CHECK_EQ(got, c.s);
    if (got != STATUS_OK) CHECK(std::memcmp(&before, &s, sizeof(s)) == 0);
  }
  // A steps/unit that would push the travel past 2^24 steps is refused as well.
  CHECK_EQ(settings_set(s, 130, 30000.0f), STATUS_OK);
  CHECK_EQ(settings_set(s, 100, 600.0f), STATUS_BAD_NUMBER_FORMAT);
  CHECK_EQ(settings_set(s, 130, 100.0f), STATUS_OK);
  // Axis values keep the three decimals $$ prints, and the integers follow them.
  CHECK_EQ(settings_set(s, 100, 78.7404f), STATUS_OK);
  CHECK(settings_get(s, 100, v) && v == 78.74f);
  CHECK_EQ(s.spu_milli[AXIS_X], 78740);
  CHECK_EQ(s.travel_steps[AXIS_X], 7874);
}
