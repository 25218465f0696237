"""Beyond the VLP-16: the paper's method and ours on every model, on the paper's bench (twin).

    .venv/bin/python benchmarks/bench_models.py                     # 10 poses x 10 scans
    .venv/bin/python benchmarks/bench_models.py --poses 50 --scans 50 --models VLP-32C

The reference paper ends: "If the LiDAR is replaced with a higher resolution model, then the
proposed algorithm can provide a higher level of performance." This measures it. Protocol of
benchmarks/bench_align.py (paper, section IV-B): random poses, angles within +-3 deg and x within
+-30 mm, N scans each; the twin of each model (`twin.core.sensors`: its lasers, timing, distance
unit; the paper's 14 mm range noise scaled by the model's datasheet accuracy), laser offsets and
beam divergence off, the sharp beam told to the estimator. Every scan goes through the model's
packets, our decoder and the assembler first (what a user's capture of that sensor gives).

Per model, method (``paper``: section III; ``rays``: ours) and mode (single scan; N scans
fused), per axis (tilt, roll, yaw deg; x mm): precision = mean over poses of the per-pose
standard deviation of the single-scan estimates (fused: RMS error over poses), chi2 = mean of
(error / reported sigma)^2 (1 for an honest sigma). The anchor is the paper's own VLP-16
simulation precision (its table: 0.15 / 0.20 / 0.10 deg, 4.8 mm); ratio = anchor / figure (> 1:
better than the paper's VLP-16). The bound column (the information bound per model) is left to
`align.design.bound`. CPU seconds of this process (`time.process_time`), one BLAS thread.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_align import AXES, PAPER, UNITS, errors, random_pose

import align
from twin.core.sensors import MODELS
from twin.lidar.scans import ScanAssembler
from twin.sim.bench import BenchSim
from twin.sim.emulation import EmulationConfig


def captured_scans(sim: BenchSim, n: int) -> list:
    """``n`` whole rotations of the twin as decoded from its own packets."""
    payloads, _, scans = sim.packets(n + 1)
    asm = ScanAssembler()
    whole = [s for s in asm.push_many(payloads) + asm.finish() if s.complete]
    truth = scans[0].meta["truth_pose"]
    return whole[:n], truth


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--poses", type=int, default=10, help="random poses (paper: 200)")
    ap.add_argument("--scans", type=int, default=10, help="scans per pose (paper: 50)")
    ap.add_argument("--seed", type=int, default=2026)
    ap.add_argument("--models", default=",".join(MODELS), help="comma-separated")
    ap.add_argument("--methods", default="paper,rays", help="comma-separated")
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    models = [m for m in args.models.split(",") if m]
    methods = [m for m in args.methods.split(",") if m]
    hints = align.Hints(edge_tolerance=(0.0, 0.0))  # the twin's sharp beam (divergence off)
    anchor = np.array(PAPER["precision"])
    rows = []
    c_start = time.process_time()
    for model in models:
        cfg = EmulationConfig(model=model, laser_offset_sigma=0.0, divergence=False)
        rng = np.random.default_rng(args.seed)
        single = {m: ([], [], []) for m in methods}  # per-pose stds, errors, sigmas
        fused = {m: ([], []) for m in methods}
        fails = {m: [0, 0] for m in methods}
        cpu = dict.fromkeys(methods, 0.0)
        for _ in range(args.poses):
            params, x, yaw = random_pose(rng, 3.0, 30.0, 0.0)
            sim = BenchSim(params, seed=int(rng.integers(2**31)), noise=cfg)
            sim.move_to(x_m=x, yaw_rad=np.deg2rad(yaw))
            scans, truth = captured_scans(sim, args.scans)
            for m in methods:
                c0 = time.process_time()
                errs, sigs = [], []
                for s in scans:
                    est = align.estimate(s, method=m, hints=hints)
                    if est.success:
                        e, sg = errors(est, truth)
                        errs.append(e)
                        sigs.append(sg)
                    else:
                        fails[m][0] += 1
                if len(errs) > 1:
                    single[m][0].append(np.std(errs, axis=0, ddof=1))
                single[m][1].extend(errs)
                single[m][2].extend(sigs)
                est = align.estimate(scans, method=m, hints=hints)
                if est.success:
                    e, sg = errors(est, truth)
                    fused[m][0].append(e)
                    fused[m][1].append(sg)
                else:
                    fails[m][1] += 1
                cpu[m] += time.process_time() - c0
        for m in methods:
            stds, errs, sigs = (np.array(v).reshape(-1, 4) for v in single[m])
            if len(stds):
                rows.append((model, m, "single", "precision", stds.mean(axis=0),
                             np.nanmean((errs / sigs) ** 2, axis=0), fails[m][0]))
            fe, fs = (np.array(v).reshape(-1, 4) for v in fused[m])
            if len(fe):
                rows.append((model, m, f"fused {args.scans}", "RMS error",
                             np.sqrt((fe**2).mean(axis=0)), np.nanmean((fe / fs) ** 2, axis=0),
                             fails[m][1]))
            rows.append((model, m, "cpu", f"{cpu[m] / args.poses:.2f} s/pose", None, None, 0))
    print(f"\n# the paper's bench on the twin, per model: {args.poses} poses x {args.scans} "
          f"scans, angles within +-3 deg, x within +-30 mm, seed {args.seed}; "
          f"cpu {time.process_time() - c_start:.0f} s\n")
    hdr = " ".join(f"{a + ' ' + u:>10}" for a, u in zip(AXES, UNITS, strict=True))
    print(f"{'model':12} {'method':6} {'mode':9} {'figure':10} {hdr}  {'ratio (anchor/figure)':>34}"
          f"  {'chi2':>27} failed  bound")
    print(f"{'VLP-16':12} {'paper':6} {'table':9} {'anchor':10} "
          + " ".join(f"{v:10.3f}" for v in anchor) + "  (the paper's simulation precision)")
    for model, m, mode, name, v, chi2, failed in rows:
        if v is None:
            print(f"{model:12} {m:6} {mode:9} {name}")
            continue
        ratio = " ".join(f"{r:8.2f}" for r in anchor / v)
        print(f"{model:12} {m:6} {mode:9} {name:10} " + " ".join(f"{x:10.3f}" for x in v)
              + f"  {ratio:>34}  " + " ".join(f"{c:6.2f}" for c in chi2)
              + f" {failed:6d}  (align.design.bound)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
