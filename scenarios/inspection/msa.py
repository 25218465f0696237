"""Measurement-system analysis of the station: gauge R&R, and bias and linearity.

**Gauge R&R** (AIAG, Measurement Systems Analysis, 4th ed., the ANOVA method): p parts
(units) x o appraisers (operators, or re-mountings of each unit on the station) x r trials,
crossed and balanced. Per axis, the two-way ANOVA with interaction (sums of squares by
statsmodels) gives the mean squares MS_P, MS_A, MS_PA, MS_E; with the random-effects model

    repeatability (EV)     s2_E  = MS_E
    interaction            s2_PA = max(0, (MS_PA - MS_E) / r)
    appraiser              s2_A  = max(0, (MS_A - MS_PA) / (p r))
    reproducibility (AV)   s2_AV = s2_A + s2_PA
    GRR                    s2_GRR = s2_E + s2_AV
    part variation (PV)    s2_P  = max(0, (MS_P - MS_PA) / (o r))
    total (TV)             s2_TV = s2_GRR + s2_P

The interaction is pooled into the error when its p-value exceeds 0.25 (AIAG). F tests of
parts and appraisers are against MS_PA (against the pooled error once pooled). Reported: each
component's standard deviation, its study variation 6 sigma, %GRR against the tolerance
(100 x 6 sigma_GRR / (USL - LSL), USL - LSL = 2 x the station's limit) and against the total
variation, the number of distinct categories ndc = floor(1.41 sigma_P / sigma_GRR), and AIAG's
acceptance bands (%GRR < 10 %: acceptable; 10-30 %: marginal, may be acceptable for the
application; > 30 %: not acceptable; ndc >= 5). Confidence intervals (95 % unless told): a
parametric bootstrap of the fitted random-effects model (2000 replicate studies, percentiles),
because sigma_P, %GRR and ndc are differences and ratios of mean squares that have no exact
interval.

**Bias across units** (the twin, where the truth is known): a new unit's own sensor errors
bias its estimate by an amount the estimator's covariance does not hold. Over n twin units
(each its own sensor, `acquire.unit_sensor`) the error estimate - truth per axis gives the
mean bias, the spread between units and the chi-square of the estimator's sigma; the spread
beyond the estimator's is the measurement-system term the station file may state
(``tolerances.system_sigma``).

**Bias and linearity** (AIAG, against references): the stages give known references, the
rotation stage for yaw and the linear stage for x; at each reference m measurements; per
reference the bias (measured - reference) with its t-test, and over all the regression of the
bias on the reference (slope: linearity, intercept: the bias at zero; each with its standard
error, p-value and interval; scipy). On the real bench the unit's own mounting error is a
constant offset, which the intercept holds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import stats

#: AIAG: pool the interaction into the error when its p-value exceeds this.
POOL_P = 0.25
#: AIAG acceptance bands of %GRR.
ACCEPTABLE_PCT = 10.0
MARGINAL_PCT = 30.0
MIN_NDC = 5
#: The study variation's width in sigmas (AIAG 4th edition; 5.15 in older editions).
STUDY_SIGMAS = 6.0


def acceptance(pct: float) -> str:
    if not math.isfinite(pct):
        return "unknown"
    if pct < ACCEPTABLE_PCT:
        return "acceptable"
    if pct <= MARGINAL_PCT:
        return "marginal"
    return "not acceptable"


def balanced_ss(y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sums of squares and degrees of freedom (parts, appraisers, interaction, error) of a
    balanced crossed design ``y[..., part, appraiser, trial]`` (leading axes: many studies at
    once, for the bootstrap)."""
    p, o, r = y.shape[-3:]
    grand = y.mean(axis=(-3, -2, -1), keepdims=True)
    cell = y.mean(axis=-1, keepdims=True)
    part = y.mean(axis=(-2, -1), keepdims=True)
    appr = y.mean(axis=(-3, -1), keepdims=True)
    ss_p = o * r * ((part - grand) ** 2).sum(axis=(-3, -2, -1))
    ss_a = p * r * ((appr - grand) ** 2).sum(axis=(-3, -2, -1))
    ss_pa = r * ((cell - part - appr + grand) ** 2).sum(axis=(-3, -2, -1))
    ss_e = ((y - cell) ** 2).sum(axis=(-3, -2, -1))
    dfs = np.array([p - 1, o - 1, (p - 1) * (o - 1), p * o * (r - 1)], dtype=float)
    return np.stack([ss_p, ss_a, ss_pa, ss_e], axis=-1), dfs


def anova_table(y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(SS, df) of parts, appraisers, interaction and error from statsmodels' ANOVA of the
    linear model y ~ part + appraiser + part:appraiser (the reported table)."""
    from scenarios.extras import require

    require("statsmodels", "the gauge R&R's ANOVA")
    import pandas as pd
    from statsmodels.formula.api import ols
    from statsmodels.stats.anova import anova_lm

    p, o, r = y.shape
    ip, ia, _ = np.meshgrid(np.arange(p), np.arange(o), np.arange(r), indexing="ij")
    df = pd.DataFrame({"y": y.reshape(-1), "part": ip.reshape(-1), "appraiser": ia.reshape(-1)})
    fit = ols("y ~ C(part) + C(appraiser) + C(part):C(appraiser)", data=df).fit()
    t = anova_lm(fit, typ=2)
    names = ["C(part)", "C(appraiser)", "C(part):C(appraiser)", "Residual"]
    return t.loc[names, "sum_sq"].to_numpy(float), t.loc[names, "df"].to_numpy(float)


def components(ss: np.ndarray, dfs: np.ndarray, p: int, o: int, r: int,
               pool: bool | None = None) -> dict[str, np.ndarray]:
    """Variance components (module docstring) from (..., 4) sums of squares. ``pool``: pool
    the interaction (None: as its F test says, per study)."""
    ms = ss / dfs
    f_int = ms[..., 2] / np.where(ms[..., 3] > 0, ms[..., 3], np.nan)
    p_int = stats.f.sf(f_int, dfs[2], dfs[3])
    pooled = (p_int > POOL_P) if pool is None else np.full(np.shape(p_int), bool(pool))
    ms_pool = (ss[..., 2] + ss[..., 3]) / (dfs[2] + dfs[3])
    ms_e = np.where(pooled, ms_pool, ms[..., 3])
    ms_pa = np.where(pooled, ms_pool, ms[..., 2])
    s2_e = ms_e
    s2_pa = np.where(pooled, 0.0, np.maximum(0.0, (ms[..., 2] - ms[..., 3]) / r))
    s2_a = np.maximum(0.0, (ms[..., 1] - ms_pa) / (p * r))
    s2_p = np.maximum(0.0, (ms[..., 0] - ms_pa) / (o * r))
    grr = s2_e + s2_a + s2_pa
    return {"EV": s2_e, "appraiser": s2_a, "interaction": s2_pa, "AV": s2_a + s2_pa,
            "GRR": grr, "PV": s2_p, "TV": grr + s2_p, "pooled": pooled, "p_interaction": p_int,
            "ms": ms}


@dataclass
class GaugeRR:
    """One axis's gauge R&R (edge units: mm or deg)."""

    axis: str
    unit: str
    parts: int
    appraisers: int
    trials: int
    tolerance_width: float | None
    anova: list[dict]
    pooled: bool
    sigma: dict[str, float]
    pct_tolerance: dict[str, float]
    pct_total: dict[str, float]
    ndc: int
    ci: dict[str, tuple[float, float]] = field(default_factory=dict)
    confidence: float = 0.95
    status: str = "ok"

    @property
    def verdict(self) -> str:
        pct = self.pct_tolerance.get("GRR", math.nan)
        if not math.isfinite(pct):
            pct = self.pct_total.get("GRR", math.nan)
        return acceptance(pct)

    def to_dict(self) -> dict[str, Any]:
        return {"axis": self.axis, "unit": self.unit, "parts": self.parts,
                "appraisers": self.appraisers, "trials": self.trials,
                "tolerance_width": self.tolerance_width, "anova": self.anova,
                "interaction_pooled": self.pooled, "sigma": self.sigma,
                "study_variation": {k: STUDY_SIGMAS * v for k, v in self.sigma.items()},
                "pct_tolerance": self.pct_tolerance, "pct_total": self.pct_total,
                "ndc": self.ndc, "ci": {k: list(v) for k, v in self.ci.items()},
                "confidence": self.confidence, "acceptance": self.verdict,
                "status": self.status}


def _figures(comp: dict[str, np.ndarray], tol_width: float | None) -> dict[str, np.ndarray]:
    out = {}
    grr = np.sqrt(comp["GRR"])
    for k in ("EV", "AV", "GRR", "PV"):
        s = np.sqrt(comp[k])
        out[f"sigma_{k}"] = s
        out[f"pct_total_{k}"] = 100.0 * s / np.sqrt(comp["TV"])
        if tol_width:
            out[f"pct_tolerance_{k}"] = 100.0 * STUDY_SIGMAS * s / tol_width
    out["ndc_raw"] = 1.41 * np.sqrt(comp["PV"]) / np.where(grr > 0, grr, np.nan)
    return out


def gauge_rr(y: np.ndarray, axis: str, unit: str, tolerance_width: float | None,
             confidence: float = 0.95, n_boot: int = 2000, seed: int = 0) -> GaugeRR:
    """The gauge R&R of one axis from ``y[part, appraiser, trial]`` (edge units)."""
    y = np.asarray(y, float)
    if y.ndim != 3 or min(y.shape) < 1 or y.shape[0] < 2 or y.shape[1] < 1 or y.shape[2] < 2:
        raise ValueError("a gauge R&R needs at least 2 parts, 1 appraiser and 2 trials")
    p, o, r = y.shape
    ss, dfs = anova_table(y) if o > 1 else balanced_ss(y)
    comp = components(ss, dfs, p, o, r, pool=True if o == 1 else None)
    ms = comp["ms"]
    pooled = bool(comp["pooled"])
    den_pa = (ss[2] + ss[3]) / (dfs[2] + dfs[3]) if pooled else ms[2]
    den_df = dfs[2] + dfs[3] if pooled else dfs[2]
    rows = []
    for i, name in enumerate(("part", "appraiser", "part x appraiser", "repeatability")):
        row = {"source": name, "df": float(dfs[i]), "SS": float(ss[i]), "MS": float(ms[i])}
        if i < 2 and dfs[i] > 0 and den_pa > 0:
            f = ms[i] / den_pa
            row.update(F=float(f), p=float(stats.f.sf(f, dfs[i], den_df)))
        elif i == 2 and ms[3] > 0 and dfs[2] > 0:
            f = ms[2] / ms[3]
            row.update(F=float(f), p=float(stats.f.sf(f, dfs[2], dfs[3])))
        rows.append(row)
    fig = _figures(comp, tolerance_width)
    sigma = {k: float(fig[f"sigma_{k}"]) for k in ("EV", "AV", "GRR", "PV")}
    sigma["TV"] = float(np.sqrt(comp["TV"]))
    pct_tol = ({k: float(fig[f"pct_tolerance_{k}"]) for k in ("EV", "AV", "GRR", "PV")}
               if tolerance_width else {})
    pct_tot = {k: float(fig[f"pct_total_{k}"]) for k in ("EV", "AV", "GRR", "PV")}
    ndc = int(np.floor(fig["ndc_raw"])) if np.isfinite(fig["ndc_raw"]) else 0
    # Parametric bootstrap: studies drawn from the fitted random-effects model.
    rng = np.random.default_rng(seed)
    b = n_boot
    sd = {k: math.sqrt(float(comp[k])) for k in ("PV", "appraiser", "interaction", "EV")}
    yb = (rng.normal(0, sd["PV"], (b, p, 1, 1)) + rng.normal(0, sd["appraiser"], (b, 1, o, 1))
          + rng.normal(0, sd["interaction"], (b, p, o, 1)) + rng.normal(0, sd["EV"], (b, p, o, r)))
    ssb, dfb = balanced_ss(yb)
    cb = components(ssb, dfb, p, o, r, pool=True if o == 1 else None)
    fb = _figures(cb, tolerance_width)
    lo_q, hi_q = 50 * (1 - confidence), 100 - 50 * (1 - confidence)
    ci = {}
    for key in [*(f"sigma_{k}" for k in ("EV", "AV", "GRR", "PV")),
                *((f"pct_tolerance_{k}" for k in ("EV", "AV", "GRR", "PV"))
                  if tolerance_width else ()), "pct_total_GRR", "ndc_raw"]:
        v = fb[key]
        v = v[np.isfinite(v)]
        if len(v):
            ci[key.replace("_raw", "")] = (float(np.percentile(v, lo_q)),
                                           float(np.percentile(v, hi_q)))
    if "ndc" in ci:
        ci["ndc"] = (math.floor(ci["ndc"][0]), math.floor(ci["ndc"][1]))
    return GaugeRR(axis, unit, p, o, r, tolerance_width, rows, pooled, sigma, pct_tol,
                   pct_tot, ndc, ci, confidence)


# -- bias ---------------------------------------------------------------------------------------

@dataclass
class AxisBias:
    """The error estimate - truth of one axis over n units (edge units)."""

    axis: str
    unit: str
    n: int
    mean: float
    mean_ci: tuple[float, float]
    sd_between: float
    sd_estimator: float
    chi2: float
    system_sigma: float

    def to_dict(self) -> dict[str, Any]:
        return {**self.__dict__, "mean_ci": list(self.mean_ci)}


def bias_across_units(errors: np.ndarray, sigmas: np.ndarray, axis: str, unit: str,
                      confidence: float = 0.95) -> AxisBias:
    """Bias of one axis from the errors (estimate - truth) and the estimator's sigmas of n
    units: the mean with its t interval, the spread, the chi-square of the estimator's sigma
    (mean of (error / sigma)^2: 1 when it is honest) and the system term that would make it so:
    sqrt(max(0, mean(error^2) - mean(sigma^2)))."""
    e, s = np.asarray(errors, float), np.asarray(sigmas, float)
    n = len(e)
    mean = float(e.mean())
    half = float(stats.t.ppf(0.5 + confidence / 2, n - 1) * e.std(ddof=1) / math.sqrt(n)) \
        if n > 1 else math.inf
    extra = math.sqrt(max(0.0, float((e ** 2).mean() - (s ** 2).mean())))
    return AxisBias(axis, unit, n, mean, (mean - half, mean + half),
                    float(e.std(ddof=1)) if n > 1 else math.nan,
                    float(np.sqrt((s ** 2).mean())), float(((e / s) ** 2).mean()), extra)


@dataclass
class Linearity:
    """Bias and linearity of one axis against references (edge units)."""

    axis: str
    unit: str
    references: list[dict]
    slope: float
    slope_ci: tuple[float, float]
    slope_p: float
    intercept: float
    intercept_ci: tuple[float, float]
    intercept_p: float
    r2: float

    def to_dict(self) -> dict[str, Any]:
        return {**self.__dict__, "slope_ci": list(self.slope_ci),
                "intercept_ci": list(self.intercept_ci)}


def linearity(reference: np.ndarray, measured: np.ndarray, axis: str, unit: str,
              confidence: float = 0.95) -> Linearity:
    """AIAG bias and linearity from paired references and measurements (module docstring)."""
    ref, meas = np.asarray(reference, float), np.asarray(measured, float)
    bias = meas - ref
    per = []
    for v in np.unique(ref):
        b = bias[ref == v]
        row = {"reference": float(v), "n": len(b), "bias": float(b.mean())}
        if len(b) > 1:
            se = b.std(ddof=1) / math.sqrt(len(b))
            t = row["bias"] / se if se > 0 else math.inf
            row.update(sd=float(b.std(ddof=1)), t=float(t),
                       p=float(2 * stats.t.sf(abs(t), len(b) - 1)))
        per.append(row)
    fit = stats.linregress(ref, bias)
    dof = len(ref) - 2
    q = float(stats.t.ppf(0.5 + confidence / 2, dof)) if dof > 0 else math.inf
    t_int = fit.intercept / fit.intercept_stderr if fit.intercept_stderr > 0 else math.inf
    p_int = float(2 * stats.t.sf(abs(t_int), dof)) if dof > 0 else math.nan
    return Linearity(axis, unit, per, float(fit.slope),
                     (fit.slope - q * fit.stderr, fit.slope + q * fit.stderr), float(fit.pvalue),
                     float(fit.intercept), (fit.intercept - q * fit.intercept_stderr,
                                            fit.intercept + q * fit.intercept_stderr),
                     p_int, float(fit.rvalue ** 2))


# -- the Type-1 gauge study ------------------------------------------------------------------

#: The Type-1 study's conventions (Bosch booklet 10 since its 2003 edition, Minitab's and
#: JASP's defaults): the gauge may use K = 20 % of the tolerance, its spread counted as L = 6
#: standard deviations (+-3 s), and it is capable when Cg and Cgk are both at least 1.33. Some
#: company rules count L = 4 (`type1(..., sigmas=4)`): 6/4 the figures, a laxer test; the
#: published convention is the one a customer's auditor recomputes, so it is the default.
TYPE1_PCT = 20.0
TYPE1_SIGMAS = 6.0
TYPE1_MIN_C = 1.33
#: The fewest repeats of the reference part a Type-1 study accepts (50 preferred).
TYPE1_MIN_N = 25


@dataclass
class Type1:
    """A Type-1 gauge study of one characteristic: n repeats of a reference part.

    Cg = (K/100 T) / (L s); Cgk = (K/200 T - |bias|) / (L/2 s), bias = mean - reference, its
    t = bias / (s / sqrt n) against Student's t with n - 1 degrees of freedom (two-sided p).
    """

    axis: str
    unit: str
    n: int
    reference: float
    tolerance: float
    mean: float
    sd: float
    bias: float
    t: float
    p: float
    cg: float
    cgk: float
    pct: float = TYPE1_PCT
    sigmas: float = TYPE1_SIGMAS
    alpha: float = 0.05

    @property
    def capable(self) -> bool:
        return self.cg >= TYPE1_MIN_C and self.cgk >= TYPE1_MIN_C

    @property
    def bias_significant(self) -> bool:
        return self.p < self.alpha

    def to_dict(self) -> dict[str, Any]:
        return {**self.__dict__, "capable": self.capable,
                "bias_significant": self.bias_significant}


def type1(values: np.ndarray, reference: float, tolerance: float, axis: str, unit: str,
          pct: float = TYPE1_PCT, sigmas: float = TYPE1_SIGMAS, alpha: float = 0.05) -> Type1:
    """The Type-1 study of `values` (repeats of a part whose true value is `reference`)
    against a tolerance of width `tolerance` (USL - LSL), all in one unit."""
    x = np.asarray(values, float)
    x = x[np.isfinite(x)]
    n = len(x)
    if n < 2:
        raise ValueError("a Type-1 study needs at least two measurements")
    if not tolerance > 0:
        raise ValueError(f"the tolerance's width must be positive, not {tolerance}")
    mean, sd = float(x.mean()), float(x.std(ddof=1))
    bias = mean - float(reference)
    if sd > 0:
        t = bias / (sd / math.sqrt(n))
        p = float(2 * stats.t.sf(abs(t), n - 1))
        cg = pct / 100 * tolerance / (sigmas * sd)
        cgk = (pct / 200 * tolerance - abs(bias)) / (sigmas / 2 * sd)
    else:  # a gauge that reads the same every time: only its bias can be judged
        t = math.inf if bias else 0.0
        p = 0.0 if bias else 1.0
        cg = math.inf
        cgk = math.inf if abs(bias) <= pct / 200 * tolerance else -math.inf
    return Type1(axis, unit, n, float(reference), float(tolerance), mean, sd, bias, float(t),
                 p, float(cg), float(cgk), pct, sigmas, alpha)
