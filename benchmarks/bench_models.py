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
better than the paper's VLP-16). Method ``bound``: the precision bound of `align.design.bound`
at each pose's truth with the model's lasers and firing (`twin.sim.sensor_twins.firing_of` for
an Ouster's or a Hesai's twin, a Velodyne's own firing sequence) and the twin's range noise with
the packet's unit, RMS over poses, single and fused (the beam sharp, as the twins'). CPU seconds
of this process (`time.process_time`), one BLAS thread.

Ouster OS0/OS1/OS2 x 32/64/128 (1024x10) go through `twin.sim.ouster_twin` (a real unit's
metadata, its LEGACY packets, our decoder), the Hesai PandarXT32 and PandarQT128 through
`twin.sim.hesai_twin` (nebula's angle corrections, their packets with each channel cast where
the head turned to when it fired, our decoder, which puts that rotation back as Hesai's SDK 2.0
does with its firetime file); then the decode rows: Ouster agreement with ouster-sdk on its own
real captures (LEGACY and the other packet profiles) and on the twin's OS1-128 pcap (LEGACY and
RNG19_RFL8_SIG16_NIR16), and frames per second against ouster-sdk's, both
run now beside ours (ouster-sdk from the extra ``ouster``, `tools/setup.sh ouster`; without it
those rows say so), and each Hesai model's agreement with nebula's decoder on a real capture
(its test's ground-truth points; our decode without the firing rotation, as nebula's).
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import contextlib
import math
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
from twin.sim.sensor_twins import HESAI_MODELS as HESAI
from twin.sim.sensor_twins import own_twin_scans


def captured_scans(sim: BenchSim, n: int) -> list:
    """``n`` whole rotations of the twin as decoded from its own packets."""
    payloads, _, scans = sim.packets(n + 1)
    asm = ScanAssembler()
    whole = [s for s in asm.push_many(payloads) + asm.finish() if s.complete]
    truth = scans[0].meta["truth_pose"]
    return whole[:n], truth


def ouster_decode_rows() -> list[str]:
    """Decode agreement with ouster-sdk, run now beside ours: on its own real OS1-32 capture
    (its digest of every field; ouster-sdk's decode of every frame, field for field; its
    XYZLut's points) and on a 20-frame OS1-128 1024x10 pcap of the twin (the same); then decode
    throughput of that pcap, ours and ouster-sdk's, and of the same frames as an OSF."""
    import hashlib
    import json

    from twin.lidar.ouster import OusterInfo, decode_packets
    from twin.lidar.ouster import frames as ouster_frames
    from twin.lidar.ouster_sdk import OusterSdkMissingError, sdk
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
    rows = [f"decode agreement with ouster-sdk's digest (its OS1-32 capture): {same}/{len(md5)} "
            f"fields' md5 equal (anchor {len(md5)})"]
    try:
        sdk("the comparison with ouster-sdk")
    except OusterSdkMissingError as exc:
        return [*rows, f"ouster-sdk rows skipped: {exc}"]
    rows.append(_sdk_agreement_row("its OS1-32 capture", data / "OS-1-32-G_v2.1.1_1024x10.pcap",
                                   data / "OS-1-32-G_v2.1.1_1024x10.json"))
    for folder, pcap, meta in PROFILE_CAPTURES:  # its captures in the other packet profiles
        d = data.parent / folder
        profile = OusterInfo.from_json(d / meta).udp_profile_lidar
        rows.append(_sdk_agreement_row(f"its {pcap}, {profile}", d / pcap, d / meta))
    with tempfile.TemporaryDirectory() as tmp:
        rows += _ouster_throughput_rows(Path(tmp))
    return rows


#: ouster-sdk's own captures in the packet profiles other than LEGACY (tests/data/SOURCE.md):
#: folder, pcap, metadata.
PROFILE_CAPTURES = (
    ("ouster-os2-128-rng19", "OS-2-128-U1_v2.3.0_1024x10.pcap", "OS-2-128-U1_v2.3.0_1024x10.json"),
    ("ouster-os0-32-dual", "OS-0-32-U1_v2.2.0_1024x10.pcap", "OS-0-32-U1_v2.2.0_1024x10.json"),
    ("ouster-os0-128-rng15", "OS-0-128-U1_v2.3.0_1024x10.pcap", "OS-0-128-U1_v2.3.0_1024x10.json"),
    ("ouster-fw3-crc", "crc_test.pcap", "crc_test.json"),
    ("ouster-os1-128-fusa-dual", "OS-1-128_767798045_1024x10_20230712_120049.pcap",
     "OS-1-128_767798045_1024x10_20230712_120049.json"),
)


def _sdk_agreement_row(what: str, pcap: Path, metadata: Path) -> str:
    """ouster-sdk's decode of a pcap against ours, frame by frame: the fields equal, and the
    largest difference of its XYZLut's points from ours."""
    from twin.lidar.ouster import OusterInfo, decode_packets
    from twin.lidar.ouster import frames as ouster_frames
    from twin.lidar.ouster_sdk import pcap_frames, sdk, sdk_xyz
    from twin.lidar.pcap import read_pcap

    info = OusterInfo.from_json(metadata)
    ours = list(ouster_frames(decode_packets(
        [r.payload for r in read_pcap(pcap, ports=None)], info), info))
    _, theirs, lidar_frames = pcap_frames(pcap, metadata)
    fields = ("range_mm", "reflectivity", "signal", "near_ir", "timestamp_ns", "measurement_id",
              "status")
    equal = sum(all(np.array_equal(getattr(a, k), getattr(b, k)) for k in fields)
                and a.frame_id == b.frame_id for a, b in zip(ours, theirs, strict=False))
    sensor_info = sdk()[0].SensorInfo(metadata.read_text())
    dxyz = 0.0
    for lf, a in zip(lidar_frames, ours, strict=False):
        hit = a.range_mm > 0
        mine = xyz_lidar(a.range_mm, info) * 1e-3 + info.lidar_to_sensor[:3, 3] * 1e-3
        dxyz = max(dxyz, float(np.abs(sdk_xyz(lf, sensor_info)[hit] - mine[hit]).max()))
    return (f"decode agreement with ouster-sdk {_sdk_version()} run now ({what}): "
            f"{equal}/{len(ours)} frames with all {len(fields)} fields and the frame id equal "
            f"(ouster-sdk: {len(theirs)} frames), points within {dxyz:.1e} m of its XYZLut's")


def _sdk_version() -> str:
    from importlib.metadata import version

    return version("ouster-sdk")


def _ouster_throughput_rows(tmp: Path) -> list[str]:
    """A 20-frame OS1-128 1024x10 pcap of the twin (and its frames as an OSF): agreement, then
    frames a second, ours (pcap -> scans in {L}, through the source layer) against ouster-sdk's
    (pcap -> frames -> XYZLut, its C++), the least CPU time of `_RUNS` each, run in turn now;
    the same for the frames as RNG19_RFL8_SIG16_NIR16 packets."""
    from twin.lidar.ouster_sdk import sdk
    from twin.sim.ouster_twin import write_ouster_osf

    pcap, osf = tmp / "os1128.pcap", tmp / "os1128.osf"
    info = nominal_info("OS1-128")
    write_ouster_pcap(BenchSim(seed=1), info, pcap, 20, rng=np.random.default_rng(1))
    write_ouster_osf(BenchSim(seed=1), info, osf, 20, rng=np.random.default_rng(1))
    rows = [_sdk_agreement_row("the twin's OS1-128 pcap", pcap, pcap.with_suffix(".json"))]
    core, _, pcap_mod = sdk()

    def theirs_pcap(pcap: Path = pcap) -> None:
        src = pcap_mod.PcapFrameSetSource(str(pcap), meta=[str(pcap.with_suffix(".json"))])
        lut = core.XYZLut(src.sensor_info[0], use_extrinsics=False)
        for fs in src:
            lut(fs[0].field(core.ChanField.RANGE))
        src.close()

    ours, theirs, ours_osf = (20 / t for t in _best_times(
        lambda: sum(1 for _ in open_scans(pcap)), theirs_pcap,
        lambda: sum(1 for _ in open_scans(osf))))
    # the same frames in the profile recent firmware sends by default
    r19 = tmp / "os1128-rng19.pcap"
    write_ouster_pcap(BenchSim(seed=1), nominal_info("OS1-128", "1024x10",
                                                     "RNG19_RFL8_SIG16_NIR16"),
                      r19, 20, rng=np.random.default_rng(1))
    rows.append(_sdk_agreement_row("the twin's OS1-128 RNG19_RFL8_SIG16_NIR16 pcap", r19,
                                   r19.with_suffix(".json")))
    ours_r19, theirs_r19 = (20 / t for t in _best_times(
        lambda: sum(1 for _ in open_scans(r19)), lambda: theirs_pcap(r19)))
    rows.append(f"decode throughput, OS1-128 1024x10 pcap -> scans (points in {{L}}): "
                f"{ours:.1f} frames/s; ouster-sdk pcap -> frames -> XYZLut {theirs:.1f} frames/s "
                f"(measured now, the same pcap, CPU time, best of {_RUNS} taken in turn); ratio "
                f"{ours / theirs:.2f}; real time needs 10")
    rows.append(f"OSF read, the same 20 frames (ouster-sdk's reader -> our scans): "
                f"{ours_osf:.1f} frames/s")
    rows.append(f"the same 20 frames as RNG19_RFL8_SIG16_NIR16 packets -> scans: "
                f"{ours_r19:.1f} frames/s (LEGACY's above: {ours:.1f}); ouster-sdk "
                f"{theirs_r19:.1f} frames/s; ratio {ours_r19 / theirs_r19:.2f}")
    return rows


#: Per Hesai model: its real capture in tests/data, nebula's points of it, nebula's test's
#: nearest range (m; nebula keeps a return at it: 0.3 m, 75 units, is common on the QT128)
#: and dual-return threshold (m; 0: only an echo repeated is dropped).
HESAI_CASES = {
    "PandarXT32": ("nebula-xt32", "xt32-one-turn.pcap", "xt32-nebula-points-first-quarter.npy",
                   0.05, 0.0),
    "PandarQT128": ("nebula-qt128", "qt128-first-quarter.pcap",
                    "qt128-nebula-points-first-quarter.npy", 0.3, 0.1),
}


def hesai_decode_rows(models: list[str]) -> list[str]:
    """Each Hesai model's decode agreement with nebula's C++ decoder: its real capture
    (nebula's decoder test recording) against the ground-truth points nebula's decoder wrote
    of its first quarter, with nebula's test settings, nearest neighbours both ways (as
    tests/test_hesai.py and tests/test_hesai_qt128.py)."""
    from scipy.spatial import cKDTree

    from twin.lidar.hesai import HesaiAngles, decode_hesai
    from twin.lidar.pcap import read_pcap

    data = Path(__file__).resolve().parent.parent / "tests" / "data"
    rows = []
    for model in (m for m in models if m in HESAI_CASES):
        folder, pcap, points, near, threshold = HESAI_CASES[model]
        angles = HesaiAngles.from_csv(data / folder / f"{model}.csv", model)
        payloads = [r.payload for r in read_pcap(data / folder / pcap)]
        # nebula's azimuths: its decoder leaves the firing rotation out (twin.lidar.hesai)
        dec = decode_hesai(payloads, angles, firetime=False)
        d = dec.distance
        keep = (d >= near) & (d <= angles.model.max_range)
        # a dual pair's first block (the last return): dropped when it repeats the strongest,
        # or is within the threshold of it (nebula's hesai_decoder.hpp convert_returns)
        gap = np.abs(d[:, 0::2] - d[:, 1::2])
        keep[:, 0::2] &= gap >= threshold if threshold else gap > 0
        xyz = np.stack([dec.x, dec.y, dec.z], axis=-1)
        ours = xyz[keep]
        if model == "PandarXT32":  # the rotation's packets up to 90 deg (the first: the turn
            # before, but for its blocks past 0 deg)
            end = 1 + int(np.argmax(dec.block_azimuth_cdeg[1:, 0] >= 9000))
            quarter = xyz[1:end][keep[1:end]]
        else:  # the quarter by the points' own azimuth
            a = np.degrees(np.arctan2(ours[:, 0], ours[:, 1])) % 360
            quarter = ours[(a >= 0) & (a < 90)]
        truth = np.load(data / folder / points).astype(np.float64)
        to_ours, _ = cKDTree(ours).query(truth)
        to_truth, _ = cKDTree(truth).query(quarter)
        rows.append(f"decode agreement with nebula's decoder ({model}, its real capture): "
                    f"quarter rotation {len(quarter)} points, its {len(truth)}; each of its "
                    f"within {to_ours.max():.1e} m of ours, each of ours within "
                    f"{to_truth.max():.1e} m of its")
    return rows


def bound_of(model: str, truth, n: int, seed: int, lasers) -> np.ndarray:
    """The precision bound (tilt, roll, yaw deg, x mm) of ``n`` scans at ``truth`` (the board
    frame of the paper's level board) for the model's lasers and firing."""
    from align.design.bound import Firing, RangeNoise, precision_bound
    from twin.core.sensors import model_named
    from twin.sim.sensor_twins import firing_of

    own = firing_of(model)
    if own is not None:  # an Ouster's or a Hesai's twin: 10 mm noise, its packet's unit
        firing = Firing(rpm=own.rpm, period=own.period, laser_times=own.laser_times,
                        phase_locked=own.phase_locked)
        sigma, unit = 0.01, (0.004 if model in HESAI else 0.001)
    else:  # a Velodyne's: BenchSim's noise for the model (the paper's scaled), its unit
        m = model_named(model)
        firing = Firing(rpm=600.0, period=m.sequence_period,
                        laser_times=tuple(float(v) for v in m.firing_offset))
        sigma = float(EmulationConfig(model=model).range_noise_sigma)
        unit = m.distance_unit
    noise = RangeNoise(sigma=float(np.hypot(sigma, unit / np.sqrt(12))), offset_sigma=0.0)
    b = precision_bound(truth, lasers=lasers, firing=firing, noise=noise, n_scans=n, seed=seed)
    std = np.asarray(b.std)
    return np.array([np.degrees(std[4]), np.degrees(std[3]), np.degrees(std[5]), std[0] * 1e3])


#: Runs of each throughput measurement (the best is kept).
_RUNS = 5


def _best_times(*fns) -> list[float]:
    """Each function's least CPU time (s; the process's, so other work on shared cores counts
    less than in wall time) over `_RUNS` runs, the functions run in turn."""
    best = [math.inf] * len(fns)
    for _ in range(_RUNS):
        for i, fn in enumerate(fns):
            t = time.process_time()
            fn()
            best[i] = min(best[i], time.process_time() - t)
    return best


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--poses", type=int, default=10, help="random poses (paper: 200)")
    ap.add_argument("--scans", type=int, default=10, help="scans per pose (paper: 50)")
    ap.add_argument("--seed", type=int, default=2026)
    ap.add_argument("--models", default=",".join((*MODELS, *OUSTER_MODELS, *HESAI)),
                    help="comma-separated (Velodyne, Ouster, Hesai PandarXT32, PandarQT128)")
    ap.add_argument("--no-decode", action="store_true",
                    help="skip the Ouster and Hesai decode agreement and throughput rows")
    ap.add_argument("--no-bound", action="store_true", help="skip the bound rows")
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
        cfg = (None if is_ouster_model(model) or model in HESAI else
               EmulationConfig(model=model, laser_offset_sigma=0.0, divergence=False))
        rng = np.random.default_rng(args.seed)
        single = {m: ([], [], []) for m in methods}  # per-pose stds, errors, sigmas
        fused = {m: ([], []) for m in methods}
        fails = {m: [0, 0] for m in methods}
        cpu = dict.fromkeys(methods, 0.0)
        bounds: dict[str, list] = {"single": [], f"fused {args.scans}": []}
        for _ in range(args.poses):
            params, x, yaw = random_pose(rng, 3.0, 30.0, 0.0)
            seed = int(rng.integers(2**31))
            if cfg is None:  # an Ouster's or a Hesai's own twin, through its packets
                scans, truth = own_twin_scans(params, model, x=x, yaw=np.deg2rad(yaw),
                                              n=args.scans, seed=seed)
            else:
                sim = BenchSim(params, seed=seed, noise=cfg)
                sim.move_to(x_m=x, yaw_rad=np.deg2rad(yaw))
                scans, truth = captured_scans(sim, args.scans)
            if not args.no_bound:
                for mode, n in zip(bounds, (1, args.scans), strict=True):
                    with contextlib.suppress(ValueError):  # a geometry the bound cannot take
                        bounds[mode].append(bound_of(model, truth, n, seed, scans[0].lasers))
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
        for mode, b in bounds.items():
            if b:
                rows.append((model, "bound", mode, "RMS", np.sqrt(np.mean(np.square(b), axis=0)),
                             None, 0))
    print(f"\n# the paper's bench on the twin, per model: {args.poses} poses x {args.scans} "
          f"scans, angles within +-3 deg, x within +-30 mm, seed {args.seed}; "
          f"cpu {time.process_time() - c_start:.0f} s\n")
    hdr = " ".join(f"{a + ' ' + u:>10}" for a, u in zip(AXES, UNITS, strict=True))
    print(f"{'model':12} {'method':6} {'mode':9} {'figure':10} {hdr}  {'ratio (anchor/figure)':>34}"
          f"  {'chi2':>27} failed")
    print(f"{'VLP-16':12} {'paper':6} {'table':9} {'anchor':10} "
          + " ".join(f"{v:10.3f}" for v in anchor) + "  (the paper's simulation precision)")
    for model, m, mode, name, v, chi2, failed in rows:
        if v is None:
            print(f"{model:12} {m:6} {mode:9} {name}")
            continue
        ratio = " ".join(f"{r:8.2f}" for r in anchor / v)
        chi = (" ".join(f"{c:6.2f}" for c in chi2) + f" {failed:6d}") if chi2 is not None else ""
        print(f"{model:12} {m:6} {mode:9} {name:10} " + " ".join(f"{x:10.3f}" for x in v)
              + f"  {ratio:>34}  " + chi)
    if not args.no_decode:
        print()
        if any(is_ouster_model(m) for m in models):
            for row in ouster_decode_rows():
                print(row)
        for row in hesai_decode_rows(models):
            print(row)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
