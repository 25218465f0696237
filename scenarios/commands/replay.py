"""`aimbench replay`: watch a run or a capture in rerun, after the fact.

    aimbench replay runs/NAME        [--save FILE.rrd | --connect [URL] | --serve | --spawn]
                                     [--no-clouds] [--clouds-per-reference N] [--points-every N]
    aimbench replay SOURCE           [--method NAME] [--truth FILE.json] [--limit N] [sinks]

A run folder: its result store (every scan's estimate, truth, stage position and status, and the
run's events) and its scans again (re-simulated for a run on the twin, re-read for a run that
replayed a capture). A SOURCE (a capture, udp://HOST:PORT until Ctrl-C or --limit N, a ROS bag,
a PCD file): every whole scan with align's estimate, and the truth of ``CAPTURE.truth.json`` if
it exists. With no sink chosen, the recording is saved beside the input
(``runs/NAME/replay.rrd``, ``CAPTURE.rrd``); open it with ``rerun FILE.rrd``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import align  # its names load on first use: METHODS and DEFAULT_METHOD without the estimator
from scenarios import cliargs
from scenarios.commands.info import add_sensor_arguments, sensor_options
from scenarios.recording.options import (
    add_cloud_arguments,
    add_sink_arguments,
    points_every,
    sink_options,
)
from twin.core.errors import AimbenchError

if TYPE_CHECKING:  # tqdm's bar, made when the replay reports its first scan (issue 38)
    from scenarios.progress import Bar


class _Progress:
    """The replay's ``progress(done, total)`` callback on a `scenarios.progress.Bar` (a bar on a
    terminal, a line every 25 scans otherwise), made at the first call, when the total is known."""

    def __init__(self, enabled: bool) -> None:
        self.enabled = enabled
        self.bar: Bar | None = None

    def __call__(self, done: int, total: int) -> None:
        if self.bar is None:
            from scenarios.progress import Bar

            self.bar = Bar(total, "replay", "scans", enabled=self.enabled, every=25)
        self.bar.update(done - self.bar.done)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def run(args: argparse.Namespace) -> int:
    from scenarios.extras import require

    require("rerun", "aimbench replay")
    from scenarios.recording import log as rl
    from scenarios.recording import replay
    from scenarios.recording.observer import close_recording, open_recording
    from scenarios.truth import truth_path

    src = Path(args.source)
    tol = rl.tolerance_band(args.tolerance_deg, args.tolerance_mm)
    progress = _Progress(not args.no_progress)
    if src.is_dir() and (src / "run.sqlite").is_file():
        sinks = sink_options(args, default_save=src / "replay.rrd")
        rec = open_recording(f"replay {src.name}", sinks, truth=_run_has_truth(src))
        try:
            summary = replay.replay_run(
                src, rec, clouds=not args.no_clouds,
                clouds_per_reference=args.clouds_per_reference, points_every=points_every(args),
                color_by=args.color_by, tolerances=tol, progress=progress)
        finally:
            progress.close()
            close_recording(rec, sinks)
    else:
        name = _source_or_run(args.source)
        if name.live:
            default = Path(f"replay-{name.host}-{name.port}.rrd")
            truth = Path(args.truth) if args.truth else None
        else:
            default = src.with_suffix(".rrd")
            truth = Path(args.truth) if args.truth else truth_path(src)
        sinks = sink_options(args, default_save=default)
        label = args.source if name.live else src.name
        rec = open_recording(f"replay {label}", sinks,
                             truth=truth is not None and truth.is_file())
        try:
            summary = replay.replay_capture(
                args.source, rec, method=args.method, truth=args.truth, limit=args.limit,
                points_every=points_every(args), color_by=args.color_by, tolerances=tol,
                progress=progress, **sensor_options(args))
        finally:
            progress.close()
            close_recording(rec, sinks)
    print(f"replay: {summary.line()}", file=sys.stderr)
    for note in summary.notes:
        print(f"replay: {note}", file=sys.stderr)
    return 0


def _source_or_run(text: str):
    """The source a replay names (`twin.lidar.sources.SourceName`); else say what it takes."""
    from twin.lidar.sources import SourceError, parse_source

    try:
        return parse_source(text)
    except SourceError as exc:
        raise AimbenchError(f"{exc}; or a run folder (runs/NAME, with its run.sqlite)") from None


def _run_has_truth(run_dir: Path) -> bool:
    """A run on the twin has the truth (error plots); a hardware run only its estimates."""
    from scenarios.config import RunConfig
    from scenarios.store import Store

    with Store.open(run_dir) as store:
        return RunConfig.from_dict(store.get("config")).bench == "sim"


def register(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser("replay", help="build a rerun recording of a run folder or a capture",
                       description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("source", help="run folder (runs/NAME), or a lidar source: a capture "
                                  "(.pcap/.pcapng), udp://HOST:PORT, a ROS bag or a .pcd file")
    add_sink_arguments(p, "write the recording to this .rrd file (default: runs/NAME/replay.rrd "
                          "or CAPTURE.rrd)")
    p.add_argument("--no-clouds", action="store_true",
                   help="run folder: only what the store holds, no point clouds (fast)")
    p.add_argument("--clouds-per-reference", type=int, metavar="N",
                   help="run folder: point clouds of the first N scans of each reference only")
    add_cloud_arguments(p)
    p.add_argument("--color-by", choices=("intensity", "ring"), default="intensity",
                   help="colour of the raw returns (default intensity)")
    p.add_argument("--method", type=cliargs.estimation_method, choices=align.METHODS,
                   help=f"capture: estimation method (default: align's, {align.DEFAULT_METHOD})")
    p.add_argument("--truth", help="capture: truth file (default CAPTURE.truth.json if present)")
    p.add_argument("--limit", "--scans", type=int, metavar="N",
                   help="source: the first N whole scans only (a live sensor: stop after N)")
    add_sensor_arguments(p)
    p.add_argument("--tolerance-deg", type=float, default=0.2,
                   help="band of the angle error plots, deg (default 0.2, the report's)")
    p.add_argument("--tolerance-mm", type=float, default=4.0,
                   help="band of the x error plot, mm (default 4, the report's)")
    p.add_argument("--no-progress", action="store_true", help="no progress line")
    p.set_defaults(func=run)
    return p
