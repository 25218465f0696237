"""A study's figures per design point and scans fused: the simulation beside the bound.

`summarize` reads the store and returns one `DesignResult` per (design point, scans fused), in
edge units (mm, deg), per axis (x, y, z, roll, tilt, yaw, in the station frame):

- ``rms``: RMS error of the estimates against the twin's truth; ``bias``: their mean error;
  ``precision``: the mean over poses of the per-pose standard deviation (NaN with one estimate
  per pose);
- ``bound``: the bound's RMS over the same poses (the square root of its mean variance: the
  bound is per pose, a protocol of random poses averages variances); ``ratio``: rms / bound;
- ``chi2``: the mean of (error / reported sigma)^2, 1 for an honest sigma; ``chi2_p``: the
  two-sided p-value of its sum against a chi-square with as many degrees of freedom as
  estimates (a sigma that is too small or too large shows as a p near 0);
- ``failures``: estimates without a pose (status not ok), and the time an inspection of this
  design takes: the scans fused at the spin rate plus the median CPU time of one estimate.

`cheapest` picks the design that meets a per-axis target within a time, the smallest board
first (the board is what one builds), then the fastest.
"""

from __future__ import annotations

import math
import re
import warnings
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from scenarios.study.store import AXES, StudyStore
from twin.core.errors import AimbenchError

UNITS = ("mm", "mm", "mm", "deg", "deg", "deg")
SCALE = np.array([1e3, 1e3, 1e3, *([180.0 / math.pi] * 3)])
EDGE = tuple(f"{a}_{u}" for a, u in zip(AXES, UNITS, strict=True))
#: Seconds per scan of the twin's sensor (600 rpm).
SCAN_PERIOD_S = 0.1


@dataclass
class DesignResult:
    """One design point at one number of scans fused (edge units, per axis in `EDGE` order)."""

    point: int
    fused: int
    params: dict[str, Any]
    poses: int
    estimates: int
    failures: int
    rms: np.ndarray
    bias: np.ndarray
    precision: np.ndarray
    bound: np.ndarray
    chi2: np.ndarray
    chi2_p: np.ndarray
    cpu_ms: float
    bound_cpu_ms: float
    board_area_m2: float
    diagnostics: dict = field(default_factory=dict)

    @property
    def ratio(self) -> np.ndarray:
        with np.errstate(divide="ignore", invalid="ignore"):
            return self.rms / self.bound

    @property
    def failed_fraction(self) -> float:
        return self.failures / self.estimates if self.estimates else math.nan

    @property
    def time_s(self) -> float:
        """An inspection of this design: the scans fused plus one estimate's CPU time."""
        return self.fused * SCAN_PERIOD_S + self.cpu_ms / 1e3

    def row(self) -> dict[str, Any]:
        """Flat, for tables and Parquet."""
        out: dict[str, Any] = {"point": self.point, "scans_fused": self.fused,
                               **{f"param {k}": v for k, v in self.params.items()},
                               "poses": self.poses, "estimates": self.estimates,
                               "failures": self.failures, "failed_fraction": self.failed_fraction}
        for j, name in enumerate(EDGE):
            for what in ("rms", "bias", "precision", "bound", "ratio", "chi2", "chi2_p"):
                key = f"{name}_{what}" if what in ("rms", "bias", "precision", "bound") \
                    else f"{name.rsplit('_', 1)[0]}_{what}"
                out[key] = float(getattr(self, what)[j])
        out.update(cpu_ms=self.cpu_ms, bound_cpu_ms=self.bound_cpu_ms, time_s=self.time_s,
                   board_area_m2=self.board_area_m2)
        return out


def summarize(store: StudyStore) -> list[DesignResult]:
    """Every (design point, scans fused) with stored estimates, in design order."""
    from scenarios import station as stations
    from scenarios.study.spec import StudySpec, apply

    spec = StudySpec.model_validate(store.get("spec"))
    base = stations.from_dict(store.get("station"), "the study's station")
    points = store.points()
    est, bnd = store.estimates(), store.bounds()
    out = []
    for i, values in enumerate(points):
        station, _ = apply(base, spec, values)
        area = station.board.width_mm * station.board.height_mm * 1e-6
        for n in spec.fused():
            m = (est["point"] == i) & (est["fused"] == n)
            if not m.any():
                continue
            mb = (bnd["point"] == i) & (bnd["fused"] == n)
            out.append(_result(i, n, values, est, m, bnd, mb, area))
    return out


def _result(i: int, n: int, values: dict, est: dict, m: np.ndarray, bnd: dict,
            mb: np.ndarray, area: float) -> DesignResult:
    ok = m & (est["success"] == 1)
    err = np.column_stack([est[f"err_{a}"][ok] for a in AXES]) * SCALE
    sig = np.column_stack([est[f"sigma_{a}"][ok] for a in AXES]) * SCALE
    std = np.column_stack([bnd[f"std_{a}"][mb] for a in AXES]) * SCALE
    nan6 = np.full(6, np.nan)
    with np.errstate(invalid="ignore", divide="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a design without any estimate
        rms = np.sqrt(np.mean(err**2, axis=0)) if len(err) else nan6
        bias = np.mean(err, axis=0) if len(err) else nan6
        poses = est["pose"][ok]
        spreads = [err[poses == k].std(axis=0, ddof=1) for k in np.unique(poses)
                   if np.sum(poses == k) > 1]
        precision = np.mean(spreads, axis=0) if spreads else nan6
        z2 = (err / sig) ** 2
        good = np.isfinite(z2)
        dof = good.sum(axis=0)
        total = np.where(good, z2, 0.0).sum(axis=0)
        chi2 = np.where(dof > 0, total / np.maximum(dof, 1), np.nan)
        from scipy import stats  # (lazy: scipy.stats costs ~1 s to import, and every
        # command's start imports this module through the CLI's parser)

        p_low = stats.chi2.cdf(total, np.maximum(dof, 1))
        chi2_p = np.where(dof > 0, 2 * np.minimum(p_low, 1 - p_low), np.nan)
        finite = np.isfinite(std)
        bound = np.where(finite.any(axis=0),
                         np.sqrt(np.nanmean(np.where(finite, std**2, np.nan), axis=0))
                         if len(std) else nan6, np.nan) if len(std) else nan6
    return DesignResult(
        point=i, fused=n, params=values, poses=len(np.unique(est["pose"][m])),
        estimates=int(m.sum()), failures=int(m.sum() - ok.sum()), rms=rms, bias=bias,
        precision=precision, bound=bound, chi2=chi2, chi2_p=chi2_p,
        cpu_ms=1e3 * float(np.median(est["cpu_s"][m])) if m.any() else math.nan,
        bound_cpu_ms=1e3 * float(np.median(bnd["cpu_s"][mb])) if mb.any() else math.nan,
        board_area_m2=area)


# -- targets -------------------------------------------------------------------------------

_TARGET = re.compile(r"^(?P<axis>x|y|z|roll|tilt|yaw)_(?P<unit>mm|deg)=(?P<value>[0-9.eE+-]+)$")


def parse_target(text: str) -> dict[str, float]:
    """``roll_deg=0.05,x_mm=2`` -> {"roll_deg": 0.05, "x_mm": 2.0}; one clear error otherwise."""
    out: dict[str, float] = {}
    for part in (p.strip() for p in text.split(",") if p.strip()):
        m = _TARGET.match(part)
        unit = dict(zip(AXES, UNITS, strict=True)).get(m["axis"]) if m else None
        if m is None or unit != m["unit"]:
            raise AimbenchError(f"--target: {part!r} is not AXIS_UNIT=VALUE with AXIS_UNIT one of "
                                f"{', '.join(EDGE)} (e.g. roll_deg=0.05,x_mm=2)")
        value = float(m["value"])
        if not value > 0:
            raise AimbenchError(f"--target: {part!r}: the limit must be positive")
        out[f"{m['axis']}_{unit}"] = value
    if not out:
        raise AimbenchError("--target: give at least one AXIS_UNIT=VALUE (e.g. roll_deg=0.05)")
    return out


def meets(r: DesignResult, target: dict[str, float], within_s: float | None,
          by: str = "sim", max_failed: float = 0.01) -> bool:
    """Whether a design meets the per-axis target (RMS of the simulation, or the bound), in
    at most `within_s` seconds, with at most `max_failed` of its estimates failing."""
    values = r.rms if by == "sim" else r.bound
    for key, limit in target.items():
        v = values[EDGE.index(key)]
        if not (math.isfinite(v) and v <= limit):
            return False
    if within_s is not None and not r.time_s <= within_s:
        return False
    return by == "bound" or (r.estimates > 0 and r.failed_fraction <= max_failed)


def cheapest(results: list[DesignResult], target: dict[str, float], within_s: float | None,
             by: str = "sim", max_failed: float = 0.01) -> DesignResult | None:
    """The design meeting the target with the smallest board, then the shortest time."""
    ok = [r for r in results if meets(r, target, within_s, by, max_failed)]
    return min(ok, key=lambda r: (r.board_area_m2, r.time_s, r.point)) if ok else None


def export_parquet(store: StudyStore, results: list[DesignResult]) -> list[Any]:
    """``designs.parquet`` (one row per design and scans fused) and ``estimates.parquet``
    (every estimate, SI and edge units) in the study folder, with the study file in their
    metadata."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from scenarios.store import dumps

    meta = {f"aimbench.{k}": dumps(store.get(k)) for k in ("spec", "station", "config")}
    folder = store.folder
    rows = [r.row() for r in results]
    names = list(dict.fromkeys(k for r in rows for k in r))
    designs = pa.table({k: pa.array([_plain(r.get(k)) for r in rows]) for k in names}
                       ) if rows else pa.table({"point": pa.array([], pa.int64())})
    pq.write_table(designs.replace_schema_metadata(meta), folder / "designs.parquet")
    est = store.estimates()
    cols: dict[str, Any] = {k: est[k] for k in ("point", "pose", "fused", "grp", "status",
                                                "success", "cpu_s")}
    for j, (a, edge) in enumerate(zip(AXES, EDGE, strict=True)):
        cols[f"err_{a}"] = est[f"err_{a}"]
        cols[f"sigma_{a}"] = est[f"sigma_{a}"]
        cols[f"err_{edge}"] = est[f"err_{a}"] * SCALE[j]
        cols[f"sigma_{edge}"] = est[f"sigma_{a}"] * SCALE[j]
    table = pa.table({k: pa.array(list(v) if v.dtype == object else v) for k, v in cols.items()})
    pq.write_table(table.replace_schema_metadata(meta), folder / "estimates.parquet")
    return [folder / "designs.parquet", folder / "estimates.parquet"]


def _plain(v: Any) -> Any:
    if isinstance(v, float) and not math.isfinite(v):
        return None
    if isinstance(v, bool | int | float | str) or v is None:
        return v
    return str(v)
