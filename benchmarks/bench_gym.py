"""Environment steps per second of `aimbench/LidarAlign-v0` on the twin, against the real bench.

    .venv/bin/python benchmarks/bench_gym.py [--steps 20] [--episodes 5] [--scans 1,2]
                                             [--rounds 3]

The env runs over the MuJoCo twin (`SimBench`, every emulation effect on) with the real
estimator (`align`, default method). Two workloads, the same every round:

- random: one seeded episode of ``--steps`` steps to stage targets drawn uniformly within the
  paper's Monte Carlo range (+-3 deg, +-30 mm): the large moves of an exploring policy;
- scripted: ``--episodes`` seeded episodes of `scenarios.envs.lidar_align.scripted_policy` (read the
  estimate, command the correction) until aligned: small corrective moves.

Only `env.step` is timed. The process is pinned to one CPU core; each figure is the best of
``--rounds`` rounds. Wall time suffers from other load on the machine, so the table also gives
steps per CPU second of this process (what a quiet core would do) and the load average.

Anchor: the same steps on the real bench. A step there costs the stages' coordinated move (the
firmware's speeds and accelerations, `twin.stage.motion`) plus its scans at the VLP-16's 10 scans/s;
the env reports this as ``info["step_time_s"]``. Ratio > 1: the twin steps faster than the real
bench would.
"""

from __future__ import annotations

import argparse
import math
import os
import time
from collections.abc import Callable

import numpy as np

from scenarios.envs.lidar_align import LidarAlignEnv, scripted_policy

Policy = Callable[[dict, int], np.ndarray]  # (observation, step index) -> action


def timed_steps(env: LidarAlignEnv, episodes: list[tuple[int, Policy]],
                max_steps: int) -> dict[str, float]:
    """Run (seed, policy) episodes, up to `max_steps` steps each or until aligned; totals."""
    out = {"steps": 0, "wall": 0.0, "cpu": 0.0, "bench": 0.0, "estimate": 0.0}
    for seed, policy in episodes:
        obs, _ = env.reset(seed=seed)
        for k in range(max_steps):
            action = policy(obs, k)
            w0, c0 = time.perf_counter(), time.process_time()
            obs, _, terminated, truncated, info = env.step(action)
            out["wall"] += time.perf_counter() - w0
            out["cpu"] += time.process_time() - c0
            out["steps"] += 1
            out["bench"] += info["step_time_s"]
            out["estimate"] += env.last_estimate.timings.get("total", 0.0)
            if terminated or truncated:
                break
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=20, help="random-workload steps (default 20)")
    ap.add_argument("--episodes", type=int, default=5,
                    help="scripted-workload episodes (default 5)")
    ap.add_argument("--scans", default="1,2", help="scans per step to compare (default 1,2)")
    ap.add_argument("--rounds", type=int, default=3, help="rounds, best kept (default 3)")
    args = ap.parse_args()
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})

    half = np.array([math.radians(3.0), 0.030])
    targets = np.random.default_rng(0).uniform(-half, half, size=(args.steps, 2))

    rows = []
    for n in (int(v) for v in args.scans.split(",")):
        env = LidarAlignEnv(scans_per_step=n)

        def random_policy(obs: dict, k: int) -> np.ndarray:
            return targets[k]

        def scripted(obs: dict, k: int, env: LidarAlignEnv = env) -> np.ndarray:
            return scripted_policy(env, obs)

        workloads: dict[str, tuple[list[tuple[int, Policy]], int]] = {
            "random": ([(0, random_policy)], args.steps),
            "scripted": ([(s, scripted) for s in range(args.episodes)], 20),
        }
        try:
            for name, (episodes, max_steps) in workloads.items():
                best = None
                for _ in range(args.rounds):
                    r = timed_steps(env, episodes, max_steps)
                    best = r if best is None or r["wall"] < best["wall"] else best
                rows.append((name, n, best))
        finally:
            env.close()

    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"aimbench/LidarAlign-v0 on the twin: best of {args.rounds} rounds, one CPU core, "
          f"load average {load:.1f} on {os.cpu_count()} CPUs")
    head = ("workload", "scans/step", "steps", "twin steps/s", "steps/CPU-s",
            "real bench steps/s", "ratio", "estimator share")
    print(" | ".join(head))
    print(" | ".join("-" * len(h) for h in head))
    for name, n, r in rows:
        twin = r["steps"] / r["wall"]
        cpu = r["steps"] / r["cpu"]
        real = r["steps"] / r["bench"]
        print(f"{name:>8} | {n:>10d} | {r['steps']:>5d} | {twin:>12.2f} | {cpu:>11.2f} | "
              f"{real:>18.2f} | {twin / real:>4.1f}x | {r['estimate'] / r['wall']:>15.0%}")
    print("real bench steps/s: the same moves at the firmware's speeds and accelerations plus the "
          "scans at the VLP-16's 10 scans/s (info['step_time_s']); ratio = twin / real bench.")


if __name__ == "__main__":
    main()
