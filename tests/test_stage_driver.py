"""StageController against the real firmware in simavr (or a real board with --port), and the
accuracy of motion: observed step counts equal the commanded positions exactly, and both axes
of a combined move take their last step together.
"""

from __future__ import annotations

import math
import re
import time
from collections.abc import Iterator

import pytest
from stage_support import STEPS_PER_DEG, STEPS_PER_MM, Bench, bench

from twin.stage.controller import (
    GrblAlarm,
    GrblError,
    StageConnectionError,
    StageController,
    StageTimeout,
    trapezoid_time,
)
from twin.stage.hil import SimavrHarness

pytestmark = [pytest.mark.simavr, pytest.mark.slow]
__all__ = ["bench"]

MM = 1e-3
DEG = math.pi / 180.0


@pytest.fixture(scope="module")
def stage(bench: Bench) -> Iterator[StageController]:
    with StageController(bench.url) as s:
        s.set_setting(110, 600)  # defaults, whatever a previous run left
        yield s


@pytest.fixture
def homed(stage: StageController) -> StageController:
    stage.reset()
    stage.home()
    return stage


def machine_steps(x_m: float, yaw_rad: float) -> tuple[int, int]:
    """Commanded position (bench reference, SI) in machine steps, half a step rounding up."""
    return (
        math.floor((50.0 + x_m / MM) * STEPS_PER_MM + 0.5),
        math.floor((30.0 + yaw_rad / DEG) * STEPS_PER_DEG + 0.5),
    )


def test_connect_reads_banner_and_settings(stage: StageController) -> None:
    assert stage.banner is not None and stage.banner.startswith("Grbl 1.1")
    assert stage.mpos_axes == "XA"
    s = stage.settings()
    assert (s[100], s[101], s[110], s[111], s[120], s[121], s[130], s[131]) == (
        400, 800, 600, 1200, 50, 40, 100, 60)
    assert stage.cached_settings == s


def test_home_then_position_is_machine_zero(bench: Bench, homed: StageController) -> None:
    here = homed.position()
    assert here.x_m == pytest.approx(-50 * MM) and here.yaw_rad == pytest.approx(-30 * DEG)
    if bench.hil is not None:
        p = bench.hil.positions()
        assert (p.x_steps, p.a_steps) == (0, 0)
        assert p.x_m == pytest.approx(-0.05) and p.yaw_rad == pytest.approx(-30 * DEG)


def test_moves_are_exact_in_steps(bench: Bench, homed: StageController) -> None:
    hil = bench.need_hil()
    # Near home (short moves), odd values that exercise the rounding to steps.
    targets = [
        (-48.7654 * MM, -28.1234 * DEG),
        (-49.99875 * MM, -29.99937 * DEG),   # 0.5 and 0.504 steps: rounding decides
        (-49.9987 * MM, -29.99938 * DEG),
        (-47.0 * MM, -26.5 * DEG),
        (-48.0001 * MM, -29.0 * DEG),
    ]
    for x_m, yaw in targets:
        homed.move_to(x_m=x_m, yaw_rad=yaw)
        p = hil.positions()
        assert (p.x_steps, p.a_steps) == machine_steps(x_m, yaw)
        # The firmware's own count agrees with the pins, to its 3-decimal report.
        st = homed.status()
        assert st.x_mm == pytest.approx(p.x_steps / STEPS_PER_MM, abs=5e-4)
        assert st.yaw_deg == pytest.approx(p.a_steps / STEPS_PER_DEG, abs=5e-4)
        assert abs(p.x_m - x_m) <= 0.5 / STEPS_PER_MM * MM + 1e-12
        assert abs(p.yaw_rad - yaw) <= 0.5 / STEPS_PER_DEG * DEG + 1e-12


def test_relative_moves_accumulate_exactly(bench: Bench, homed: StageController) -> None:
    hil = bench.need_hil()
    homed.move_to(x_m=-48 * MM, yaw_rad=-28 * DEG)
    for _ in range(4):
        homed.move_by(dx_m=0.25 * MM, dyaw_rad=0.5 * DEG)
    p = hil.positions()
    assert (p.x_steps, p.a_steps) == (3 * STEPS_PER_MM, 4 * STEPS_PER_DEG)


def test_combined_move_axes_finish_together(bench: Bench, homed: StageController) -> None:
    hil = bench.need_hil()
    before = hil.positions()
    homed.move_to(x_m=-47 * MM, yaw_rad=-25 * DEG)  # 3 mm and 5 deg: 1200 and 4000 steps
    p = hil.positions()
    assert (p.pulses[0] - before.pulses[0], p.pulses[1] - before.pulses[1]) == (1200, 4000)
    # The last pulses of both axes come out in the same interrupt: equal simulated times.
    assert p.last_step_s[0] == p.last_step_s[1]


def test_move_time_follows_the_trapezoid(bench: Bench, homed: StageController) -> None:
    hil = bench.need_hil()
    # Short moves come out a little quicker than the ideal triangle: the firmware starts and ends
    # at the speed half a step of acceleration gives (sqrt(a) steps/s), not at zero.
    for deg, lo, hi in ((1.0, 0.95, 1.02), (8.0, 0.97, 1.02)):
        ideal = trapezoid_time(deg, 20.0, 40.0)
        goal = hil.positions().a_steps + round(deg * STEPS_PER_DEG)
        homed.command(f"G91G0A{deg}")
        deadline = time.monotonic() + 10
        while hil.positions().a_steps != goal and time.monotonic() < deadline:
            time.sleep(0.005)  # watch the pins, send nothing: the command stays the last input
        end = hil.positions()
        homed.wait_idle(5)
        # From the command's last byte entering the UART to the last step pulse, on the
        # simulated clock: the host's scheduling plays no part.
        moved = end.last_step_s[1] - end.last_rx_s
        assert lo * ideal < moved < hi * ideal, (deg, moved, ideal)


def test_soft_limit_raises_grbl_error(bench: Bench, homed: StageController) -> None:
    before = bench.pulses()
    with pytest.raises(GrblError) as err:
        homed.move_to(x_m=0.051, yaw_rad=0.0)
    assert err.value.code == 15 and "travel" in err.value.meaning
    assert "error:15" in str(err.value)
    assert bench.pulses() == before


def test_hard_limit_raises_grbl_alarm(bench: Bench, homed: StageController) -> None:
    homed.set_setting(20, 0)
    try:
        with pytest.raises(GrblAlarm) as err:
            homed.move_by(dx_m=-3 * MM, dyaw_rad=0.0)
        assert err.value.code == 1 and "hard limit" in err.value.meaning
        assert homed.status().state == "Alarm"
        with pytest.raises(GrblError) as locked:
            homed.move_to(x_m=-0.05, yaw_rad=-30 * DEG)
        assert locked.value.code == 9
        homed.unlock()
        homed.move_to(x_m=-0.05, yaw_rad=-30 * DEG)
    finally:
        homed.set_setting(20, 1)


def test_stop_resume_and_reset_during_move(bench: Bench, homed: StageController) -> None:
    homed.move_to(x_m=-0.05, yaw_rad=-22 * DEG, wait=False)
    time.sleep(0.2)
    homed.stop()
    time.sleep(0.5)
    st = homed.status()
    assert st.state == "Hold" and st.substate == 0
    homed.resume()
    st = homed.wait_idle(10)
    assert st.yaw_deg == 8.0
    homed.move_to(x_m=-0.05, yaw_rad=-30 * DEG, wait=False)
    time.sleep(0.2)
    homed.reset()
    assert homed.last_alarm == 3
    with pytest.raises(GrblAlarm) as err:
        homed.wait_idle(2)
    assert err.value.code == 3


def test_wait_idle_times_out_clearly(homed: StageController) -> None:
    homed.move_to(x_m=-0.05, yaw_rad=-24 * DEG, wait=False)
    with pytest.raises(StageTimeout, match="did not come to rest"):
        homed.wait_idle(timeout=0.1)
    homed.wait_idle(10)


def test_lost_reply_times_out_clearly(homed: StageController) -> None:
    homed.move_to(x_m=-0.05, yaw_rad=-28 * DEG, wait=False)
    time.sleep(0.1)
    homed.stop()  # G4 waits for the motion, which the hold never finishes: no reply
    old = homed.reply_timeout_s
    homed.reply_timeout_s = 0.5
    try:
        with pytest.raises(StageTimeout, match="no reply to 'G4P0'"):
            homed.command("G4P0")
    finally:
        homed.reply_timeout_s = old
        homed.reset()


def test_settings_write_and_read(homed: StageController) -> None:
    homed.set_setting(110, 550)
    assert homed.settings()[110] == 550
    homed.set_setting(110, 600)
    with pytest.raises(GrblError) as err:
        homed.set_setting(999, 1)
    assert err.value.code == 3


def test_axis_letters_the_controller_lacks(bench: Bench, stage: StageController) -> None:
    if bench.hil is None:
        pytest.skip("depends on the bench firmware's axis set")
    stage.close()
    try:
        with pytest.raises(StageConnectionError, match="axis Z is not an axis"):
            StageController(bench.url, axis_letters=("X", "Z")).connect()
    finally:
        stage.connect()


def test_board_that_does_not_reset_on_open() -> None:
    # A board without DTR auto-reset sends no banner when the port opens: the driver finds it
    # with a status query (not a soft reset, which would abort a move in progress).
    with SimavrHarness(start_x_mm=1.0, start_a_deg=1.0, reset_on_open=False) as hil:
        time.sleep(0.2)
        t = time.monotonic()
        with StageController(hil.url, boot_timeout_s=0.5) as s:
            assert s.banner in (None, "")
            assert s.mpos_axes == "XA"  # from $I: its [VER:] names aimbench
            assert time.monotonic() - t < 3.0
            assert s.status().state == "Alarm"
            assert s.settings()[100] == 400
        assert hil.positions().resets == 0  # never reset by opening the port


def test_reconnect_keeps_position(bench: Bench, homed: StageController) -> None:
    # close() leaves DTR up (HUPCL cleared): the next open does not reset the board, so a homed
    # machine stays homed between two `aimbench stage` commands.
    homed.move_to(x_m=-0.049, yaw_rad=-29 * DEG)
    resets = bench.hil.positions().resets if bench.hil else None
    homed.close()
    try:
        with StageController(bench.url) as again:
            st = again.status()
            assert st.state == "Idle"
            assert (st.x_mm, st.yaw_deg) == (1.0, 1.0)
        if bench.hil is not None:
            assert bench.hil.positions().resets == resets
    finally:
        homed.connect()


def test_stage_command_shows_the_position_while_it_homes_and_moves(
    capsys: pytest.CaptureFixture[str],
) -> None:
    # `aimbench stage home` / `move` wait seconds for the stages: the position is shown as it
    # changes (here, not a terminal: a line per ten status reports), then the final status.
    from scenarios.cli import main

    with SimavrHarness(start_x_mm=8.0, start_a_deg=6.0) as hil:
        assert main(["stage", "--port", hil.url, "home"]) == 0
        out, err = capsys.readouterr()
        homing = re.findall(r"^homing: \d+ reports \| Home\s+x\s+(\S+) mm\s+yaw\s+(\S+) deg$",
                            err, re.M)
        assert len(set(homing)) >= 2, err  # seen moving, not only where it ended
        assert re.search(r"^state\s+Idle$", out, re.M)
        assert re.search(r"^x\s+-50\.000 mm from the bench centre", out, re.M), out

        assert main(["stage", "--port", hil.url, "move", "--x-mm", "-46", "--yaw-deg",
                     "-28"]) == 0
        out, err = capsys.readouterr()
        xs = [float(x) for x in re.findall(r"^moving: \d+ reports \| Run\s+x\s+(\S+) mm", err,
                                           re.M)]
        assert xs and all(-50.0 < x < -46.0 for x in xs), err  # on the way
        assert re.search(r"^x\s+-46\.000 mm from the bench centre", out, re.M), out
