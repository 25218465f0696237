/* Pin map of the stage controller on an Arduino Mega 2560.
 *
 * Plain C macros so that the simavr harness (C) includes this very file and watches the pins the
 * firmware drives. The map is grbl-Mega's default one (CPU_MAP_2560_INITIAL in its cpu_map.h):
 * the rotary stage sits on grbl-Mega's Y pins, so the same wiring runs a stock grbl-Mega board,
 * whose Y axis is then the rotary stage (the host driver picks the letters X and Y there).
 *
 *   signal            port/bit  Arduino pin   notes
 *   X STEP            PA2       D24           rising edge = one step
 *   A STEP            PA3       D25           (grbl-Mega's Y STEP)
 *   X DIR             PC7       D30           high = negative direction (before $3 inversion)
 *   A DIR             PC6       D31           (grbl-Mega's Y DIR)
 *   STEPPERS ENABLE   PB7       D13           low = drivers enabled (before $4 inversion); D13 LED
 *   X LIMIT           PB4       D10           input, pull-up; low = switch hit (before $5)
 *   A LIMIT           PB5       D11           input, pull-up; low = switch hit (before $5)
 *   (Z LIMIT)         PB6       D12           grbl-Mega's Z switch: not used here
 *   UART0             PE0/PE1   D0/D1         115200 8N1 through the Mega's USB bridge
 *
 * Each axis has one limit input; its min and max switches are wired in parallel to it (normally
 * open to ground), as in Grbl. The firmware tells min from max by the direction of travel.
 */
#ifndef BENCH_PINS_H
#define BENCH_PINS_H

#define STEP_PORT_LETTER 'A'
#define STEP_BIT_X 2
#define STEP_BIT_A 3

#define DIR_PORT_LETTER 'C'
#define DIR_BIT_X 7
#define DIR_BIT_A 6

#define ENABLE_PORT_LETTER 'B'
#define ENABLE_BIT 7

#define LIMIT_PORT_LETTER 'B'
#define LIMIT_BIT_X 4
#define LIMIT_BIT_A 5

#define BAUD_RATE 115200UL

#endif
