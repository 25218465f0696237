"""Environment steps per second of `aimbench/LidarAlign-v0` on the twin, against the real bench.

    .venv/bin/python benchmarks/bench_gym.py [--steps 20] [--scans 1,2,4] [--rounds 3]

Workload: the env over the MuJoCo twin (`SimBench`, every emulation effect on) with the real
estimator (`align`, default method). Each round resets with a fixed seed and takes ``--steps``
steps to stage targets drawn uniformly within the paper's Monte Carlo range (+-3 deg, +-30 mm),
the moves an alignment policy makes; the same targets every round. The process is pinned to one
CPU core; the figure is the best of ``--rounds`` rounds (the least disturbed by other load).

Anchor: the same steps on the real bench. A step there costs the stages' coordinated move (the
firmware's speeds and accelerations, `twin.motion`) plus its scans at the VLP-16's 10 scans/s;
the env reports this as ``info["step_time_s"]``. Ratio > 1: the twin steps faster than real time.
A second anchor: scans emulated and estimated per second against the sensor's 10 scans/s.
"""

from __future__ import annotations

import argparse
import math
import os
import time

import numpy as np

from twin.gym_env import SCAN_PERIOD_S, LidarAlignEnv

SENSOR_SCANS_PER_S = 1.0 / SCAN_PERIOD_S  # VLP-16 at 600 rpm


def run_round(env: LidarAlignEnv, actions: np.ndarray) -> dict[str, float]:
    """One seeded episode of `actions` (no early stop); wall and modelled times in s."""
    env.reset(seed=0)
    wall = est = bench_s = 0.0
    for a in actions:
        t0 = time.perf_counter()
        _, _, _, _, info = env.step(a)
        wall += time.perf_counter() - t0
        est += env.last_estimate.timings.get("total", 0.0) if env.last_estimate else 0.0
        bench_s += info["step_time_s"]
    return {"wall": wall, "estimate": est, "bench": bench_s}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=20, help="steps per round (default 20)")
    ap.add_argument("--scans", default="1,2,4", help="scans per step to compare (default 1,2,4)")
    ap.add_argument("--rounds", type=int, default=3, help="rounds, best kept (default 3)")
    args = ap.parse_args()
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})

    rng = np.random.default_rng(0)
    half = np.array([math.radians(3.0), 0.030])
    actions = rng.uniform(-half, half, size=(args.steps, 2))

    rows = []
    for n in (int(v) for v in args.scans.split(",")):
        env = LidarAlignEnv(scans_per_step=n)
        try:
            best = min((run_round(env, actions) for _ in range(args.rounds)),
                       key=lambda r: r["wall"])
        finally:
            env.close()
        twin_sps = args.steps / best["wall"]
        real_sps = args.steps / best["bench"]
        rows.append((n, twin_sps, real_sps, twin_sps / real_sps, twin_sps * n,
                     twin_sps * n / SENSOR_SCANS_PER_S, best["estimate"] / best["wall"]))

    print(f"aimbench/LidarAlign-v0 on the twin: {args.steps} steps to targets within +-3 deg, "
          f"+-30 mm; best of {args.rounds} rounds, one CPU core")
    head = ("scans/step", "twin steps/s", "real bench steps/s", "ratio",
            "scans/s", "vs sensor 10/s", "estimator share")
    print(" | ".join(head))
    print(" | ".join("-" * len(h) for h in head))
    for n, tw, rb, ratio, sps, vs, share in rows:
        print(f"{n:>10d} | {tw:>12.2f} | {rb:>18.2f} | {ratio:>5.2f}x | {sps:>7.2f} | "
              f"{vs:>13.2f}x | {share:>14.0%}")
    print("real bench steps/s: the same moves with the firmware's speeds and accelerations plus "
          "the scans at 10 scans/s (info['step_time_s']); ratio = twin / real bench.")


if __name__ == "__main__":
    main()
