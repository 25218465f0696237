// The line protocol: collecting bytes into lines, and parsing a line into a command.
// Pure C++ (no AVR registers), compiled into the host-side unit tests as well.
#ifndef BENCH_PROTOCOL_H
#define BENCH_PROTOCOL_H

#include <stdint.h>
#include "codes.h"
#include "config.h"

// Realtime bytes, acted on as they arrive and never part of a line.
#define RT_STATUS_REPORT '?'
#define RT_FEED_HOLD '!'
#define RT_CYCLE_START '~'
#define RT_RESET 0x18
#define RT_JOG_CANCEL 0x85  // Grbl 1.1's extended realtime byte

enum LineEvent : uint8_t { LINE_NONE = 0, LINE_READY, LINE_OVERFLOW };

// Builds one line from the byte stream: upper-cases, drops spaces, control bytes, bytes >= 0x7F
// and comments ("(...)" and ";" to the end). "\r\n" ends one line, not two. A line longer than
// LINE_BUFFER_SIZE-1 is flagged and rejected whole when its end arrives.
class LineCollector {
 public:
  LineCollector() { reset(); }
  void reset();
  // Feeds one byte; on LINE_READY the line is in line() (NUL-terminated) until the next feed.
  LineEvent feed(char c);
  // Marks the line being collected as damaged (bytes were lost): it ends as LINE_OVERFLOW.
  void mark_overflow() { overflow_ = true; }
  const char *line() const { return buf_; }

 private:
  char buf_[LINE_BUFFER_SIZE];
  uint8_t len_;
  bool overflow_;
  bool paren_;
  bool semicolon_;
  bool last_cr_;
};

enum MotionMode : uint8_t { MOTION_RAPID = 0, MOTION_LINEAR = 1 };

// A number exactly as written: mantissa x 10^exponent (at most 9 significant digits kept). Axis
// words stay in this form until they are turned into steps with integer arithmetic
// (decimal_to_steps), so that single precision never moves a target by a step.
struct Decimal {
  int32_t mantissa;
  int8_t exponent;
};

// Modal state kept between lines (G0/G1, G90/G91, F).
struct ParserState {
  MotionMode motion;
  bool absolute;
  float feed;  // units/min; 0 = not set yet
};

void parser_state_reset(ParserState &st);

enum CommandKind : uint8_t {
  CMD_EMPTY = 0,       // nothing to do (empty line, or modal words only)
  CMD_MOVE,            // axis words: a move in the block's motion mode
  CMD_DWELL,           // G4 P<seconds>
  CMD_SYS_HELP,        // $
  CMD_SYS_SETTINGS,    // $$
  CMD_SYS_SET,         // $N=value
  CMD_SYS_HOME,        // $H
  CMD_SYS_UNLOCK,      // $X
  CMD_SYS_INFO,        // $I
  CMD_SYS_STATE,       // $G
  CMD_SYS_RESTORE,     // $RST=$ / $RST=*
  CMD_SYS_PARAMS,      // $#
  CMD_SYS_STARTUP,     // $N (list the startup lines; there are none)
  CMD_SYS_CHECK,       // $C (toggle check mode)
  CMD_JOG,             // $J=<G91/G90, axis words, F>
};

struct Command {
  CommandKind kind;
  // CMD_MOVE
  MotionMode motion;
  bool absolute;
  float feed;                 // units/min (G1), 0 for G0
  bool has_axis[N_AXIS];
  float axis[N_AXIS];         // units as written (absolute or incremental per `absolute`)
  Decimal axis_dec[N_AXIS];   // the same, exactly as written
  // CMD_DWELL
  float dwell_s;
  // CMD_SYS_SET
  uint16_t setting;
  float value;
  // The modal state to keep once the command has been carried out (commit only on success).
  ParserState next;
};

// Parses a collected line. On an error nothing of the line may be acted on, and `st` is unchanged.
Status parse_line(const char *line, const ParserState &st, Command &out);

// Reads a decimal number (optional sign, digits, optional point; no exponent) at line[*i].
// Advances *i past it. Returns false for a malformed number.
bool read_float(const char *line, uint8_t *i, float *out);
bool read_decimal(const char *line, uint8_t *i, Decimal *out);
float decimal_to_float(const Decimal &d);

#endif
