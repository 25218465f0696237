"""`aimbench grr`: qualify the inspection station as a gauge (docs/inspection.md).

    aimbench grr --twin --parts 10 --appraisers 3 --trials 2 --db grr.sqlite   # on the twin
    aimbench grr --db line.sqlite [--batch NAME]       # from a real line's records
    aimbench grr --bias --twin --units 30 --db bias.sqlite   # bias across units (twin)
    aimbench grr --linearity --bench sim|serve|hw      # bias and linearity on the stages
    aimbench grr --type1 --reference ref.toml --twin --db t1.sqlite   # Type-1 study (twin)
    aimbench grr --type1 --reference ref.toml --db line.sqlite [--batch NAME]   # from records

Gauge R&R: the AIAG crossed ANOVA (parts x appraisers or re-mountings x trials) per judged
axis: EV, AV, GRR, PV with their 95 % intervals, %GRR against the station's tolerance (and
against the total variation), ndc, and the acceptance band (< 10 % acceptable, 10-30 %
marginal, > 30 % not acceptable). From records, the parts are the units and the appraisers the
operators (``--operator``), each unit inspected by each operator the same number of times.

``--bias --twin``: the error estimate - truth of n twin units, each with its own sensor: mean,
spread, the chi-square of the estimator's sigma, and the measurement-system term the station
file may state as ``[tolerances.system_sigma]``. ``--linearity``: AIAG bias and linearity of
yaw and x against the stages' references. ``--type1 --reference FILE``: the Type-1 study
of one reference part (FILE: ``unit = "ID"`` and a ``[reference]`` table of its calibrated
mounting error, ``tilt_deg = 0.3``...) measured ``--repeats`` times (at least 25): per judged
axis Cg = 0.2 T / 6 s and Cgk = (0.1 T - |bias|) / 3 s against the tolerance T = 2 x limit
(capable: both >= 1.33), the bias with its t-test, and VDA 5's Q_MP = 2 U / T. Studies on the
twin are stored in ``--db`` and resume where they stopped.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from scenarios import cliargs, station_options
from scenarios.extras import require
from scenarios.inspection.verdict import EDGE_SCALE, EDGE_UNIT, edge_key, limits_si
from twin.core.errors import AimbenchError

# scipy.stats and statsmodels load only when a study runs (a second or two); the station model
# and the records (pydantic, numpy) when the command runs, not for its parser (issue 38).
if TYPE_CHECKING:
    from scenarios import station as stations
    from scenarios.inspection import msa
    from scenarios.inspection.records import Records


def __getattr__(name: str) -> Any:
    """``grr_report`` (scenarios.inspection.studies'), which this module has always offered,
    loaded when it is asked for (PEP 562)."""
    if name == "grr_report":
        from scenarios.inspection.studies import grr_report

        return grr_report
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _station_of(args: argparse.Namespace, rows: list[dict]) -> stations.Station:
    from scenarios import station as stations

    if args.station is not None or not rows:
        return stations.from_args(args)[0]
    return stations.from_dict(rows[-1]["station_json"], "the records' station")


def grr_lines(results: list[msa.GaugeRR]) -> list[str]:
    if not results:
        return []
    g0 = results[0]
    lines = [f"gauge R&R (AIAG crossed ANOVA): {g0.parts} parts x {g0.appraisers} appraisers x "
             f"{g0.trials} trials; {100 * g0.confidence:g} % intervals (parametric bootstrap)",
             f"{'axis':<10}{'EV':>22}{'AV':>22}{'GRR':>22}{'PV':>22}"
             f"{'%GRR tol':>20}{'%GRR TV':>9}{'ndc':>10}  acceptance"]
    for g in results:
        def sd(k: str, g: msa.GaugeRR = g) -> str:
            lo, hi = g.ci.get(f"sigma_{k}", (float("nan"),) * 2)
            return f" {g.sigma[k]:.3f} [{lo:.3f},{hi:.3f}]"
        lo, hi = g.ci.get("pct_tolerance_GRR", (float("nan"),) * 2)
        nlo, nhi = g.ci.get("ndc", (0, 0))
        pool = " (interaction pooled)" if g.pooled else ""
        lines.append(f"{g.axis:<10}{sd('EV'):>22}{sd('AV'):>22}{sd('GRR'):>22}{sd('PV'):>22}"
                     f"{g.pct_tolerance.get('GRR', float('nan')):>7.1f} [{lo:5.1f},{hi:5.1f}]"
                     f"{g.pct_total['GRR']:>9.1f}{g.ndc:>4d} [{nlo},{nhi}]  {g.verdict}{pool}")
    lines.append("sigmas in the axis's unit (mm, deg); %GRR tol = 100 x 6 sigma_GRR / (2 x "
                 "limit); ndc = floor(1.41 PV / GRR); < 10 % acceptable, 10-30 % marginal")
    return lines


def run(args: argparse.Namespace) -> int:
    from scenarios import station as stations
    from scenarios.inspection import studies
    from scenarios.inspection.records import Records
    from scenarios.inspection.studies import grr_report

    if args.linearity:
        return _linearity(args)
    db = Path(args.db) if args.db else None
    if db is None:
        raise AimbenchError("give --db: the records to analyse (a twin study is stored there)")
    if args.type1 and not args.reference:
        raise AimbenchError("--type1 needs --reference FILE: the reference part's id and its "
                            "calibrated mounting error (docs/inspection.md)")
    if not (args.bias or args.type1):  # before a study runs or a record is read
        require("statsmodels", "the gauge R&R's ANOVA (aimbench grr)")
    with Records.open(db, create=args.twin) as records:
        if args.type1:
            return _type1(args, records)
        if args.bias:
            return _bias(args, records)
        if args.twin:
            station = stations.from_args(args, twin=True)[0]
            placement = {**studies.DEFAULT_PLACEMENT}
            if args.placement_deg is not None:
                placement.update({k: args.placement_deg for k in placement if k.endswith("deg")})
            if args.placement_mm is not None:
                placement.update({k: args.placement_mm for k in placement if k.endswith("mm")})
            batch = studies.run_grr_twin(
                station, records, parts=args.parts, appraisers=args.appraisers,
                trials=args.trials, seed=args.seed, scans=args.scans, placement=placement,
                sensor_errors=not args.no_sensor_errors, range_noise_mm=args.range_noise_mm,
                on_record=_progress(args))
        else:
            batch = args.batch
        rows = _batch_rows(records, batch)
        station = _station_of(args, rows)
        results = grr_report(rows, station, args.confidence, args.seed)
    if args.json:
        print(json.dumps({"batch": batch, "station": station.name,
                          "axes": [g.to_dict() for g in results]}))
    else:
        for line in grr_lines(results):
            print(line)
    return 0


def _batch_rows(records: Records, batch: str | None) -> list[dict]:
    """The records of a batch (all without one); a batch with no record is an error that
    lists the batches there are."""
    if not batch:
        return records.rows()
    rows = records.rows("WHERE batch = ?", (batch,))
    if not rows:
        there = records.batches()
        listed = "; ".join(f"{b!r} ({n} records)" for b, n in there.items()) or "none"
        raise AimbenchError(f"no records of batch {batch!r} in {records.path}; its batches: "
                            f"{listed}")
    return rows


def _type1(args: argparse.Namespace, records: Records) -> int:
    from scenarios import station as stations
    from scenarios.inspection import msa, studies
    from scenarios.inspection.verdict import VDA5_QMP_MAX, q_mp, system_sigma_si

    unit, reference = studies.read_reference(args.reference)
    repeats = args.repeats if args.repeats is not None else msa.TYPE1_MIN_N
    if repeats < msa.TYPE1_MIN_N:
        raise AimbenchError(f"--repeats {repeats}: a Type-1 study takes at least "
                            f"{msa.TYPE1_MIN_N} repeats of the reference part (50 preferred)")
    if args.twin:
        station = stations.from_args(args, twin=True)[0]
        batch = studies.run_type1_twin(station, records, unit=unit, reference=reference,
                                       repeats=repeats, seed=args.seed, scans=args.scans,
                                       sensor_errors=not args.no_sensor_errors,
                                       on_record=_progress(args))
        rows = _batch_rows(records, batch)
    else:
        batch = args.batch
        rows = [r for r in _batch_rows(records, batch) if r["unit"] == unit]
        if not rows:
            raise AimbenchError(f"no records of the reference part {unit!r} in {records.path}"
                                + (f" batch {batch!r}" if batch else "") + "; inspect it with "
                                f"--unit {unit} at least {msa.TYPE1_MIN_N} times")
        station = _station_of(args, rows)
    tol = station.tolerances
    system = system_sigma_si(tol)
    results, qmp = [], {}
    for axis, lim in limits_si(tol).items():
        x = studies.type1_data(rows, axis)
        if len(x) < msa.TYPE1_MIN_N:
            raise AimbenchError(f"{len(x)} measurements of {unit} with a pose; a Type-1 study "
                                f"takes at least {msa.TYPE1_MIN_N}")
        key, s = edge_key(axis), EDGE_SCALE[axis]
        res = msa.type1(x, reference[key], 2 * lim * s, key, EDGE_UNIT[axis])
        results.append(res)
        # the measurement process's u: the gauge's repeatability and bias (from this study)
        # with the station's stated system term, in quadrature (VDA 5's U_MP, simplified)
        u = (res.sd ** 2 + res.bias ** 2 + (system[axis] * s) ** 2) ** 0.5
        qmp[key] = q_mp(u, lim * s, tol.coverage_k)
    if args.json:
        print(json.dumps({"batch": batch, "unit": unit, "station": station.name,
                          "axes": [{**r.to_dict(), "q_mp": qmp[r.axis]} for r in results]}))
        return 0
    print(f"Type-1 study of {unit} ({results[0].n if results else 0} repeats; Cg = "
          f"{msa.TYPE1_PCT:g} % T / {msa.TYPE1_SIGMAS:g} s, capable when Cg and Cgk >= "
          f"{msa.TYPE1_MIN_C}; bias t-test two-sided, alpha 0.05)")
    print(f"{'axis':<10}{'reference':>10}{'mean':>10}{'s':>9}{'bias':>10}{'t':>8}{'p':>8}"
          f"{'Cg':>7}{'Cgk':>7}{'Q_MP':>7}  verdict")
    for r in results:
        verdict = "capable" if r.capable else "NOT capable"
        if r.bias_significant:
            verdict += ", bias significant"
        if qmp[r.axis] > VDA5_QMP_MAX:
            verdict += f", Q_MP over {100 * VDA5_QMP_MAX:g} %"
        print(f"{r.axis:<10}{r.reference:>+10.3f}{r.mean:>+10.3f}{r.sd:>9.4f}{r.bias:>+10.4f}"
              f"{r.t:>8.2f}{r.p:>8.3f}{r.cg:>7.2f}{r.cgk:>7.2f}{100 * qmp[r.axis]:>6.1f}%  "
              f"{verdict}")
    return 0 if all(r.capable for r in results) else 1


def _progress(args: argparse.Namespace) -> Any:
    if args.json:
        return None

    def show(insp: Any, rid: int) -> None:
        print(f"  record {rid}: {insp.unit} {str(insp.verdict).upper()}", file=sys.stderr)
    return show


def _bias(args: argparse.Namespace, records: Records) -> int:
    from scenarios import station as stations
    from scenarios.inspection import msa, studies

    if not args.twin:
        raise AimbenchError("--bias needs the truth: run it on the twin (--twin)")
    station = stations.from_args(args, twin=True)[0]
    batch = studies.run_bias_twin(station, records, units=args.units, seed=args.seed,
                                  scans=args.scans, sensor_errors=not args.no_sensor_errors,
                                  on_record=_progress(args))
    rows = [r for r in records.rows("WHERE batch = ?", (batch,)) if r["status"] == "ok"]
    out = []
    for axis in ("x", "y", "z", "roll", "tilt", "yaw"):
        e = [(r[f"err_{axis}"] - r[f"true_{axis}"]) * EDGE_SCALE[axis] for r in rows]
        s = [r[f"u_est_{axis}"] * EDGE_SCALE[axis] for r in rows]
        out.append(msa.bias_across_units(e, s, edge_key(axis), EDGE_UNIT[axis],
                                         args.confidence))
    if args.json:
        print(json.dumps({"batch": batch, "units": len(rows),
                          "axes": [b.to_dict() for b in out]}))
        return 0
    print(f"bias across {len(rows)} twin units ({batch}): error = estimate - truth")
    print(f"{'axis':<10}{'mean':>9}{'95% interval':>22}{'sd':>9}{'sd est.':>9}{'chi2':>8}"
          f"{'system':>9}")
    for b in out:
        print(f"{b.axis:<10}{b.mean:>+9.3f}  [{b.mean_ci[0]:+8.3f}, {b.mean_ci[1]:+8.3f}]"
              f"{b.sd_between:>9.3f}{b.sd_estimator:>9.3f}{b.chi2:>8.2f}{b.system_sigma:>9.3f}")
    print("the system term in station-file form (the spread beyond the estimator's sigma):")
    print("[tolerances.system_sigma]")
    for b in out:
        print(f"{b.axis} = {b.system_sigma:.3g}")
    return 0


def _linearity(args: argparse.Namespace) -> int:
    from scenarios import station as stations
    from scenarios.bench import open_bench
    from scenarios.config import RunConfig
    from scenarios.inspection import msa, studies

    station = stations.from_args(args, twin=args.bench != "hw")[0]
    bench = open_bench(RunConfig(bench=args.bench, port=args.port, lidar=args.lidar,
                                 seed=args.seed, station=station))
    yaw = [float(v) for v in args.yaw_refs_deg.split(",")]
    xs = [float(v) for v in args.x_refs_mm.split(",")]
    with bench:
        data = studies.run_linearity(bench, station, yaw_deg=yaw, x_mm=xs,
                                     repeats=args.repeats or 3, scans=args.scans,
                                     progress=True)  # on stderr: --json's stdout stays JSON
    results = [msa.linearity(*data[a], edge_key(a), EDGE_UNIT[a], args.confidence)
               for a in ("yaw", "x") if len(data[a][0]) > 2]
    if args.json:
        print(json.dumps({"bench": args.bench, "axes": [r.to_dict() for r in results]}))
        return 0
    for r in results:
        print(f"{r.axis}: bias = {r.intercept:+.4f} [{r.intercept_ci[0]:+.4f}, "
              f"{r.intercept_ci[1]:+.4f}] (p {r.intercept_p:.3f}) + {r.slope:+.5f} "
              f"[{r.slope_ci[0]:+.5f}, {r.slope_ci[1]:+.5f}] (p {r.slope_p:.3f}) x reference; "
              f"R2 {r.r2:.3f}")
        for ref in r.references:
            extra = (f" sd {ref['sd']:.4f} t {ref['t']:+.2f} p {ref['p']:.3f}" if "t" in ref
                     else "")
            print(f"   reference {ref['reference']:+8.3f} {r.unit}: n {ref['n']}, bias "
                  f"{ref['bias']:+.4f}{extra}")
    return 0


def register(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser("grr", help="gauge R&R, bias and linearity of the inspection station",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    station_options.add_arguments(p, board=False)
    p.add_argument("--db", metavar="FILE", help="the inspection records (SQLite)")
    p.add_argument("--batch", help="analyse only the records of this batch (a study's name)")
    p.add_argument("--twin", action="store_true", help="run the study on the twin first")
    p.add_argument("--parts", type=cliargs.int_at_least(2), default=10,
                   help="twin: parts (units), default 10")
    p.add_argument("--appraisers", type=cliargs.positive_int, default=3,
                   help="twin: appraisers (re-mountings), default 3")
    p.add_argument("--trials", type=cliargs.int_at_least(2), default=2,
                   help="twin: trials per mounting, default 2")
    p.add_argument("--scans", type=cliargs.positive_int, default=10,
                   help="scans per measurement (default 10)")
    p.add_argument("--seed", type=cliargs.seed, default=0, help="the twin study's seed")
    p.add_argument("--placement-deg", type=cliargs.non_negative_float, default=None,
                   help="twin: a re-mounting's placement error, 1-sigma deg (default 0.05)")
    p.add_argument("--placement-mm", type=cliargs.non_negative_float, default=None,
                   help="twin: a re-mounting's placement error, 1-sigma mm (default 0.5)")
    p.add_argument("--range-noise-mm", type=cliargs.non_negative_float, default=None,
                   help="twin: the sensor's range noise, 1-sigma mm (default the twin's 14)")
    p.add_argument("--no-sensor-errors", action="store_true",
                   help="twin: sensors without per-laser or common range offsets")
    p.add_argument("--confidence", type=cliargs.probability, default=0.95,
                   help="interval level (0.95)")
    p.add_argument("--bias", action="store_true", help="bias across twin units (with --twin)")
    p.add_argument("--units", type=cliargs.int_at_least(2), default=30,
                   help="--bias: twin units (default 30)")
    p.add_argument("--linearity", action="store_true",
                   help="bias and linearity against the stages' references")
    p.add_argument("--bench", choices=("sim", "serve", "hw"), default="sim",
                   help="--linearity: the bench (default sim)")
    p.add_argument("--port", default=None, help="--linearity --bench hw: the stage controller")
    p.add_argument("--lidar", default=None, help="--linearity --bench hw: the LiDAR source")
    p.add_argument("--yaw-refs-deg", default="-1.5,-0.75,0,0.75,1.5",
                   help="--linearity: rotation stage references, deg")
    p.add_argument("--x-refs-mm", default="-15,-7.5,0,7.5,15",
                   help="--linearity: linear stage references, mm")
    p.add_argument("--repeats", type=cliargs.positive_int, default=None,
                   help="--linearity: measurements at each reference (default 3); --type1: "
                        "repeats of the reference part (default and least 25)")
    p.add_argument("--type1", action="store_true",
                   help="Type-1 gauge study of a reference part (Cg, Cgk, bias; with "
                        "--reference)")
    p.add_argument("--reference", metavar="FILE",
                   help="--type1: the reference part (TOML: unit and its [reference] errors)")
    p.add_argument("--json", action="store_true", help="one JSON object")
    p.set_defaults(func=run)
    return p
