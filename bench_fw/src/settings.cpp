// Settings: defaults, validation of $N=value, and the EEPROM image (struct + 8-bit checksum).
#include "settings.h"

#include <math.h>
#include <string.h>

Settings settings;

static const uint16_t kNumbers[] = {0, 1, 2, 3, 4, 5, 20, 21, 22, 23, 24, 25, 26, 27,
                                    100, 101, 110, 111, 120, 121, 130, 131};

uint8_t settings_numbers(const uint16_t *&numbers) {
  numbers = kNumbers;
  return sizeof(kNumbers) / sizeof(kNumbers[0]);
}

bool settings_is_integer(uint16_t n) { return n < 24 || n == 26; }

void settings_defaults(Settings &s) {
  memset(&s, 0, sizeof(s));
  s.version = SETTINGS_VERSION;
  s.pulse_us = DEFAULT_STEP_PULSE_US;
  s.idle_delay_ms = DEFAULT_STEP_IDLE_DELAY_MS;
  s.step_invert_mask = DEFAULT_STEP_INVERT_MASK;
  s.dir_invert_mask = DEFAULT_DIR_INVERT_MASK;
  s.enable_invert = DEFAULT_ENABLE_INVERT;
  s.limit_invert = DEFAULT_LIMIT_INVERT;
  s.soft_limits = DEFAULT_SOFT_LIMITS;
  s.hard_limits = DEFAULT_HARD_LIMITS;
  s.homing_enable = DEFAULT_HOMING_ENABLE;
  s.homing_dir_mask = DEFAULT_HOMING_DIR_MASK;
  s.homing_feed = DEFAULT_HOMING_FEED;
  s.homing_seek = DEFAULT_HOMING_SEEK;
  s.homing_debounce_ms = DEFAULT_HOMING_DEBOUNCE_MS;
  s.homing_pulloff = DEFAULT_HOMING_PULLOFF;
  s.steps_per_unit[AXIS_X] = DEFAULT_X_STEPS_PER_UNIT;
  s.steps_per_unit[AXIS_A] = DEFAULT_A_STEPS_PER_UNIT;
  s.max_rate[AXIS_X] = DEFAULT_X_MAX_RATE;
  s.max_rate[AXIS_A] = DEFAULT_A_MAX_RATE;
  s.accel[AXIS_X] = DEFAULT_X_ACCEL;
  s.accel[AXIS_A] = DEFAULT_A_ACCEL;
  s.max_travel[AXIS_X] = DEFAULT_X_MAX_TRAVEL;
  s.max_travel[AXIS_A] = DEFAULT_A_MAX_TRAVEL;
  settings_derive(s);
}

// Thousandths of `v` (v >= 0, at most SETTING_MAX_TRAVEL), rounded half up.
static int32_t milli(float v) { return static_cast<int32_t>(lroundf(v * 1000.0f)); }

void settings_derive(Settings &s) {
  for (uint8_t k = 0; k < N_AXIS; k++) {
    s.spu_milli[k] = milli(s.steps_per_unit[k]);
    // travel (milli-units) x steps/unit (milli) / 10^6, in integers: the same rounding as a
    // target written with three decimals (decimal_to_steps).
    int64_t p = static_cast<int64_t>(milli(s.max_travel[k])) * s.spu_milli[k];
    s.travel_steps[k] = static_cast<int32_t>((p + 500000) / 1000000);
  }
}

static uint8_t checksum(const Settings &s) {
  const uint8_t *p = reinterpret_cast<const uint8_t *>(&s);
  uint8_t sum = 0xA5;  // a blank (0xFF) or zeroed EEPROM must not pass
  for (uint16_t i = 0; i < sizeof(Settings); i++) sum = static_cast<uint8_t>((sum << 1 | sum >> 7) ^ p[i]);
  return sum;
}

void settings_save(const Settings &s) {
  nvm_write(SETTINGS_EEPROM_ADDR, &s, sizeof(Settings));
  uint8_t sum = checksum(s);
  nvm_write(SETTINGS_EEPROM_ADDR + sizeof(Settings), &sum, 1);
}

bool settings_load(Settings &s) {
  Settings image;
  uint8_t sum = 0;
  nvm_read(SETTINGS_EEPROM_ADDR, &image, sizeof(Settings));
  nvm_read(SETTINGS_EEPROM_ADDR + sizeof(Settings), &sum, 1);
  if (image.version == SETTINGS_VERSION && sum == checksum(image)) {
    s = image;
    settings_derive(s);
    return true;
  }
  settings_defaults(s);
  settings_save(s);
  return false;
}

bool settings_get(const Settings &s, uint16_t n, float &v) {
  if (n >= 100 && n < 140 && (n % 10) < N_AXIS) {
    uint8_t axis = n % 10;
    switch (n / 10) {
      case 10: v = s.steps_per_unit[axis]; return true;
      case 11: v = s.max_rate[axis]; return true;
      case 12: v = s.accel[axis]; return true;
      case 13: v = s.max_travel[axis]; return true;
    }
    return false;
  }
  switch (n) {
    case 0: v = s.pulse_us; return true;
    case 1: v = s.idle_delay_ms; return true;
    case 2: v = s.step_invert_mask; return true;
    case 3: v = s.dir_invert_mask; return true;
    case 4: v = s.enable_invert; return true;
    case 5: v = s.limit_invert; return true;
    case 20: v = s.soft_limits; return true;
    case 21: v = s.hard_limits; return true;
    case 22: v = s.homing_enable; return true;
    case 23: v = s.homing_dir_mask; return true;
    case 24: v = s.homing_feed; return true;
    case 25: v = s.homing_seek; return true;
    case 26: v = s.homing_debounce_ms; return true;
    case 27: v = s.homing_pulloff; return true;
  }
  return false;
}

// The fastest step rate any axis of `s` asks for (steps/s), and the slowest.
static float fastest_rate(const Settings &s, float *slowest) {
  float hi = 0.0f, lo = 1e30f;
  for (uint8_t k = 0; k < N_AXIS; k++) {
    float r = s.steps_per_unit[k] * s.max_rate[k] / 60.0f;
    hi = fmaxf(hi, r);
    lo = fminf(lo, r);
  }
  *slowest = lo;
  return hi;
}

// Checks that hold between settings: every axis' rate within what the step interrupt makes at
// this pulse width, and every distance within the step counter's exact range.
static Status check_combination(const Settings &s) {
  float slowest;
  float fastest = fastest_rate(s, &slowest);
  float limit = fminf(MAX_STEP_RATE, 1e6f / static_cast<float>(s.pulse_us + STEP_ISR_US));
  if (fastest > limit) return STATUS_MAX_STEP_RATE_EXCEEDED;
  if (slowest < MIN_STEP_RATE) return STATUS_BAD_NUMBER_FORMAT;  // slower than the timer can
  for (uint8_t k = 0; k < N_AXIS; k++) {
    if (s.spu_milli[k] <= 0) return STATUS_BAD_NUMBER_FORMAT;
    if (s.travel_steps[k] <= 0 || s.travel_steps[k] > SETTING_MAX_STEPS)
      return STATUS_BAD_NUMBER_FORMAT;
    if (s.homing_pulloff * s.steps_per_unit[k] > static_cast<float>(SETTING_MAX_STEPS))
      return STATUS_BAD_NUMBER_FORMAT;
  }
  return STATUS_OK;
}

static bool in_range(float v, float lo, float hi) { return v >= lo && v <= hi; }

// Rounds to the three decimals $$ prints, so what is listed is what is used.
static float three_decimals(float v) { return static_cast<float>(lroundf(v * 1000.0f)) / 1000.0f; }

Status settings_set(Settings &s, uint16_t n, float value) {
  float unused;
  if (!settings_get(s, n, unused)) return STATUS_INVALID_STATEMENT;
  if (value < 0.0f) return STATUS_NEGATIVE_VALUE;
  Settings next = s;  // validate on a copy: a refused value changes nothing
  if (n >= 100) {
    uint8_t axis = n % 10;
    switch (n / 10) {
      case 10:
        if (!in_range(value, SETTING_MIN_STEPS_PER_UNIT, SETTING_MAX_STEPS_PER_UNIT))
          return STATUS_BAD_NUMBER_FORMAT;
        next.steps_per_unit[axis] = three_decimals(value);
        break;
      case 11:
        if (!in_range(value, 1e-3f, SETTING_MAX_RATE)) return STATUS_BAD_NUMBER_FORMAT;
        next.max_rate[axis] = value;
        break;
      case 12:
        if (!in_range(value, 1e-3f, SETTING_MAX_ACCEL)) return STATUS_BAD_NUMBER_FORMAT;
        next.accel[axis] = value;
        break;
      case 13:
        if (!in_range(value, 1e-3f, SETTING_MAX_TRAVEL)) return STATUS_BAD_NUMBER_FORMAT;
        next.max_travel[axis] = three_decimals(value);
        break;
    }
  } else if (settings_is_integer(n)) {
    if (value > 65535.0f) return STATUS_BAD_NUMBER_FORMAT;
    uint16_t iv = static_cast<uint16_t>(value);
    if (static_cast<float>(iv) != value) return STATUS_BAD_NUMBER_FORMAT;
    if (n != 26 && iv > 255) return STATUS_BAD_NUMBER_FORMAT;
    uint8_t b = static_cast<uint8_t>(iv);
    // Masks have a bit per report slot (X Y Z); switches are 0 or 1.
    if ((n == 2 || n == 3 || n == 23) && iv > 7) return STATUS_BAD_NUMBER_FORMAT;
    if ((n == 4 || n == 5 || (n >= 20 && n <= 22)) && iv > 1) return STATUS_BAD_NUMBER_FORMAT;
    bool flag = iv != 0;
    switch (n) {
      case 0:
        if (iv < 3) return STATUS_SETTING_STEP_PULSE_MIN;
        if (iv > 50) return STATUS_BAD_NUMBER_FORMAT;  // would eat the step ISR's time budget
        next.pulse_us = b;
        break;
      case 1: next.idle_delay_ms = b; break;
      case 2: next.step_invert_mask = b; break;
      case 3: next.dir_invert_mask = b; break;
      case 4: next.enable_invert = flag; break;
      case 5: next.limit_invert = flag; break;
      case 20:
        if (flag && !next.homing_enable) return STATUS_SOFT_LIMIT_ERROR;
        next.soft_limits = flag;
        break;
      case 21: next.hard_limits = flag; break;
      case 22:
        next.homing_enable = flag;
        if (!flag) next.soft_limits = 0;  // Grbl: soft limits need a homed machine
        break;
      case 23: next.homing_dir_mask = b; break;
      case 26: next.homing_debounce_ms = iv; break;
    }
  } else {
    switch (n) {
      case 24:
        if (!in_range(value, 1e-3f, SETTING_MAX_RATE)) return STATUS_BAD_NUMBER_FORMAT;
        next.homing_feed = value;
        break;
      case 25:
        if (!in_range(value, 1e-3f, SETTING_MAX_RATE)) return STATUS_BAD_NUMBER_FORMAT;
        next.homing_seek = value;
        break;
      case 27:
        if (!in_range(value, 0.0f, SETTING_MAX_PULLOFF)) return STATUS_BAD_NUMBER_FORMAT;
        next.homing_pulloff = value;
        break;
    }
  }
  settings_derive(next);
  Status st = check_combination(next);
  if (st != STATUS_OK) return st;
  s = next;
  settings_save(s);
  return STATUS_OK;
}

#ifdef __AVR__
#include <avr/eeprom.h>
void nvm_read(uint16_t addr, void *dst, uint16_t n) {
  eeprom_read_block(dst, reinterpret_cast<const void *>(addr), n);
}
void nvm_write(uint16_t addr, const void *src, uint16_t n) {
  // update: only bytes that changed are written, sparing the EEPROM's 100k write cycles
  eeprom_update_block(src, reinterpret_cast<void *>(addr), n);
}
#endif
