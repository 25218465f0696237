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

Ouster OS0/OS1/OS2 x 32/64/128 (1024x10) go through `twin.sim.ouster_twin` (a real unit's
metadata, its LEGACY packets, our decoder), the Hesai PandarXT32 through `twin.sim.hesai_twin`
(nebula's angle corrections, its packets, our decoder); then two rows on Ouster decoding:
agreement with ouster-sdk on its own real capture, and frames per second against ouster-sdk's
(measured when ouster-sdk can be imported).
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_align import AXES, PAPER, UNITS, errors, random_pose

import align
from twin.core.sensors import MODELS
from twin.lidar.ouster import (
    OUSTER_MODELS,
    is_ouster_model,
    nominal_info,
    xyz_lidar,
)
from twin.lidar.scans import ScanAssembler
from twin.lidar.sources import open_scans
from twin.sim.bench import BenchSim
from twin.sim.emulation import EmulationConfig
from twin.sim.ouster_twin import write_ouster_pcap
from twin.sim.sensor_twins import own_twin_scans


def captured_scans(sim: BenchSim, n: int) -> list:
    """``n`` whole rotations of the twin as decoded from its own packets."""
    payloads, _, scans = sim.packets(n + 1)
    asm = ScanAssembler()
    whole = [s for s in asm.push_many(payloads) + asm.finish() if s.complete]
    truth = scans[0].meta["truth_pose"]
    return whole[:n], truth


def ouster_decode_rows() -> list[str]:
    """Decode agreement with ouster-sdk on its own real OS1-32 capture (its digest of every
    field; its XYZLut's points), and decode throughput against ouster-sdk's when installed."""
    import hashlib
    import json

    from twin.lidar.ouster import OusterInfo, decode_packets
    from twin.lidar.ouster import frames as ouster_frames
    from twin.lidar.pcap import read_pcap

    data = Path(__file__).resolve().parent.parent / "tests" / "data" / "ouster-os1-32"
    info = OusterInfo.from_json(data / "OS-1-32-G_v2.1.1_1024x10.json")
    payloads = [r.payload for r in read_pcap(data / "OS-1-32-G_v2.1.1_1024x10.pcap", ports=None)]
    (f,) = list(ouster_frames(decode_packets(payloads, info), info))
    digest = json.loads((data / "OS-1-32-G_v2.1.1_1024x10_digest.json").read_text())["scans"][0]
    md5 = {"RANGE": f.range_mm, "SIGNAL": f.signal, "NEAR_IR": f.near_ir,
           "REFLECTIVITY": f.reflectivity, "TIMESTAMP": f.timestamp_ns,
           "MEASUREMENT_ID": f.measurement_id, "STATUS": f.status.astype(np.uint64)}
    same = sum(hashlib.md5(np.ascontiguousarray(a).tobytes()).hexdigest() == digest[k]
               for k, a in md5.items())
    ref = json.loads((data / "OS-1-32-G_v2.1.1_1024x10_xyz_ouster_sdk.json").read_text())
    p = xyz_lidar(f.range_mm, info)[ref["row"], ref["column"]] * 1e-3
    p[:, 2] += info.lidar_to_sensor[2, 3] * 1e-3
    dxyz = float(np.abs(p - np.asarray(ref["xyz"])).max())
    rows = [f"decode agreement with ouster-sdk (its OS1-32 capture): {same}/{len(md5)} fields' "
            f"md5 equal (anchor {len(md5)}), points within {dxyz:.1e} m of its XYZLut's "
            f"({len(ref['row'])} points)"]
    # throughput: a 20-frame OS1-128 1024x10 pcap of the twin, through the source layer
    with tempfile.TemporaryDirectory() as tmp:
        pcap = Path(tmp) / "os1128.pcap"
        sim = BenchSim(seed=1)
        write_ouster_pcap(sim, nominal_info("OS1-128"), pcap, 20, rng=np.random.default_rng(1))
        best = min(_time(lambda: sum(1 for _ in open_scans(pcap))) for _ in range(3))
        ours = 20 / best
        try:
            from ouster.sdk import core, open_source

            def sdk() -> None:
                src = open_source(str(pcap), meta=[str(pcap.with_suffix(".json"))],
                                  index=False)
                lut = core.XYZLut(src.sensor_info[0], use_extrinsics=False)
                for fs in src:
                    lut(fs[0].field(core.ChanField.RANGE))

            theirs = 20 / min(_time(sdk) for _ in range(3))
            note = "measured now"
        except ImportError:
            theirs = 80.2  # ouster-sdk 1.0.1 in its own venv, this machine, one core, 2026-12-07
            note = "ouster-sdk not installed here (it pins rosbags 0.9.23): measured 2026-12-07"
    rows.append(f"decode throughput, OS1-128 1024x10 pcap -> scans (points in {{L}}): "
                f"{ours:.1f} frames/s; ouster-sdk pcap -> frames -> XYZLut {theirs:.1f} frames/s "
                f"({note}); ratio {ours / theirs:.2f}; real time needs 10")
    return rows


def _time(fn) -> float:
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--poses", type=int, default=10, help="random poses (paper: 200)")
    ap.add_argument("--scans", type=int, default=10, help="scans per pose (paper: 50)")
    ap.add_argument("--seed", type=int, default=2026)
    ap.add_argument("--models", default=",".join((*MODELS, *OUSTER_MODELS, "PandarXT32")),
                    help="comma-separated (Velodyne, Ouster, Hesai PandarXT32)")
    ap.add_argument("--no-decode", action="store_true",
                    help="skip the Ouster decode agreement and throughput rows")
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
        cfg = (None if is_ouster_model(model) or model == "PandarXT32" else
               EmulationConfig(model=model, laser_offset_sigma=0.0, divergence=False))
        rng = np.random.default_rng(args.seed)
        single = {m: ([], [], []) for m in methods}  # per-pose stds, errors, sigmas
        fused = {m: ([], []) for m in methods}
        fails = {m: [0, 0] for m in methods}
        cpu = dict.fromkeys(methods, 0.0)
        for _ in range(args.poses):
            params, x, yaw = random_pose(rng, 3.0, 30.0, 0.0)
            seed = int(rng.integers(2**31))
            if cfg is None:  # an Ouster's or the PandarXT32's own twin, through its packets
                scans, truth = own_twin_scans(params, model, x=x, yaw=np.deg2rad(yaw),
                                              n=args.scans, seed=seed)
            else:
                sim = BenchSim(params, seed=seed, noise=cfg)
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
    if not args.no_decode:
        print()
        for row in ouster_decode_rows():
            print(row)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
