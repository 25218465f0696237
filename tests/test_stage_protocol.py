"""The stage firmware's protocol, as command/response tables, against the real firmware in simavr
(or a real board with --port): every command, every error and alarm path, soft and hard limits,
homing, reset during a move, a flood of garbage bytes. See bench_fw/PROTOCOL.md.

Moves are kept short (the simulation runs in real time).
"""

from __future__ import annotations

import random
import re
import time
from collections.abc import Iterator

import pytest
from stage_support import STEPS_PER_DEG, STEPS_PER_MM, Bench, RawLink, bench, expect

from twin.stage import grbl

pytestmark = [pytest.mark.simavr, pytest.mark.slow]
__all__ = ["bench"]  # the fixture, re-exported for pytest

UNLOCK_MSG = re.escape("[MSG:'$H'|'$X' to unlock]")
BANNER = r"Grbl 1\.1h \[aimbench .* '\$' for help\]"


@pytest.fixture(scope="module")
def link(bench: Bench) -> Iterator[RawLink]:
    lk = RawLink(bench.url)
    lines = lk.boot_lines()  # opening the port resets the board (DTR)
    assert any(re.fullmatch(BANNER, x) for x in lines), lines
    assert lk.send("$RST=$")[-1] == "ok"  # defaults, whatever a previous run left
    yield lk
    lk.drain(quiet=0.05, limit=1.0)
    lk.write(grbl.SOFT_RESET)
    lk.drain(quiet=0.1, limit=1.0)
    lk.send("$RST=$")
    lk.close()


@pytest.fixture
def idle(link: RawLink) -> RawLink:
    """Reset, unlocked, parser at its defaults; position wherever the last test left it."""
    link.prepare(homed=False)
    return link


@pytest.fixture
def homed(link: RawLink) -> RawLink:
    """Reset and homed: at machine zero, position known."""
    link.prepare(homed=True)
    return link


def mpos(link: RawLink) -> tuple[float, ...]:
    return link.status().mpos


# ---- power-up and the alarm lock ------------------------------------------------------------

def test_power_up_banner_alarm_lock_and_unlock(bench: Bench, link: RawLink) -> None:
    # Re-open the port: a real Mega (and the harness) resets; homing is required at power-up.
    lines = link.reopen()
    expect(lines, [BANNER, UNLOCK_MSG])
    assert link.status().state == "Alarm"
    for cmd in ("G0X1", "G4P0", "G90", "F100", "X1"):
        expect(link.send(cmd), ["error:9"])
    # $ commands still work in alarm.
    assert len(link.send("$$")) == 23
    expect(link.send("$G"), [r"\[GC:.*\]", "ok"])
    expect(link.send("$110=600"), ["ok"])
    expect(link.send("$X"), [re.escape("[MSG:Caution: Unlocked]"), "ok"])
    assert link.status().state == "Idle"
    expect(link.send("$X"), ["ok"])  # nothing left to unlock
    if bench.hil is not None:
        assert bench.hil.positions().resets >= 2


# ---- command tables ---------------------------------------------------------------------------

OK_TABLE = [
    ("", ["ok"]),
    ("G90", ["ok"]),
    ("G91", ["ok"]),
    ("G21", ["ok"]),
    ("G94", ["ok"]),
    ("F250", ["ok"]),
    ("N10G90G0", ["ok"]),
    ("g90 (lower case, spaces, a comment) ; and a tail", ["ok"]),
    ("G0", ["ok"]),
    ("G1F100", ["ok"]),
    ("G4P0", ["ok"]),
    ("$", [r"\[HLP:.*\]", "ok"]),
    ("$I", [r"\[VER:1\.1h\.aimbench-[\d.]+:\]", re.escape("[OPT:,7,256]"),
            re.escape("[AXS:2:XA]"), "ok"]),
    ("$G", [re.escape("[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]"), "ok"]),
    ("$#", [*(re.escape(f"[G{n}:0.000,0.000,0.000]") for n in (54, 55, 56, 57, 58, 59, 28, 30, 92)),
            re.escape("[TLO:0.000]"), re.escape("[PRB:0.000,0.000,0.000:0]"), "ok"]),
    ("$N", [re.escape("$N0="), re.escape("$N1="), "ok"]),
    ("$X", ["ok"]),
    ("$110=600", ["ok"]),
    ("$27=1", ["ok"]),
]

ERROR_TABLE = [
    ("1X", 1),
    ("=5", 1),
    ("XA", 2),
    ("X", 2),
    ("$1=abc", 2),
    ("$1=256", 2),
    ("$100=0", 2),
    ("$Q", 3),
    ("$J", 3),
    ("$N0=G0X1", 3),
    ("$J=X1", 22),
    ("$J=F100", 26),
    ("$J=G0X1F100", 16),
    ("$J=X100.01F100", 15),
    ("$J=A60.01F100", 15),
    ("$102=1", 3),
    ("F-1", 4),
    ("G4P-1", 4),
    ("$100=-400", 4),
    ("$0=2", 6),
    ("$111=2400", 12),
    ("$111=1600", 12),
    ("$110=3001", 12),
    ("G0X100.01", 15),
    ("G0A60.01", 15),
    ("G0X-0.01", 15),
    ("G0A-0.01", 15),
    ("Z1", 20),
    ("Y1A1", 25),
    ("$130=5368709", 2),
    ("$131=5368709", 2),
    ("$2=8", 2),
    ("$0=50", 12),
    ("M3", 20),
    ("T1", 20),
    ("G2X1", 20),
    ("G20", 20),
    ("G38.2X1", 20),
    ("G0G1X1", 21),
    ("G90G91", 21),
    ("G1X1", 22),
    ("G1F0X1", 22),
    ("X1X2", 25),
    ("F1F2", 25),
    ("N1.5", 27),
    ("G4", 28),
    ("G4P1X1", 31),
    ("P1", 36),
    ("X" + "0" * 100 + "1", 11),
]


@pytest.mark.parametrize(("line", "replies"), OK_TABLE, ids=[repr(r[0]) for r in OK_TABLE])
def test_ok_table(bench: Bench, idle: RawLink, line: str, replies: list[str]) -> None:
    before = bench.pulses()
    expect(idle.send(line), replies)
    assert bench.pulses() == before, "a command that is not a move moved a stage"


@pytest.mark.parametrize(("line", "code"), ERROR_TABLE, ids=[repr(r[0][:20]) for r in ERROR_TABLE])
def test_error_table(bench: Bench, idle: RawLink, line: str, code: int) -> None:
    before = bench.pulses()
    expect(idle.send(line), [f"error:{code}"])
    assert idle.status().state == "Idle"
    assert bench.pulses() == before, "a refused line moved a stage"
    assert code in grbl.ERRORS


def test_settings_listing(idle: RawLink) -> None:
    lines = idle.send("$$")
    assert lines[-1] == "ok"
    got = dict(grbl.parse_setting(x) for x in lines[:-1])  # type: ignore[misc]
    assert got == {
        0: 5, 1: 255, 2: 0, 3: 0, 4: 0, 5: 0, 20: 1, 21: 1, 22: 1, 23: 3,
        24: 25, 25: 500, 26: 25, 27: 1,
        100: 400, 101: 800, 110: 600, 111: 1200, 120: 50, 121: 40, 130: 100, 131: 60,
    }


def test_setting_write_persists_across_power_cycle(bench: Bench, link: RawLink) -> None:
    link.prepare(homed=False)
    expect(link.send("$110=590.5"), ["ok"])
    assert "$110=590.500" in link.send("$$")
    # Re-open: the MCU resets; the value comes back from EEPROM.
    lines = link.reopen()
    assert not any("defaults restored" in x for x in lines), lines
    assert "$110=590.500" in link.send("$$")
    expect(link.send("$RST=$"), ["ok"])
    assert "$110=600.000" in link.send("$$")


def test_soft_limits_need_homing_setting(idle: RawLink) -> None:
    expect(idle.send("$22=0"), ["ok"])           # homing off turns soft limits off too
    assert "$20=0" in idle.send("$$")
    expect(idle.send("$20=1"), ["error:10"])
    expect(idle.send("$H"), ["error:5"])
    expect(idle.send("$22=1"), ["ok"])
    expect(idle.send("$20=1"), ["ok"])


def test_dwell_waits(idle: RawLink) -> None:
    t = time.monotonic()
    expect(idle.send("G4P0.3"), ["ok"])
    assert 0.28 <= time.monotonic() - t < 1.5


# ---- homing, moves, realtime ------------------------------------------------------------------

def test_homing_sets_zero(bench: Bench, link: RawLink) -> None:
    link.prepare(homed=False)
    expect(link.send("G90G0X1.5A0.5"), ["ok"])
    link.wait_state("Idle")
    t = time.monotonic()
    expect(link.send("$H", timeout=60), ["ok"])
    assert time.monotonic() - t < 30
    st = link.status()
    assert st.state == "Idle" and st.mpos == (0.0, 0.0, 0.0)
    if bench.hil is not None:
        p = bench.hil.positions()
        assert (p.x_steps, p.a_steps) == (0, 0)  # the switch model: homed zero == step 0


def test_status_report_format(homed: RawLink) -> None:
    # Three values, X Y Z, as every Grbl 1.1 build reports: the rotary stage in Y, Z unused.
    assert re.fullmatch(r"<Idle\|MPos:0\.000,0\.000,0\.000\|FS:0,0>", homed.status_line())
    expect(homed.send("G0A3"), ["ok"])
    time.sleep(0.05)
    assert re.fullmatch(r"<Run\|MPos:0\.000,\d+\.\d{3},0\.000\|FS:0,0>", homed.status_line())
    homed.wait_state("Idle")
    assert homed.status().mpos == (0.0, 3.0, 0.0)


def test_move_and_g1_feed(bench: Bench, homed: RawLink) -> None:
    expect(homed.send("G1F120X1"), ["ok"])  # 2 mm/s for 1 mm: about 0.55 s
    t = time.monotonic()
    homed.wait_state("Idle")
    assert 0.4 < time.monotonic() - t < 2.0
    expect(homed.send("G91G0X0.5A-0"), ["ok"])
    homed.wait_state("Idle")
    assert homed.status().mpos == (1.5, 0.0, 0.0)
    if bench.hil is not None:
        assert bench.hil.positions().x_steps == 600


def test_not_idle_errors(homed: RawLink) -> None:
    expect(homed.send("G0A6"), ["ok"])  # about 0.8 s
    for cmd in ("$$", "$H", "$X", "$110=600", "$RST=$"):
        expect(homed.send(cmd), ["error:8"])
    homed.wait_state("Idle")
    assert homed.status().mpos == (0.0, 6.0, 0.0)


def test_queue_full_holds_replies(bench: Bench, homed: RawLink) -> None:
    # More moves than the 7-slot queue holds: replies wait for room, none is lost.
    t = time.monotonic()
    for _ in range(10):
        expect(homed.send("G91G0A0.5", timeout=5), ["ok"])
    assert time.monotonic() - t > 0.3, "the 8th move's ok should wait for a free slot"
    homed.wait_state("Idle")
    assert homed.status().mpos == (0.0, 5.0, 0.0)
    if bench.hil is not None:
        assert bench.hil.positions().a_steps == 5 * STEPS_PER_DEG


def test_feed_hold_and_resume(bench: Bench, homed: RawLink) -> None:
    expect(homed.send("G0A8"), ["ok"])
    time.sleep(0.25)
    homed.write(grbl.FEED_HOLD)
    st = homed.status()
    assert st.state == "Hold" and st.substate in (0, 1)
    st = homed.wait_state("Hold", timeout=2)
    deadline = time.monotonic() + 2
    while homed.status().substate != 0:
        assert time.monotonic() < deadline, "hold never came to rest"
        time.sleep(0.02)
    held = homed.status().mpos
    before = bench.pulses()
    time.sleep(0.3)
    assert homed.status().mpos == held and bench.pulses() == before, "moved while held"
    assert 0.0 < held[1] < 8.0
    homed.write(grbl.CYCLE_START)
    homed.wait_state("Idle", timeout=5)
    assert homed.status().mpos == (0.0, 8.0, 0.0)
    if bench.hil is not None:
        assert bench.hil.positions().a_steps == 8 * STEPS_PER_DEG


def test_reset_while_idle_keeps_position(homed: RawLink) -> None:
    expect(homed.send("G0X0.25"), ["ok"])
    homed.wait_state("Idle")
    expect(homed.reset(), [BANNER])
    assert homed.status().state == "Idle" and homed.status().mpos == (0.25, 0.0, 0.0)


def test_reset_during_move_alarm_3(bench: Bench, homed: RawLink) -> None:
    expect(homed.send("G0A8"), ["ok"])
    time.sleep(0.3)
    lines = homed.reset()
    expect(lines, ["ALARM:3", BANNER, UNLOCK_MSG])
    before = bench.pulses()
    time.sleep(0.2)
    assert bench.pulses() == before, "steps after the reset"
    st = homed.status()
    assert st.state == "Alarm" and 0.0 < st.mpos[1] < 8.0
    if bench.hil is not None:  # the firmware counted every step it made
        assert round(st.mpos[1] * STEPS_PER_DEG) == bench.hil.positions().a_steps
    expect(homed.send("G0A0"), ["error:9"])


def test_reset_abandons_pending_line(homed: RawLink) -> None:
    homed.write(b"G4P5\n")
    time.sleep(0.2)
    lines = homed.reset()
    assert "ok" not in lines and re.fullmatch(BANNER, lines[-1])
    assert homed.status().state == "Idle"


def test_reset_during_homing_alarm_6(link: RawLink) -> None:
    link.prepare(homed=False)
    expect(link.send("G0X2A2"), ["ok"])
    link.wait_state("Idle")
    link.write(b"$H\n")
    time.sleep(0.1)
    assert link.status().state == "Home"
    expect(link.reset(), ["ALARM:6", BANNER, UNLOCK_MSG])
    assert link.status().state == "Alarm"


def test_soft_limit_refuses_and_never_moves(bench: Bench, homed: RawLink) -> None:
    expect(homed.send("G0X1A1"), ["ok"])
    homed.wait_state("Idle")
    before = bench.pulses()
    for cmd in ("G91G0X-1.01", "G91G0A-1.01", "G90G0X100.0025", "G91G0X99.01A0", "G0X50A61"):
        expect(homed.send(cmd), ["error:15"])
    assert bench.pulses() == before
    assert homed.status().state == "Idle"
    expect(homed.send("G91G0X-1A-1"), ["ok"])  # exactly onto the end of travel is allowed
    homed.wait_state("Idle")
    assert homed.status().mpos == (0.0, 0.0, 0.0)


def test_hard_limit_alarm_1(bench: Bench, homed: RawLink) -> None:
    expect(homed.send("$20=0"), ["ok"])
    try:
        expect(homed.send("G91G0X-3"), ["ok"])  # the switch sits 1 mm (pull-off) below zero
        first = homed.readline(5.0)
        lines = ([first] if first else []) + homed.drain(quiet=0.3, limit=5)
        expect(lines, ["ALARM:1", UNLOCK_MSG])
        st = homed.status()
        assert st.state == "Alarm" and st.pins == "X"  # the X slot's switch
        if bench.hil is not None:
            # Stopped dead at the first step past the switch's trip point.
            assert bench.hil.positions().x_steps == -1 * STEPS_PER_MM - 1
            assert round(st.mpos[0] * STEPS_PER_MM) == -401
        expect(homed.send("G90G0X0"), ["error:9"])
        expect(homed.send("$X"), [re.escape("[MSG:Caution: Unlocked]"), "ok"])
        expect(homed.send("G90G0X0"), ["ok"])  # driving off the switch is no new alarm
        homed.wait_state("Idle")
        assert homed.status().pins == ""
    finally:
        homed.drain(quiet=0.05)
        homed.send("$20=1")


def test_homing_fail_approach_alarm_9(link: RawLink) -> None:
    link.prepare(homed=True)
    try:
        # Home toward max over a 1 mm travel: the search (1.5 x travel) finds no switch.
        expect(link.send("$23=2"), ["ok"])
        expect(link.send("$130=1"), ["ok"])
        expect(link.send("$H", timeout=20), ["ALARM:9", UNLOCK_MSG, "error:9"])
        assert link.status().state == "Alarm"
    finally:
        link.send("$23=3")
        link.send("$130=100")


def test_homing_fail_pulloff_alarm_8(link: RawLink) -> None:
    link.prepare(homed=True)
    try:
        # Inverted switch inputs read "hit" away from the switches: the locate pass never sees
        # a release.
        expect(link.send("$5=1"), ["ok"])
        expect(link.send("$24=200"), ["ok"])
        expect(link.send("$H", timeout=20), ["ALARM:8", UNLOCK_MSG, "error:9"])
        assert link.status().state == "Alarm"
    finally:
        link.send("$5=0")
        link.send("$24=25")
        link.send("$H", timeout=60)


def test_overlong_line_rejected_whole(bench: Bench, homed: RawLink) -> None:
    before = bench.pulses()
    line = "G91G0X0.0" + "0" * 80 + "1"  # a valid move, but longer than the 80-byte buffer
    expect(homed.send(line), ["error:11"])
    expect(homed.send("G4P0"), ["ok"])   # the next line is intact
    assert bench.pulses() == before


def test_garbage_flood(bench: Bench, homed: RawLink) -> None:
    rng = random.Random(5)
    realtime = set(b"?!~\x18")
    junk = bytes(b for b in rng.randbytes(20000) if b not in realtime)
    before = bench.pulses()
    homed.write(junk + b"\n")
    lines = homed.drain(quiet=0.5, limit=30)
    assert lines, "no replies to the garbage"
    bad = [x for x in lines if not re.fullmatch(r"ok|error:\d+", x)]
    assert not bad, f"unexpected lines: {bad[:5]}"
    assert any(x == "error:11" for x in lines)
    assert bench.pulses() == before, "garbage moved a stage"
    expect(homed.send("$I")[-1:], ["ok"])
    expect(homed.send("G91G0X0.5"), ["ok"])
    homed.wait_state("Idle")
    assert homed.status().mpos == (0.5, 0.0, 0.0)


def test_garbage_flood_with_realtime_bytes(bench: Bench, homed: RawLink) -> None:
    rng = random.Random(11)
    junk = rng.randbytes(4000)  # includes Ctrl-X, ?, !, ~
    before = bench.pulses()
    homed.write(junk)
    homed.drain(quiet=0.5, limit=30)
    lines = homed.reset()
    assert re.fullmatch(BANNER, [x for x in lines if x.startswith("Grbl")][-1])
    if homed.status().state == "Alarm":
        homed.send("$X")
    assert homed.status().state == "Idle"
    assert bench.pulses() == before
    expect(homed.send("G90G0A0.25"), ["ok"])
    homed.wait_state("Idle")
    assert homed.status().mpos[1] == 0.25


# ---- Grbl 1.1 queries, check mode, jogging, exact step rounding -------------------------------

def test_targets_round_to_steps_exactly(bench: Bench, homed: RawLink) -> None:
    # Parsed in single precision, 60.000624 deg (48000.4992 steps) became 48000.5 and was refused
    # as beyond the 60 deg travel; 65.818749 mm (26327.4996 steps) arrived a step off.
    expect(homed.send("G0X65.818749A60.000624", timeout=5), ["ok"])
    st = homed.wait_state("Idle", timeout=20)
    assert st.mpos == (65.818, 60.0, 0.0)  # 26327 steps = 65.8175 mm, printed half away from 0
    if bench.hil is not None:
        p = bench.hil.positions()
        assert (p.x_steps, p.a_steps) == (26327, 48000)
    expect(homed.send("G0A60.000625"), ["error:15"])  # 48000.5 steps: half a step beyond


def test_rotary_axis_answers_to_its_slot_letter(bench: Bench, homed: RawLink) -> None:
    # A sender that knows only X, Y, Z sees the rotary stage as Y and may drive it as Y.
    expect(homed.send("G91G0Y0.5"), ["ok"])
    assert homed.wait_state("Idle").mpos == (0.0, 0.5, 0.0)
    if bench.hil is not None:
        assert bench.hil.positions().a_steps == STEPS_PER_DEG // 2


def test_check_mode_checks_without_moving(bench: Bench, homed: RawLink) -> None:
    before = bench.pulses()
    expect(homed.send("$C"), [re.escape("[MSG:Enabled]"), "ok"])
    assert homed.status().state == "Check"
    expect(homed.send("G0X10A5"), ["ok"])
    expect(homed.send("G91G0X95"), ["error:15"])   # 105 mm: the parser's position counts
    expect(homed.send("G4P5"), ["ok"])              # no dwell in check mode
    expect(homed.send("$H"), ["error:8"])
    expect(homed.send("$J=X1F100"), ["error:8"])
    assert homed.status().mpos == (0.0, 0.0, 0.0) and bench.pulses() == before
    # Leaving check mode resets, as Grbl does: the reply, then the banner.
    homed.write(b"$C\n")
    lines = homed.wait_banner()
    expect(lines, [re.escape("[MSG:Disabled]"), "ok", BANNER])
    st = homed.status()
    assert st.state == "Idle" and st.mpos == (0.0, 0.0, 0.0)
    expect(homed.send("G91G0X1"), ["ok"])  # from the machine's position, not the parser's
    assert homed.wait_state("Idle").mpos == (1.0, 0.0, 0.0)
    assert bench.pulses() != before


def test_jog_moves_and_keeps_the_modal_state(bench: Bench, homed: RawLink) -> None:
    expect(homed.send("$J=G91X0.5A0.25F300"), ["ok"])
    assert homed.status().state == "Jog"
    expect(homed.send("G0X1"), ["error:9"])  # G-code is locked while jogging, as in Grbl
    homed.wait_state("Idle")
    assert homed.status().mpos == (0.5, 0.25, 0.0)
    expect(homed.send("$G"), [re.escape("[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]"), "ok"])
    expect(homed.send("$J=X1A1F600"), ["ok"])  # absolute: the parser's G90
    assert homed.wait_state("Idle").mpos == (1.0, 1.0, 0.0)


def test_jog_cancel_stops_and_keeps_the_position(bench: Bench, homed: RawLink) -> None:
    expect(homed.send("$J=G91A20F1200"), ["ok"])   # 20 deg at 20 deg/s
    expect(homed.send("$J=G91A20F1200"), ["ok"])   # queued behind it
    time.sleep(0.4)
    homed.write(grbl.JOG_CANCEL)
    st = homed.wait_state("Idle", timeout=3)
    assert 0.0 < st.mpos[1] < 20.0, st
    time.sleep(0.3)
    if bench.hil is not None:  # stopped for good, and the firmware counted every step it made
        p = bench.hil.positions()
        assert round(st.mpos[1] * STEPS_PER_DEG) == p.a_steps
        time.sleep(0.2)
        assert bench.hil.positions().pulses == p.pulses
    # A feed hold while jogging cancels the jog as well.
    expect(homed.send("$J=G91A5F1200"), ["ok"])
    time.sleep(0.1)
    homed.write(grbl.FEED_HOLD)
    st = homed.wait_state("Idle", timeout=3)
    assert homed.status().state == "Idle"
