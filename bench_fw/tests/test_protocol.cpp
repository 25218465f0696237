// Line collection and parsing: every grammar rule and every error code the parser can return.
#include <string>

#include "check.h"
#include "protocol.h"

static std::string collect(const char *bytes, LineEvent *last = nullptr) {
  LineCollector lc;
  std::string out;
  LineEvent ev = LINE_NONE;
  for (const char *p = bytes; *p; p++) {
    ev = lc.feed(*p);
    if (ev == LINE_READY) out += std::string(lc.line()) + "|";
    if (ev == LINE_OVERFLOW) out += "<overflow>|";
  }
  if (last) *last = ev;
  return out;
}

TEST(collector_normalises_lines) {
  CHECK(collect("g0 x1.5 a-2\n") == "G0X1.5A-2|");
  CHECK(collect("G1 (comment) X1 ; trailing\n") == "G1X1|");
  CHECK(collect("X1\r\nX2\rX3\n") == "X1|X2|X3|");   // \r\n is one line end
  CHECK(collect("\n") == "|");                        // empty line: answered ok
  CHECK(collect("X\x01\x02\x7f\xff" "1\n") == "X1|"); // control and non-ASCII bytes dropped
  CHECK(collect("$$\n") == "$$|");
}

TEST(collector_rejects_long_line_whole) {
  std::string line(LINE_BUFFER_SIZE - 1, '1');
  CHECK(collect(("X" + line.substr(1) + "\n").c_str()) == "X" + line.substr(1) + "|");
  std::string longer = "X" + std::string(LINE_BUFFER_SIZE, '1') + "\nX2\n";
  CHECK(collect(longer.c_str()) == "<overflow>|X2|");
  // Spaces and comments do not count toward the limit.
  std::string spaced = "X1" + std::string(200, ' ') + "(" + std::string(200, 'c') + ")\n";
  CHECK(collect(spaced.c_str()) == "X1|");
}

TEST(collector_marked_damaged_line) {
  LineCollector lc;
  lc.feed('X');
  lc.mark_overflow();
  lc.feed('5');
  CHECK_EQ(lc.feed('\n'), LINE_OVERFLOW);
  lc.feed('X');
  CHECK_EQ(lc.feed('\n'), LINE_READY);
}

TEST(read_float_formats) {
  struct Case { const char *s; bool ok; float v; uint8_t end; } cases[] = {
      {"1", true, 1.0f, 1},      {"-1.5", true, -1.5f, 4}, {"+.25", true, 0.25f, 4},
      {"0.0025", true, 0.0025f, 6}, {"12.", true, 12.0f, 3}, {"-", false, 0, 0},
      {".", false, 0, 0},        {"", false, 0, 0},        {"1.2.3", true, 1.2f, 3},
      {"123456789012", true, 123456789012.0f, 12},
  };
  for (auto &c : cases) {
    uint8_t i = 0;
    float v = 0;
    bool ok = read_float(c.s, &i, &v);
    CHECK_EQ(ok, c.ok);
    if (ok && c.ok) {
      CHECK_NEAR(v, c.v, std::fabs(c.v) * 1e-6 + 1e-9);
      CHECK_EQ(i, c.end);
    }
  }
}

static Status parse(const char *line, Command &cmd, ParserState st) {
  return parse_line(line, st, cmd);
}

static ParserState fresh() {
  ParserState st;
  parser_state_reset(st);
  return st;
}

TEST(parser_moves_and_modal_state) {
  Command c;
  CHECK_EQ(parse("G0X10A-5", c, fresh()), STATUS_OK);
  CHECK_EQ(c.kind, CMD_MOVE);
  CHECK_EQ(c.motion, MOTION_RAPID);
  CHECK(c.has_axis[0] && c.has_axis[1]);
  CHECK_NEAR(c.axis[0], 10.0, 1e-6);
  CHECK_NEAR(c.axis[1], -5.0, 1e-6);
  CHECK_NEAR(c.feed, 0.0, 0);
  // Power-up modal state is G0 G90: a bare axis word moves rapid, absolute.
  CHECK_EQ(parse("X1", c, fresh()), STATUS_OK);
  CHECK(c.kind == CMD_MOVE && c.absolute && c.motion == MOTION_RAPID);
  CHECK_EQ(parse("G91G1F300A2", c, fresh()), STATUS_OK);
  CHECK(c.kind == CMD_MOVE && !c.absolute && c.motion == MOTION_LINEAR);
  CHECK_NEAR(c.feed, 300.0, 1e-6);
  CHECK(c.next.feed == 300.0f && !c.next.absolute && c.next.motion == MOTION_LINEAR);
  // Modal words only: nothing to do, state carried in `next`.
  CHECK_EQ(parse("G91", c, fresh()), STATUS_OK);
  CHECK(c.kind == CMD_EMPTY && !c.next.absolute);
  CHECK_EQ(parse("G21G94F100N12", c, fresh()), STATUS_OK);
  CHECK(c.kind == CMD_EMPTY && c.next.feed == 100.0f);
  // G1 keeps a feed set on an earlier line.
  ParserState st = fresh();
  st.feed = 50.0f;
  CHECK_EQ(parse("G1X1", c, st), STATUS_OK);
  CHECK_NEAR(c.feed, 50.0, 1e-6);
}

TEST(parser_dwell) {
  Command c;
  CHECK_EQ(parse("G4P0.25", c, fresh()), STATUS_OK);
  CHECK(c.kind == CMD_DWELL);
  CHECK_NEAR(c.dwell_s, 0.25, 1e-6);
  CHECK_EQ(parse("G4", c, fresh()), STATUS_GCODE_VALUE_WORD_MISSING);
  CHECK_EQ(parse("G4P-1", c, fresh()), STATUS_NEGATIVE_VALUE);
  CHECK_EQ(parse("G4P1X2", c, fresh()), STATUS_GCODE_AXIS_WORDS_EXIST);
  CHECK_EQ(parse("P1", c, fresh()), STATUS_GCODE_UNUSED_WORDS);
}

TEST(parser_errors) {
  struct Case { const char *line; Status s; } cases[] = {
      {"1X", STATUS_EXPECTED_COMMAND_LETTER},
      {"=", STATUS_EXPECTED_COMMAND_LETTER},
      {"XA", STATUS_BAD_NUMBER_FORMAT},
      {"X", STATUS_BAD_NUMBER_FORMAT},
      {"G", STATUS_BAD_NUMBER_FORMAT},
      {"Z1", STATUS_GCODE_UNSUPPORTED_COMMAND},     // not an axis of this machine
      {"Y1A1", STATUS_GCODE_WORD_REPEATED},         // Y is the rotary axis' report slot: A again
      {"M3", STATUS_GCODE_UNSUPPORTED_COMMAND},
      {"G2X1", STATUS_GCODE_UNSUPPORTED_COMMAND},
      {"G20", STATUS_GCODE_UNSUPPORTED_COMMAND},    // inches: no
      {"G0.5X1", STATUS_GCODE_UNSUPPORTED_COMMAND},
      {"G0G1X1", STATUS_GCODE_MODAL_GROUP_VIOLATION},
      {"G90G91", STATUS_GCODE_MODAL_GROUP_VIOLATION},
      {"G1X1", STATUS_GCODE_UNDEFINED_FEED_RATE},
      {"G1F0X1", STATUS_GCODE_UNDEFINED_FEED_RATE},
      {"F-5", STATUS_NEGATIVE_VALUE},
      {"X1X2", STATUS_GCODE_WORD_REPEATED},
      {"F1F2", STATUS_GCODE_WORD_REPEATED},
      {"N1.5", STATUS_GCODE_INVALID_LINE_NUMBER},
      {"N-1", STATUS_GCODE_INVALID_LINE_NUMBER},
  };
  for (auto &c : cases) {
    Command cmd;
    Status s = parse(c.line, cmd, fresh());
    if (s != c.s) std::printf("  line %s\n", c.line);
    CHECK_EQ(s, c.s);
  }
}

TEST(parser_jog) {
  // $J= takes G90/G91, G21, G94, axis words, F (required) and N, as Grbl's jog does, and never
  // changes the modal state.
  ParserState st = fresh();
  Command c;
  CHECK(parse("$J=G91X1.5Y-2F300", c, st) == STATUS_OK && c.kind == CMD_JOG);
  CHECK(!c.absolute && c.feed == 300.0f && c.has_axis[AXIS_X] && c.has_axis[AXIS_A]);
  CHECK(c.axis_dec[AXIS_X].mantissa == 15 && c.axis_dec[AXIS_X].exponent == -1);
  CHECK(c.next.absolute && c.next.feed == 0.0f);  // G91 and F were the jog's only
  CHECK(parse("$J=A3F100", c, st) == STATUS_OK && c.absolute);
  CHECK_EQ(parse("$J=X1", c, st), STATUS_GCODE_UNDEFINED_FEED_RATE);
  CHECK_EQ(parse("$J=F100", c, st), STATUS_GCODE_NO_AXIS_WORDS);
  CHECK_EQ(parse("$J=G0X1F100", c, st), STATUS_INVALID_JOG_COMMAND);
  CHECK_EQ(parse("$J=G4P1", c, st), STATUS_INVALID_JOG_COMMAND);
  CHECK_EQ(parse("$J=M3X1F10", c, st), STATUS_INVALID_JOG_COMMAND);
  CHECK_EQ(parse("$J=X1F-1", c, st), STATUS_NEGATIVE_VALUE);
}

TEST(parser_error_leaves_state) {
  // An error must not leak modal changes: `next` is only taken on success, and parse_line does
  // not touch the state it was given.
  ParserState st = fresh();
  Command c;
  CHECK(parse("G91G1X1", c, st) == STATUS_GCODE_UNDEFINED_FEED_RATE);
  CHECK(st.absolute && st.motion == MOTION_RAPID && st.feed == 0.0f);
}

TEST(parser_system_commands) {
  Command c;
  CHECK(parse("$", c, fresh()) == STATUS_OK && c.kind == CMD_SYS_HELP);
  CHECK(parse("$$", c, fresh()) == STATUS_OK && c.kind == CMD_SYS_SETTINGS);
  CHECK(parse("$H", c, fresh()) == STATUS_OK && c.kind == CMD_SYS_HOME);
  CHECK(parse("$X", c, fresh()) == STATUS_OK && c.kind == CMD_SYS_UNLOCK);
  CHECK(parse("$I", c, fresh()) == STATUS_OK && c.kind == CMD_SYS_INFO);
  CHECK(parse("$G", c, fresh()) == STATUS_OK && c.kind == CMD_SYS_STATE);
  CHECK(parse("$RST=$", c, fresh()) == STATUS_OK && c.kind == CMD_SYS_RESTORE);
  CHECK(parse("$110=450.5", c, fresh()) == STATUS_OK && c.kind == CMD_SYS_SET);
  CHECK(c.setting == 110 && c.value == 450.5f);
  CHECK_EQ(parse("$Q", c, fresh()), STATUS_INVALID_STATEMENT);
  CHECK(parse("$#", c, fresh()) == STATUS_OK && c.kind == CMD_SYS_PARAMS);
  CHECK(parse("$N", c, fresh()) == STATUS_OK && c.kind == CMD_SYS_STARTUP);
  CHECK(parse("$C", c, fresh()) == STATUS_OK && c.kind == CMD_SYS_CHECK);
  CHECK_EQ(parse("$N0=G0X1", c, fresh()), STATUS_INVALID_STATEMENT);  // no startup lines
  CHECK_EQ(parse("$J", c, fresh()), STATUS_INVALID_STATEMENT);
  CHECK_EQ(parse("$HX", c, fresh()), STATUS_INVALID_STATEMENT);
  CHECK_EQ(parse("$1", c, fresh()), STATUS_INVALID_STATEMENT);
  CHECK_EQ(parse("$1000=1", c, fresh()), STATUS_INVALID_STATEMENT);
  CHECK_EQ(parse("$1=", c, fresh()), STATUS_BAD_NUMBER_FORMAT);
  CHECK_EQ(parse("$1=2x", c, fresh()), STATUS_BAD_NUMBER_FORMAT);
}
