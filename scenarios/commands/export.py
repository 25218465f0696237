"""`aimbench export RUN --csv FILE | --parquet FILE`: every scan of a run as a table.

One row per (reference, scan): the reference (deg, mm), the estimate and its standard deviations
and, on the simulated bench, the truth, each in edge units (mm, deg) and in SI, plus the status,
timings and diagnostics (JSON). The Parquet file carries the run's plan, configuration, bench and
software versions as schema metadata.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path

from scenarios import cliargs
from twin.core.errors import AimbenchError


def run(args: argparse.Namespace) -> int:
    # here, not at the top: the store imports the station model and numpy, which the parser does
    # not need (issue 38)
    from scenarios.store import Store

    if not args.csv and not args.parquet:
        raise AimbenchError("give --csv FILE and/or --parquet FILE")
    with Store.open(Path(args.run)) as store:
        n = store.scan_count()
        for path, write in ((args.csv, store.export_csv), (args.parquet, store.export_parquet)):
            if path:
                print(f"{_write(path, write)}: {n} scans", file=sys.stderr)
    return 0


def _write(path: Path, write: Callable[[Path], Path]) -> Path:
    """`write` to `path`, a file system's refusal (permissions, a full disk) as one line."""
    try:
        return write(path)
    except OSError as exc:
        raise AimbenchError(f"cannot write {path}: {exc.strerror or exc}; choose another "
                            "file") from None


def register(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser("export", help="export a run's scans to CSV or Parquet",
                       description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run", help="run folder (holding run.sqlite)")
    p.add_argument("--csv", type=cliargs.output_file, help="CSV file to write")
    p.add_argument("--parquet", type=cliargs.output_file, help="Parquet file to write")
    p.set_defaults(func=run)
    return p
