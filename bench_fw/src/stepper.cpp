// Stepper ISR and acceleration tick for the ATmega2560. Pins: see pins.h.
#include "stepper.h"

#include <avr/interrupt.h>
#include <avr/io.h>
#include <math.h>

#include "codes.h"
#include "pins.h"
#include "settings.h"

BlockQueue block_queue;

#define STEP_MASK (_BV(STEP_BIT_X) | _BV(STEP_BIT_A))
#define DIR_MASK (_BV(DIR_BIT_X) | _BV(DIR_BIT_A))
static const uint8_t kStepBit[N_AXIS] = {_BV(STEP_BIT_X), _BV(STEP_BIT_A)};
static const uint8_t kDirBit[N_AXIS] = {_BV(DIR_BIT_X), _BV(DIR_BIT_A)};

static volatile int32_t position[N_AXIS];  // steps, machine coordinates
static Block *current = nullptr;           // block being executed (owned by the queue)
static uint32_t events_done;
static uint32_t counter[N_AXIS];
static float rate;                         // dominant-axis steps/s (accel tick only)
static uint32_t ramp_origin;               // step event where the current speed ramp began
static volatile uint16_t interval_ticks;   // next step interval, written by the accel tick
static volatile bool running = false;
static volatile uint8_t hold = 0;          // 0 none, 1 decelerating, 2 at rest
static volatile uint8_t alarm = 0;
static volatile bool stopped_by_switch = false;
static volatile bool homing = false;
static uint8_t limit_prev = 0;
// Cached from settings for the ISR: port bit patterns.
static uint8_t step_idle_bits = 0;   // $2 mapped onto the STEP port bits
static uint8_t dir_invert_bits = 0;  // $3 mapped onto the DIR port bits
static uint8_t pulse_ticks = 10;

uint8_t limits_read() {
  uint8_t pins = PINB;
  uint8_t hit = 0;
  // Switches close to ground: a low pin is a hit, unless $5 inverts it.
  if (!(pins & _BV(LIMIT_BIT_X))) hit |= 1 << AXIS_X;
  if (!(pins & _BV(LIMIT_BIT_A))) hit |= 1 << AXIS_A;
  if (settings.limit_invert) hit ^= (1 << AXIS_X) | (1 << AXIS_A);
  return hit;
}

void stepper_enable(bool on) {
  bool level_high = on ? false : true;  // active-low enable
  if (settings.enable_invert) level_high = !level_high;
  if (level_high) PORTB |= _BV(ENABLE_BIT);
  else PORTB &= static_cast<uint8_t>(~_BV(ENABLE_BIT));
}

void stepper_apply_settings() {
  uint8_t sreg = SREG;
  cli();
  step_idle_bits = 0;
  dir_invert_bits = 0;
  for (uint8_t k = 0; k < N_AXIS; k++) {
    if (settings.step_invert_mask & (1 << k)) step_idle_bits |= kStepBit[k];
    if (settings.dir_invert_mask & (1 << k)) dir_invert_bits |= kDirBit[k];
  }
  pulse_ticks = static_cast<uint8_t>(settings.pulse_us * (STEP_TIMER_HZ / 1000000UL));
  PORTA = static_cast<uint8_t>((PORTA & ~STEP_MASK) | step_idle_bits);
  SREG = sreg;
}

void stepper_init() {
  DDRA |= STEP_MASK;
  DDRC |= DIR_MASK;
  DDRB |= _BV(ENABLE_BIT);
  DDRB &= static_cast<uint8_t>(~(_BV(LIMIT_BIT_X) | _BV(LIMIT_BIT_A)));
  PORTB |= _BV(LIMIT_BIT_X) | _BV(LIMIT_BIT_A);  // pull-ups: an open switch reads high
  stepper_apply_settings();
  stepper_enable(false);
  // Timer1: CTC on OCR1A, stopped until a block arrives.
  TCCR1A = 0;
  TCCR1B = _BV(WGM12);
  TIMSK1 = 0;
  // Timer3: CTC at ACCEL_TICK_HZ (2 MHz / 2000), always running; it returns at once when idle.
  TCCR3A = 0;
  TCCR3B = _BV(WGM32) | _BV(CS31);
  OCR3A = static_cast<uint16_t>(STEP_TIMER_HZ / ACCEL_TICK_HZ - 1);
  TIMSK3 = _BV(OCIE3A);
}

static uint16_t ticks_for(float r) {
  float t = static_cast<float>(STEP_TIMER_HZ) / r;
  if (t > 65535.0f) return 65535;
  // The step ISR waits for TCNT1 to pass the pulse width; the period must leave room for that
  // and for the ISR itself, or the counter would wrap before it and the ISR never end.
  float shortest = static_cast<float>(pulse_ticks) +
                   static_cast<float>(STEP_ISR_US * (STEP_TIMER_HZ / 1000000UL));
  if (t < shortest) return static_cast<uint16_t>(shortest);
  return static_cast<uint16_t>(t);
}

static void timer_stop() {
  TCCR1B = _BV(WGM12);  // clock off
  TIMSK1 = 0;
  running = false;
}

static void timer_start(uint16_t first) {
  // Start from a count of 1 with the compare well above it: simavr 1.6 never fires a Timer1
  // compare that is armed while the counter sits at 0.
  TCNT1 = 1;
  OCR1A = first;
  TIFR1 = _BV(OCF1A);
  TIMSK1 = _BV(OCIE1A);
  running = true;
  TCCR1B = _BV(WGM12) | _BV(CS11);  // clk/8 = 2 MHz
}

static uint8_t homing_mask = 0;            // limit bit of the current homing block's axis
static uint8_t dir_negative = 0;           // the current block's dir_negative_mask

// Makes the oldest queued block current (ISR context or interrupts off).
static void load_block() {
  current = block_queue.peek();
  if (!current) return;
  events_done = 0;
  for (uint8_t k = 0; k < N_AXIS; k++) counter[k] = 0;
  dir_negative = current->dir_negative_mask;
  uint8_t dir = 0;
  for (uint8_t k = 0; k < N_AXIS; k++)
    if (dir_negative & (1 << k)) dir |= kDirBit[k];
  PORTC = static_cast<uint8_t>((PORTC & ~DIR_MASK) | (dir ^ dir_invert_bits));
  homing_mask = static_cast<uint8_t>(1 << current->homing_axis);
  rate = current->start_rate;
  ramp_origin = 0;
  interval_ticks = ticks_for(rate);
  stopped_by_switch = false;
  limit_prev = limits_read();
}

// One axis' Bresenham step: written out per axis (no loop, no variable shifts) because this
// interrupt runs at up to MAX_STEP_RATE and its length sets that limit (PROTOCOL.md, Step rate).
#define STEP_AXIS(k, bit)                                  \
  do {                                                     \
    counter[k] += b->steps[k];                             \
    if (counter[k] >= n) {                                 \
      counter[k] -= n;                                     \
      bits |= kStepBit[k];                                 \
      if (dir_negative & (bit)) position[k]--;             \
      else position[k]++;                                  \
    }                                                      \
  } while (0)

ISR(TIMER1_COMPA_vect) {
  Block *b = current;
  if (!b) {
    timer_stop();
    return;
  }
  uint32_t n = b->step_event_count;
  uint8_t bits = 0;
  // Bresenham from 0: an axis' last step falls on the block's last event, with the dominant
  // axis, so the axes finish in the same interrupt.
  STEP_AXIS(AXIS_X, 1 << AXIS_X);
  STEP_AXIS(AXIS_A, 1 << AXIS_A);
  PORTA = static_cast<uint8_t>((PORTA & ~STEP_MASK) | (step_idle_bits ^ bits));
  uint32_t done_events = events_done + 1;
  events_done = done_events;
  uint8_t lim = limits_read();
  // Hold the pulse for $0 us: TCNT1 restarted at this compare match, so it times the pulse.
  while (TCNT1 < pulse_ticks) {
  }
  PORTA = static_cast<uint8_t>((PORTA & ~STEP_MASK) | step_idle_bits);

  bool done = done_events >= n;
  BlockMode mode = b->mode;
  if (mode == BLOCK_STOP_ON_TRIGGER) {
    if (lim & homing_mask) { stopped_by_switch = true; done = true; }
  } else if (mode == BLOCK_STOP_ON_RELEASE) {
    if (!(lim & homing_mask)) { stopped_by_switch = true; done = true; }
  } else if (!homing && settings.hard_limits && (lim & ~limit_prev)) {
    // A switch closed during a move: stop dead (decelerating would drive further into it).
    alarm = ALARM_HARD_LIMIT;
    current = nullptr;
    block_queue.clear();
    hold = 0;
    timer_stop();
    return;
  }
  limit_prev = lim;
  if (done) {
    block_queue.pop();
    load_block();
    if (!current) {
      timer_stop();
      return;
    }
  }
  OCR1A = interval_ticks;
}

// Acceleration tick. The rate follows the trapezoid in position, not in time: the speed at step
// s of a block is min(sqrt(v0^2 + 2a (s - s0)), nominal, sqrt(v0^2 + 2a (n - s))), which ends
// every block at its last step exactly on the braking curve (a time-driven ramp drifts and
// either crawls or arrives fast). s0 is where the current ramp started (0, or a resume).
// A feed hold decelerates in time (there is no end point to brake for).
// The float arithmetic runs with interrupts on, so it never delays a step pulse. Its own
// interrupt is masked meanwhile: a tick that overran its millisecond (a loaded CPU) is taken
// after it, never nested in it - nested ticks would pile frames on the stack until it overflowed.
ISR(TIMER3_COMPA_vect) {
  if (!running) return;
  TIMSK3 = 0;
  Block *b = current;  // a consistent snapshot: interrupts are still off here
  uint32_t done = events_done;
  uint32_t origin = ramp_origin;
  sei();
  if (b) {
    float start = b->start_rate;
    float v0sq = start * start;
    float two_a = 2.0f * b->accel;
    float braking = v0sq + two_a * static_cast<float>(b->step_event_count - done);
    float r;
    bool stop = false;
    if (hold == 1) {
      r = fminf(rate - b->accel / ACCEL_TICK_HZ, sqrtf(braking));
      stop = r <= start;
    } else {
      float ramp = v0sq + two_a * static_cast<float>(done - origin);
      float nominal_sq = b->nominal_rate * b->nominal_rate;
      r = sqrtf(fminf(fminf(ramp, braking), nominal_sq));
      if (r < start) r = start;
    }
    uint16_t t = ticks_for(r);
    cli();
    if (current == b) {  // the step ISR may have moved on to the next block meanwhile
      if (stop) {
        timer_stop();
        hold = 2;
      } else {
        rate = r;
        interval_ticks = t;
      }
    }
  }
  cli();
  TIMSK3 = _BV(OCIE3A);
}

void stepper_wake() {
  uint8_t sreg = SREG;
  cli();
  if (!running && hold == 0 && !block_queue.empty()) {
    if (!current) load_block();
    if (current) {
      stepper_enable(true);
      timer_start(interval_ticks);
    }
  }
  SREG = sreg;
}

bool stepper_abort() {
  uint8_t sreg = SREG;
  cli();
  bool was_running = running;
  timer_stop();
  current = nullptr;
  block_queue.clear();
  hold = 0;
  PORTA = static_cast<uint8_t>((PORTA & ~STEP_MASK) | step_idle_bits);
  SREG = sreg;
  return was_running;
}

bool stepper_busy() { return running || current != nullptr || !block_queue.empty(); }
bool stepper_running() { return running; }

void stepper_hold() {
  uint8_t sreg = SREG;
  cli();
  if (running && hold == 0) hold = 1;
  SREG = sreg;
}

bool stepper_hold_complete() { return hold == 2; }

void stepper_resume() {
  uint8_t sreg = SREG;
  cli();
  if (hold == 2) {
    hold = 0;
    if (current) {
      rate = current->start_rate;
      ramp_origin = events_done;  // a new ramp from rest
      interval_ticks = ticks_for(rate);
      limit_prev = limits_read();
      timer_start(interval_ticks);
    }
  } else if (hold == 1) {
    hold = 0;  // not yet at rest: ramp up again from the present speed
    if (current) {
      float v0 = current->start_rate;
      float back = (rate * rate - v0 * v0) / (2.0f * current->accel);
      ramp_origin = back < static_cast<float>(events_done)
                        ? events_done - static_cast<uint32_t>(back) : 0;
    }
  }
  SREG = sreg;
}

void stepper_get_position(int32_t out[N_AXIS]) {
  uint8_t sreg = SREG;
  cli();
  for (uint8_t k = 0; k < N_AXIS; k++) out[k] = position[k];
  SREG = sreg;
}

void stepper_set_position(uint8_t axis, int32_t steps) {
  uint8_t sreg = SREG;
  cli();
  position[axis] = steps;
  SREG = sreg;
}

uint8_t stepper_take_alarm() {
  uint8_t sreg = SREG;
  cli();
  uint8_t a = alarm;
  alarm = 0;
  SREG = sreg;
  return a;
}

bool stepper_stopped_by_switch() { return stopped_by_switch; }
void stepper_set_homing(bool on) { homing = on; }
