"""Statistical process control of the line's measured mounting errors (issue 36).

No well-kept Python library computes these the textbook way (with the run rules and both
capability pairs), so the project does, checked in tests/test_spc.py against published worked
examples (the NIST/SEMATECH e-Handbook of Statistical Methods, sections 6.3.2.2 and 6.1.6).

**Individuals and moving-range charts** (I-MR; the line inspects one unit at a time, so every
subgroup has one value): MR_i = |x_i - x_(i-1)|, MR-bar their mean; the short-term sigma is
MR-bar / d2 with d2 = 1.128 (the range of two normal values); the I chart's limits are
x-bar +- 3 sigma, the MR chart's upper limit D4 MR-bar with D4 = 3.267 (lower 0).

**Run rules** on the I chart, in zones of the short-term sigma about the centre line:
Western Electric (1956): 1 a point beyond 3 sigma; 2 two of three in a row beyond 2 sigma on
one side; 3 four of five beyond 1 sigma on one side; 4 eight in a row on one side.
Nelson (1984) keeps 1, 5 (= WE 2), 6 (= WE 3) and adds 2 nine in a row on one side, 3 six in
a row steadily rising or falling, 4 fourteen in a row alternating up and down, 7 fifteen in a
row within 1 sigma, 8 eight in a row with none within 1 sigma and points on both sides of the
centre line. A signal is reported at the point that completes the pattern. (The published
statements of both sets that tests/test_spc.py checks them against are cited there.)

**Capability** against the two-sided specification [LSL, USL]: Cp = (USL - LSL) / 6 sigma,
Cpk = min(USL - mean, mean - LSL) / 3 sigma with the short-term sigma (MR-bar / d2); Pp and
Ppk the same with the overall sample standard deviation (n - 1). A station's limit L on an
axis's error is the specification [-L, +L].
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field

import numpy as np

#: d2 and D4 for moving ranges of two (ASTM E2587, Montgomery's appendix VI).
D2 = 1.128
D4 = 3.267
RULE_SETS = ("western-electric", "nelson")

WESTERN_ELECTRIC = {
    1: "one point beyond 3 sigma",
    2: "two of three in a row beyond 2 sigma on one side",
    3: "four of five in a row beyond 1 sigma on one side",
    4: "eight in a row on one side of the centre line",
}
NELSON = {
    1: "one point beyond 3 sigma",
    2: "nine in a row on one side of the centre line",
    3: "six in a row steadily rising or falling",
    4: "fourteen in a row alternating up and down",
    5: "two of three in a row beyond 2 sigma on one side",
    6: "four of five in a row beyond 1 sigma on one side",
    7: "fifteen in a row within 1 sigma",
    8: "eight in a row none within 1 sigma, on both sides",
}


@dataclass(frozen=True)
class Signal:
    """A run rule broken: which rule of which set, at which point (0-based), what it means."""

    rules: str
    rule: int
    index: int
    text: str


@dataclass
class IMRChart:
    """An individuals and moving-range chart (module docstring), in the values' unit."""

    values: list[float]
    moving_ranges: list[float]
    center: float
    mr_bar: float
    sigma: float
    ucl: float
    lcl: float
    mr_ucl: float
    mr_lcl: float = 0.0
    signals: list[Signal] = field(default_factory=list)
    mr_signals: list[int] = field(default_factory=list)

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class Capability:
    """Cp, Cpk (short-term sigma) and Pp, Ppk (overall sigma) against [lsl, usl]."""

    n: int
    mean: float
    sigma_within: float
    sigma_overall: float
    lsl: float
    usl: float
    cp: float
    cpk: float
    pp: float
    ppk: float

    def to_dict(self) -> dict:
        return asdict(self)


def _clean(values: Sequence[float]) -> np.ndarray:
    x = np.asarray([v for v in values if v is not None], dtype=float)
    return x[np.isfinite(x)]


def moving_ranges(values: Sequence[float]) -> np.ndarray:
    x = _clean(values)
    return np.abs(np.diff(x))


def imr_chart(values: Sequence[float], rules: str = "nelson",
              last_only: bool = False) -> IMRChart:
    """The I-MR chart of `values` in their order, with the run rules' signals (``last_only``:
    those of the last point only)."""
    x = _clean(values)
    if len(x) < 2:
        raise ValueError("an individuals chart needs at least two values")
    mr = np.abs(np.diff(x))
    center, mr_bar = float(x.mean()), float(mr.mean())
    sigma = mr_bar / D2
    chart = IMRChart(values=x.tolist(), moving_ranges=mr.tolist(), center=center, mr_bar=mr_bar,
                     sigma=sigma, ucl=center + 3 * sigma, lcl=center - 3 * sigma,
                     mr_ucl=D4 * mr_bar)
    chart.signals = run_rules(x, center, sigma, rules, last_only)
    chart.mr_signals = [i + 1 for i, r in enumerate(mr) if r > chart.mr_ucl]
    return chart


def run_rules(values: Sequence[float], center: float, sigma: float,
              rules: str = "nelson", last_only: bool = False) -> list[Signal]:
    """The run-rule signals of `values` about `center` in zones of `sigma` (module docstring),
    in the order of the points, each rule reported at every point that completes it
    (``last_only``: only those the last point completes, what a live alarm needs)."""
    if rules not in RULE_SETS:
        raise ValueError(f"unknown run rules {rules!r}; use one of {RULE_SETS}")
    x = _clean(values)
    if sigma <= 0 or not math.isfinite(sigma):
        # no spread: only the sides of the centre line mean anything; nothing to test
        return []
    z = (x - center) / sigma
    side = np.sign(z)
    text = WESTERN_ELECTRIC if rules == "western-electric" else NELSON
    # rule numbers of each test in this set
    num = ({"beyond3": 1, "two_of_three": 2, "four_of_five": 3, "run_side": 4}
           if rules == "western-electric" else
           {"beyond3": 1, "run_side": 2, "trend": 3, "alternate": 4, "two_of_three": 5,
            "four_of_five": 6, "within1": 7, "none_within1": 8})
    run_len = 8 if rules == "western-electric" else 9
    out: list[Signal] = []

    def hit(test: str, i: int) -> None:
        out.append(Signal(rules, num[test], i, text[num[test]]))

    for i in range(len(z) - 1 if last_only else 0, len(z)):
        if abs(z[i]) > 3:
            hit("beyond3", i)
        for s in (1, -1):
            w = z[max(0, i - 2):i + 1]
            if len(w) == 3 and s * z[i] > 2 and np.sum(s * w > 2) >= 2:
                hit("two_of_three", i)
            w = z[max(0, i - 4):i + 1]
            if len(w) == 5 and s * z[i] > 1 and np.sum(s * w > 1) >= 4:
                hit("four_of_five", i)
        w = side[max(0, i - run_len + 1):i + 1]
        if len(w) == run_len and (np.all(w > 0) or np.all(w < 0)):
            hit("run_side", i)
        if rules == "nelson":
            d = np.diff(x[max(0, i - 5):i + 1])
            if len(d) == 5 and (np.all(d > 0) or np.all(d < 0)):
                hit("trend", i)
            d = np.sign(np.diff(x[max(0, i - 13):i + 1]))
            if len(d) == 13 and np.all(d != 0) and np.all(d[1:] == -d[:-1]):
                hit("alternate", i)
            w = z[max(0, i - 14):i + 1]
            if len(w) == 15 and np.all(np.abs(w) < 1):
                hit("within1", i)
            w = z[max(0, i - 7):i + 1]
            # Nelson's 8 is a mixture: the points jump across the centre, so both sides
            # must be there (eight beyond 1 sigma on one side is a shift, his 2, 5 and 6)
            if len(w) == 8 and np.all(np.abs(w) > 1) and np.any(w > 0) and np.any(w < 0):
                hit("none_within1", i)
    return out


def capability(values: Sequence[float], lsl: float, usl: float,
               sigma_within: float | None = None) -> Capability:
    """Cp, Cpk, Pp, Ppk of `values` against [lsl, usl]. ``sigma_within``: the short-term
    sigma if known (else MR-bar / d2 of the values in their order)."""
    x = _clean(values)
    if len(x) < 2:
        raise ValueError("capability needs at least two values")
    if not usl > lsl:
        raise ValueError(f"the specification's upper limit {usl} is not above its lower {lsl}")
    mean = float(x.mean())
    within = float(np.abs(np.diff(x)).mean() / D2) if sigma_within is None else float(
        sigma_within)
    overall = float(x.std(ddof=1))
    return Capability(len(x), mean, within, overall, float(lsl), float(usl),
                      *indices(mean, within, lsl, usl), *indices(mean, overall, lsl, usl))


def indices(mean: float, sigma: float, lsl: float, usl: float) -> tuple[float, float]:
    """(Cp, Cpk) for a process of this mean and sigma (Pp, Ppk with the overall sigma)."""
    if sigma <= 0:
        return math.inf, (math.inf if lsl <= mean <= usl else -math.inf)
    return (usl - lsl) / (6 * sigma), min(usl - mean, mean - lsl) / (3 * sigma)


@dataclass(frozen=True)
class Histogram:
    """Counts of values per bin; edges has one more entry than counts."""

    edges: list[float]
    counts: list[int]

    def to_dict(self) -> dict:
        return asdict(self)


def histogram(values: Sequence[float], bins: int | None = None,
              span: tuple[float, float] | None = None) -> Histogram:
    """The histogram of `values` (numpy's; ``bins`` default: Sturges' rule), over ``span``
    (e.g. the specification widened to hold every value) when given."""
    x = _clean(values)
    if bins is None:
        bins = max(5, math.ceil(math.log2(max(len(x), 1)) + 1))
    if span is not None and len(x):
        span = (min(span[0], float(x.min())), max(span[1], float(x.max())))
    counts, edges = np.histogram(x, bins=bins, range=span)
    return Histogram(edges.tolist(), counts.astype(int).tolist())


# -- a line's records ---------------------------------------------------------------------------

@dataclass
class AxisSPC:
    """One judged axis of a line's records, in its edge unit (mm, deg)."""

    axis: str
    unit: str
    limit: float
    chart: IMRChart | None
    capability: Capability | None
    histogram: Histogram | None

    def to_dict(self) -> dict:
        return {"axis": self.axis, "unit": self.unit, "limit": self.limit,
                "chart": None if self.chart is None else self.chart.to_dict(),
                "capability": None if self.capability is None else self.capability.to_dict(),
                "histogram": None if self.histogram is None else self.histogram.to_dict()}


def line_spc(rows: list[dict], rules: str = "nelson", last_only: bool = False
             ) -> list[AxisSPC]:
    """SPC of every judged axis of a line's records (in their order; records without a pose
    left out): the I-MR chart of the mounting errors with the run rules, Cp/Cpk/Pp/Ppk against
    [-limit, +limit], the histogram over the specification."""
    from scenarios.inspection.verdict import AXES, EDGE_SCALE, EDGE_UNIT, edge_key

    out = []
    ok = [r for r in rows if r["status"] == "ok"]
    for a in AXES:
        limits = [r[f"limit_{a}"] for r in ok if r[f"limit_{a}"] is not None]
        if not limits:
            continue
        s = EDGE_SCALE[a]
        lim = limits[-1] * s
        x = [r[f"err_{a}"] * s for r in ok if r[f"err_{a}"] is not None]
        enough = len(x) >= 2
        out.append(AxisSPC(edge_key(a), EDGE_UNIT[a], lim,
                           imr_chart(x, rules, last_only) if enough else None,
                           capability(x, -lim, lim) if enough else None,
                           histogram(x, span=(-lim, lim)) if x else None))
    return out


def summary_lines(rows: list[dict]) -> list[str]:
    """The line's summary as text: the verdicts' tally, then per judged axis the mean, the
    short-term and overall sigma, Cp, Cpk, Pp, Ppk and the run rules broken."""
    n = len(rows)
    counts = {v: sum(r["verdict"] == v for r in rows) for v in ("pass", "fail", "inconclusive")}
    units = len({r["unit"] for r in rows})
    out = [f"{n} inspections of {units} units: " + ", ".join(
        f"{counts[v]} {v.upper()}" + (f" ({100 * counts[v] / n:.1f} %)" if n else "")
        for v in counts)]
    axes = line_spc(rows)
    if not axes:
        return out
    out.append(f"{'axis':<10}{'limit':>8}{'n':>5}{'mean':>10}{'s within':>10}{'s overall':>10}"
               f"{'Cp':>7}{'Cpk':>7}{'Pp':>7}{'Ppk':>7}  run rules (Nelson)")
    for ax in axes:
        c = ax.capability
        if c is None:
            out.append(f"{ax.axis:<10}{ax.limit:>8.3g}  fewer than two values")
            continue
        rules = sorted({s.rule for s in ax.chart.signals}) if ax.chart else []
        broken = ", ".join(f"{r} x{sum(s.rule == r for s in ax.chart.signals)}" for r in rules)
        out.append(f"{ax.axis:<10}{ax.limit:>8.3g}{c.n:>5}{c.mean:>+10.3f}"
                   f"{c.sigma_within:>10.3f}{c.sigma_overall:>10.3f}{c.cp:>7.2f}{c.cpk:>7.2f}"
                   f"{c.pp:>7.2f}{c.ppk:>7.2f}  {broken or 'none'}")
    return out
