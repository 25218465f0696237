"""Each driver's point cloud against the packets it came from: the pose estimated from the cloud
against the pose estimated from the packets, in the packets' sigmas.

    .venv/bin/python benchmarks/bench_cloud_drivers.py                  # 4 models, 3 poses each
    .venv/bin/python benchmarks/bench_cloud_drivers.py --models VLP-32C --poses 10

Per model (the twin's, its packets decoded by us), per driver's cloud of the same packets (the
ROS velodyne driver's XYZIRT and nebula's, written after their sources by
`twin.lidar.conventions`; velodyne_decoder's by velodyne_decoder itself), read back through
`twin.lidar.clouds` with the convention told by the fields or the points: the largest
|pose difference| / sigma over the six axes and the poses (the figure), against the anchor 1
sigma (ratio = anchor / figure: how far inside one sigma). The reference pose is the packets'
decoded with or without the lasers' vertical offsets as the driver writes them (the ROS driver
and nebula leave them out). Also the cloud read the old way (every laser's firing delay assumed
in its point): whether the board is still found.
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

import align
from twin.core.sensors import model_named
from twin.lidar.clouds import Cloud, scan_from_cloud
from twin.lidar.conventions import cloud_fields, nebula_cloud, ros_velodyne_cloud
from twin.lidar.packets import decode_data_packets
from twin.lidar.scans import scans_from_packets
from twin.sim.bench import BenchSim
from twin.sim.emulation import EmulationConfig
from twin.sim.params import BenchParams

HINTS = align.Hints(edge_tolerance=(0.0, 0.0))
VD_MODELS = {"VLP-16": "VLP16", "Puck Hi-Res": "PuckHiRes", "VLP-32C": "VLP32C",
             "HDL-32E": "HDL32E"}


def velodyne_decoder_cloud(payloads, timestamps_us, model: str) -> np.ndarray:
    import velodyne_decoder as vd

    packets = vd.PacketVector([vd.VelodynePacket(float(t) * 1e-6, bytes(p))
                               for t, p in zip(timestamps_us, payloads, strict=True)])
    cfg = vd.Config(model=getattr(vd.Model, VD_MODELS[model]))
    return vd.ScanDecoder(cfg).decode(packets, as_pcl_structs=True)[1]


def read(rec: np.ndarray, sensor, convention=None):
    fields, _ = cloud_fields(rec)
    cloud = Cloud.from_ros(rec["x"], rec["y"], rec["z"], **fields)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return scan_from_cloud(cloud, sensor.lasers, model=sensor, convention=convention)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--models", default="VLP-16,Puck Hi-Res,VLP-32C,HDL-32E")
    ap.add_argument("--poses", type=int, default=3)
    ap.add_argument("--seed", type=int, default=7)
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    print(f"\n# each driver's cloud vs its packets: {args.poses} random poses per model "
          f"(angles within +-3 deg), seed {args.seed}\n")
    print(f"{'model':12} {'driver':17} {'told':7} {'max |d|/sigma':>14} {'anchor':>7} "
          f"{'ratio':>7}  {'read the old way':>18}")
    for model in [m for m in args.models.split(",") if m]:
        sensor = model_named(model)
        worst: dict[str, list[float]] = {}
        told: dict[str, str] = {}
        old = {"found": 0, "n": 0}
        for _ in range(args.poses):
            r, t, y = rng.uniform(-3, 3, 3)
            noise = EmulationConfig(model=model, laser_offset_sigma=0.0, divergence=False)
            sim = BenchSim(BenchParams.from_edge(roll_deg=r, tilt_deg=t, yaw_deg=y),
                           seed=int(rng.integers(2**31)), noise=noise)
            payloads, _, _ = sim.packets(1)
            ref = {}
            for offsets in (True, False):
                scan = next(s for s in scans_from_packets(payloads, vertical_offsets=offsets)
                            if s.complete)
                ref[offsets] = align.estimate(scan, hints=HINTS)
            dec = decode_data_packets(payloads, vertical_offsets=False)
            clouds = {"ros-velodyne": ros_velodyne_cloud(dec), "nebula": nebula_cloud(dec),
                      "velodyne-decoder": velodyne_decoder_cloud(payloads, dec.timestamp_us,
                                                                 model)}
            for driver, rec in clouds.items():
                scan = read(rec, sensor)
                told[driver] = scan.meta["cloud_convention_from"]
                res = align.estimate(scan, hints=HINTS)
                want = ref[scan.vertical_offsets_applied]
                if not (res.success and want.success):
                    worst.setdefault(driver, []).append(np.inf)
                    continue
                z = (res.pose.as_array() - want.pose.as_array()) / np.sqrt(
                    np.diag(want.covariance))
                worst.setdefault(driver, []).append(float(np.abs(z).max()))
            wrong = read(clouds["ros-velodyne"], sensor, convention="aimbench")
            old["n"] += 1
            old["found"] += int(align.estimate(wrong, hints=HINTS).success)
        for driver, w in worst.items():
            fig = max(w)
            note = (f"{old['found']}/{old['n']} estimated" if driver == "ros-velodyne" else "")
            print(f"{model:12} {driver:17} {told[driver]:7} {fig:14.3f} {1.0:7.1f} "
                  f"{1.0 / fig if fig else np.inf:7.1f}  {note:>18}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
