// Settings kept in EEPROM, with Grbl's numbering ($N=value). Pure C++ apart from the EEPROM
// access, so the host-side unit tests exercise validation and storage with g++.
#ifndef BENCH_SETTINGS_H
#define BENCH_SETTINGS_H

#include <stdint.h>
#include "codes.h"
#include "config.h"

// Bumped whenever the layout changes, so an old EEPROM image is replaced by the defaults.
#define SETTINGS_VERSION 3
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
};

extern Settings settings;

void settings_defaults(Settings &s);
// Loads from EEPROM; returns false (and keeps the defaults, written back) if the image is invalid.
bool settings_load(Settings &s);
void settings_save(const Settings &s);
// $N=value: validates, applies and saves. Returns STATUS_OK or the Grbl error code.
Status settings_set(Settings &s, uint16_t number, float value);
// The value of setting N (false if there is no such setting).
bool settings_get(const Settings &s, uint16_t number, float &value);
// Setting numbers in $$ order; returns how many.
uint8_t settings_numbers(const uint16_t *&numbers);
// True for settings printed as integers.
bool settings_is_integer(uint16_t number);

// Storage backend: EEPROM on the AVR, a RAM image in the host tests.
void nvm_read(uint16_t addr, void *dst, uint16_t n);
void nvm_write(uint16_t addr, const void *src, uint16_t n);

#endif
