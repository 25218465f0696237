"""Third-party Grbl senders drive the real firmware in simavr (issue 22): connect, status, home,
stream, jog, alarm.

grbl-streamer 2.0.2 (GPLv3, a test dependency only) is the strict one: its reader thread died on
a two-value MPos and its boot query `$#` got error:3. pygrbl-streamer 1.0.5 (MIT) streams with
character counting and checks every ack. Both are used as published, through their public API.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator

import pytest
from stage_support import STEPS_PER_DEG, STEPS_PER_MM

from twin.stage.hil import SimavrHarness

pytestmark = [pytest.mark.simavr, pytest.mark.slow]


def wait_for(predicate: Callable[[], bool], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.02)


@pytest.fixture(scope="module")
def hil() -> Iterator[SimavrHarness]:
    with SimavrHarness(start_x_mm=2.0, start_a_deg=2.0) as h:
        yield h


def test_grbl_streamer_connect_status_home_stream_jog_alarm(hil: SimavrHarness) -> None:
    grbl_streamer = pytest.importorskip("grbl_streamer")
    events: list[tuple[str, tuple]] = []
    g = grbl_streamer.GrblStreamer(lambda ev, *args: events.append((ev, args)))
    g.poll_interval = 0.05
    g.cnect(hil.url)
    try:
        # Connect: the banner, then its boot queries $# and $$ (no error), then $G by polling.
        wait_for(lambda: any(e == "on_boot" for e, _ in events), 10, "the boot")
        g.poll_start()
        wait_for(lambda: g.cmode == "Alarm", 5, "the first status report")
        wait_for(lambda: "PRB" in g.settings_hash, 5, "the $# answer")
        assert g.settings_hash["G54"] == (0.0, 0.0, 0.0)
        assert not [a for e, a in events if e == "on_error"], "an error at connect"
        # Home.
        g.homing()
        wait_for(lambda: g.cmode == "Home", 5, "homing to start")
        wait_for(lambda: g.cmode == "Idle", 60, "homing to finish")
        assert g.cmpos == (0.0, 0.0, 0.0)
        # Stream: its preprocessor splits modal words and counts characters in the RX buffer.
        g.write("G91\nG0 X1 A0.5\nG0 X1 A0.5\nG90\nG0 X3 A2\n")
        g.job_run()
        wait_for(lambda: any(e == "on_job_completed" for e, _ in events[-50:]), 20, "the job")
        wait_for(lambda: g.cmode == "Idle" and g.cmpos == (3.0, 2.0, 0.0), 20, "the stream")
        p = hil.positions()
        assert (p.x_steps, p.a_steps) == (3 * STEPS_PER_MM, 2 * STEPS_PER_DEG)
        # Jog, with the rotary stage as the Y it reports.
        g.send_immediately("$J=G91X1Y1F600")
        wait_for(lambda: g.cmode == "Jog", 5, "the jog")
        wait_for(lambda: g.cmode == "Idle", 10, "the jog to end")
        assert g.cmpos == (4.0, 3.0, 0.0)
        # Alarm: a reset in motion (ALARM:3) reaches its alarm callback; $X unlocks.
        g.send_immediately("$J=G91Y20F1200")
        wait_for(lambda: g.cmode == "Jog", 5, "the second jog")
        g.softreset()
        wait_for(lambda: any(e == "on_alarm" for e, _ in events), 5, "the alarm")
        wait_for(lambda: g.cmode == "Alarm", 5, "the alarm state")
        g.killalarm()
        wait_for(lambda: g.cmode == "Idle", 5, "the unlock")
        assert g._thread_read_iface.is_alive(), "grbl-streamer's reader thread died"
        errors = [a for e, a in events if e == "on_error"]
        assert not errors, errors
    finally:
        g.disconnect()


def test_pygrbl_streamer_connect_home_stream_and_alarm(hil: SimavrHarness) -> None:
    pygrbl_streamer = pytest.importorskip("pygrbl_streamer")
    alarms: list[str] = []
    errors: list[str] = []
    s = pygrbl_streamer.GrblStreamer(hil.url, auto_unlock=False)
    s.alarm_callback = alarms.append
    s.error_callback = errors.append
    s.connect(reset=True)
    try:
        assert s.command("$X")
        assert s.home(timeout=60, wait_idle=True)
        assert s.stream(["G91", "G0 X0.5 A0.25", "G0 X0.5 A0.25", "G4 P0.1"], completion_timeout=30)
        assert s.last_status["raw"].startswith("<Idle|MPos:1.000,0.500,0.000|")
        assert not errors
        # A jog is taken when Idle (in Run it is error:8, as on a stock Grbl).
        assert s.command("$J=G91X1Y1F600")
        goal = (2 * STEPS_PER_MM, 3 * STEPS_PER_DEG // 2)
        wait_for(lambda: (hil.positions().x_steps, hil.positions().a_steps) == goal, 10, "the jog")
        assert s.sync() == pygrbl_streamer.State.IDLE
        assert s.last_status["raw"].startswith("<Idle|MPos:2.000,1.500,0.000|")
        assert not s.command("G0 Z1")  # no Z on this machine: refused, reported
        wait_for(lambda: errors[-1:] == ["error:20"], 5, "the error callback (its own thread)")
        assert s.command("$20=0")
        try:  # drive X past its switch: a hard-limit alarm
            s.write_line("G91 G0 X-5")
            wait_for(lambda: bool(alarms), 10, "the hard-limit alarm")
            assert alarms[0] == "ALARM:1"
        finally:
            assert s.command("$X") and s.command("$20=1")
    finally:
        s.disconnect()
