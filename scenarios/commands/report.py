"""`aimbench report RUN`: accuracy and precision tables, plots and a verdict for a run folder.

Writes report.md, report.html and errors_*.png into the run folder (or --out) and prints the
verdict and the paper-form table. Exit code 0 on PASS, 1 on FAIL. Works on a run still in
progress or interrupted (it reads the committed scans).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from scenarios.commands.sweep import add_tolerance_arguments, tolerances


def run(args: argparse.Namespace) -> int:
    # here, not at the top: the report and the store import numpy, matplotlib's helpers and the
    # station model, which the parser does not need (issue 38)
    from scenarios.report import summary_lines, write
    from scenarios.store import Store, StoreError

    with Store.open(Path(args.run)) as store:
        if args.out is None and store.read_only:
            raise StoreError(f"{args.run} cannot be written here (a read-only filesystem or "
                             "folder), and the report goes into the run folder; give --out DIR "
                             "to write it elsewhere")
        rep, md, page = write(store, tolerances(args), args.out)
        if args.csv:
            store.export_csv(Path(args.out or store.run_dir) / "scans.csv")
        if args.parquet:
            store.export_parquet(Path(args.out or store.run_dir) / "scans.parquet")
    for line in summary_lines(rep):
        print(line)
    print(f"report: {md} and {page}", file=sys.stderr)
    return 0 if rep.verdict()[0] else 1


def register(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser("report", help="accuracy/precision tables, plots and a pass/fail verdict "
                                      "for a run folder", description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run", help="run folder (holding run.sqlite)")
    p.add_argument("--out", help="write the report here instead of the run folder")
    p.add_argument("--csv", action="store_true", help="also export scans.csv")
    p.add_argument("--parquet", action="store_true", help="also export scans.parquet")
    add_tolerance_arguments(p)
    p.set_defaults(func=run)
    return p
