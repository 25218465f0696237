// Settings: defaults equal the bench's fixed numbers, validation of $N=value, EEPROM round trip.
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
  // 800 steps/deg * 2400 deg/min = 32 kHz: more than the ISR can make.
  CHECK_EQ(settings_set(s, 111, 2400.0f), STATUS_MAX_STEP_RATE_EXCEEDED);
  CHECK_EQ(settings_set(s, 101, 1600.0f), STATUS_MAX_STEP_RATE_EXCEEDED);
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
