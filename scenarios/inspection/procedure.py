"""One unit's inspection: take scans, estimate the mounting, judge it, re-measure if unproven.

    trigger -> N scans -> align.estimate (fused) -> mounting error in {S} with its covariance
            -> verdict per axis (`verdict`) -> INCONCLUSIVE? take more scans, estimate again
            from all of them, judge again (up to ``max_scans``) -> the unit's verdict

A re-measure fuses the new scans with the first ones: the estimator's sigma shrinks (roughly as
1/sqrt(N) for the plane's tilt and yaw, faster for roll and x), the stated system term does not,
so a unit whose doubt comes from the system term stays INCONCLUSIVE, as it should. An estimate
that found no board (someone walked through the beam) is re-measured the same way.

The result is scipy-style: ``status`` (``ok``, or the estimator's reason for no pose),
``verdict``, the per-axis judgements, diagnostics and timings.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

import align
from align.calibration import LaserCalibration
from scenarios import calibrate
from scenarios.defaults import INSPECTION_SCANS as DEFAULT_SCANS
from scenarios.inspection import mounting
from scenarios.inspection.acquire import Acquisition, AcquisitionError
from scenarios.inspection.verdict import (
    AXES,
    EDGE_SCALE,
    RULE_TEXT,
    AxisJudgement,
    Verdict,
    edge_key,
    judge_axis,
    limits_si,
    overall,
    system_sigma_si,
)
from scenarios.station import Station
from twin.core.pose import Pose
from twin.core.scan import Scan

#: A re-measure adds this many times the first scans (so 10 -> 30 scans in all).
REMEASURE_FACTOR = 2


@dataclass
class Inspection:
    """What one unit's inspection found (SI inside; `to_edge` for people)."""

    unit: str
    status: str
    verdict: Verdict
    rule: str
    k: float
    axes: list[AxisJudgement] = field(default_factory=list)
    error: np.ndarray | None = None          # mounting error (6,), every axis, m and rad
    covariance: np.ndarray | None = None     # its 6 x 6 covariance (estimator only)
    estimate: Any = None                     # the last align.PoseEstimate (board frame)
    pose_in_station: Pose | None = None
    nominal: Pose | None = None
    nominal_from: str = "station"
    truth_error: np.ndarray | None = None    # the twin's true mounting error, if known
    attempts: list[dict] = field(default_factory=list)
    scans: list[Scan] = field(default_factory=list)
    diagnostics: dict = field(default_factory=dict)
    timings: dict = field(default_factory=dict)
    message: str = ""

    @property
    def scans_used(self) -> int:
        return len(self.scans)

    def axis(self, name: str) -> AxisJudgement | None:
        return next((a for a in self.axes if a.axis == name), None)

    def true_verdict(self, limits: dict[str, float]) -> Verdict | None:
        """Whether the unit truly conforms (twin only): every judged axis's true error within
        its limit."""
        if self.truth_error is None:
            return None
        inside = all(abs(self.truth_error[AXES.index(a)]) <= lim for a, lim in limits.items())
        return Verdict.PASS if inside else Verdict.FAIL

    def to_edge(self) -> dict[str, Any]:
        """JSON-ready, mm and deg: what ``--json`` prints and the record keeps."""
        out: dict[str, Any] = {"unit": self.unit, "status": self.status,
                               "verdict": str(self.verdict), "rule": self.rule,
                               "rule_text": RULE_TEXT[self.rule], "k": self.k,
                               "scans": self.scans_used, "message": self.message}
        for i, a in enumerate(AXES):
            key = edge_key(a)
            s = EDGE_SCALE[a]
            out[key] = None if self.error is None else float(self.error[i] * s)
            sd = None if self.covariance is None else float(np.sqrt(max(
                self.covariance[i, i], 0.0)) * s)
            out[f"{key}_std"] = sd
            if self.truth_error is not None:
                out[f"{key}_true"] = float(self.truth_error[i] * s)
        out["axes"] = [j.to_edge() for j in self.axes]
        if self.pose_in_station is not None:
            out["pose_in_station"] = _edge(self.pose_in_station)
        if self.nominal is not None:
            out["nominal"] = _edge(self.nominal)
            out["nominal_from"] = self.nominal_from
        out["attempts"] = self.attempts
        out["diagnostics"] = self.diagnostics
        out["timings"] = self.timings
        return out


def _edge(pose: Pose) -> dict[str, float]:
    return {k: float(v) for k, v in pose.to_edge().items()}


def inspect_unit(acq: Acquisition, station: Station, unit: str, *,
                 scans: int = DEFAULT_SCANS, max_scans: int | None = None,
                 method: str = align.DEFAULT_METHOD, hints: align.Hints | None = None,
                 calibration: LaserCalibration | None = None,
                 on_attempt: Any = None) -> Inspection:
    """Inspect one unit from `acq` (module docstring). ``max_scans``: the most scans a
    re-measure may reach (default ``scans`` x (1 + `REMEASURE_FACTOR`); equal to ``scans``: no
    re-measure). ``calibration``: a per-laser range calibration to apply to every scan.
    ``on_attempt(inspection)``: called after each judgement (the live view)."""
    if scans < 1:
        raise ValueError("an inspection needs at least 1 scan")
    max_scans = scans * (1 + REMEASURE_FACTOR) if max_scans is None else max(max_scans, scans)
    if hints is None:
        # a unit on the line is a new one: its own range offset (the station's prior on it)
        # is estimated with its pose, not taken as zero
        # and the board is where the station puts it: its distance stated (a panel hiding the
        # board must not pass for it), its region where the station gives a tolerance
        at = mounting.nominal_pose(station)[0]
        hints = align.Hints(roll_prior=station.roll_prior(),
                            expected_distance=station.board_distance(at),
                            board_region=station.board_region(at),
                            **station.range_offset_hints(calibrated=calibration is not None))
    t_trigger = time.perf_counter()
    cpu0 = time.process_time()
    tol = station.tolerances
    limits, system = limits_si(tol), system_sigma_si(tol)
    nominal, nominal_from = mounting.nominal_pose(station)
    board = station.board_spec()
    taken: list[Scan] = []
    attempts: list[dict] = []
    want = scans
    compute_s = 0.0
    while True:
        new = acq.take(want - len(taken))
        if calibration is not None:
            new = [calibrate.apply(s, calibration) for s in new]
        taken += new
        if not taken:
            raise AcquisitionError(f"{acq.source}: no whole scan to inspect ({acq.rejected} "
                                   "rejected); check the sensor with `aimbench info`")
        t0 = time.perf_counter()
        est = align.estimate(taken, board, method, hints)
        result = _judge(unit, est, station, nominal, nominal_from, limits, system, taken)
        compute_s += time.perf_counter() - t0
        attempts.append({"scans": len(taken), "status": result.status,
                         "verdict": str(result.verdict),
                         "compute_s": time.perf_counter() - t0})
        result.attempts = attempts
        if on_attempt is not None:
            on_attempt(result)
        if result.verdict != Verdict.INCONCLUSIVE or want >= max_scans or len(new) == 0:
            break
        want = min(max_scans, want + scans * REMEASURE_FACTOR)
    result.diagnostics.update({"rejected_scans": acq.rejected, "scans_taken": acq.taken})
    result.timings = {"acquire_s": acq.acquire_s, "compute_s": compute_s,
                      "total_s": time.perf_counter() - t_trigger,
                      "cpu_s": time.process_time() - cpu0}
    return result


#: Estimator diagnostics a record keeps (the rest stays in the estimate).
_DIAGNOSTICS = ("rings", "rays", "hits", "brackets", "range_sigma_m", "chi2_per_dof", "scans",
                "scans_used", "reason")


def _judge(unit: str, est: Any, station: Station, nominal: Pose, nominal_from: str,
           limits: dict[str, float], system: dict[str, float], scans: list[Scan]) -> Inspection:
    """The judgement of one estimate."""
    tol = station.tolerances
    truth = mounting.true_error(scans[0].meta, station, nominal)
    diag = {k: est.diagnostics[k] for k in _DIAGNOSTICS if k in est.diagnostics}
    used = est.used.get("board") if est.used else None
    diag["board_found"] = bool(est.success)
    diag["board_points"] = len(used) if used is not None else 0
    common = dict(unit=unit, rule=tol.rule, k=tol.coverage_k, estimate=est, nominal=nominal,
                  nominal_from=nominal_from, truth_error=truth, scans=list(scans),
                  diagnostics=diag)
    if not est.success:
        reason = est.diagnostics.get("reason", "")
        return Inspection(status=str(est.status), verdict=Verdict.INCONCLUSIVE,
                          message=f"no pose: {est.status}{': ' + reason if reason else ''}",
                          **common)
    err, cov, in_station = mounting.mounting_error(est.pose, est.covariance, station, nominal)
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None)) if cov is not None else np.full(6, np.inf)
    axes = [judge_axis(a, err[AXES.index(a)], sd[AXES.index(a)], system[a], lim, tol.rule,
                       tol.coverage_k) for a, lim in limits.items()]
    verdict = overall([j.verdict for j in axes])
    return Inspection(status="ok", verdict=verdict, axes=axes, error=err, covariance=cov,
                      pose_in_station=in_station, message=_message(verdict, axes), **common)


def _message(verdict: Verdict, axes: list[AxisJudgement]) -> str:
    bad = [j for j in axes if j.verdict != Verdict.PASS]
    if verdict == Verdict.PASS:
        return "every judged axis within its limit by more than U"
    parts = [f"{edge_key(j.axis)} {j.verdict!s} ({j.to_edge()['error']:+.3g} "
             f"+- {j.to_edge()['U']:.2g}, limit {j.to_edge()['limit']:.3g})" for j in bad]
    return "; ".join(parts)
