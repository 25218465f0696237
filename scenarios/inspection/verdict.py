"""Decision rules: is a measured mounting error within its tolerance, given its uncertainty?

ISO 14253-1:2017 (Geometrical product specifications - Inspection by measurement of workpieces
and measuring equipment - Part 1: Decision rules for verifying conformity or nonconformity with
specifications) makes the measurement uncertainty count against whoever claims: conformity is
proven only when the measured value lies inside the specification zone reduced by the expanded
uncertainty U = k u on each side (the acceptance zone), nonconformity only when it lies outside
the zone widened by U (the rejection zone); between the two neither is proven. With a
symmetric limit L on an error e:

    PASS          |e| + U <= L
    FAIL          |e| - U >  L
    INCONCLUSIVE  otherwise (re-measure with more scans, then a person decides)

``vda5`` is VDA 5's acceptance (VDA Volume 5, Capability of Measurement Processes, 2nd ed.
2010, chapter 8): the tolerance narrowed by the expanded uncertainty on each side is the
acceptance zone, and a line accepts a unit only there; outside it the unit is rejected (there
is no third outcome to hand to a person): PASS when |e| + U <= L, else FAIL. It takes the
same U as ISO 14253-1's rule; VDA 5 also asks the measurement process itself to be suitable,
Q_MP = 2 U / T <= 30 % with T = 2 L the tolerance's width (`q_mp`).

``simple`` is the shared-risk rule (no guard band): PASS when |e| <= L, else FAIL. The
standard uncertainty u of an axis is the estimator's sigma combined in quadrature with the
station's stated measurement-system term (``tolerances.system_sigma``), the same for every unit.

SI inside (m, rad); `AxisJudgement.to_edge` gives mm and deg.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

#: The judged axes in the pose's order, with the edge unit of each.
AXES = ("x", "y", "z", "roll", "tilt", "yaw")
EDGE_UNIT = {"x": "mm", "y": "mm", "z": "mm", "roll": "deg", "tilt": "deg", "yaw": "deg"}
EDGE_SCALE = {"x": 1e3, "y": 1e3, "z": 1e3, "roll": 180.0 / math.pi, "tilt": 180.0 / math.pi,
              "yaw": 180.0 / math.pi}

RULE_TEXT = {
    "iso14253-1": ("ISO 14253-1 guard bands: PASS when |error| + U <= limit, FAIL when "
                   "|error| - U > limit, otherwise INCONCLUSIVE (U = k u)"),
    "vda5": ("VDA 5 acceptance: the tolerance narrowed by U; PASS when |error| + U <= limit, "
             "otherwise FAIL (U = k u)"),
    "simple": "simple acceptance (no guard band): PASS when |error| <= limit, otherwise FAIL",
}
#: VDA 5's largest ratio Q_MP = 2 U / T of a suitable measurement process.
VDA5_QMP_MAX = 0.30


class Verdict(enum.StrEnum):
    """The outcome of a judgement."""

    PASS = "pass"
    FAIL = "fail"
    INCONCLUSIVE = "inconclusive"


def edge_key(axis: str) -> str:
    """``roll`` -> ``roll_deg``, ``x`` -> ``x_mm``."""
    return f"{axis}_{EDGE_UNIT[axis]}"


@dataclass(frozen=True)
class AxisJudgement:
    """One axis: the error, its uncertainty budget, the limit and the verdict (SI units).

    u_estimator: the estimator's 1-sigma; u_system: the station's stated system term; u: both
    in quadrature; expanded: U = k u; limit: the largest allowed |error|.
    """

    axis: str
    error: float
    u_estimator: float
    u_system: float
    u: float
    k: float
    limit: float
    verdict: Verdict

    @property
    def expanded(self) -> float:
        return self.k * self.u

    def to_edge(self) -> dict[str, float | str]:
        s, key = EDGE_SCALE[self.axis], edge_key(self.axis)
        return {"axis": key, "error": self.error * s, "u_estimator": self.u_estimator * s,
                "u_system": self.u_system * s, "u": self.u * s, "k": self.k,
                "U": self.expanded * s, "limit": self.limit * s, "verdict": str(self.verdict)}


def judge(error: float, u: float, limit: float, rule: str = "iso14253-1",
          k: float = 2.0) -> Verdict:
    """The verdict on one axis (module docstring). A non-finite u can prove nothing."""
    if rule not in RULE_TEXT:
        raise ValueError(f"unknown decision rule {rule!r}; use one of {tuple(RULE_TEXT)}")
    if rule == "simple":
        return Verdict.PASS if abs(error) <= limit else Verdict.FAIL
    if not math.isfinite(u) or not math.isfinite(error):
        # nothing proven: VDA 5 accepts only what is proven inside, ISO 14253-1 hands it on
        return Verdict.FAIL if rule == "vda5" else Verdict.INCONCLUSIVE
    big_u = k * u
    if abs(error) + big_u <= limit:
        return Verdict.PASS
    if rule == "vda5":
        return Verdict.FAIL
    if abs(error) - big_u > limit:
        return Verdict.FAIL
    return Verdict.INCONCLUSIVE


def q_mp(u: float, limit: float, k: float = 2.0) -> float:
    """VDA 5's capability ratio of the measurement process, 2 U / T with T = 2 x limit: at most
    `VDA5_QMP_MAX` for a process fit to judge this tolerance."""
    return 2 * k * u / (2 * limit)


def judge_axis(axis: str, error: float, u_estimator: float, u_system: float, limit: float,
               rule: str = "iso14253-1", k: float = 2.0) -> AxisJudgement:
    u = math.hypot(u_estimator, u_system)
    return AxisJudgement(axis, float(error), float(u_estimator), float(u_system), float(u),
                         float(k), float(limit), judge(error, u, limit, rule, k))


def overall(verdicts: list[Verdict]) -> Verdict:
    """The unit's verdict: FAIL if any axis fails, PASS if every judged axis passes, otherwise
    INCONCLUSIVE (no judged axis at all proves nothing either)."""
    if any(v == Verdict.FAIL for v in verdicts):
        return Verdict.FAIL
    if verdicts and all(v == Verdict.PASS for v in verdicts):
        return Verdict.PASS
    return Verdict.INCONCLUSIVE


def limits_si(tolerances: object) -> dict[str, float]:
    """The station's ``[tolerances]`` per judged axis, SI (axes without a limit left out)."""
    out = {}
    for axis in AXES:
        v = getattr(tolerances, edge_key(axis))
        if v is not None:
            out[axis] = float(v) / EDGE_SCALE[axis]
    return out


def system_sigma_si(tolerances: object) -> dict[str, float]:
    """The station's ``[tolerances.system_sigma]`` per axis, SI."""
    sys_sigma = tolerances.system_sigma  # type: ignore[attr-defined]
    return {axis: float(getattr(sys_sigma, edge_key(axis))) / EDGE_SCALE[axis] for axis in AXES}
