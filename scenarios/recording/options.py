"""What a recording keeps and where it goes, as command-line options: light (no rerun, no
numpy), so that a command registers them without loading what recording needs
(`scenarios.recording.observer` does the recording)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

#: The default decimation of a recording's clouds: every 32nd return away from the board (the
#: board's neighbourhood whole), so that a 2,100-scan sweep records in under 100 MB (issue 38;
#: benchmarks/bench_rerun.py); ``--full-clouds`` logs every return.
DEFAULT_POINTS_EVERY = 32

@dataclass
class SinkOptions:
    """Where a recording goes (rerun's ``--save``/``--connect``/``--serve`` conventions)."""

    save: str | Path | None = None
    connect: str | bool | None = None  # True: rerun's default URL; a str: that URL
    serve: bool = False
    spawn: bool = False
    web_port: int | None = None
    grpc_port: int | None = None

    @property
    def any(self) -> bool:
        return bool(self.save or self.connect or self.serve or self.spawn)

    def describe(self) -> str:
        parts = []
        if self.save:
            parts.append(f"saving {self.save}")
        if self.connect:
            url = (self.connect if isinstance(self.connect, str)
                   else "rerun+http://127.0.0.1:9876/proxy")
            parts.append(f"streaming to the viewer at {url}")
        if self.serve:
            parts.append("serving the web viewer")
        if self.spawn:
            parts.append("spawning a viewer")
        return ", ".join(parts) or "buffering in memory"


def add_sink_arguments(p: Any, save_help: str) -> None:
    """rerun's sink flags on an argparse parser: --save, --connect [URL], --serve, --spawn."""
    p.add_argument("--save", metavar="PATH", help=save_help)
    p.add_argument("--connect", nargs="?", const=True, default=None, metavar="URL",
                   help="stream to a running rerun viewer (default URL "
                        "rerun+http://127.0.0.1:9876/proxy)")
    p.add_argument("--serve", action="store_true",
                   help="host a gRPC server and rerun's web viewer (http://localhost:9090); "
                        "stays up until Ctrl-C")
    p.add_argument("--spawn", action="store_true", help="start the native rerun viewer")
    p.add_argument("--web-port", type=int, help="web viewer port with --serve (default 9090)")


def sink_options(args: Any, default_save: str | Path | None = None) -> SinkOptions:
    """`SinkOptions` from parsed arguments; with no sink chosen, save to ``default_save``."""
    opts = SinkOptions(save=getattr(args, "save", None), connect=getattr(args, "connect", None),
                       serve=bool(getattr(args, "serve", False)),
                       spawn=bool(getattr(args, "spawn", False)),
                       web_port=getattr(args, "web_port", None))
    if not opts.any and default_save is not None:
        opts.save = default_save
    return opts


def add_rerun_arguments(p: Any) -> None:
    """``--rerun`` and rerun's sink flags for ``aimbench sweep``."""
    p.add_argument("--rerun", action="store_true",
                   help="log the sweep to rerun: saved to RUN/run.rrd unless --save, --connect, "
                        "--serve or --spawn says otherwise (see docs/replay.md)")
    add_sink_arguments(p, "with --rerun: write the recording to this .rrd file "
                          "(default RUN/run.rrd)")
    add_cloud_arguments(p, "--rerun-points-every")


def add_cloud_arguments(p: Any, every_flag: str = "--points-every") -> None:
    """How much of each point cloud a recording keeps: ``every_flag`` N and ``--full-clouds``."""
    p.add_argument(every_flag, type=int, default=None, metavar="N", dest="points_every",
                   help="log every N-th return of a scan away from the board, the board's "
                        f"neighbourhood whole (default {DEFAULT_POINTS_EVERY})")
    p.add_argument("--full-clouds", action="store_true",
                   help="log every return of every scan (recordings several times larger)")


def points_every(args: Any) -> int:
    """The decimation ``add_cloud_arguments`` asked for (1 with --full-clouds)."""
    if getattr(args, "full_clouds", False):
        return 1
    n = getattr(args, "points_every", None)
    return DEFAULT_POINTS_EVERY if n is None else max(1, int(n))
