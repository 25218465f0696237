"""`aimbench inspect SOURCE --unit ID --db inspections.sqlite`: is this unit's LiDAR mounted within
its specification? (docs/inspection.md)

SOURCE: ``sim`` (the twin: ``--roll-deg``.. set the unit's mount misalignment; the unit has its
own sensor errors, drawn from ``--seed``), ``udp://HOST:PORT`` (the live sensor; default: the
station's sensor network) or a recording (pcap/pcapng, bags, PCD). Takes ``--scans N`` (default
10: 1 s of data), estimates the mounting pose in the station frame with its covariance, judges
every axis the station's ``[tolerances]`` limit (ISO 14253-1 guard bands unless the station
says ``rule = "simple"``), re-measures with more scans when that is inconclusive
(``--max-scans``), stores the record (crash-safe SQLite, with the raw capture kept beside it)
and only then prints the verdict. Exit status: 0 PASS, 1 FAIL, 3 INCONCLUSIVE, 2 an error.

    aimbench inspect sim --unit VIN123 --tilt-deg 0.4 --db line.sqlite --report reports/
    aimbench inspect udp://0.0.0.0:2368 --station my-line.toml --unit VIN124 --db line.sqlite
    aimbench inspect sim --units 200 --seed 7 --db line.sqlite   # a simulated line (resumable)
    aimbench inspect --db line.sqlite --list | --show 12 | --export line.parquet
    aimbench inspect --db line.sqlite --summary [--report reports/]   # + --batch NAME

``--batch NAME`` files the records under a batch (a shift, a lot, a study), which
``aimbench grr --batch NAME`` and ``--summary --batch NAME`` read back. A simulated line
without ``--batch`` is filed under its seed and spread. Ctrl-C stops after saying which units
have records and how to go on.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import align  # its names load on first use: METHODS and DEFAULT_METHOD without the estimator
from scenarios import cliargs, station_options
from scenarios.defaults import INSPECTION_SCANS as DEFAULT_SCANS
from scenarios.defaults import LINE_SPREAD as DEFAULT_SPREAD
from scenarios.inspection.verdict import RULE_TEXT, Verdict
from twin.core.errors import AimbenchError

# The procedure, the acquisition (the twin or a sensor), the records and the station model are
# imported by the functions that run (numpy, pydantic, MuJoCo, the estimator: about a second),
# not for the parser (issue 38).
if TYPE_CHECKING:
    from align.calibration import LaserCalibration
    from scenarios.inspection import records as rec_mod
    from scenarios.inspection.procedure import Inspection

EXIT = {Verdict.PASS: 0, Verdict.FAIL: 1, Verdict.INCONCLUSIVE: 3}


def verdict_line(insp: Inspection, rid: int | None = None, trial: int | None = None) -> str:
    """One line per unit: the verdict, then each judged axis as error +- U (limit) verdict."""
    head = f"{insp.unit:<14} {str(insp.verdict).upper():<13}"
    if insp.status != "ok":
        return f"{head} {insp.message}"
    cells = []
    for j in insp.axes:
        e = j.to_edge()
        mark = {"pass": "", "fail": " FAIL", "inconclusive": " ?"}[e["verdict"]]
        cells.append(f"{e['axis']} {e['error']:+.3f} +-{e['U']:.3f}{mark}")
    tail = f"  [{insp.scans_used} scans" + (f", record {rid}" if rid is not None else "") + \
        (f", trial {trial}" if trial and trial > 1 else "") + "]"
    return head + "  ".join(cells) + tail


def unit_seed(unit: str) -> int:
    """A twin unit's seed drawn from its id: each id its own sensor (one default seed made
    ``--unit T1`` and ``--unit T2`` the same unit), the same id always the same."""
    return int.from_bytes(hashlib.sha256(unit.encode("utf-8")).digest()[:4], "little")


def _misalignment(args: argparse.Namespace) -> dict[str, float]:
    keys = ("x_mm", "y_mm", "z_mm", "roll_deg", "tilt_deg", "yaw_deg")
    return {k: float(getattr(args, k)) for k in keys if getattr(args, k) is not None}


def _one(args: argparse.Namespace, records: rec_mod.Records, station: Any, unit: str,
         source: str, misalignment: dict[str, float], seed: int, batch: str | None,
         calibration: LaserCalibration | None, cal_file: str | None, live: Any
         ) -> tuple[Inspection, int]:
    """Inspect one unit and commit its record; returns the inspection and its record id."""
    from scenarios.inspection import records as rec_mod
    from scenarios.inspection.acquire import open_acquisition
    from scenarios.inspection.identity import calibration_identity
    from scenarios.inspection.procedure import inspect_unit

    keep = (source == "sim" or source.startswith("udp://")) and not args.no_captures
    capture = records.capture_path(unit) if keep else None
    started = time.time()
    acq = open_acquisition(source, station, capture, misalignment=misalignment, seed=seed,
                           sensor_errors=not args.no_sensor_errors)
    try:
        insp = inspect_unit(acq, station, unit, scans=args.scans, max_scans=args.max_scans,
                            method=args.method, calibration=calibration,
                            on_attempt=live.on_attempt if live is not None else None)
    except BaseException:
        acq.close(complete=False)  # no verdict: its capture stays a .part file, no record
        raise
    acq.close()
    row = rec_mod.record_row(
        insp, station=station, operator=args.operator, source=source, capture=acq.capture,
        capture_sha256=acq.capture_sha256(), sensor=acq.sensor,
        calibration=calibration_identity(station, cal_file), started_at=started, batch=batch)
    rid, trial = records.add(row)
    if args.report:
        from scenarios.inspection.report import unit_report

        unit_report(records.get(rid), insp, Path(args.report))
    if live is not None:
        live.on_verdict(insp, rid)
    if args.json:
        print(json.dumps({"record": rid, "trial": trial, **insp.to_edge()}, default=str),
              flush=True)
    else:
        print(verdict_line(insp, rid, trial), flush=True)
    return insp, rid


def run(args: argparse.Namespace) -> int:
    try:
        return _run(args)
    except KeyboardInterrupt:
        print(f"aimbench inspect: {_interrupted(args)}", file=sys.stderr, flush=True)
        return 130


def _interrupted(args: argparse.Namespace) -> str:
    """What Ctrl-C leaves and how to go on (a unit without a verdict has no record)."""
    if args.units is not None:
        return ("interrupted: every unit reported above has its record; run the same command "
                "again to inspect the rest (recorded units are skipped)")
    if args.unit:
        return (f"interrupted: unit {args.unit} has no record (nothing half-written); inspect "
                "it again with the same command")
    return "interrupted"


def _run(args: argparse.Namespace) -> int:
    from scenarios import calibrate
    from scenarios import station as stations
    from scenarios.inspection import records as rec_mod
    from scenarios.inspection.line import line_units

    db = Path(args.db)
    if args.list or args.show or args.export or args.summary:
        return _browse(args, db)
    if args.scans < 1:
        raise AimbenchError(f"--scans {args.scans}: give at least 1")
    if args.max_scans is not None and args.max_scans < args.scans:
        raise AimbenchError(f"--max-scans {args.max_scans} is below --scans {args.scans}; give "
                            "at least as many (equal: no re-measure)")
    source = args.source
    station, _ = stations.from_args(args, twin=source in (None, "sim"))
    if source is None:
        source = station.lidar_url()
    misalignment = _misalignment(args)
    if args.units is not None and source != "sim":
        raise AimbenchError("--units N simulates a line of twin units: give the source sim")
    if args.units is None and not args.unit:
        raise AimbenchError("give the unit's id with --unit ID (a VIN, a serial), or --units N "
                            "for a simulated line")
    cal_file = args.calibration or station.sensor.range_calibration
    calibration = calibrate.read(cal_file) if cal_file else None
    tol = station.tolerances
    if not args.json:
        print(f"station {station.name}: rule {tol.rule} ({RULE_TEXT[tol.rule]}, k = "
              f"{tol.coverage_k:g})", file=sys.stderr)
    live = None
    if args.rerun:
        from scenarios.inspection.live import LiveView

        live = LiveView.from_args(args, station)
    try:
        with rec_mod.Records.open(db, create=True) as records:
            if not args.json and not args.no_captures and (
                    source == "sim" or source.startswith("udp://")):
                print(f"captures: each unit's raw packets kept in {records.captures}/ (about "
                      f"2 MB per unit of a VLP-16's 10 scans; --no-captures keeps none)",
                      file=sys.stderr)
            if args.units is None:
                seed = args.seed if args.seed is not None else unit_seed(args.unit)
                insp, _ = _one(args, records, station, args.unit, source, misalignment,
                               seed, args.batch, calibration, cal_file, live)
                return EXIT[insp.verdict]
            if misalignment:
                raise AimbenchError("a simulated line draws each unit's misalignment: give "
                                    "--units without --roll-deg .. --z-mm")
            line_seed = args.seed or 0
            batch = args.batch or f"sim-line seed {line_seed} spread {args.spread:g}"
            done = records.units_of_batch(batch)
            new = 0
            for u in line_units(station, args.units, line_seed, args.spread):
                if u.name in done:
                    continue
                _one(args, records, station, u.name, "sim", u.misalignment, u.seed, batch,
                     calibration, cal_file, live)
                new += 1
            if not args.json:
                _tally(records, batch, new)
            return 0
    finally:
        if live is not None:
            live.close()


def _tally(records: rec_mod.Records, batch: str, new: int) -> None:
    """The simulated line's final tally: its verdicts, and against the twin's truth the
    wrong ones (a PASS of a unit truly out, a FAIL of a unit truly in)."""
    from scenarios.inspection import records as rec_mod

    rows = records.rows("WHERE batch = ?", (batch,))
    counts = {v: sum(r["verdict"] == v for r in rows) for v in ("pass", "fail", "inconclusive")}
    wrong_pass = wrong_fail = 0
    for r in rows:
        true = [r[f"true_{a}"] for a in rec_mod.AXES if r[f"limit_{a}"] is not None]
        lims = [r[f"limit_{a}"] for a in rec_mod.AXES if r[f"limit_{a}"] is not None]
        if not lims or any(t is None for t in true):
            continue
        inside = all(abs(t) <= lim for t, lim in zip(true, lims, strict=True))
        wrong_pass += r["verdict"] == "pass" and not inside
        wrong_fail += r["verdict"] == "fail" and inside
    n = len(rows)
    kept = sum(p.stat().st_size for p in records.captures.glob("*.pcap")) \
        if records.captures.is_dir() else 0
    if kept:
        print(f"captures: {kept / 1e6:.0f} MB in {records.captures}/", file=sys.stderr)
    print(f"line {batch!r}: {n} units ({new} inspected now, {n - new} recorded before): "
          + ", ".join(f"{counts[v]} {v.upper()} ({100 * counts[v] / max(n, 1):.1f} %)"
                      for v in counts)
          + f"; against the twin's truth {wrong_pass} wrong PASS, {wrong_fail} wrong FAIL",
          file=sys.stderr)


def _browse(args: argparse.Namespace, db: Path) -> int:
    from scenarios.inspection import records as rec_mod

    with rec_mod.Records.open(db) as records:
        rows = records.rows()
        if args.batch:
            rows = [r for r in rows if r["batch"] == args.batch]
            if not rows:
                there = "; ".join(f"{b!r} ({n} records)" for b, n in records.batches().items())
                raise AimbenchError(f"no records of batch {args.batch!r} in {db}; its "
                                    f"batches: {there or 'none'}")
        if args.list:
            for line in list_lines(rows):
                print(line)
        if args.show:
            row = records.get(args.show)
            if args.json:
                print(json.dumps(row, default=str))
            else:
                for line in show_lines(row):
                    print(line)
        if args.export:
            path = records.export(args.export)
            print(f"wrote {path} ({records.count()} records)", file=sys.stderr)
        if args.summary:
            from scenarios.inspection import spc

            if args.json:
                print(json.dumps({"batch": args.batch, "records": len(rows),
                                  "axes": [a.to_dict() for a in spc.line_spc(rows)]}))
            else:
                for line in spc.summary_lines(rows):
                    print(line)
            if args.report:
                from scenarios.inspection.report import line_summary

                page = line_summary(rows, Path(args.report))
                print(f"wrote {page}", file=sys.stderr)
    return 0


def list_lines(rows: list[dict]) -> list[str]:
    out = [f"{'id':>5} {'unit':<14} {'trial':>5} {'when (UTC)':<19} {'operator':<10} "
           f"{'verdict':<12} {'scans':>5}  source"]
    for r in rows:
        when = time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(r["started_at"]))
        out.append(f"{r['id']:>5} {r['unit']:<14} {r['trial']:>5} {when:<19} "
                   f"{(r['operator'] or '-'):<10} {r['verdict'].upper():<12} {r['scans']:>5}  "
                   f"{r['source']}")
    return out


def show_lines(r: dict) -> list[str]:
    from scenarios.inspection import records as rec_mod

    when = time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime(r["started_at"]))
    lines = [f"record {r['id']}: unit {r['unit']} (trial {r['trial']}), {when}, operator "
             f"{r['operator'] or '-'}",
             f"verdict {r['verdict'].upper()} ({r['status']}; rule {r['rule']}, k = "
             f"{r['coverage_k']:g}): {r['message']}",
             f"station {r['station']} (sha256 {r['station_sha256'][:16]}...), aimbench "
             f"{r['software_version']} at {r['git_commit'] or 'unknown commit'}",
             f"sensor {r['sensor_model']} serial {r['sensor_serial'] or '(not reported)'}; "
             f"calibration {json.dumps(r['calibration']) if r['calibration'] else 'none'}",
             f"source {r['source']}; capture {r['capture_path'] or '-'} (sha256 "
             f"{r['capture_sha256'] or '-'})",
             f"scans {r['scans']} (rejected {r['rejected_scans']}), board found "
             f"{bool(r['board_found'])}, rings {r['rings']}, points {r['board_points']}",
             f"{'axis':<10}{'error':>10}{'u est':>9}{'u sys':>9}{'U':>9}{'limit':>9}  verdict"]
    for a in rec_mod.AXES:
        if r[f"err_{a}"] is None:
            continue
        s, unit = rec_mod.SCALE[a], rec_mod.UNIT[a]
        def cell(c: str, r: dict = r, a: str = a, s: float = s) -> str:
            v = r[f"{c}_{a}"]
            return f"{'-':>9}" if v is None else f"{v * s:>9.3f}"
        big_u = None if r[f"u_{a}"] is None else r[f"u_{a}"] * r["coverage_k"] * s
        true = r[f"true_{a}"]
        lines.append(f"{a + '_' + unit:<10}{r[f'err_{a}'] * s:>+10.3f}{cell('u_est')}"
                     f"{cell('u_sys')}{'-' if big_u is None else f'{big_u:.3f}':>9}"
                     f"{cell('limit')}  {r[f'verdict_{a}'] or 'not judged'}"
                     + ("" if true is None else f"   (true {true * s:+.3f})"))
    return lines


def register(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser("inspect", help="inspect a unit's LiDAR mounting against the station's "
                                       "tolerances (guard-banded verdict, per-unit records)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("source", nargs="?", metavar="SOURCE",
                   help="sim, udp://HOST:PORT or a recording (default: the station's sensor)")
    station_options.add_arguments(p)
    p.add_argument("--unit", type=cliargs.unit_id, help="the unit's id (a VIN, a serial number)")
    p.add_argument("--db", required=True, metavar="FILE",
                   help="the record store (SQLite, created if missing; captures kept in "
                        "FILE's folder under NAME.captures/)")
    p.add_argument("--scans", type=cliargs.positive_int, default=DEFAULT_SCANS,
                   help=f"scans per measurement (default {DEFAULT_SCANS}: 1 s of data)")
    p.add_argument("--max-scans", type=cliargs.positive_int, default=None, metavar="N",
                   help="most scans an automatic re-measure may reach (default 3 x --scans; "
                        "= --scans: no re-measure)")
    p.add_argument("--operator", default=None, help="who inspects (kept in the record)")
    p.add_argument("--batch", default=None, metavar="NAME",
                   help="file the records under this batch (a lot, a shift; grr --batch reads "
                        "it); with --list/--summary: only this batch's records")
    p.add_argument("--report", default=None, metavar="DIR",
                   help="write the unit's one-page report (HTML and PNG) into DIR")
    p.add_argument("--json", action="store_true", help="one JSON object per unit")
    p.add_argument("--no-captures", action="store_true",
                   help="keep no raw capture of the twin's or a live sensor's packets (about "
                        "2 MB per unit; a recording given as the source is its own capture)")
    p.add_argument("--method", type=cliargs.estimation_method, default=align.DEFAULT_METHOD,
                   choices=align.METHODS,
                   help=f"estimator (default {align.DEFAULT_METHOD})")
    p.add_argument("--calibration", default=None, metavar="FILE",
                   help="per-laser range calibration to apply (default: the station's "
                        "sensor.range_calibration, if any)")
    twin = p.add_argument_group("the twin (source sim)")
    for key, what in (("roll_deg", "roll, deg"), ("tilt_deg", "tilt, deg"),
                      ("yaw_deg", "yaw, deg"), ("x_mm", "x shift, mm"), ("y_mm", "y shift, mm"),
                      ("z_mm", "z shift, mm")):
        twin.add_argument(f"--{key.replace('_', '-')}", dest=key, type=cliargs.finite_float,
                          default=None,
                          help=f"the unit's mount misalignment: {what}")
    twin.add_argument("--seed", type=cliargs.seed, default=None,
                      help="the twin unit's seed: its sensor errors and noise (default: drawn "
                           "from the unit's id, so that --unit T1 and T2 are two units; a "
                           "line's: 0)")
    twin.add_argument("--no-sensor-errors", action="store_true",
                      help="a sensor without per-laser or common range offsets (noise stays)")
    twin.add_argument("--units", type=cliargs.positive_int, default=None, metavar="N",
                      help="a simulated line: N twin units with random misalignments (unit i "
                           "is the same for a given --seed; a rerun skips units recorded)")
    twin.add_argument("--spread", type=cliargs.non_negative_float, default=DEFAULT_SPREAD,
                      help="with --units: misalignments uniform within +-SPREAD x each limit "
                           f"(default {DEFAULT_SPREAD})")
    browse = p.add_argument_group("the records")
    browse.add_argument("--list", action="store_true", help="list the records")
    browse.add_argument("--show", metavar="ID", help="one record (an id, or a unit's latest)")
    browse.add_argument("--export", metavar="FILE", help="every record to FILE (.csv, .parquet)")
    browse.add_argument("--summary", action="store_true",
                        help="the line's summary: the tally, and per axis Cp/Cpk/Pp/Ppk and "
                             "the run rules broken; with --report DIR also the page "
                             "(histograms, control charts)")
    p.add_argument("--rerun", action="store_true",
                   help="show the inspection live in rerun (the board, the points, the "
                        "estimated and nominal frames, the verdict)")
    from scenarios.recording.options import add_sink_arguments

    add_sink_arguments(p, "with --rerun: write the recording to this .rrd file")
    p.set_defaults(func=run)
    return p
