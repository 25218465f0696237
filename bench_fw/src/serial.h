// UART0 with interrupt-driven ring buffers. The receive interrupt picks the realtime bytes
// (? ! ~ Ctrl-X) out of the stream at once, as Grbl does, so they act even while the main loop
// is busy (homing, a dwell, a full planner queue). The Arduino core's HardwareSerial cannot do
// that, so this replaces it (it is not linked).
#ifndef BENCH_SERIAL_H
#define BENCH_SERIAL_H

#include <stdint.h>

#define UART_RX_BUFFER_SIZE 256
#define UART_TX_BUFFER_SIZE 128
#define SERIAL_NO_DATA 0xFFFF

void serial_init();
// True if a received byte is waiting.
bool serial_available();
// Next received (non-realtime) byte, or SERIAL_NO_DATA.
uint16_t serial_read();
// Stands in the receive stream for bytes lost to a full buffer: the line it ends is rejected.
#define SERIAL_DAMAGE_MARK 0x01
void serial_reset_rx();
void serial_write(uint8_t c);
void serial_print(const char *s);
void serial_print_P(const char *progmem_s);
void serial_print_uint(uint32_t v);
// Thousandths as a value with three decimals ("-12.345").
void serial_print_milli(int32_t milli);
// A value with three decimals, like Grbl's reports ("-12.345").
void serial_print_float3(float v);
// Realtime requests set by the receive interrupt (bits of rt_exec).
#define EXEC_STATUS_REPORT 0x01
#define EXEC_FEED_HOLD 0x02
#define EXEC_CYCLE_START 0x04
#define EXEC_RESET 0x08
#define EXEC_RESET_IN_MOTION 0x10
#define EXEC_JOG_CANCEL 0x20
extern volatile uint8_t rt_exec;

#endif
