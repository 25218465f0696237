// UART0 driver (ATmega2560): 115200 baud with U2X, RX/TX rings, realtime byte filter.
#include "serial.h"

#include <avr/interrupt.h>
#include <avr/io.h>
#include <avr/pgmspace.h>
#include <math.h>

#include "pins.h"
#include "protocol.h"
#include "stepper.h"

volatile uint8_t rt_exec = 0;

static uint8_t rx_buf[UART_RX_BUFFER_SIZE];
static volatile uint8_t rx_head = 0, rx_tail = 0;  // 256-entry ring: uint8 indices wrap by themselves
// Set when a byte was lost to a full buffer: the rest of that line is dropped and the line is
// closed with SERIAL_DAMAGE_MARK + '\n', so it is rejected whole (error:11), never run in part.
static volatile bool rx_damaged = false;
static uint8_t tx_buf[UART_TX_BUFFER_SIZE];
static volatile uint8_t tx_head = 0, tx_tail = 0;

void serial_init() {
  // U2X: 16 MHz / (8 * (16 + 1)) = 117647 baud, 2.1 % from 115200 (the Arduino core's choice).
  UCSR0A = _BV(U2X0);
  uint16_t ubrr = static_cast<uint16_t>((F_CPU / 4 / BAUD_RATE - 1) / 2);
  UBRR0H = static_cast<uint8_t>(ubrr >> 8);
  UBRR0L = static_cast<uint8_t>(ubrr);
  UCSR0C = _BV(UCSZ01) | _BV(UCSZ00);  // 8N1
  UCSR0B = _BV(RXEN0) | _BV(TXEN0) | _BV(RXCIE0);
}

ISR(USART0_RX_vect) {
  uint8_t c = UDR0;
  switch (c) {
    case RT_STATUS_REPORT: rt_exec |= EXEC_STATUS_REPORT; return;
    case RT_FEED_HOLD: rt_exec |= EXEC_FEED_HOLD; return;
    case RT_CYCLE_START: rt_exec |= EXEC_CYCLE_START; return;
    case RT_JOG_CANCEL: rt_exec |= EXEC_JOG_CANCEL; return;
    case RT_RESET:
      // Stop the motors now, from the interrupt: the main loop may be busy for a while.
      if (stepper_abort()) rt_exec |= EXEC_RESET_IN_MOTION;
      rt_exec |= EXEC_RESET;
      return;
  }
  if (c == SERIAL_DAMAGE_MARK) return;  // reserved; a control byte means nothing in a line anyway
  uint8_t free_slots = static_cast<uint8_t>(rx_tail - rx_head - 1);
  if (rx_damaged) {
    if ((c == '\n' || c == '\r') && free_slots >= 2) {
      rx_buf[rx_head] = SERIAL_DAMAGE_MARK;
      rx_buf[static_cast<uint8_t>(rx_head + 1)] = '\n';
      rx_head = static_cast<uint8_t>(rx_head + 2);
      rx_damaged = false;
    }
    return;
  }
  if (free_slots == 0) {
    rx_damaged = true;
    return;
  }
  rx_buf[rx_head] = c;
  rx_head = static_cast<uint8_t>(rx_head + 1);
}

bool serial_available() { return rx_head != rx_tail; }

uint16_t serial_read() {
  if (rx_head == rx_tail) return SERIAL_NO_DATA;
  uint8_t c = rx_buf[rx_tail];
  rx_tail = static_cast<uint8_t>(rx_tail + 1);
  return c;
}

void serial_reset_rx() {
  uint8_t sreg = SREG;
  cli();
  rx_tail = rx_head;
  rx_damaged = false;
  SREG = sreg;
}

ISR(USART0_UDRE_vect) {
  if (tx_head == tx_tail) {
    UCSR0B &= static_cast<uint8_t>(~_BV(UDRIE0));
    return;
  }
  UDR0 = tx_buf[tx_tail];
  tx_tail = static_cast<uint8_t>((tx_tail + 1) % UART_TX_BUFFER_SIZE);
}

void serial_write(uint8_t c) {
  uint8_t next = static_cast<uint8_t>((tx_head + 1) % UART_TX_BUFFER_SIZE);
  while (next == tx_tail) {
    // Buffer full: wait for the UDRE interrupt to drain it (interrupts are on in the main loop).
  }
  tx_buf[tx_head] = c;
  tx_head = next;
  UCSR0B |= _BV(UDRIE0);
}

void serial_print(const char *s) {
  while (*s) serial_write(static_cast<uint8_t>(*s++));
}

void serial_print_P(const char *s) {
  char c;
  while ((c = static_cast<char>(pgm_read_byte(s++))) != 0) serial_write(static_cast<uint8_t>(c));
}

void serial_print_uint(uint32_t v) {
  char digits[11];
  uint8_t n = 0;
  do {
    digits[n++] = static_cast<char>('0' + v % 10);
    v /= 10;
  } while (v);
  while (n) serial_write(static_cast<uint8_t>(digits[--n]));
}

void serial_print_milli(int32_t milli) {
  if (milli < 0) {
    serial_write('-');
    milli = -milli;
  }
  uint32_t m = static_cast<uint32_t>(milli);
  serial_print_uint(m / 1000);
  serial_write('.');
  uint16_t frac = static_cast<uint16_t>(m % 1000);
  serial_write(static_cast<uint8_t>('0' + frac / 100));
  serial_write(static_cast<uint8_t>('0' + (frac / 10) % 10));
  serial_write(static_cast<uint8_t>('0' + frac % 10));
}

void serial_print_float3(float v) {
  // avr-libc's printf has no %f by default; print fixed point with round-half-away (lroundf).
  // "-0.000" would read oddly: the sign only shows when something nonzero follows.
  serial_print_milli(static_cast<int32_t>(lroundf(v * 1000.0f)));
}
