"""Hesai's own ROS driver's cloud against the packets it came from: the pose estimated from the
cloud against the pose estimated from the packets, in the packets' sigmas.

    .venv/bin/python benchmarks/bench_hesai_ros_clouds.py                 # XT32 and QT128, 3 poses
    .venv/bin/python benchmarks/bench_hesai_ros_clouds.py --models PandarXT32 --poses 10

Per model (the twin's, its packets decoded by us), per random pose (angles within +-3 deg):
the driver's frames written as its cloud (`twin.lidar.hesai_ros_clouds.hesai_ros_cloud`, the
driver's defaults: Hesai's frame, no firetime file, frames cut at 0 deg) and read back
(`scan_from_hesai_ros`), fused over the frames, against the packets' own scans cut where the
frames begin: the largest |pose difference| / sigma over the six axes and the poses (the
figure), against the anchor 0.1 sigma (ratio = anchor / figure: how far inside it). Also the
same frames read as the driver's cloud stands (the head's rotation until each channel fires
left out: its largest |difference| / sigma, and the poses where it gave no estimate), and the
CPU to read one frame.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import align
from twin.lidar.hesai import (
    HesaiAngles,
    decode_hesai,
    default_angles,
    hesai_model,
    scans_from_hesai,
)
from twin.lidar.hesai_ros_clouds import frames, hesai_ros_cloud, scan_from_hesai_ros
from twin.sim.bench import BenchSim
from twin.sim.hesai_twin import emulate_hesai
from twin.sim.params import BenchParams

HINTS = align.Hints(edge_tolerance=(0.0, 0.0))  # the twin's sharp beam
ANCHOR = 0.1
FRAMES = {"PandarXT32": 3, "PandarQT128": 1}


def _z(res, want) -> float:
    if not (res.success and want.success):
        return float("inf")
    return float(np.abs((res.pose.as_array() - want.pose.as_array())
                        / np.sqrt(np.diag(want.covariance))).max())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--models", default="PandarXT32,PandarQT128")
    ap.add_argument("--poses", type=int, default=3)
    ap.add_argument("--seed", type=int, default=7)
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    print(f"\n# Hesai's ROS driver's cloud vs its packets: {args.poses} random poses per model "
          f"(angles within +-3 deg), seed {args.seed}\n")
    print(f"{'model':12} {'frames':>6} {'max |d|/sigma':>14} {'anchor':>7} {'ratio':>8}  "
          f"{'as it stands':>13} {'read s/frame':>13}")
    for name in [m for m in args.models.split(",") if m]:
        model = hesai_model(name)
        angles = HesaiAngles.from_csv(default_angles(model), model)
        n = FRAMES[model.name]
        worst, stands, cpu = [], [], []
        for _ in range(args.poses):
            r, t, y = rng.uniform(-3, 3, 3)
            sim = BenchSim(BenchParams.from_edge(roll_deg=r, tilt_deg=t, yaw_deg=y),
                           seed=int(rng.integers(2**31)))
            packets, _ = emulate_hesai(sim, angles, n + 1, rng=rng, start_cdeg=9000)
            dec = decode_hesai(packets, angles)
            fr = frames(packets, angles)[:n]
            cut = int(dec.block_azimuth_cdeg[fr[0].start, 0])
            by_packets = scans_from_hesai(dec, angles, cut_cdeg=cut)[:n]
            raw = scans_from_hesai(decode_hesai(packets, angles, firetime=False), angles,
                                   cut_cdeg=cut)[:n]
            clouds = [hesai_ros_cloud(packets, angles, packets=f) for f in fr]
            t0 = time.process_time()
            by_cloud = [scan_from_hesai_ros(c, angles) for c in clouds]
            cpu.append((time.process_time() - t0) / n)
            want = align.estimate(by_packets, hints=HINTS)
            worst.append(_z(align.estimate(by_cloud, hints=HINTS), want))
            stands.append(_z(align.estimate(raw, hints=HINTS), want))
        fig = max(worst)
        finite = [v for v in stands if np.isfinite(v)]
        lost = len(stands) - len(finite)  # poses where the cloud as it stands gave no estimate
        stood = f"{max(finite) if finite else np.inf:.2f}" + (f" ({lost} lost)" if lost else "")
        print(f"{model.name:12} {n:6d} {fig:14.3g} {ANCHOR:7.1f} "
              f"{ANCHOR / fig if fig else np.inf:8.3g}  {stood:>13} "
              f"{float(np.median(cpu)):13.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
