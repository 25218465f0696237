"""Property-based hardware-in-the-loop test of the stage firmware's safety (issue 19).

Hypothesis draws settings within what the firmware accepts (rates up to its step-rate limit,
any acceleration) and sequences of moves, absolute and relative, some beyond the travel, sent
back to back with or without 20 ms status polling. The real firmware runs in simavr; the harness
counts its STEP/DIR pulses and records how far each axis really went between polls. Properties:

- the step pulses never leave the travel ([0, $13x] after homing), not even for a moment;
- a move beyond the travel is refused (error:15) and nothing of it moves;
- once Idle, the reported MPos equals the pulses, step for step; the MCU never resets.

Seeded (derandomized) with a bounded budget: AIMBENCH_HIL_EXAMPLES examples each with and
without polling (default 3); a longer hunt sets it higher.
"""

from __future__ import annotations

import os
import re
import time
from collections.abc import Iterator
from decimal import ROUND_HALF_UP, Decimal

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from stage_support import STEPS_PER_DEG, STEPS_PER_MM, RawLink

from twin.stage.hil import SimavrHarness

pytestmark = [pytest.mark.simavr, pytest.mark.slow]

MAX_STEP_RATE = 20000  # steps/s: bench_fw's limit (config.h, PROTOCOL.md "Step rate")
X_TRAVEL = 100 * STEPS_PER_MM
A_TRAVEL = 60 * STEPS_PER_DEG
EXAMPLES = int(os.environ.get("AIMBENCH_HIL_EXAMPLES", "3"))
FINAL = re.compile(r"^(ok|error:\d+)$")


@pytest.fixture(scope="module")
def rig() -> Iterator[tuple[SimavrHarness, RawLink]]:
    with SimavrHarness(start_x_mm=2.0, start_a_deg=2.0) as hil:
        link = RawLink(hil.url)
        link.boot_lines()
        assert link.send("$RST=$")[-1] == "ok"
        assert link.send("$H", timeout=60)[-1] == "ok"
        yield hil, link
        link.send("$RST=$")
        link.close()


# Fast enough that an example takes seconds in real time, up to the firmware's own limit.
x_rates = st.integers(1200, MAX_STEP_RATE * 60 // STEPS_PER_MM)     # mm/min
a_rates = st.integers(600, MAX_STEP_RATE * 60 // STEPS_PER_DEG)     # deg/min
accels = st.integers(50, 3000)                                      # units/s^2


@st.composite
def moves(draw: st.DrawFn) -> list[str]:
    """1 to 4 G-code moves: absolute or relative, with 3 to 6 decimals, a few beyond the
    travel."""
    out = []
    for _ in range(draw(st.integers(1, 4))):
        if draw(st.booleans()):
            x = draw(st.floats(-2.0, 102.0, allow_nan=False))
            a = draw(st.floats(-2.0, 62.0, allow_nan=False))
            out.append(f"G90G0X{x:.{draw(st.integers(3, 6))}f}A{a:.4f}")
        else:
            dx = draw(st.floats(-30.0, 30.0, allow_nan=False))
            da = draw(st.floats(-20.0, 20.0, allow_nan=False))
            out.append(f"G91G0X{dx:.3f}A{da:.5f}")
    return out


def expected_steps(word: str, spu: int) -> int:
    """A number as written, in steps: the nearest, half a step away from zero (PROTOCOL.md)."""
    return int((Decimal(word) * spu).to_integral_value(rounding=ROUND_HALF_UP))


def model(here: tuple[int, int], line: str) -> tuple[int, int]:
    """Where `line` sends the stages from `here` (steps), exactly as the firmware must round."""
    relative = line.startswith("G91")
    m = re.fullmatch(r"G9[01]G0X(-?[\d.]+)A(-?[\d.]+)", line)
    assert m, line
    x = expected_steps(m.group(1), STEPS_PER_MM)
    a = expected_steps(m.group(2), STEPS_PER_DEG)
    return (here[0] + x, here[1] + a) if relative else (x, a)


def send_watching(link: RawLink, line: str, poll: bool) -> str:
    """Send one line; return its ok/error. With poll, a status query every 20 ms meanwhile."""
    link.write(line.encode() + b"\n")
    last = 0.0
    deadline = time.monotonic() + 30.0
    while time.monotonic() < deadline:
        if poll and time.monotonic() - last >= 0.02:
            link.write(b"?")
            last = time.monotonic()
        reply = link.readline(0.005)
        if reply is not None and FINAL.match(reply):
            return reply
        if reply is not None and not reply.startswith("<"):
            raise AssertionError(f"unexpected line {reply!r} after {line!r}")
    raise AssertionError(f"no reply to {line!r}")


def wait_idle(link: RawLink, poll: bool, timeout: float = 40.0) -> None:
    """Until Idle: polling every 20 ms, or watching silently and asking once a second."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        st_ = link.status()
        if st_.state == "Idle":
            return
        assert st_.state in ("Run",), f"state {st_.state} while moving"
        time.sleep(0.02 if poll else 1.0)
    raise AssertionError("the stages never came to rest")


@pytest.mark.parametrize("poll", [False, True], ids=["silent", "polled-20ms"])
@settings(
    max_examples=EXAMPLES,
    derandomize=True,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(x_rate=x_rates, a_rate=a_rates, x_accel=accels, a_accel=accels, lines=moves())
def test_moves_never_leave_the_travel_and_mpos_equals_pulses(
    rig: tuple[SimavrHarness, RawLink], x_rate: int, a_rate: int, x_accel: int, a_accel: int,
    lines: list[str], poll: bool,
) -> None:
    hil, link = rig
    link.drain(quiet=0.02, limit=1.0)
    for number, value in ((110, x_rate), (111, a_rate), (120, x_accel), (121, a_accel)):
        assert link.send(f"${number}={value}") == ["ok"], "a rate within the limit was refused"
    start = hil.positions()
    here = (start.x_steps, start.a_steps)
    hil.mark()
    for line in lines:
        goal = model(here, line)
        inside = 0 <= goal[0] <= X_TRAVEL and 0 <= goal[1] <= A_TRAVEL
        reply = send_watching(link, line, poll)
        assert reply == ("ok" if inside else "error:15"), (line, goal, reply)
        if inside:
            here = goal  # a refused move leaves the target where it was
    wait_idle(link, poll)
    p = hil.positions()
    assert (p.x_steps, p.a_steps) == here, ("the stages are not where the moves sent them", lines)
    (x_lo, x_hi), (a_lo, a_hi) = p.extremes
    assert x_lo >= 0 and x_hi <= X_TRAVEL, ("X left the travel", p.extremes, lines)
    assert a_lo >= 0 and a_hi <= A_TRAVEL, ("A left the travel", p.extremes, lines)
    st_ = link.status()
    assert st_.state == "Idle"
    assert (round(st_.mpos[0] * STEPS_PER_MM), round(st_.mpos[1] * STEPS_PER_DEG)) == (
        p.x_steps, p.a_steps), ("MPos does not match the pulses", st_.mpos, p)
    assert p.resets == start.resets, "the MCU reset during the moves"
