"""`aimbench simulate`: a lidar capture of the simulated bench, with the true pose of every scan.

    aimbench simulate --yaw-deg 5 --x-mm 10 --roll-deg 0.5 --tilt-deg -1 --scans 20 --seed 1 \\
        --out capture.pcap

writes ``capture.pcap`` (any Velodyne tool reads it; ``--model`` picks VLP-16, Puck Hi-Res,
VLP-32C or HDL-32E, default the station's sensor.model) and ``capture.truth.json`` beside it:
the bench (its station and parameters), the emulation settings and, for every scan, the true
LiDAR pose in the board frame (x_m, y_m, z_m, roll_deg, tilt_deg, yaw_deg) at the scan's first
firing.

The twin is built from ``--station FILE`` (docs/station.md; default: the paper's bench); the
mount misalignments add to the station's nominal mount, and the stage positions must lie within
the station's travel.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from pathlib import Path
from typing import TYPE_CHECKING

from models import SCENES  # the MJCF files' paths only
from scenarios import cliargs, station_options
from twin.core.errors import AimbenchError
from twin.core.sensor_names import (
    HESAI_NAMES,
    LIDAR_MODES,
    OUSTER_MODELS,
    OUSTER_TWIN_PROFILES,
    VELODYNE_NAMES,
)

# The station model, the twin and the writers are imported by the functions that run (pydantic,
# numpy, MuJoCo: about a second), not for the parser (issue 38).
if TYPE_CHECKING:
    from scenarios import station as stations


def _jsonable(obj) -> dict:
    return {k: (list(v) if isinstance(v, tuple) else v)
            for k, v in dataclasses.asdict(obj).items()}


def _check_travel(station: stations.Station, args: argparse.Namespace) -> None:
    """The stage positions within the station's travel (the twin's own is checked on the move)."""
    (y0, y1), (x0, x1) = station.travel()
    yaw, x = math.radians(args.yaw_deg), args.x_mm * 1e-3
    if not (y0 - 1e-12 <= yaw <= y1 + 1e-12 and x0 - 1e-12 <= x <= x1 + 1e-12):
        s = station.stages
        raise AimbenchError(
            f"--yaw-deg {args.yaw_deg:g} / --x-mm {args.x_mm:g} is outside the travel the "
            f"station allows (stages.yaw_travel_deg {list(s.yaw_travel_deg)}, stages.x_travel_mm "
            f"{list(s.x_travel_mm)}); move less or widen the travel in the station file")


def run(args: argparse.Namespace) -> int:
    from scenarios import station as stations
    from scenarios.truth import write_truth
    from twin.lidar.ouster import is_ouster_model
    from twin.sim.bench import BenchSim
    from twin.sim.emulation import EmulationConfig

    if args.scans < 1:
        raise AimbenchError("--scans must be at least 1")
    out = Path(args.out)
    if not out.parent.exists():
        raise AimbenchError(f"the folder of --out {out} does not exist; create it first")
    station, station_file = stations.from_args(args, twin=True)
    _check_travel(station, args)
    base = station.bench_params(**({} if args.scene is None else {"scene": args.scene}))
    params = dataclasses.replace(
        base, mount_roll=base.mount_roll + math.radians(args.roll_deg),
        mount_tilt=base.mount_tilt + math.radians(args.tilt_deg),
        mount_yaw=base.mount_yaw + math.radians(args.mount_yaw_deg))
    model = args.model or station.sensor.model
    if out.suffix.lower() == ".osf":
        _check_osf(model)
    if is_ouster_model(model):
        return _simulate_ouster(args, params, model, out, station, station_file)
    if model in HESAI_NAMES:
        return _simulate_hesai(args, params, model, out, station, station_file)
    try:
        noise = (EmulationConfig.ideal(model=model) if args.ideal
                 else EmulationConfig(model=model))
        noise = noise.with_(rpm=args.rpm, return_mode=args.return_mode)
    except ValueError as exc:
        raise AimbenchError(f"{exc}; pick a value inside the {model}'s range") from None
    sim = BenchSim(params, seed=args.seed, noise=noise)
    sim.move_to(x_m=args.x_mm * 1e-3, yaw_rad=math.radians(args.yaw_deg))  # checks the travel
    scans = sim.write_pcap(out, args.scans)
    truth = write_truth(
        out, scans, seed=args.seed, ideal=bool(args.ideal),
        stage={"x_mm": sim.stage_x() * 1e3, "yaw_deg": math.degrees(sim.stage_yaw())},
        station=station.to_dict(), station_file=station_file,
        params=_jsonable(params), emulation=_jsonable(noise),
        laser_offsets_m=[float(v) for v in sim.emulator.laser_offsets])
    if not args.quiet:
        p = scans[0].meta["truth_pose"]
        # The stages' position and the LiDAR's pose in the board frame {O} are two things:
        # "--x-mm 10" then "true pose: x 710.0 mm" read as a wrong x (issue 37).
        print(f"wrote {out} ({len(scans)} scans) and {truth.name}; stages at stage_x "
              f"{args.x_mm:+.1f} mm, stage yaw {args.yaw_deg:+.3f} deg; true pose of the LiDAR "
              f"in the board frame {{O}}: x {p.x * 1e3:.1f} mm, y {p.y * 1e3:.1f} mm, "
              f"z {p.z * 1e3:.1f} mm, roll {_deg(p.roll)} deg, tilt {_deg(p.tilt)} deg, "
              f"yaw {_deg(p.yaw)} deg")
    return 0


def _deg(rad: float) -> str:
    """Degrees to 3 decimals, a value that rounds to zero printed 0.000, not -0.000."""
    return f"{round(math.degrees(rad), 3) + 0.0:.3f}"


def _truth_file(args: argparse.Namespace, out: Path, scans: list, sim, station: stations.Station,
                station_file, params, sensor: dict) -> Path:
    """The truth file of another sensor's capture of the twin: what `simulate` writes for a
    Velodyne's, with the sensor it emulated."""
    from scenarios.truth import write_truth

    return write_truth(out, scans, seed=args.seed, ideal=bool(args.ideal),
                       stage={"x_mm": sim.stage_x() * 1e3,
                              "yaw_deg": math.degrees(sim.stage_yaw())},
                       station=station.to_dict(), station_file=station_file,
                       params=_jsonable(params), sensor=sensor)


def _check_osf(model: str) -> None:
    """An OSF (`--out FILE.osf`) is an Ouster's frames, written by ouster-sdk: both checked
    before the twin is built."""
    from scenarios.extras import require
    from twin.lidar.ouster import is_ouster_model

    if not is_ouster_model(model):
        raise AimbenchError(f"--out FILE.osf writes an Ouster's frames, not a {model}'s: give "
                            f"--model {OUSTER_MODELS[0]} (or another Ouster), or write .pcap")
    require("ouster.sdk", "--out FILE.osf")


def _simulate_ouster(args: argparse.Namespace, params, model: str, out: Path,
                     station: stations.Station, station_file) -> int:
    """An Ouster's frames of the twin's bench (`twin.sim.ouster_twin`): the pcap with its
    metadata JSON beside it (what the sensor's tools record), or an OSF with the metadata in
    it (``--out FILE.osf``, through ouster-sdk), and the truth file."""
    import numpy as np

    from twin.lidar.ouster import nominal_info, scans_from_payloads
    from twin.lidar.pcap import read_pcap
    from twin.lidar.sources import open_scans
    from twin.sim.bench import BenchSim
    from twin.sim.ouster_twin import write_ouster_osf, write_ouster_pcap

    info = nominal_info(model, args.lidar_mode, args.udp_profile)
    sim = BenchSim(params, seed=args.seed)
    sim.move_to(x_m=args.x_mm * 1e-3, yaw_rad=math.radians(args.yaw_deg))  # checks the travel
    rng = np.random.default_rng(args.seed)
    osf = out.suffix.lower() == ".osf"
    write = write_ouster_osf if osf else write_ouster_pcap
    truth_pose = write(sim, info, out, args.scans, rng=rng,
                       range_sigma=0.0 if args.ideal else 0.01)
    if osf:  # read back through ouster-sdk, as `estimate` reads it
        with open_scans(out) as source:
            scans = list(source)
    else:
        scans = scans_from_payloads([r.payload for r in read_pcap(out, ports=None)], info)
    for s in scans:
        s.meta["truth_pose"] = truth_pose
    truth = _truth_file(args, out, scans, sim, station, station_file, params,
                        {"model": model, "lidar_mode": args.lidar_mode,
                         "udp_profile_lidar": args.udp_profile, "metadata": info.source})
    if not args.quiet:
        p = truth_pose
        meta = "its metadata in it" if osf else f"{out.with_suffix('.json').name} (its metadata)"
        print(f"wrote {out} ({len(scans)} {model} frames, {args.lidar_mode}, "
              f"{args.udp_profile} packets), "
              f"{meta} and {truth.name}; true pose: "
              f"x {p.x * 1e3:.1f} mm, y {p.y * 1e3:.1f} mm, z {p.z * 1e3:.1f} mm, "
              f"roll {math.degrees(p.roll):.3f} deg, tilt {math.degrees(p.tilt):.3f} deg, "
              f"yaw {math.degrees(p.yaw):.3f} deg")
    return 0


def _simulate_hesai(args: argparse.Namespace, params, model: str, out: Path,
                    station: stations.Station, station_file) -> int:
    """A Hesai PandarXT32's or PandarQT128's packets of the twin's bench
    (`twin.sim.hesai_twin`) and the truth file; its rotations cut at 180 deg, read back with
    ``--model`` the same."""
    import numpy as np

    from twin.lidar.capture import PcapSource
    from twin.lidar.hesai import HesaiAngles, HesaiScans, default_angles
    from twin.sim.bench import BenchSim
    from twin.sim.hesai_twin import write_hesai_pcap

    angles = HesaiAngles.from_csv(default_angles(model), model)
    sim = BenchSim(params, seed=args.seed)
    sim.move_to(x_m=args.x_mm * 1e-3, yaw_rad=math.radians(args.yaw_deg))  # checks the travel
    truth_pose = write_hesai_pcap(sim, angles, out, args.scans + 1,
                                  rng=np.random.default_rng(args.seed), rpm=args.rpm,
                                  range_sigma=0.0 if args.ideal else 0.01, start_cdeg=9000)
    scans = list(HesaiScans(PcapSource(out), angles))
    for s in scans:
        s.meta["truth_pose"] = truth_pose
    truth = _truth_file(args, out, scans, sim, station, station_file, params,
                        {"model": model, "angles": str(default_angles(model))})
    if not args.quiet:
        print(f"wrote {out} ({len(scans)} {model} rotations; read it with --model "
              f"{model}) and {truth.name}")
    return 0


def register(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser("simulate", help="write a lidar capture of the simulated bench and its "
                                        "ground truth")
    p.add_argument("--yaw-deg", type=cliargs.finite_float, default=0.0,
                   help="rotation stage position, deg (within the station's travel; "
                        "the paper's: +-30)")
    p.add_argument("--x-mm", type=cliargs.finite_float, default=0.0,
                   help="linear stage position, mm (within the station's travel; "
                        "the paper's: +-50)")
    p.add_argument("--roll-deg", type=cliargs.finite_float, default=0.0,
                   help="mount misalignment: roll, deg")
    p.add_argument("--tilt-deg", type=cliargs.finite_float, default=0.0,
                   help="mount misalignment: tilt, deg")
    p.add_argument("--mount-yaw-deg", type=cliargs.finite_float, default=0.0,
                   help="mount misalignment: yaw on the turntable, deg")
    p.add_argument("--scans", type=cliargs.positive_int, default=10, help="number of rotations")
    p.add_argument("--seed", type=cliargs.seed, default=0, help="seed of every random draw")
    p.add_argument("--ideal", action="store_true", help="turn every error source off")
    p.add_argument("--rpm", type=cliargs.finite_float, default=600.0,
                   help="spin rate, rpm (300..1200)")
    p.add_argument("--return-mode", choices=("strongest", "last", "dual"), default="strongest")
    p.add_argument("--out", required=True, type=cliargs.output_file,
                   help="capture file to write (.pcap; an Ouster's also .osf, through "
                        "ouster-sdk)")
    station_options.add_arguments(p)
    p.add_argument("--scene", choices=tuple(SCENES), default=None,
                   help="the scene the bench stands in (default: the station's twin.scene; "
                        "'bench': floor, wall and beams; 'lab': a cluttered lab around it)")
    p.add_argument("--quiet", action="store_true", help="print nothing on success")
    p.add_argument("--model", choices=(*VELODYNE_NAMES, *OUSTER_MODELS, *HESAI_NAMES),
                   default=None,
                   help="the sensor emulated (default: the station's sensor.model; the "
                        "paper's: VLP-16); an Ouster's pcap gets its metadata JSON beside it")
    p.add_argument("--lidar-mode", choices=LIDAR_MODES, default="1024x10",
                   help="an Ouster's columns x frames a second (default 1024x10)")
    p.add_argument("--udp-profile", choices=OUSTER_TWIN_PROFILES, default="LEGACY",
                   help="an Ouster's lidar packet profile (default LEGACY; recent firmware "
                        "sends RNG19_RFL8_SIG16_NIR16 unless set)")
    p.set_defaults(func=run)
    return p
