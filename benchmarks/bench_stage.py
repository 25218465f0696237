"""Stage controller benchmark: the real firmware in simavr, driven by the real host driver.

    .venv/bin/python benchmarks/bench_stage.py

Prints a table of
- command round trip: a realtime status query (``?`` -> ``<...>``) and a G-code line
  (``G90`` -> ``ok``) through the pty, pyserial and the simulated UART at 115200 baud;
- a 21-position yaw sweep (-10 .. +10 deg in 1 deg steps at x = 0, as in the reference paper):
  the time of each 1 deg move through the firmware, against the trapezoidal-profile time computed
  from the controller's own settings ($111 max rate, $121 acceleration), with the ratio. The
  firmware's time is measured on the simulated clock (the command's last byte entering the UART
  -> last step pulse on the STEP pin, on the way back down without status polls; and the host
  about to send -> last pulse) and on the host's wall clock (command sent -> Idle seen by status
  polling).
"""

from __future__ import annotations

import argparse
import math
import resource
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from twin.stage.controller import StageController, trapezoid_time
from twin.stage.hil import SimavrHarness

T0 = time.perf_counter()


def percentile(values: list[float], q: float) -> float:
    s = sorted(values)
    return s[min(len(s) - 1, round(q * (len(s) - 1)))]


MAX_STEP_RATE = 20000.0  # steps/s, bench_fw/src/config.h


def cruise_load(hil: SimavrHarness, stage: StageController, fraction: float) -> tuple[float, float]:
    """(step rate seen on the pins at cruise, CPU load) for a combined move with both axes at
    `fraction` of the limit, polled every 20 ms."""
    stage.set_setting(110, 3000 * fraction)  # 400 steps/mm: 20 kHz at 3000 mm/min
    stage.set_setting(111, 1500 * fraction)  # 800 steps/deg: 20 kHz at 1500 deg/min
    stage.move_to(x_m=-0.05, yaw_rad=math.radians(-30))
    stage.move_to(x_m=0.05, yaw_rad=math.radians(30), wait=False)
    samples = []
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        st = stage.status()
        samples.append(hil.positions())
        if st.state == "Idle" and len(samples) > 3:
            break
        time.sleep(0.02)
    # The cruise: the middle half of the samples (away from both ramps).
    a, b = samples[len(samples) // 4], samples[3 * len(samples) // 4]
    dt = b.sim_time_s - a.sim_time_s
    rate = (b.pulses[1] - a.pulses[1]) / dt
    load = 1.0 - (b.idle_s - a.idle_s) / dt
    stage.wait_idle(10)
    return rate, load


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--round-trips", type=int, default=200, help="samples per round-trip row")
    args = ap.parse_args(argv)

    with SimavrHarness(start_x_mm=2.0, start_a_deg=2.0) as hil, StageController(hil.url) as stage:
        stage.home()
        settings = stage.settings()
        rate_dps = settings[111] / 60.0
        accel = settings[121]

        # Round trips.
        rt_status: list[float] = []
        rt_line: list[float] = []
        for _ in range(args.round_trips):
            t = time.perf_counter()
            stage.status()
            rt_status.append(time.perf_counter() - t)
            t = time.perf_counter()
            stage.command("G90")
            rt_line.append(time.perf_counter() - t)

        # The sweep: first to -10 deg (not timed), then 20 moves of +1 deg.
        yaws = [math.radians(d) for d in range(-10, 11)]
        stage.move_to(x_m=0.0, yaw_rad=yaws[0])
        sim_times: list[float] = []
        pulse_times: list[float] = []
        wall_times: list[float] = []
        sim0, wall0 = hil.positions().sim_time_s, time.perf_counter()
        for yaw in yaws[1:]:
            before = hil.positions()
            t = time.perf_counter()
            stage.move_to(x_m=0.0, yaw_rad=yaw)
            wall_times.append(time.perf_counter() - t)
            after = hil.positions()
            assert after.a_steps - before.a_steps == 800, "a 1 deg move must be 800 steps"
            sim_times.append(after.last_step_s[1] - before.sim_time_s)
        pace = (hil.positions().sim_time_s - sim0) / (time.perf_counter() - wall0)
        # The same sweep back down, without status polls during each move, so the command is
        # the host's last input: command's last byte in the UART -> last step pulse.
        for yaw in reversed(yaws[:-1]):
            goal = round((30 + math.degrees(yaw)) * settings[101])
            stage.command(f"G90G0X50A{30 + math.degrees(yaw):.6f}")
            deadline = time.monotonic() + 10.0
            while hil.positions().a_steps != goal and time.monotonic() < deadline:
                time.sleep(0.005)  # watch the pins only: no bytes to the controller
            after = hil.positions()
            pulse_times.append(after.last_step_s[1] - after.last_rx_s)
            stage.wait_idle(5)
        ideal = trapezoid_time(1.0, rate_dps, accel)
        final = hil.positions()

        # The step-rate limit, at half of it and at it.
        stage.set_setting(120, 1000)
        stage.set_setting(121, 1000)
        half_rate, half_load = cruise_load(hil, stage, 0.5)
        full_rate, full_load = cruise_load(hil, stage, 1.0)
        per_step = (full_load - half_load) / (full_rate - half_rate)  # CPU share per step/s
        ceiling = full_rate + (1.0 - full_load) / per_step
        stage.command("$RST=$")

    n = len(sim_times)
    rows = [
        ("round trip `?` -> status report, median", f"{statistics.median(rt_status) * 1e3:.2f} ms",
         f"p95 {percentile(rt_status, 0.95) * 1e3:.2f} ms, n={len(rt_status)}"),
        ("round trip `G90` -> `ok`, median", f"{statistics.median(rt_line) * 1e3:.2f} ms",
         f"p95 {percentile(rt_line, 0.95) * 1e3:.2f} ms, n={len(rt_line)}"),
        ("sweep: trapezoid time per 1 deg move", f"{ideal * 1e3:.1f} ms",
         f"from $111={settings[111]:g} deg/min, $121={accel:g} deg/s^2"),
        ("sweep down: firmware, command fed to UART -> last step",
         f"{statistics.mean(pulse_times) * 1e3:.1f} ms",
         f"ratio {statistics.mean(pulse_times) / ideal:.3f}, min {min(pulse_times) * 1e3:.1f}, "
         f"max {max(pulse_times) * 1e3:.1f} ms"),
        ("sweep up: firmware, host about to send -> last step",
         f"{statistics.mean(sim_times) * 1e3:.1f} ms",
         f"ratio {statistics.mean(sim_times) / ideal:.3f}, min {min(sim_times) * 1e3:.1f}, "
         f"max {max(sim_times) * 1e3:.1f} ms"),
        ("sweep up: host, command -> Idle seen (wall clock)",
         f"{statistics.mean(wall_times) * 1e3:.1f} ms",
         f"ratio {statistics.mean(wall_times) / ideal:.3f} (incl. 20 ms status polling)"),
        (f"sweep: {n + 1} positions, {n} moves, total (sim / wall / trapezoid)",
         f"{sum(sim_times):.3f} s",
         f"wall {sum(wall_times):.3f} s, trapezoid {n * ideal:.3f} s"),
        ("simulation pace (sim time / wall time)", f"{pace:.3f}", "1.000 = real time"),
        ("final yaw from the STEP pulses", f"{math.degrees(final.yaw_rad):+.4f} deg",
         f"{final.a_steps} steps (commanded -10 deg = {(30 - 10) * 800} steps)"),
        ("step rate at the limit, combined move, 20 ms polls", f"{full_rate:.0f} steps/s",
         f"limit {MAX_STEP_RATE:.0f}, ratio {full_rate / MAX_STEP_RATE:.3f}"),
        ("MCU CPU load at half the limit / at the limit", f"{full_load * 100:.1f} %",
         f"half: {half_load * 100:.1f} % at {half_rate:.0f} steps/s"),
        ("cost of a step (both axes stepping)", f"{per_step * 16e6:.0f} cycles",
         "from the two loads, 16 MHz"),
        ("step rate that would fill the CPU (ceiling)", f"{ceiling:.0f} steps/s",
         f"limit / ceiling {MAX_STEP_RATE / ceiling:.2f}; the old 30000 would be "
         f"{30000 / ceiling:.2f}"),
    ]
    w0 = max(len(r[0]) for r in rows)
    w1 = max(len(r[1]) for r in rows)
    print(f"| {'stage controller (bench_fw in simavr)':<{w0}} | {'value':>{w1}} | notes")
    print(f"|{'-' * (w0 + 2)}|{'-' * (w1 + 2)}|------")
    for name, value, note in rows:
        print(f"| {name:<{w0}} | {value:>{w1}} | {note}")
    me = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime
    wall = time.perf_counter() - T0
    print(f"CPU time: {cpu:.1f} s (this process and the harness), wall {wall:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
