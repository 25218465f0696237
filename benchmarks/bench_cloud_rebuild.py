"""What a point cloud costs against raw packets: the same twin scans estimated from their packets
and from a PCD export of them (returns only, the misses rebuilt by twin/lidar/clouds.py).

    .venv/bin/python benchmarks/bench_cloud_rebuild.py [--poses 3] [--scans 20] [--seed 7]

For each of ``--poses`` random poses of the paper's bench (mount angles within +-2 deg, stage yaw
within +-8 deg, x within +-20 mm; the twin's default noise, beam divergence on), the twin's
packets are assembled into scans (the anchor: what a pcap gives), written to a PCD file as a
ROS driver would (`aimbench decode --out X.pcd`) and read back. Per path: the firings
compared (count, misses, the rebuilt misses' azimuth error), and align's estimate per scan
against the twin's truth (RMS error of tilt, roll, yaw, x), side by side with the ratio.

Two more runs drop one packet per rotation (4.8 deg of firings): where it crosses the board's
centre, and where it crosses the board's right-hand edge. The pcap path knows a packet is
missing (the scan is flagged incomplete, the rays are absent); a cloud cannot know, and its
rebuilt grid turns the lost rays into misses. "flagged": scans marked incomplete. CPU seconds
of this process (`time.process_time`); wall time beside it.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import math
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import align
from twin.core import vlp16
from twin.lidar.capture import Packet, read_capture
from twin.lidar.export import export_scans
from twin.lidar.pcd import read_pcd_scans
from twin.sim.bench import BenchSim
from twin.sim.params import BenchParams

AXES = ("tilt_deg", "roll_deg", "yaw_deg", "x_mm")
CASES = {"whole": "every packet",
         "centre": "one packet per rotation lost where it crosses the board's centre",
         "edge": "one packet per rotation lost where it crosses the board's right-hand edge"}


def error(est: align.PoseEstimate, truth) -> np.ndarray | None:
    if not est.success:
        return None
    e = est.pose.as_array() - truth.as_array()
    return np.array([math.degrees(e[4]), math.degrees(e[3]), math.degrees(e[5]), 1e3 * e[0]])


def board_azimuths(truth, width_m: float = 0.9) -> tuple[float, float]:
    """Azimuths of the board's centre and of its right-hand edge seen from the LiDAR, rad."""
    rot = truth.rotation().T
    centre = -rot @ truth.translation
    edge = rot @ (np.array([width_m / 2, 0.0, 0.0]) - truth.translation)
    return math.atan2(centre[0], centre[1]), math.atan2(edge[0], edge[1])


def drop_packets(payloads: np.ndarray, at_rad: float) -> np.ndarray:
    """The payloads without the one per rotation whose 4.8 deg span holds azimuth ``at_rad``."""
    az = payloads[:, 2].astype(np.int64) | (payloads[:, 3].astype(np.int64) << 8)
    rel = (az / 100.0 - math.degrees(at_rad) + 180.0) % 360.0 - 180.0
    return payloads[~((rel > -4.0) & (rel <= 0.8))]


def assemble(payloads: np.ndarray) -> list:
    packets = [Packet(i * vlp16.PACKET_PERIOD, vlp16.DATA_PORT, bytes(p))
               for i, p in enumerate(payloads)]
    return [s for s in read_capture(packets).scans if not s.meta.get("partial")]


def _shift(a, b) -> int:
    """How many firings later the rebuilt scan ``b`` holds the packets' scan ``a``'s firings. A
    scan cut at an azimuth begins mid-sequence; the rebuilt grid begins with the first sequence
    that has a return, whole: ``a.laser_id[0]`` firings later, or a sequence less."""
    best, shift = math.inf, 0
    for s in (int(a.laser_id[0]) + d for d in (-16, 0, 16)):
        lo, hi = max(0, -s), min(len(a), len(b) - s)
        if hi - lo < 100:
            continue
        d = (a.azimuth[lo:hi] - b.azimuth[lo + s:hi + s] + np.pi) % (2 * np.pi) - np.pi
        if float(np.median(np.abs(d))) < best:
            best, shift = float(np.median(np.abs(d))), s
    return shift


def compare(raw: list, cloud: list) -> dict:
    """Firing-level agreement of the rebuilt scans with the packets' scans: laser ids, hits and
    misses, and azimuths, over the firings both hold."""
    same, az_err, extra = 0, [], 0
    for a, b in zip(raw, cloud, strict=True):
        s = _shift(a, b)
        lo, hi = max(0, -s), min(len(a), len(b) - s)
        ra, rb = slice(lo, hi), slice(lo + s, hi + s)
        extra += len(b) - len(a)
        if np.array_equal(a.laser_id[ra], b.laser_id[rb]) and np.array_equal(
                a.distance[ra] > 0, b.distance[rb] > 0):
            same += 1
            d = (a.azimuth[ra] - b.azimuth[rb] + np.pi) % (2 * np.pi) - np.pi
            az_err.append(float(np.degrees(np.abs(d)).max()))
    return {"same grid": f"{same}/{len(raw)}", "extra": extra / max(1, len(raw)),
            "max azimuth error deg": max(az_err) if az_err else float("nan")}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--poses", type=int, default=3)
    ap.add_argument("--scans", type=int, default=20, help="scans per pose")
    ap.add_argument("--seed", type=int, default=7)
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    rng = np.random.default_rng(args.seed)
    errs = {(case, path): [] for case in CASES for path in ("pcap", "pcd")}
    fails = dict.fromkeys(errs, 0)
    flagged = dict.fromkeys(errs, 0)
    cpu = {"decode": 0.0, "export+read": 0.0}
    wall0 = time.perf_counter()
    firing = []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(args.poses):
            roll, tilt, myaw = rng.uniform(-2.0, 2.0, 3)
            yaw = math.radians(rng.uniform(-8.0, 8.0))
            params = BenchParams.from_edge(roll_deg=roll, tilt_deg=tilt, yaw_deg=myaw)
            sim = BenchSim(params, seed=int(rng.integers(2**31)))
            sim.move_to(x_m=rng.uniform(-0.02, 0.02), yaw_rad=yaw)
            payloads, _, sim_scans = sim.packets(args.scans + 2)
            truth = sim_scans[0].meta["truth_pose"]
            centre, edge = board_azimuths(truth)
            for case, data in (("whole", payloads), ("centre", drop_packets(payloads, centre)),
                               ("edge", drop_packets(payloads, edge))):
                c0 = time.process_time()
                raw = assemble(data)
                cpu["decode"] += time.process_time() - c0
                c0 = time.process_time()
                pcd = Path(tmp) / f"pose{k}-{case}.pcd"
                export_scans(raw, pcd)
                cloud = read_pcd_scans(pcd)
                cpu["export+read"] += time.process_time() - c0
                if case == "whole":
                    firing.append(compare(raw, cloud))
                for path, scans in (("pcap", raw), ("pcd", cloud)):
                    flagged[(case, path)] += sum(not s.complete for s in scans)
                    for s in scans:
                        e = error(align.estimate(s), truth)
                        if e is None:
                            fails[(case, path)] += 1
                        else:
                            errs[(case, path)].append(e)
            print(f"  {k + 1}/{args.poses} poses, {time.perf_counter() - wall0:.0f} s wall",
                  file=sys.stderr)

    n = args.poses * args.scans
    print(f"\n# a PCD export against its packets: {args.poses} poses x ~{args.scans} whole "
          f"scans of the twin (seed {args.seed}), align's default method, single scans")
    print("\nfirings (rebuilt from the cloud vs the packets' scans):")
    for k, f in enumerate(firing):
        print(f"  pose {k}: the same firings, hits and misses in {f['same grid']} scans "
              f"({f['extra']:.1f} firings more per scan: the cut sequences completed), "
              f"azimuths within {f['max azimuth error deg']:.4f} deg")
    for case, title in CASES.items():
        print(f"\n{title}: RMS error against the truth (anchor: the pcap path)")
        header = f"{'source':<8} {'ok':>9} {'flagged':>8} " + " ".join(f"{a:>10}" for a in AXES)
        print(header)
        print("-" * len(header))
        rms = {}
        for path in ("pcap", "pcd"):
            e = np.array(errs[(case, path)]).reshape(-1, 4)
            rms[path] = np.sqrt(np.mean(e**2, axis=0)) if len(e) else np.full(4, np.nan)
            ok = f"{len(e)}/{len(e) + fails[(case, path)]}"
            print(f"{path:<8} {ok:>9} {flagged[(case, path)]:>8} "
                  + " ".join(f"{v:10.4f}" for v in rms[path]))
        print(f"{'pcd/pcap':<8} {'':>9} {'':>8} " + " ".join(f"{v:10.2f}" for v in rms["pcd"] /
                                                                 rms["pcap"]))
    print(f"\nCPU: assembling packets into scans {cpu['decode']:.2f} s, PCD export and read "
          f"with the grid rebuilt {cpu['export+read']:.2f} s (for ~{3 * n} scans); "
          f"wall {time.perf_counter() - wall0:.0f} s in all")
    return 0


if __name__ == "__main__":
    sys.exit(main())
