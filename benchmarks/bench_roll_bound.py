"""What the hit/miss labels carry about roll: `rays` with the true plane against the estimated one.

    .venv/bin/python benchmarks/bench_roll_bound.py                  # base and sweep range
    .venv/bin/python benchmarks/bench_roll_bound.py --poses 50 --scans 10

Roll comes only from where rays hit or miss the board. Given the true plane, the `rays` posterior
(`align.posterior.hit_miss`, the exact hit/miss posterior) is what those labels allow: its RMS
over the paper's protocol is the single-scan roll bound for that geometry, measured rather than
derived. The same scans are estimated twice, once as `align.estimate` does (the ranges' plane,
integrated out) and once with the truth's plane substituted for the ranges' fit (a patch of
`align.rays.pipeline.label_posterior`, restored after). Protocols: the paper's (angles within +-3
deg, x within +-30 mm) and the bench's sweep range (stage yaw +-10 deg on top), sharp beam, 14 mm
noise, seed 2024 (the poses of `bench_align.py`). Prints roll RMS with the estimated and the true
plane, the issue's bound (0.22 deg, for the base geometry) and the ratios.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import sys
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_align import BOUNDS, random_pose

import align
import align.rays.pipeline
from align.geometry import plane_of_pose
from twin.sim.bench import BenchSim
from twin.sim.emulation import EmulationConfig

SHARP = align.Hints(edge_tolerance=(0.0, 0.0))


def roll_errors(stage_yaw_deg: float, poses: int, scans: int, seed: int
                ) -> tuple[np.ndarray, np.ndarray]:
    """Single-scan roll errors (rad) with the estimated and with the true plane, same scans."""
    cfg = EmulationConfig(laser_offset_sigma=0.0, divergence=False)
    rng = np.random.default_rng(seed)
    posterior = align.rays.pipeline.label_posterior
    truth: dict[str, np.ndarray] = {}

    def with_true_plane(rays, board, theta, sd_roll, ml_plane, n_scans, rng_):
        n, d = plane_of_pose(truth["pose"])
        # the ranges' covariance shrunk to nothing: the plane is known
        return posterior(rays, board, theta, sd_roll, (n, d, ml_plane[2] * 1e-8), n_scans, rng_)

    est, known = [], []
    try:
        for _ in range(poses):
            params, x, yaw = random_pose(rng, 3.0, 30.0, stage_yaw_deg)
            sim = BenchSim(params, seed=int(rng.integers(2**31)), noise=cfg)
            sim.move_to(x_m=x, yaw_rad=np.deg2rad(yaw))
            for s in [sim.scan() for _ in range(scans)]:
                truth["pose"] = t = s.meta["truth_pose"].as_array()
                align.rays.pipeline.label_posterior = posterior
                a = align.estimate(s, hints=SHARP)
                align.rays.pipeline.label_posterior = with_true_plane
                b = align.estimate(s, hints=SHARP)
                if a.success and b.success:
                    est.append(a.pose.roll - t[3])
                    known.append(b.pose.roll - t[3])
    finally:
        align.rays.pipeline.label_posterior = posterior
    return np.array(est), np.array(known)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--poses", type=int, default=200)
    ap.add_argument("--scans", type=int, default=20, help="scans per pose")
    ap.add_argument("--seed", type=int, default=2024)
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    bound = BOUNDS[1][1]
    print(f"# single-scan roll RMS, deg: {args.poses} poses x {args.scans} scans, seed "
          f"{args.seed}, sharp beam, 14 mm noise")
    print(f"{'protocol':22} {'estimated plane':>16} {'true plane':>11} {'issue bound':>12} "
          f"{'est./true':>10} {'true/bound':>11}")
    for name, yaw in (("paper (+-3 deg)", 0.0), ("sweep (stage +-10)", 10.0)):
        e, k = roll_errors(yaw, args.poses, args.scans, args.seed)
        rms_e, rms_k = (float(np.rad2deg(np.sqrt(np.mean(v**2)))) for v in (e, k))
        print(f"{name:22} {rms_e:16.4f} {rms_k:11.4f} {bound:12.3f} {rms_e / rms_k:10.3f} "
              f"{rms_k / bound:11.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
