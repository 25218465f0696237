// Settings kept in EEPROM, with Grbl's numbering ($N=value). Pure C++ apart from the EEPROM
// access, so the host-side unit tests exercise validation and storage with g++.
#ifndef BENCH_SETTINGS_H
#define BENCH_SETTINGS_H

#include <stdint.h>
#include "codes.h"
#include "config.h"

// Bumped whenever the layout changes, so an old EEPROM image is replaced by the defaults.
#define SETTINGS_VERSION 4
#define SETTINGS_EEPROM_ADDR 0

struct Settings {
  uint8_t version;
  uint8_t pulse_us;           // $0  us
  uint8_t idle_delay_ms;      // $1  ms, 255 = never disable
  uint8_t step_invert_mask;   // $2  bit per axis
  uint8_t dir_invert_mask;    // $3  bit per axis
  uint8_t enable_invert;      // $4  bool
  uint8_t limit_invert;       // $5  bool
  uint8_t soft_limits;        // $20 bool
  uint8_t hard_limits;        // $21 bool
  uint8_t homing_enable;      // $22 bool
  uint8_t homing_dir_mask;    // $23 bit per axis: 1 = home toward min
  uint16_t homing_debounce_ms;  // $26 ms
  float homing_feed;          // $24 units/min
  float homing_seek;          // $25 units/min
  float homing_pulloff;       // $27 units
  float steps_per_unit[N_AXIS];  // $100+ steps/mm or steps/deg
  float max_rate[N_AXIS];        // $110+ units/min
  float accel[N_AXIS];           // $120+ units/s^2
  float max_travel[N_AXIS];      // $130+ units
  // Derived from the above (settings_derive), the integers every step decision uses:
  int32_t spu_milli[N_AXIS];     // $10x in thousandths of a step per unit (exact: 3 decimals)
  int32_t travel_steps[N_AXIS];  // $13x in steps, rounded like every target
};

// Limits of the values a setting may take (PROTOCOL.md lists them): beyond them a value would
// overflow a step count or ask for a rate the step interrupt cannot make.
#define SETTING_MAX_STEPS_PER_UNIT 10000.0f
#define SETTING_MIN_STEPS_PER_UNIT 0.001f
#define SETTING_MAX_RATE 1000000.0f      // units/min
#define SETTING_MAX_ACCEL 1000000.0f     // units/s^2
#define SETTING_MAX_TRAVEL 100000.0f     // units
#define SETTING_MAX_PULLOFF 1000.0f      // units
#define SETTING_MAX_STEPS 16777216L      // 2^24 steps: positions stay exact in single precision

extern Settings settings;

void settings_defaults(Settings &s);
// Loads from EEPROM; returns false (and keeps the defaults, written back) if the image is invalid.
bool settings_load(Settings &s);
void settings_save(const Settings &s);
// $N=value: validates, applies and saves. Returns STATUS_OK or the Grbl error code.
Status settings_set(Settings &s, uint16_t number, float value);
// The value of setting N (false if there is no such setting).
bool settings_get(const Settings &s, uint16_t number, float &value);
// Fills the derived integers (spu_milli, travel_steps) from the float settings.
void settings_derive(Settings &s);
// Setting numbers in $$ order; returns how many.
uint8_t settings_numbers(const uint16_t *&numbers);
// True for settings printed as integers.
bool settings_is_integer(uint16_t number);

// Storage backend: EEPROM on the AVR, a RAM image in the host tests.
void nvm_read(uint16_t addr, void *dst, uint16_t n);
void nvm_write(uint16_t addr, const void *src, uint16_t n);

#endif
