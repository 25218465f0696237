"""SPC (scenarios/inspection/spc.py) against published worked examples, to their printed
precision, and the run rules on sequences built to break exactly one rule each."""

from __future__ import annotations

import pytest

from scenarios.inspection import spc

#: NIST/SEMATECH e-Handbook of Statistical Methods, section 6.3.2.2 "Individuals Control
#: Charts", the example of the flow rate of the first 10 batches of a new process
#: (https://www.itl.nist.gov/div898/handbook/pmc/section3/pmc322.htm). Printed there:
#: x-bar 50.81, MR-bar 1.8778, I chart UCL 55.8041, LCL 45.8159, MR chart UCL 6.1347.
NIST_FLOW = [49.6, 47.6, 49.9, 51.3, 47.8, 51.2, 52.6, 52.4, 53.6, 52.1]
NIST_MR = [2.0, 2.3, 1.4, 3.5, 3.4, 1.4, 0.2, 1.2, 1.5]


def test_individuals_chart_equals_the_nist_handbook_example():
    c = spc.imr_chart(NIST_FLOW)
    assert [round(v, 1) for v in c.moving_ranges] == NIST_MR
    assert round(c.center, 2) == 50.81
    assert round(c.mr_bar, 4) == 1.8778
    assert round(c.ucl, 4) == 55.8041
    assert round(c.lcl, 4) == 45.8159
    assert round(c.mr_ucl, 4) == 6.1347
    assert c.mr_lcl == 0.0
    # the handbook's chart shows the process in control: no point beyond the limits
    assert [s for s in c.signals if s.rule == 1] == [] and c.mr_signals == []


def test_capability_equals_the_nist_handbook_example():
    """e-Handbook section 6.1.6 "What is Process Capability?" (pmc16.htm): USL 20, LSL 8,
    mean 16, sigma 2 gives Cp 1, Cpk 0.6667 (Cpu 0.6667, Cpl 1.3333)."""
    cp, cpk = spc.indices(16.0, 2.0, 8.0, 20.0)
    assert cp == 1.0
    assert round(cpk, 4) == 0.6667
    assert round((16.0 - 8.0) / (3 * 2.0), 4) == 1.3333  # Cpl, the far side


def test_capability_of_values_uses_short_term_and_overall_sigma():
    c = spc.capability(NIST_FLOW, 45.0, 57.0)
    assert c.sigma_within == pytest.approx(1.8778 / spc.D2, abs=1e-4)
    assert c.cp == pytest.approx(12.0 / (6 * c.sigma_within))
    assert c.cpk == pytest.approx((50.81 - 45.0) / (3 * c.sigma_within))  # nearer LSL
    # the flow rate drifts upward, so the overall sigma exceeds the short-term one: Pp < Cp
    assert c.sigma_overall > c.sigma_within and c.pp < c.cp and c.ppk < c.cpk
    with pytest.raises(ValueError, match="not above"):
        spc.capability(NIST_FLOW, 5.0, 5.0)


# One sequence per rule, in zones of sigma 1 about 0; each breaks its rule at the last point.
CASES = [
    ("western-electric", 1, [0.1, -0.2, 3.5]),
    ("western-electric", 2, [0.1, 2.5, 0.3, 2.4]),
    ("western-electric", 3, [0.2, 1.5, 1.2, 0.5, 1.1, 1.3]),
    ("western-electric", 4, [-0.5, *[0.4] * 8]),
    ("nelson", 2, [-0.5, *[0.3] * 9]),
    ("nelson", 3, [0.0, -0.5, -0.4, -0.3, -0.2, -0.1, 0.1]),
    ("nelson", 4, [0.5 * (-1) ** i for i in range(14)]),
    ("nelson", 7, [0.3 * (-1) ** i * (1 + (i % 3) / 10) for i in range(15)]),
    ("nelson", 8, [1.5 * (-1) ** (i // 2) for i in range(8)]),
]


@pytest.mark.parametrize(("rules", "rule", "values"), CASES)
def test_each_run_rule_fires_where_its_pattern_completes(rules, rule, values):
    signals = spc.run_rules(values, 0.0, 1.0, rules)
    fired = {s.rule for s in signals if s.index == len(values) - 1}
    assert rule in fired, signals
    # and not one point earlier: the pattern was not yet complete
    assert rule not in {s.rule for s in spc.run_rules(values[:-1], 0.0, 1.0, rules)}


def test_a_quiet_process_breaks_no_rule_and_the_histogram_counts_every_value():
    import numpy as np

    x = np.random.default_rng(3).normal(0.0, 1.0, 40)
    c = spc.imr_chart(x, "western-electric")
    assert all(s.rule != 1 for s in c.signals)
    h = spc.histogram(x, span=(-2.0, 2.0))
    assert sum(h.counts) == 40 and len(h.edges) == len(h.counts) + 1
    assert h.edges[0] <= x.min() and h.edges[-1] >= x.max()
    with pytest.raises(ValueError, match="unknown run rules"):
        spc.run_rules(x, 0.0, 1.0, "shewhart")
