"""SPC (scenarios/inspection/spc.py) against published worked examples, to their printed
precision, and the run rules, as published, on sequences built to break exactly one rule each."""

from __future__ import annotations

import pytest

from scenarios.inspection import spc

#: NIST/SEMATECH e-Handbook of Statistical Methods, section 6.3.2.2 "Individuals Control
#: Charts", https://www.itl.nist.gov/div898/handbook/pmc/section3/pmc322.htm: the flow rate of
#: the first 10 batches of a new process, their moving ranges, and as printed there x-bar
#: 50.81, MR-bar 1.8778, UCL 55.8041, LCL 45.8159. Provenance: the page itself was not in the
#: stored copies of the web this was checked with; the ten values and those four figures are
#: as an independent public transcription of the page gives them (a statistics course's
#: register of published check examples, "S-B3 NIST 6.3.2.2: 10 batches -> x-bar 50.81, MR-bar
#: 1.8778, UCL 55.8041, LCL 45.8159"). The MR chart's UCL 6.1347 is D4 = 3.267 times that
#: MR-bar (the handbook's D4 for n = 2), not a figure read off the page.
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
    """e-Handbook section 6.1.6 "What is Process Capability?",
    https://www.itl.nist.gov/div898/handbook/pmc/section1/pmc16.htm: USL 20, LSL 8, mean 16,
    sigma 2 give Cp 1.0, Cpk 0.6667 (Cpu 0.6667, Cpl 1.3333). Provenance as NIST_FLOW's: the
    figures as the same independent transcription gives them ("NIST 6.1.6: USL 20, LSL 8,
    x-bar 16, s 2 -> Cp 1.0, Cpk 0.6667, Cpu 0.6667, Cpl 1.3333"); of the page itself only
    its opening was read, in a copy that names it as its source
    (http://credit-help.biz/forex/33563): the specification's width over "6 process standard
    deviation units", which is Cp here."""
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


# The rules as published. Western Electric (Statistical Quality Control Handbook, 1956), as
# stated by StatSoft's STATISTICA glossary, "Western Electric Run Rules"
# (http://documentation.statsoft.com/STATISTICAHelp.aspx?path=Glossary/GlossaryTwo/W/
# Western_Electric_Run_Rules): besides one point beyond the control limits, "2 of 3
# consecutive points fall outside warning (2-sigma) limits", "4 of 5 consecutive points fall
# beyond 1-sigma limits", "8 consecutive points fall on one side of the centerline"; and by QI
# Macros (https://www.qimacros.com/control-chart/western-electric-rules/): the two of three
# "MUST be above OR below the centerline" (one side), "Odd point can be anywhere".
# Nelson (J. Quality Technology 16(4), 1984), as stated by Micromine's manual, "Shewhart
# Control Chart: Rules" (https://webhelp.micromine.com/mm/23.5/English/Content/mmstats/
# IDH_SHEWHART_RULES.htm) and Sepasoft's "Signals" (https://help.sepasoft.com/docs/display/
# SEPA/Signals): 1 a point more than 3 standard deviations from the mean; 2 nine (or more)
# points in a row on the same side of the mean; 3 six (or more) points in a row continually
# increasing (or decreasing); 4 fourteen (or more) points in a row alternating in direction;
# 5 two (or three) out of three points in a row more than 2 standard deviations from the mean
# in the same direction; 6 four (or five) out of five more than 1 standard deviation in the
# same direction; 7 fifteen points in a row all within 1 standard deviation; 8 eight points
# in a row with none within 1 standard deviation "and the points are in both directions from
# the mean".
# One sequence per rule, in zones of sigma 1 about 0; each breaks its rule at the last point.
CASES = [
    ("western-electric", 1, [0.1, -0.2, 3.5]),
    ("western-electric", 2, [0.1, 2.5, 0.3, 2.4]),
    ("western-electric", 3, [0.2, 1.5, 1.2, 0.5, 1.1, 1.3]),
    ("western-electric", 4, [-0.5, *[0.4] * 8]),
    ("nelson", 1, [0.1, -0.2, -3.5]),
    ("nelson", 2, [-0.5, *[0.3] * 9]),
    ("nelson", 3, [0.0, -0.5, -0.4, -0.3, -0.2, -0.1, 0.1]),
    ("nelson", 4, [0.5 * (-1) ** i for i in range(14)]),
    ("nelson", 7, [0.3 * (-1) ** i * (1 + (i % 3) / 10) for i in range(15)]),
    ("nelson", 5, [0.1, -2.5, 0.3, -2.4]),         # the odd point on the other side
    ("nelson", 6, [0.2, -1.5, -1.2, 0.5, -1.1, -1.3]),
    ("nelson", 8, [1.5 * (-1) ** (i // 2) for i in range(8)]),
]


@pytest.mark.parametrize(("rules", "rule", "values"), CASES)
def test_each_run_rule_fires_where_its_pattern_completes(rules, rule, values):
    signals = spc.run_rules(values, 0.0, 1.0, rules)
    fired = {s.rule for s in signals if s.index == len(values) - 1}
    assert rule in fired, signals
    # and not one point earlier: the pattern was not yet complete
    assert rule not in {s.rule for s in spc.run_rules(values[:-1], 0.0, 1.0, rules)}


def test_the_rules_need_what_their_statements_say_and_no_more():
    """Each rule's boundary as stated (see CASES): the patterns one point short, on the wrong
    side or one step off do not fire it."""
    def fired(values, rules="nelson"):
        return {s.rule for s in spc.run_rules(values, 0.0, 1.0, rules)
                if s.index == len(values) - 1}

    # eight beyond 1 sigma on one side is no mixture: not Nelson's 8 (his 6 fires instead)
    one_side = [0.2, *[1.5] * 8]
    assert 8 not in fired(one_side) and 6 in fired(one_side)
    # two of three beyond 2 sigma but on opposite sides: neither WE 2 nor Nelson 5
    assert 2 not in fired([0.1, 2.5, -2.4], "western-electric")
    assert 5 not in fired([0.1, 2.5, -2.4])
    # three of five beyond 1 sigma: not four of five
    assert 3 not in fired([0.2, 1.5, 0.5, 0.4, 1.1, 1.3], "western-electric")
    # a run of eight is Western Electric's 4 but not yet Nelson's 2 (nine)
    assert 4 in fired([-0.5, *[0.4] * 8], "western-electric")
    assert 2 not in fired([-0.5, *[0.4] * 8])
    # five rising is not six; a tie breaks a trend and an alternation
    assert 3 not in fired([0.0, -0.5, -0.4, -0.3, -0.2, -0.1])
    assert 3 not in fired([-0.5, -0.4, -0.3, -0.3, -0.2, -0.1])
    alt = [0.5 * (-1) ** i for i in range(14)]
    assert 4 not in fired(alt[:13]) and 4 not in fired([*alt[:12], alt[11], alt[13]])
    # a point at exactly 3 sigma is not beyond it
    assert 1 not in fired([0.0, 3.0]) and 1 in fired([0.0, 3.0001])


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
