"""The Grbl 1.1 serial protocol, independent of any transport: codes, meanings, line parsing.

The bench's stage controller (bench_fw/, see bench_fw/PROTOCOL.md) speaks a subset of Grbl 1.1,
and a stock grbl-Mega board speaks all of it; `twin.stage.controller` uses this module for both.
Positions in this module are in machine units as Grbl reports them (mm, or deg for the rotary
axis); conversion to SI happens in the driver.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

#: error:N meanings (Grbl 1.1 numbering). The bench firmware emits the ones marked in
#: PROTOCOL.md; the rest are here so a stock Grbl's replies read clearly too.
ERRORS: dict[int, str] = {
    1: "expected a command letter: a G-code word is a letter followed by a number",
    2: "bad number format, or a value out of range for that setting",
    3: "unrecognised or unsupported '$' system command",
    4: "negative value where a positive one is required",
    5: "homing is not enabled ($22=0)",
    6: "minimum step pulse time must be at least 3 us",
    7: "EEPROM read failed: settings reset to defaults",
    8: "'$' command refused while the machine is not idle",
    9: "G-code locked out during an alarm or jog: home ($H) or unlock ($X) first",
    10: "soft limits cannot be enabled without homing",
    11: "line too long: rejected whole, nothing of it was executed",
    12: "step rate would exceed the controller's maximum",
    13: "safety door open",
    14: "build info or startup line too long",
    15: "target beyond the machine's travel (soft limit): the move was refused, nothing moved",
    16: "invalid jog command",
    17: "laser mode requires PWM output",
    20: "unsupported or invalid G-code command",
    21: "two commands from the same modal group in one line",
    22: "feed rate not set (G1 needs F)",
    23: "G-code command requires an integer value",
    24: "two G-code commands that both need the axis words",
    25: "G-code word repeated in the line",
    26: "no axis words for a command that needs them",
    27: "invalid line number",
    28: "value word missing (for example G4 without P)",
    29: "G59.x work coordinate systems are not supported",
    30: "G53 only works with G0 and G1",
    31: "axis words in a line whose command does not use them",
    32: "G2/G3 arcs need at least one in-plane axis word",
    33: "motion command target is invalid",
    34: "arc radius value is invalid",
    35: "G2/G3 arcs need at least one in-plane offset word",
    36: "unused value words in the line",
    37: "G43.1 tool offset not on the configured axis",
    38: "tool number too large",
}

#: ALARM:N meanings (Grbl 1.1 numbering).
ALARMS: dict[int, str] = {
    1: "hard limit: a limit switch was hit during a move and the motors stopped dead; "
    "position is likely lost, re-home ($H)",
    2: "soft limit: a motion target exceeded the machine travel (position kept; unlock with $X)",
    3: "reset while in motion: position is likely lost, re-home ($H)",
    4: "probe fail: probe not in the expected initial state",
    5: "probe fail: probe did not trigger within the programmed travel",
    6: "homing fail: reset during the homing cycle",
    7: "homing fail: safety door opened during homing",
    8: "homing fail: the switch did not release when pulling off; check the wiring or raise $27",
    9: "homing fail: no limit switch found within the search distance; check the switch wiring",
    10: "homing fail: second dual-axis switch not found",
}

#: $N setting meanings and units (Grbl 1.1 numbering, after grbl-Mega's setting_codes table).
#: Axis settings ($100..$13x) are built by `setting_meaning`, whose unit depends on the axis.
SETTINGS: dict[int, tuple[str, str]] = {
    0: ("step pulse time", "us"),
    1: ("step idle delay (255 = keep the drivers enabled)", "ms"),
    2: ("step pulse invert", "mask"),
    3: ("step direction invert", "mask"),
    4: ("invert the drivers' enable pin", "bool"),
    5: ("invert the limit inputs", "bool"),
    6: ("invert the probe input", "bool"),
    10: ("status report options", "mask"),
    11: ("junction deviation", "mm"),
    12: ("arc tolerance", "mm"),
    13: ("report in inches", "bool"),
    20: ("soft limits", "bool"),
    21: ("hard limits", "bool"),
    22: ("homing cycle", "bool"),
    23: ("homing direction (bit set = toward the min end)", "mask"),
    24: ("homing locate feed", "units/min"),
    25: ("homing search rate", "units/min"),
    26: ("homing switch debounce", "ms"),
    27: ("homing pull-off", "units"),
    30: ("maximum spindle speed", "rpm"),
    31: ("minimum spindle speed", "rpm"),
    32: ("laser mode", "bool"),
}
_AXIS_SETTINGS = {
    10: ("steps per {unit}", "steps/{unit}"),
    11: ("maximum rate", "{unit}/min"),
    12: ("acceleration", "{unit}/s^2"),
    13: ("maximum travel", "{unit}"),
}

#: Realtime bytes: sent on their own, never followed by a newline.
STATUS_QUERY = b"?"
FEED_HOLD = b"!"
CYCLE_START = b"~"
SOFT_RESET = b"\x18"
JOG_CANCEL = b"\x85"

_BANNER = re.compile(r"^Grbl\s+(\d+\.\d+\w*)")
_ERROR = re.compile(r"^error:(\d+)$")
_ALARM = re.compile(r"^ALARM:(\d+)$")
_SETTING = re.compile(r"^\$(\d+)=(-?(?:\d+\.?\d*|\.\d+))")  # a number, never a bare "."
_AXES = re.compile(r"^\[AXS:(\d+):([XYZABCUVW]+)\]$")
_VERSION = re.compile(r"^\[VER:([^:\]]*):?(.*)\]$")


def error_meaning(code: int) -> str:
    """The meaning of Grbl's ``error:code``."""
    return ERRORS.get(code, f"unknown Grbl error {code}")


def alarm_meaning(code: int) -> str:
    """The meaning of Grbl's ``ALARM:code``."""
    return ALARMS.get(code, f"unknown Grbl alarm {code}")


@dataclass(frozen=True)
class GrblStatus:
    """One realtime status report, ``<State|MPos:...|FS:...|Pn:...>``.

    state: "Idle", "Run", "Hold", "Home", "Alarm", "Jog", "Door", "Check" or "Sleep".
    substate: the number after the colon (``Hold:0`` = at rest, ``Hold:1`` = decelerating).
    mpos: machine position per axis, in machine units (mm / deg), in the controller's axis order.
    pins: the letters of the inputs that read active (``Pn:XA``), "" if none.
    fields: every field as text, for anything else a controller reports.
    """

    state: str
    substate: int | None
    mpos: tuple[float, ...]
    feed: float | None = None
    pins: str = ""
    fields: dict[str, str] = field(default_factory=dict)


def parse_status(line: str) -> GrblStatus:
    """Parse a status report line; raises ValueError if it is not one."""
    line = line.strip()
    if not (line.startswith("<") and line.endswith(">")):
        raise ValueError(f"not a Grbl status report: {line!r}")
    parts = line[1:-1].split("|")
    state, _, sub = parts[0].partition(":")
    fields: dict[str, str] = {}
    for part in parts[1:]:
        key, _, value = part.partition(":")
        fields[key] = value
    mpos_text = fields.get("MPos")
    if mpos_text is None:
        if "WPos" in fields and "WCO" in fields:
            w = [float(v) for v in fields["WPos"].split(",")]
            o = [float(v) for v in fields["WCO"].split(",")]
            mpos = tuple(a + b for a, b in zip(w, o, strict=True))
        else:
            raise ValueError(f"status report without MPos (set $10=1 on a stock Grbl): {line!r}")
    else:
        mpos = tuple(float(v) for v in mpos_text.split(","))
    feed = None
    for key in ("FS", "F"):
        if key in fields:
            feed = float(fields[key].split(",")[0])
            break
    return GrblStatus(
        state=state,
        substate=int(sub) if sub.isdigit() else None,
        mpos=mpos,
        feed=feed,
        pins=fields.get("Pn", ""),
        fields=fields,
    )


def banner_version(line: str) -> str | None:
    """The Grbl version in a start-up banner line (``Grbl 1.1h ['$' for help]``), else None."""
    m = _BANNER.match(line.strip())
    return m.group(1) if m else None


def error_code(line: str) -> int | None:
    """N for an ``error:N`` line, else None."""
    m = _ERROR.match(line.strip())
    return int(m.group(1)) if m else None


def alarm_code(line: str) -> int | None:
    """N for an ``ALARM:N`` line, else None."""
    m = _ALARM.match(line.strip())
    return int(m.group(1)) if m else None


def parse_setting(line: str) -> tuple[int, float] | None:
    """(N, value) for a ``$N=value`` line of a ``$$`` listing, else None."""
    m = _SETTING.match(line.strip())
    return (int(m.group(1)), float(m.group(2))) if m else None


def setting_meaning(number: int, axis_letters: str = "XYZ", units: str = "mm") -> tuple[str, str]:
    """(meaning, unit) of setting $number. Axis settings $1Nk name axis_letters[k] in `units`
    (one unit per letter: "mm", "deg"; a single unit applies to every axis)."""
    if number in SETTINGS:
        return SETTINGS[number]
    group, index = divmod(number, 10)
    if group in _AXIS_SETTINGS and index < len(axis_letters):
        unit = units.split(",")[index] if "," in units else units
        meaning, unit_text = _AXIS_SETTINGS[group]
        letter = axis_letters[index]
        return f"{letter} {meaning.format(unit=unit)}", unit_text.format(unit=unit)
    return ("not a Grbl 1.1 setting", "")


def parse_axes(line: str) -> str | None:
    """The axis letters of an ``[AXS:count:letters]`` line of ``$I`` (bench_fw, grblHAL), else
    None."""
    m = _AXES.match(line.strip())
    return m.group(2) if m and int(m.group(1)) == len(m.group(2)) else None


def parse_version(line: str) -> str | None:
    """The version text of a ``[VER:1.1g.20180813:]`` line of ``$I``, else None."""
    m = _VERSION.match(line.strip())
    return m.group(1) if m else None


def format_number(value: float) -> str:
    """A number as G-code text: fixed point, 6 decimals, no exponent (a step of 1/800 deg or
    1/400 mm is written exactly)."""
    text = f"{value:.6f}".rstrip("0").rstrip(".")
    return "0" if text in ("-0", "") else text
