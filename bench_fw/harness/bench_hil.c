/* bench_hil: the stage controller's firmware in simavr, hardware in the loop without hardware.
 *
 * Runs the real bench_fw.elf on a simulated ATmega2560 at 16 MHz, paced to real time, and:
 *   - bridges UART0 to a pseudo-terminal that pyserial opens like /dev/ttyACM0; the first line on
 *     stdout is the pty's path;
 *   - resets the MCU when a host opens the pty, as a real Mega's DTR auto-reset does (after a
 *     100 ms "bootloader" pause, discarding what the host sent meanwhile) - unless the host
 *     cleared HUPCL before it last closed the port, which keeps DTR up on a real tty;
 *   - counts the step pulses on the STEP/DIR pins (pins.h) into each stage's physical position;
 *   - drives the limit-switch inputs from that position: a switch reads hit (pin low) while the
 *     stage is beyond its trip point;
 *   - publishes the live positions in a small shared-memory file (--shm, layout below) that
 *     twin/hil.py maps.
 *
 * Why a harness and not the stock `simavr` binary (simavr 1.6, Debian 12, see DESIGN.md): it has
 * no pty option, cannot be told the MCU of an Arduino ELF, its uart_pty part keeps the slave
 * end open (so a host opening the port cannot be seen) and uses a fixed path, and free-running
 * it is ~4x faster than real time, which breaks every host-side timeout.
 *
 * Shared memory file (little-endian, 192 bytes), a seqlock: read `seq`, the fields, `seq` again;
 * retry if it changed or is odd. Bytes 0..175 are the harness's; the host writes only 176.
 *   0  char[8]   magic "AIMBHIL1"
 *   8  uint32    seq
 *  12  uint32    resets          MCU resets so far (power-up counts as none)
 *  16  int64[2]  steps           physical position of X, A in steps (0 = homed machine zero)
 *  32  uint64    cycle           simulated CPU cycles since start (16 MHz)
 *  40  uint64[2] last_step_cycle cycle of each axis' latest step pulse
 *  56  uint64[2] pulses          step pulses seen per axis (either direction)
 *  72  uint32    limits          bit 0: X switch hit, bit 1: A switch hit
 *  76  uint32    frequency       Hz
 *  80  int64[2]  trip_min        a switch reads hit while steps < trip_min ...
 *  96  int64[2]  trip_max        ... or steps > trip_max
 * 112  uint64    last_rx_cycle  cycle at which the host's latest byte entered the UART
 * 120  uint64    rx_bytes       bytes from the host fed to the UART so far
 * 128  uint64    idle_cycles    cycles the MCU spent asleep (idle mode): 1 - idle/cycle = CPU load
 * 136  int64[2]  steps_min      lowest position of each axis since the last mark ...
 * 152  int64[2]  steps_max      ... and highest: where the stages really went, between polls
 * 168  uint32    mark_ack       the last mark request the extremes were reset for
 * 172  uint32    (padding)
 * 176  uint32    mark_request   written by the host: a new value resets the extremes to here
 * 192            (size)
 */
#define _GNU_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <getopt.h>
#include <poll.h>
#include <pty.h>
#include <signal.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/mman.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#include <simavr/avr_ioport.h>
#include <simavr/avr_uart.h>
#include <simavr/sim_avr.h>
#include <simavr/sim_elf.h>
#include <simavr/sim_irq.h>

#include "../src/pins.h"

#define N_AXIS 2
#define FREQ 16000000UL
#define SHM_SIZE 192

struct shm_layout {
  char magic[8];
  uint32_t seq;
  uint32_t resets;
  int64_t steps[N_AXIS];
  uint64_t cycle;
  uint64_t last_step_cycle[N_AXIS];
  uint64_t pulses[N_AXIS];
  uint32_t limits;
  uint32_t frequency;
  int64_t trip_min[N_AXIS];
  int64_t trip_max[N_AXIS];
  uint64_t last_rx_cycle;
  uint64_t rx_bytes;
  uint64_t idle_cycles;
  int64_t steps_min[N_AXIS];
  int64_t steps_max[N_AXIS];
  uint32_t mark_ack;
  uint32_t pad;
  uint32_t mark_request; /* the host's: never copied from `local` */
  uint32_t pad2[3];
};

_Static_assert(sizeof(struct shm_layout) == SHM_SIZE, "the shared-memory layout above");

static avr_t *avr;
static int master_fd = -1;
static struct shm_layout local;      /* the state; mirrored to *shared under the seqlock */
static struct shm_layout *shared;
static int dir_level[N_AXIS];
static int step_level[N_AXIS];
static int limit_level[N_AXIS] = {-1, -1};  /* last level driven on the limit pins */
static avr_irq_t *limit_irq[N_AXIS];
static avr_irq_t *uart_in_irq;
static int uart_ready = 1;
static uint64_t cycle_offset;        /* cycles before the last reset (avr_reset zeroes avr->cycle) */
static volatile sig_atomic_t stop_requested;

static uint8_t in_buf[4096];
static size_t in_len;
static uint8_t out_buf[4096];
static size_t out_len;

static const int kStepBit[N_AXIS] = {STEP_BIT_X, STEP_BIT_A};
static const int kDirBit[N_AXIS] = {DIR_BIT_X, DIR_BIT_A};
static const int kLimitBit[N_AXIS] = {LIMIT_BIT_X, LIMIT_BIT_A};

static uint64_t now_cycle(void) { return cycle_offset + avr->cycle; }

static void publish(void) {
  if (!shared) return;
  local.cycle = now_cycle();
  __atomic_store_n(&shared->seq, shared->seq + 1, __ATOMIC_RELEASE); /* odd: writing */
  __atomic_thread_fence(__ATOMIC_SEQ_CST);
  memcpy(&shared->resets, &local.resets,
         offsetof(struct shm_layout, mark_request) - offsetof(struct shm_layout, resets));
  __atomic_thread_fence(__ATOMIC_SEQ_CST);
  __atomic_store_n(&shared->seq, shared->seq + 1, __ATOMIC_RELEASE); /* even: stable */
}

/* Limit switches are normally open to ground with the MCU's pull-up: hit = pin low. */
static void drive_limits(int force) {
  for (int k = 0; k < N_AXIS; k++) {
    int hit = local.steps[k] < local.trip_min[k] || local.steps[k] > local.trip_max[k];
    int level = hit ? 0 : 1;
    if (hit) local.limits |= 1u << k;
    else local.limits &= ~(1u << k);
    if (force || level != limit_level[k]) {
      if (force) avr_raise_irq(limit_irq[k], !level); /* the irq filters repeats: toggle first */
      avr_raise_irq(limit_irq[k], level);
      limit_level[k] = level;
    }
  }
}

static void on_step(struct avr_irq_t *irq, uint32_t value, void *param) {
  (void)irq;
  int k = (int)(intptr_t)param;
  int rising = value && !step_level[k];
  step_level[k] = value ? 1 : 0;
  if (!rising) return;
  local.steps[k] += dir_level[k] ? -1 : 1; /* DIR high = negative (pins.h, $3 = 0) */
  if (local.steps[k] < local.steps_min[k]) local.steps_min[k] = local.steps[k];
  if (local.steps[k] > local.steps_max[k]) local.steps_max[k] = local.steps[k];
  local.pulses[k]++;
  local.last_step_cycle[k] = now_cycle();
  drive_limits(0); /* synchronously: the firmware reads the switch right after its step */
  publish();
}

static void on_dir(struct avr_irq_t *irq, uint32_t value, void *param) {
  (void)irq;
  dir_level[(int)(intptr_t)param] = value ? 1 : 0;
}

static void on_uart_out(struct avr_irq_t *irq, uint32_t value, void *param) {
  (void)irq;
  (void)param;
  if (out_len < sizeof(out_buf)) out_buf[out_len++] = (uint8_t)value;
}

static void on_xon(struct avr_irq_t *irq, uint32_t value, void *param) {
  (void)irq; (void)value; (void)param;
  uart_ready = 1;
}

static void on_xoff(struct avr_irq_t *irq, uint32_t value, void *param) {
  (void)irq; (void)value; (void)param;
  uart_ready = 0;
}

static void uart_quiet(void) {
  /* No console echo of the UART, and no sleeping when the firmware polls it. */
  uint32_t flags = 0;
  avr_ioctl(avr, AVR_IOCTL_UART_GET_FLAGS('0'), &flags);
  flags &= ~(AVR_UART_FLAG_STDIO | AVR_UART_FLAG_POLL_SLEEP);
  avr_ioctl(avr, AVR_IOCTL_UART_SET_FLAGS('0'), &flags);
}

static uint64_t wall_ns(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return (uint64_t)ts.tv_sec * 1000000000ull + (uint64_t)ts.tv_nsec;
}

static void sleep_ns(uint64_t ns) {
  struct timespec ts = {(time_t)(ns / 1000000000ull), (long)(ns % 1000000000ull)};
  nanosleep(&ts, NULL);
}

static void mcu_reset(void) {
  cycle_offset += avr->cycle;
  avr_reset(avr);
  avr->cycle = 0;
  uart_quiet();
  uart_ready = 1;
  in_len = 0;
  out_len = 0;
  for (int k = 0; k < N_AXIS; k++) step_level[k] = 0, dir_level[k] = 0;
  drive_limits(1); /* pull-ups read 0 after a reset until the pins are driven again */
  local.resets++;
  publish();
}

/* The firmware sleeps (idle mode) whenever it has nothing to do. simavr then jumps to the next
 * timer or interrupt event and calls avr->sleep with the skipped cycles; its default usleep()s
 * them, with the OS's oversleep each time. The pacing below keeps real time already, so skip. */
static void sleep_skip(avr_t *a, avr_cycle_count_t how_long) {
  (void)a;
  local.idle_cycles += how_long + 1; /* simavr adds 1 + how_long to the clock for a sleep */
}

/* The host asked for a new window of extremes: start it at the present position. */
static void check_mark(void) {
  if (!shared) return;
  uint32_t req = __atomic_load_n(&shared->mark_request, __ATOMIC_ACQUIRE);
  if (req == local.mark_ack) return;
  for (int k = 0; k < N_AXIS; k++) local.steps_min[k] = local.steps_max[k] = local.steps[k];
  local.mark_ack = req;
}

static void on_signal(int sig) {
  (void)sig;
  stop_requested = 1;
}

static void usage(const char *prog) {
  fprintf(stderr,
          "usage: %s [--shm PATH] [--x-start STEPS] [--a-start STEPS]\n"
          "          [--x-trip MIN,MAX] [--a-trip MIN,MAX] [--no-pace] [--no-reset-on-open]\n"
          "          FIRMWARE.elf\n"
          "Runs FIRMWARE.elf (ATmega2560, 16 MHz) with UART0 on a new pty whose path is the\n"
          "first line on stdout. Positions in steps from the homed machine zero; a switch\n"
          "reads hit while the position is < MIN or > MAX (defaults: the bench, pull-off 1).\n",
          prog);
}

static int parse_pair(const char *s, int64_t *a, int64_t *b) {
  return sscanf(s, "%ld,%ld", (long *)a, (long *)b) == 2 ? 0 : -1;
}

int main(int argc, char **argv) {
  const char *shm_path = NULL;
  int pace = 1;
  int reset_on_open = 1;
  /* Bench defaults (PROTOCOL.md): X 400 steps/mm over 100 mm, A 800 steps/deg over 60 deg,
   * 1 unit pull-off: switches trip 1 unit outside the travel. Start 20 mm / 10 deg from zero. */
  local.trip_min[0] = -400; local.trip_max[0] = 40400;
  local.trip_min[1] = -800; local.trip_max[1] = 48800;
  local.steps[0] = 8000; local.steps[1] = 8000;

  static const struct option opts[] = {
      {"shm", required_argument, 0, 's'},     {"x-start", required_argument, 0, 'x'},
      {"a-start", required_argument, 0, 'a'}, {"x-trip", required_argument, 0, 'X'},
      {"a-trip", required_argument, 0, 'A'},  {"no-pace", no_argument, 0, 'n'},
      {"no-reset-on-open", no_argument, 0, 'r'}, {"help", no_argument, 0, 'h'},
      {0, 0, 0, 0}};
  int c;
  while ((c = getopt_long(argc, argv, "h", opts, NULL)) != -1) {
    switch (c) {
      case 's': shm_path = optarg; break;
      case 'x': local.steps[0] = strtoll(optarg, NULL, 10); break;
      case 'a': local.steps[1] = strtoll(optarg, NULL, 10); break;
      case 'X': if (parse_pair(optarg, &local.trip_min[0], &local.trip_max[0])) goto bad; break;
      case 'A': if (parse_pair(optarg, &local.trip_min[1], &local.trip_max[1])) goto bad; break;
      case 'n': pace = 0; break;
      case 'r': reset_on_open = 0; break;
      case 'h': usage(argv[0]); return 0;
      default: goto bad;
    }
  }
  if (optind != argc - 1) goto bad;
  const char *elf = argv[optind];

  /* simavr's loader chats on stdout; the first stdout line must be the pty path. */
  fflush(stdout);
  int saved_stdout = dup(STDOUT_FILENO);
  dup2(STDERR_FILENO, STDOUT_FILENO);
  elf_firmware_t fw;
  memset(&fw, 0, sizeof(fw));
  if (elf_read_firmware(elf, &fw) != 0) {
    fprintf(stderr, "bench_hil: error: cannot read firmware %s (build it: make -C bench_fw)\n", elf);
    return 1;
  }
  /* Arduino ELF files carry no MCU or clock: set them. */
  strcpy(fw.mmcu, "atmega2560");
  fw.frequency = FREQ;
  avr = avr_make_mcu_by_name(fw.mmcu);
  if (!avr) {
    fprintf(stderr, "bench_hil: error: simavr has no atmega2560 core\n");
    return 1;
  }
  avr_init(avr);
  avr_load_firmware(avr, &fw);
  avr->frequency = FREQ;
  avr->sleep = sleep_skip;
  uart_quiet();
  fflush(stdout);
  dup2(saved_stdout, STDOUT_FILENO);
  close(saved_stdout);

  /* The pty: raw, so the line discipline neither echoes the firmware's output back into it nor
   * translates line ends; the slave is closed so the harness sees when a host opens it. */
  struct termios raw;
  memset(&raw, 0, sizeof(raw));
  cfmakeraw(&raw);
  cfsetispeed(&raw, B115200);
  cfsetospeed(&raw, B115200);
  raw.c_cflag |= HUPCL; /* a tty's default: closing drops DTR, so the next open resets */
  int slave_fd;
  char pty_name[256];
  if (openpty(&master_fd, &slave_fd, pty_name, &raw, NULL) != 0) {
    perror("bench_hil: openpty");
    return 1;
  }
  close(slave_fd);
  fcntl(master_fd, F_SETFL, fcntl(master_fd, F_GETFL) | O_NONBLOCK);

  if (shm_path) {
    int fd = open(shm_path, O_RDWR | O_CREAT | O_TRUNC, 0644);
    if (fd < 0 || ftruncate(fd, SHM_SIZE) != 0) {
      fprintf(stderr, "bench_hil: error: cannot create %s: %s\n", shm_path, strerror(errno));
      return 1;
    }
    shared = mmap(NULL, SHM_SIZE, PROT_READ | PROT_WRITE, MAP_SHARED, fd, 0);
    close(fd);
    if (shared == MAP_FAILED) {
      perror("bench_hil: mmap");
      return 1;
    }
    memset(shared, 0, SHM_SIZE);
    memcpy(shared->magic, "AIMBHIL1", 8);
  }
  local.frequency = FREQ;
  for (int k = 0; k < N_AXIS; k++) local.steps_min[k] = local.steps_max[k] = local.steps[k];

  for (int k = 0; k < N_AXIS; k++) {
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ(STEP_PORT_LETTER), kStepBit[k]),
                            on_step, (void *)(intptr_t)k);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ(DIR_PORT_LETTER), kDirBit[k]),
                            on_dir, (void *)(intptr_t)k);
    limit_irq[k] = avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ(LIMIT_PORT_LETTER), kLimitBit[k]);
  }
  avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUTPUT),
                          on_uart_out, NULL);
  avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUT_XON),
                          on_xon, NULL);
  avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUT_XOFF),
                          on_xoff, NULL);
  uart_in_irq = avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_INPUT);
  drive_limits(1);
  publish();

  signal(SIGINT, on_signal);
  signal(SIGTERM, on_signal);
  signal(SIGPIPE, SIG_IGN);
  pid_t parent = getppid();

  printf("%s\n", pty_name);
  fflush(stdout);
  fprintf(stderr, "bench_hil: %s on %s, %s\n", elf, pty_name, pace ? "real time" : "free-running");

  int host_open = 0;
  /* Whether DTR dropped when the host last closed the port (HUPCL set), so that the next open
   * raises it again and resets the board; true at start, like a board just plugged in. A host
   * that clears HUPCL (stty -hupcl; StageController.close does) keeps DTR up: no reset. */
  int dtr_dropped = 1;
  uint64_t wall0 = wall_ns(), sim0 = now_cycle();
  uint64_t service_every = FREQ / 5000; /* service the pty every 200 us of simulated time */
  uint64_t next_service = 0;
  unsigned polls = 0;

  while (!stop_requested) {
    int state = avr_run(avr);
    if (state == cpu_Done || state == cpu_Crashed) {
      fprintf(stderr, "bench_hil: the firmware stopped (state %d); resetting\n", state);
      mcu_reset();
      continue;
    }
    if (avr->cycle < next_service) continue;
    next_service = avr->cycle + service_every;

    /* Output from the firmware to the host (dropped while no host has the port open). */
    if (out_len) {
      if (host_open) {
        ssize_t n = write(master_fd, out_buf, out_len);
        if (n > 0) {
          memmove(out_buf, out_buf + n, out_len - (size_t)n);
          out_len -= (size_t)n;
        }
      } else {
        out_len = 0;
      }
    }

    /* Host side: open/close of the slave, and input. */
    struct pollfd pfd = {master_fd, POLLIN, 0};
    poll(&pfd, 1, 0);
    int open_now = !(pfd.revents & POLLHUP);
    if (open_now && !host_open && (!reset_on_open || !dtr_dropped)) {
      host_open = 1; /* no DTR edge (or no auto-reset circuit): the board just keeps running */
      fprintf(stderr, "bench_hil: host opened the port (no reset)\n");
    } else if (open_now && !host_open) {
      /* A host opened the port: pause like the Mega's bootloader, then reset the MCU. */
      host_open = 1;
      sleep_ns(100000000ull);
      tcflush(master_fd, TCIFLUSH);
      mcu_reset();
      fprintf(stderr, "bench_hil: host opened the port: MCU reset\n");
      next_service = 0;
      wall0 = wall_ns();
      sim0 = now_cycle();
      continue;
    }
    if (!open_now && host_open) {
      struct termios t;
      host_open = 0;
      dtr_dropped = tcgetattr(master_fd, &t) != 0 || (t.c_cflag & HUPCL) != 0;
      fprintf(stderr, "bench_hil: host closed the port%s\n", dtr_dropped ? "" : " (DTR kept up)");
    }
    if (host_open && (pfd.revents & POLLIN) && in_len < sizeof(in_buf)) {
      ssize_t n = read(master_fd, in_buf + in_len, sizeof(in_buf) - in_len);
      if (n > 0) in_len += (size_t)n;
    }
    /* Feed the UART while its receive FIFO has room (XON); it delivers at the baud rate. */
    size_t fed = 0;
    while (fed < in_len && uart_ready) avr_raise_irq(uart_in_irq, in_buf[fed++]);
    if (fed) {
      local.last_rx_cycle = now_cycle();
      local.rx_bytes += fed;
      memmove(in_buf, in_buf + fed, in_len - fed);
      in_len -= fed;
    }

    check_mark();
    publish();

    /* Pace to real time: sleep while the simulation is ahead of the wall clock. If it falls far
     * behind (a loaded machine), re-base instead of racing to catch up. */
    if (pace) {
      uint64_t sim_ns = (now_cycle() - sim0) * 1000000000ull / FREQ;
      uint64_t wall = wall_ns() - wall0;
      if (sim_ns > wall + 1000000ull) {
        sleep_ns(sim_ns - wall);
      } else if (wall > sim_ns + 200000000ull) {
        wall0 = wall_ns();
        sim0 = now_cycle();
      }
    }
    if ((++polls & 1023) == 0 && getppid() != parent) break; /* the parent died: do not linger */
  }
  fprintf(stderr, "bench_hil: stopped\n");
  return 0;

bad:
  usage(argv[0]);
  return 2;
}
