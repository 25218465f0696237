// Step generation. Timer1 (CTC, 2 MHz ticks) fires once per step event and emits the pulses of a
// Bresenham line, so every axis of a block makes exactly its step count and all axes take their
// last step in the same interrupt: they arrive together. Timer3 fires at 1 kHz and moves the step
// rate along the trapezoid, computed from the position in the block (accelerate, cruise, and
// decelerate onto the braking curve that ends at the last step).
#ifndef BENCH_STEPPER_H
#define BENCH_STEPPER_H

#include <stdint.h>
#include "config.h"
#include "planner.h"

extern BlockQueue block_queue;

void stepper_init();
// Applies settings that live in port registers ($2 $3 $4 $5); call after a settings change.
void stepper_apply_settings();
// Starts executing queued blocks if the steppers are idle.
void stepper_wake();
// Stops pulses at once and drops every queued block (reset, alarm). Safe from an interrupt.
// Returns true if steps were being generated (position may be lost).
bool stepper_abort();
// True while blocks are queued or executing (including a completed hold).
bool stepper_busy();
// True while pulses are being generated.
bool stepper_running();
void stepper_hold();               // start decelerating to a stop (feed hold)
bool stepper_hold_complete();      // the hold has come to rest
void stepper_resume();             // continue after a completed hold
// Machine position in steps, read atomically.
void stepper_get_position(int32_t out[N_AXIS]);
void stepper_set_position(uint8_t axis, int32_t steps);
// The alarm raised inside the step interrupt (hard limit), or 0; clears it.
uint8_t stepper_take_alarm();
// For homing blocks: true if the last block ended on its switch condition.
bool stepper_stopped_by_switch();
// Hard limits are ignored while homing drives into the switches on purpose.
void stepper_set_homing(bool on);
// Limit inputs that read "hit" (after $5 inversion): bit per axis.
uint8_t limits_read();
// Drivers enabled / disabled (STEPPERS ENABLE pin, $4 inversion).
void stepper_enable(bool on);

#endif
