// Line collection and parsing of the Grbl subset; see PROTOCOL.md for the grammar and the codes.
#include "protocol.h"

#include <string.h>

void LineCollector::reset() {
  len_ = 0;
  buf_[0] = 0;
  overflow_ = paren_ = semicolon_ = last_cr_ = false;
}

LineEvent LineCollector::feed(char ch) {
  uint8_t c = static_cast<uint8_t>(ch);
  if (c == '\n' || c == '\r') {
    bool skip = (c == '\n' && last_cr_);  // "\r\n" is one line end
    last_cr_ = (c == '\r');
    if (skip) return LINE_NONE;
    bool over = overflow_;
    buf_[len_] = 0;
    len_ = 0;
    overflow_ = paren_ = semicolon_ = false;
    return over ? LINE_OVERFLOW : LINE_READY;
  }
  last_cr_ = false;
  if (semicolon_) return LINE_NONE;
  if (paren_) {
    if (c == ')') paren_ = false;
    return LINE_NONE;
  }
  if (c == '(') { paren_ = true; return LINE_NONE; }
  if (c == ';') { semicolon_ = true; return LINE_NONE; }
  if (c <= ' ' || c >= 0x7F) return LINE_NONE;  // spaces, control and non-ASCII bytes
  if (c >= 'a' && c <= 'z') c = static_cast<uint8_t>(c - 'a' + 'A');
  if (len_ >= LINE_BUFFER_SIZE - 1) {
    overflow_ = true;  // keep swallowing until the line ends, then reject it whole
    return LINE_NONE;
  }
  buf_[len_++] = static_cast<char>(c);
  return LINE_NONE;
}

void parser_state_reset(ParserState &st) {
  st.motion = MOTION_RAPID;
  st.absolute = true;
  st.feed = 0.0f;
}

bool read_decimal(const char *line, uint8_t *i, Decimal *out) {
  uint8_t p = *i;
  bool neg = false;
  if (line[p] == '-' || line[p] == '+') { neg = line[p] == '-'; p++; }
  // Accumulate the digits as an integer (exact up to 9 digits) and a power of ten.
  uint32_t mantissa = 0;
  int8_t exp = 0;
  uint8_t ndigits = 0;
  bool point = false;
  for (;; p++) {
    char c = line[p];
    if (c >= '0' && c <= '9') {
      ndigits++;
      if (mantissa < 100000000UL) {
        mantissa = mantissa * 10 + static_cast<uint8_t>(c - '0');
        if (point) exp--;
      } else if (!point) {
        if (exp < 30) exp++;  // beyond any range a setting or axis accepts: refused later
      }
    } else if (c == '.' && !point) {
      point = true;
    } else {
      break;
    }
  }
  if (ndigits == 0) return false;
  out->mantissa = neg ? -static_cast<int32_t>(mantissa) : static_cast<int32_t>(mantissa);
  out->exponent = exp;
  *i = p;
  return true;
}

float decimal_to_float(const Decimal &d) {
  // Scale once: fewer rounding errors than multiplying by 10 at every digit.
  float v = static_cast<float>(d.mantissa);
  for (int8_t e = d.exponent; e < 0; e++) v *= 0.1f;
  for (int8_t e = d.exponent; e > 0; e--) v *= 10.0f;
  return v;
}

bool read_float(const char *line, uint8_t *i, float *out) {
  Decimal d;
  if (!read_decimal(line, i, &d)) return false;
  *out = decimal_to_float(d);
  return true;
}

// The wire letters of an axis: its own (AXIS_LETTERS) and, for the rotary axis, the report slot
// it occupies (Y: grbl-Mega's second axis, where the rotary stage is wired), so a sender that only
// knows X, Y and Z jogs it as Y.
static int8_t axis_index(char letter) {
  const char *letters = AXIS_LETTERS;
  for (int8_t k = 0; k < N_AXIS; k++)
    if (letters[k] == letter) return k;
  if (letter == AXIS_A_SLOT_LETTER) return AXIS_A;
  return -1;
}

static Status parse_words(const char *line, uint8_t i, const ParserState &st, bool jog,
                          Command &out);

static Status parse_system(const char *line, const ParserState &st, Command &out) {
  // line[0] == '$'
  if (line[1] == 0) { out.kind = CMD_SYS_HELP; return STATUS_OK; }
  if (line[1] == 'J') {
    if (line[2] != '=') return STATUS_INVALID_STATEMENT;
    return parse_words(line, 3, st, true, out);
  }
  if (line[2] == 0) {
    switch (line[1]) {
      case '$': out.kind = CMD_SYS_SETTINGS; return STATUS_OK;
      case 'H': out.kind = CMD_SYS_HOME; return STATUS_OK;
      case 'X': out.kind = CMD_SYS_UNLOCK; return STATUS_OK;
      case 'I': out.kind = CMD_SYS_INFO; return STATUS_OK;
      case 'G': out.kind = CMD_SYS_STATE; return STATUS_OK;
      case '#': out.kind = CMD_SYS_PARAMS; return STATUS_OK;
      case 'N': out.kind = CMD_SYS_STARTUP; return STATUS_OK;
      case 'C': out.kind = CMD_SYS_CHECK; return STATUS_OK;
    }
    if (line[1] < '0' || line[1] > '9') return STATUS_INVALID_STATEMENT;
  }
  if (strcmp(line, "$RST=$") == 0 || strcmp(line, "$RST=*") == 0) {
    out.kind = CMD_SYS_RESTORE;
    return STATUS_OK;
  }
  // $N=value
  uint8_t i = 1;
  if (line[i] < '0' || line[i] > '9') return STATUS_INVALID_STATEMENT;
  uint16_t n = 0;
  while (line[i] >= '0' && line[i] <= '9') {
    n = static_cast<uint16_t>(n * 10 + (line[i] - '0'));
    if (n > 999) return STATUS_INVALID_STATEMENT;
    i++;
  }
  if (line[i] != '=') return STATUS_INVALID_STATEMENT;
  i++;
  Decimal d;
  if (!read_decimal(line, &i, &d) || line[i] != 0) return STATUS_BAD_NUMBER_FORMAT;
  out.kind = CMD_SYS_SET;
  out.setting = n;
  out.value = decimal_to_float(d);
  return STATUS_OK;
}

Status parse_line(const char *line, const ParserState &st, Command &out) {
  memset(&out, 0, sizeof(out));
  out.next = st;
  out.kind = CMD_EMPTY;
  if (line[0] == '$') return parse_system(line, st, out);
  return parse_words(line, 0, st, false, out);
}

// The words of a G-code line, or of a jog ($J=...) from line[i]. A jog takes only G90/G91, G21,
// G94, axis words, F (required) and N, like Grbl's; it never changes the modal state.
static Status parse_words(const char *line, uint8_t i, const ParserState &st, bool jog,
                          Command &out) {
  bool seen_motion = false, seen_distance = false, seen_units = false, seen_feedmode = false;
  bool seen_dwell = false, seen_f = false, seen_p = false, seen_n = false;
  float p_value = 0.0f, jog_feed = 0.0f;
  ParserState next = st;
  while (line[i]) {
    char letter = line[i];
    if (letter < 'A' || letter > 'Z') return STATUS_EXPECTED_COMMAND_LETTER;
    i++;
    Decimal d;
    if (!read_decimal(line, &i, &d)) return STATUS_BAD_NUMBER_FORMAT;
    float v = decimal_to_float(d);
    int8_t axis = axis_index(letter);
    if (axis >= 0) {
      if (out.has_axis[axis]) return STATUS_GCODE_WORD_REPEATED;
      out.has_axis[axis] = true;
      out.axis[axis] = v;
      out.axis_dec[axis] = d;
      continue;
    }
    switch (letter) {
      case 'G': {
        if (v < 0.0f || v > 255.0f || static_cast<float>(static_cast<uint8_t>(v)) != v)
          return jog ? STATUS_INVALID_JOG_COMMAND : STATUS_GCODE_UNSUPPORTED_COMMAND;
        switch (static_cast<uint8_t>(v)) {
          case 0: case 1:
            if (jog) return STATUS_INVALID_JOG_COMMAND;
            if (seen_motion) return STATUS_GCODE_MODAL_GROUP_VIOLATION;
            seen_motion = true;
            next.motion = v == 0.0f ? MOTION_RAPID : MOTION_LINEAR;
            break;
          case 4:
            if (jog) return STATUS_INVALID_JOG_COMMAND;
            if (seen_dwell) return STATUS_GCODE_MODAL_GROUP_VIOLATION;
            seen_dwell = true;
            break;
          case 90: case 91:
            if (seen_distance) return STATUS_GCODE_MODAL_GROUP_VIOLATION;
            seen_distance = true;
            next.absolute = v == 90.0f;
            break;
          case 21:  // millimetres (degrees on A): the only units there are
            if (seen_units) return STATUS_GCODE_MODAL_GROUP_VIOLATION;
            seen_units = true;
            break;
          case 94:  // feed in units per minute: the only feed mode there is
            if (seen_feedmode) return STATUS_GCODE_MODAL_GROUP_VIOLATION;
            seen_feedmode = true;
            break;
          default:
            return jog ? STATUS_INVALID_JOG_COMMAND : STATUS_GCODE_UNSUPPORTED_COMMAND;
        }
        break;
      }
      case 'F':
        if (seen_f) return STATUS_GCODE_WORD_REPEATED;
        seen_f = true;
        if (v < 0.0f) return STATUS_NEGATIVE_VALUE;
        if (jog) jog_feed = v;
        else next.feed = v;
        break;
      case 'P':
        if (jog) return STATUS_INVALID_JOG_COMMAND;
        if (seen_p) return STATUS_GCODE_WORD_REPEATED;
        seen_p = true;
        if (v < 0.0f) return STATUS_NEGATIVE_VALUE;
        p_value = v;
        break;
      case 'N':
        if (seen_n) return STATUS_GCODE_WORD_REPEATED;
        seen_n = true;
        if (v < 0.0f || v > 10000000.0f || static_cast<float>(static_cast<int32_t>(v)) != v)
          return STATUS_GCODE_INVALID_LINE_NUMBER;
        break;
      default:
        return jog ? STATUS_INVALID_JOG_COMMAND : STATUS_GCODE_UNSUPPORTED_COMMAND;
    }
  }

  bool any_axis = false;
  for (uint8_t k = 0; k < N_AXIS; k++) any_axis |= out.has_axis[k];

  if (jog) {
    if (!seen_f || jog_feed <= 0.0f) return STATUS_GCODE_UNDEFINED_FEED_RATE;
    if (!any_axis) return STATUS_GCODE_NO_AXIS_WORDS;
    out.kind = CMD_JOG;
    out.motion = MOTION_LINEAR;
    out.absolute = next.absolute;
    out.feed = jog_feed;
    out.next = st;  // a jog leaves the parser's modal state as it was
    return STATUS_OK;
  }
  if (seen_dwell) {
    if (!seen_p) return STATUS_GCODE_VALUE_WORD_MISSING;
    if (any_axis) return STATUS_GCODE_AXIS_WORDS_EXIST;
    out.kind = CMD_DWELL;
    out.dwell_s = p_value;
  } else if (seen_p) {
    return STATUS_GCODE_UNUSED_WORDS;
  } else if (any_axis) {
    if (next.motion == MOTION_LINEAR && next.feed <= 0.0f) return STATUS_GCODE_UNDEFINED_FEED_RATE;
    out.kind = CMD_MOVE;
    out.motion = next.motion;
    out.absolute = next.absolute;
    out.feed = next.motion == MOTION_LINEAR ? next.feed : 0.0f;
  }
  out.next = next;
  return STATUS_OK;
}
