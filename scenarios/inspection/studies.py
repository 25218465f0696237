"""The station's measurement-system studies run on the twin (or read from a real line's
records), each into the record store so that a killed study resumes where it stopped.

- `run_grr_twin`: parts x re-mountings x trials. Parts are twin units with random true
  misalignments within the tolerance (each its own sensor); re-mounting j of part i puts the
  unit on the station again with a placement error (appraiser j's own systematic part plus a
  random part per mounting, ``placement`` sigma per axis in edge units), which the station
  cannot tell from the mounting; trials are new scans with the unit left in place. The records'
  operator is ``mount-j``. A measurement that found no board is kept and taken again.
- `grr_data`: the y[part, appraiser, trial] array of one axis from records (a real line's:
  units x operators x inspections), refusing an unbalanced design with what is missing.
- `run_bias_twin`: n twin units, each measured once, with the truth known.
- `run_linearity`: a bench's stage references (rotation stage for yaw, linear stage for x).
"""

from __future__ import annotations

import math
import time
from collections import defaultdict
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from scenarios.inspection import mounting
from scenarios.inspection.acquire import TwinAcquisition, unit_sensor
from scenarios.inspection.line import line_units
from scenarios.inspection.procedure import inspect_unit
from scenarios.inspection.records import AXES, Records, record_row
from scenarios.inspection.verdict import EDGE_SCALE, EDGE_UNIT, edge_key, limits_si
from twin.core.errors import AimbenchError

if TYPE_CHECKING:
    from scenarios.inspection import msa
    from scenarios.station import Station

#: A re-mounting's placement error, 1-sigma per axis (edge units), unless told: a fixture that
#: locates a vehicle to half a millimetre and 0.05 deg (assumed).
DEFAULT_PLACEMENT = {"x_mm": 0.5, "y_mm": 0.5, "z_mm": 0.5, "roll_deg": 0.05,
                     "tilt_deg": 0.05, "yaw_deg": 0.05}


class StudyError(AimbenchError):
    """A study that cannot be run or analysed as asked."""


def _noise(seed: int, sensor_errors: bool, range_noise_mm: float | None) -> Any:
    from twin.sim.emulation import EmulationConfig

    noise = unit_sensor(seed) if sensor_errors else EmulationConfig().with_(
        laser_offset_sigma=0.0, laser_offsets=None, range_bias=0.0)
    if range_noise_mm is not None:
        noise = noise.with_(range_noise_sigma=range_noise_mm * 1e-3)
    return noise


def run_grr_twin(station: Any, records: Records, *, parts: int, appraisers: int, trials: int,
                 seed: int = 0, scans: int = 10, placement: dict[str, float] | None = None,
                 sensor_errors: bool = True, range_noise_mm: float | None = None,
                 batch: str | None = None, on_record: Callable[[Any, int], None] | None = None
                 ) -> str:
    """Run (or resume) the twin's gauge R&R study into `records`; returns its batch name."""
    placement = dict(DEFAULT_PLACEMENT if placement is None else placement)
    batch = batch or (f"grr twin seed {seed} {parts}x{appraisers}x{trials} scans {scans}"
                      + (f" noise {range_noise_mm:g} mm" if range_noise_mm is not None else "")
                      + ("" if sensor_errors else " ideal sensor"))
    units = line_units(station, parts, seed, spread=1.0, prefix=f"grr{seed}-")
    done: dict[tuple[str, str], int] = defaultdict(int)  # measurements with a pose
    tried: dict[tuple[str, str], int] = defaultdict(int)  # all, failed ones too
    for r in records.rows("WHERE batch = ?", (batch,)):
        tried[(r["unit"], r["operator"])] += 1
        done[(r["unit"], r["operator"])] += r["status"] == "ok"
    rng = np.random.default_rng((int(seed), 7))
    # Appraiser j's systematic placement: half the placement variance, the rest per mounting.
    sys_part = {j: {k: rng.normal(0, s / math.sqrt(2)) for k, s in placement.items()}
                for j in range(appraisers)}
    for i, u in enumerate(units):
        for j in range(appraisers):
            op = f"mount-{j + 1}"
            mrng = np.random.default_rng((int(seed), i, j, 8))
            place = {k: sys_part[j][k] + mrng.normal(0, s / math.sqrt(2))
                     for k, s in placement.items()}
            mis = {k: u.misalignment.get(k, 0.0) + place.get(k, 0.0) for k in
                   set(u.misalignment) | set(place)}
            # A measurement without a pose (the board not found) is kept, and measured again,
            # as an operator would, up to twice per trial.
            while done[(u.name, op)] < trials and tried[(u.name, op)] < 3 * trials:
                t = tried[(u.name, op)]
                started = time.time()
                acq = TwinAcquisition(station, mis, seed=u.seed,
                                      noise=_noise(u.seed, sensor_errors, range_noise_mm),
                                      noise_seed=int(np.random.default_rng(
                                          (int(seed), i, j, t, 9)).integers(2**31)))
                with acq:
                    insp = inspect_unit(acq, station, u.name, scans=scans, max_scans=scans)
                # The part's true value is its mounting, not where it was placed this time.
                insp.truth_error = _true(u.misalignment)
                rid, _ = records.add(record_row(
                    insp, station=station, operator=op, source="sim", capture=None,
                    capture_sha256=None, sensor=acq.sensor, calibration={},
                    started_at=started, batch=batch))
                tried[(u.name, op)] += 1
                done[(u.name, op)] += insp.status == "ok"
                if on_record is not None:
                    on_record(insp, rid)
    return batch


def _true(misalignment: dict[str, float]) -> np.ndarray:
    return np.array([misalignment.get(edge_key(a), 0.0) / EDGE_SCALE[a] for a in AXES])


def grr_data(rows: list[dict], axis: str, trials: int | None = None
             ) -> tuple[np.ndarray, list[str], list[str]]:
    """y[part, appraiser, trial] of one axis (edge units) from records, with the parts' and
    appraisers' names: every unit must be inspected by every operator the same number of
    times (``trials``: use the first that many of each cell; default the smallest count)."""
    cells: dict[tuple[str, str], list[float]] = defaultdict(list)
    for r in rows:
        if r["status"] != "ok" or r[f"err_{axis}"] is None:
            continue
        cells[(r["unit"], r["operator"] or "-")].append(r[f"err_{axis}"] * EDGE_SCALE[axis])
    units = sorted({u for u, _ in cells})
    ops = sorted({o for _, o in cells})
    if len(units) < 2:
        raise StudyError(f"a gauge R&R needs at least 2 units with a pose; the records hold "
                         f"{len(units)}")
    missing = [f"{u} by {o}" for u in units for o in ops if (u, o) not in cells]
    if missing:
        raise StudyError(f"the records are not a crossed study: no inspection of "
                         f"{', '.join(missing[:5])}{' ...' if len(missing) > 5 else ''}; "
                         "every unit must be inspected by every operator (--operator)")
    least = min(len(v) for v in cells.values())
    r = least if trials is None else trials
    if r < 2 or least < r:
        raise StudyError(f"a gauge R&R needs at least {max(r, 2)} inspections of each unit by "
                         f"each operator; the fewest here is {least}")
    y = np.array([[cells[(u, o)][:r] for o in ops] for u in units])
    return y, units, ops


def run_bias_twin(station: Any, records: Records, *, units: int, seed: int = 0,
                  scans: int = 10, sensor_errors: bool = True,
                  on_record: Callable[[Any, int], None] | None = None) -> str:
    """n twin units, each with its own sensor and a random misalignment within the tolerance,
    measured once with the truth known; returns the batch name."""
    batch = f"bias twin seed {seed} scans {scans}" + ("" if sensor_errors else " ideal sensor")
    done = records.units_of_batch(batch)
    for u in line_units(station, units, seed, spread=1.0, prefix=f"bias{seed}-"):
        if u.name in done:
            continue
        started = time.time()
        with TwinAcquisition(station, u.misalignment, seed=u.seed,
                             sensor_errors=sensor_errors) as acq:
            insp = inspect_unit(acq, station, u.name, scans=scans, max_scans=scans)
        rid, _ = records.add(record_row(
            insp, station=station, operator=None, source="sim", capture=None,
            capture_sha256=None, sensor=acq.sensor, calibration={},
            started_at=started, batch=batch))
        if on_record is not None:
            on_record(insp, rid)
    return batch


def run_linearity(bench: Any, station: Any, *, yaw_deg: list[float], x_mm: list[float],
                  repeats: int = 3, scans: int = 10,
                  progress: bool = False) -> dict[str, tuple[list, list]]:
    """(references, measured) per axis (yaw in deg, x in mm) on a bench's stage references:
    the rotation stage at each yaw reference with x at 0, then the linear stage at each x
    reference with yaw at 0; ``repeats`` measurements of ``scans`` scans each. ``progress``:
    a bar of the measurements on stderr (`scenarios.progress.Bar`)."""
    import align
    from scenarios.progress import Bar

    nominal, _ = mounting.nominal_pose(station)
    board = station.board_spec()
    out: dict[str, tuple[list, list]] = {"yaw": ([], []), "x": ([], [])}
    plan = [("yaw", v, 0.0, math.radians(v)) for v in yaw_deg] + \
        [("x", v, v * 1e-3, 0.0) for v in x_mm]
    with Bar(len(plan) * repeats, "linearity", unit="measurements", enabled=progress) as bar:
        bar.set_status("homing")
        bench.home()
        for axis, ref, x_m, yaw_rad in plan:
            unit = "deg" if axis == "yaw" else "mm"
            bar.set_status(f"{axis} {ref:+g} {unit}")
            bench.move_to(x_m=x_m, yaw_rad=yaw_rad)
            bench.wait_until_there()
            for _ in range(repeats):
                est = align.estimate(list(bench.scans(scans)), board)
                bar.update(1)
                if not est.success:
                    continue
                err, _, _ = mounting.mounting_error(est.pose, None, station, nominal)
                i = AXES.index(axis)
                out[axis][0].append(ref)
                out[axis][1].append(float(err[i] * EDGE_SCALE[axis]))
    bench.move_to(x_m=0.0, yaw_rad=0.0)
    return out


def read_reference(path: str) -> tuple[str, dict[str, float]]:
    """A Type-1 study's reference part (TOML): ``unit = "REF-1"`` and a ``[reference]`` table
    of its calibrated mounting error per axis in edge units (``tilt_deg = 0.3``...); axes left
    out are 0. Returns (unit, {edge key: value})."""
    import tomllib
    from pathlib import Path

    keys = [edge_key(a) for a in AXES]
    try:
        data = tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise StudyError(f"no reference file {path}; write a TOML file with unit = \"ID\" and "
                         "a [reference] table (tilt_deg = ..., x_mm = ...)") from None
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise StudyError(f"{path} is not a readable TOML reference file: {exc}") from None
    ref = data.get("reference", {})
    if not isinstance(ref, dict):
        raise StudyError(f"{path}: [reference] must be a table of {', '.join(keys)}")
    unknown = sorted(set(ref) - set(keys)) + sorted(set(data) - {"unit", "reference"})
    if unknown:
        raise StudyError(f"{path}: unknown keys {unknown}; the file has unit = \"ID\" and a "
                         f"[reference] table of {', '.join(keys)}")
    bad = [k for k, v in ref.items() if not isinstance(v, int | float) or isinstance(v, bool)]
    if bad:
        raise StudyError(f"{path}: reference values must be numbers ({', '.join(bad)})")
    unit = data.get("unit", "REF")
    if not isinstance(unit, str) or not unit:
        raise StudyError(f"{path}: unit must be the reference part's id (a string)")
    return unit, {k: float(ref.get(k, 0.0)) for k in keys}


def run_type1_twin(station: Any, records: Records, *, unit: str, reference: dict[str, float],
                   repeats: int, seed: int = 0, scans: int = 10, sensor_errors: bool = True,
                   on_record: Callable[[Any, int], None] | None = None) -> str:
    """Type-1 study on the twin: one reference part (its mounting error `reference`, edge
    units; its own sensor from `seed`) measured `repeats` times, left in place (new scans
    each time). Resumes; returns the batch name."""
    batch = f"type1 twin {unit} seed {seed} scans {scans}" + (
        "" if sensor_errors else " ideal sensor")
    done = sum(r["status"] == "ok" for r in records.rows("WHERE batch = ?", (batch,)))
    tried = len(records.rows("WHERE batch = ?", (batch,)))
    while done < repeats and tried < 2 * repeats:
        started = time.time()
        acq = TwinAcquisition(station, reference, seed=seed, sensor_errors=sensor_errors,
                              noise_seed=int(np.random.default_rng(
                                  (int(seed), tried, 11)).integers(2**31)))
        with acq:
            insp = inspect_unit(acq, station, unit, scans=scans, max_scans=scans)
        rid, _ = records.add(record_row(
            insp, station=station, operator="type1", source="sim", capture=None,
            capture_sha256=None, sensor=acq.sensor, calibration={}, started_at=started,
            batch=batch))
        tried += 1
        done += insp.status == "ok"
        if on_record is not None:
            on_record(insp, rid)
    return batch


def type1_data(rows: list[dict], axis: str) -> np.ndarray:
    """One axis's measured errors (edge units) of the records with a pose, in their order."""
    return np.array([r[f"err_{axis}"] * EDGE_SCALE[axis] for r in rows
                     if r["status"] == "ok" and r[f"err_{axis}"] is not None])


def grr_report(rows: list[dict], station: Station, confidence: float,
               seed: int = 0) -> list[msa.GaugeRR]:
    """The gauge R&R of a study's records, per axis against the station's tolerance (the
    ANOVA needs the extra grr: statsmodels, imported here only)."""
    from scenarios.inspection import msa

    out = []
    for axis, lim in limits_si(station.tolerances).items():
        y, _, _ = grr_data(rows, axis)
        width = 2 * lim * EDGE_SCALE[axis]
        out.append(msa.gauge_rr(y, edge_key(axis), EDGE_UNIT[axis], width, confidence,
                                seed=seed))
    return out
