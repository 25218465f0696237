// Compile-time configuration of the stage controller: sizes, version, and the EEPROM defaults
// of the bench (the digital twin uses the same numbers for its simulated trapezoidal motion;
// PROTOCOL.md lists them).
#ifndef BENCH_CONFIG_H
#define BENCH_CONFIG_H

#define FW_VERSION "0.1.0"
// The banner starts with "Grbl 1.1" so that senders (UGS, bCNC, CNCjs) recognise the protocol.
#define FW_BANNER "Grbl 1.1h [aimbench " FW_VERSION " '$' for help]"

#define N_AXIS 2
#define AXIS_X 0
#define AXIS_A 1
// Axis letters on the wire: X the linear stage (mm), A the rotary stage (deg).
#define AXIS_LETTERS "XA"
// Status reports and $# carry three values, X Y Z, as every Grbl 1.1 build sends. The rotary stage
// sits in the Y slot (grbl-Mega's second axis, whose pins it is wired to) and answers to Y as well
// as A, so senders that know only X, Y and Z can drive it; Z is unused and reads 0.
#define REPORT_SLOTS 3
#define AXIS_A_SLOT_LETTER 'Y'
#define REPORT_SLOT_LETTERS "XYZ"

// 80 characters like Grbl: longer lines are rejected whole with error:11.
#define LINE_BUFFER_SIZE 80
// Moves queued ahead of the stepper; a full queue holds the next line's reply (flow control).
#define BLOCK_BUFFER_SIZE 8

// Defaults (Grbl setting numbers in brackets).
#define DEFAULT_STEP_PULSE_US 5          // $0  pulse width; DRV8825/A4988 need >= 2 us
#define DEFAULT_STEP_IDLE_DELAY_MS 255   // $1  255 = keep drivers enabled (hold the stages)
#define DEFAULT_STEP_INVERT_MASK 0       // $2
#define DEFAULT_DIR_INVERT_MASK 0        // $3
#define DEFAULT_ENABLE_INVERT 0          // $4
#define DEFAULT_LIMIT_INVERT 0           // $5  0: switches close to ground, pin low = hit
#define DEFAULT_SOFT_LIMITS 1            // $20
#define DEFAULT_HARD_LIMITS 1            // $21
#define DEFAULT_HOMING_ENABLE 1          // $22
#define DEFAULT_HOMING_DIR_MASK 3        // $23 bit set = home toward the min end (both axes)
#define DEFAULT_HOMING_FEED 25.0f        // $24 units/min, the slow locate pass
#define DEFAULT_HOMING_SEEK 500.0f       // $25 units/min, the fast search pass
#define DEFAULT_HOMING_DEBOUNCE_MS 25    // $26
#define DEFAULT_HOMING_PULLOFF 1.0f      // $27 units moved off the switch after homing

#define DEFAULT_X_STEPS_PER_UNIT 400.0f  // $100 lead screw: steps/mm
#define DEFAULT_A_STEPS_PER_UNIT 800.0f  // $101 worm gear: steps/deg
#define DEFAULT_X_MAX_RATE 600.0f        // $110 mm/min (10 mm/s)
#define DEFAULT_A_MAX_RATE 1200.0f       // $111 deg/min (20 deg/s)
#define DEFAULT_X_ACCEL 50.0f            // $120 mm/s^2
#define DEFAULT_A_ACCEL 40.0f            // $121 deg/s^2
#define DEFAULT_X_MAX_TRAVEL 100.0f      // $130 mm
#define DEFAULT_A_MAX_TRAVEL 60.0f       // $131 deg

// The stepper timer ticks at F_CPU/8 = 2 MHz; its 16-bit compare sets the slowest rate.
#define STEP_TIMER_HZ 2000000UL
#define MIN_STEP_RATE 31.0f              // steps/s: 2 MHz / 65535
// The fastest step rate the firmware accepts for an axis ($10x x $11x, $24/$25 x $10x, G1 F):
// measured in simavr (benchmarks/bench_stage.py, PROTOCOL.md "Step rate"): at 30 kHz the step
// interrupt alone took 85 % of the CPU, the acceleration tick could no longer finish within its
// millisecond and the main loop starved. At this limit the interrupts take about 62 % of it.
#define MAX_STEP_RATE 20000.0f
// The step interrupt's own duration (us) beside the pulse: the shortest step period is the pulse
// plus this (ticks_for); $0 is refused when it would make MAX_STEP_RATE unreachable.
#define STEP_ISR_US 30
#define ACCEL_TICK_HZ 1000               // velocity updates per second (Timer3)

#endif
