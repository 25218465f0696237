"""The Type-1 gauge study (msa.type1, `aimbench grr --type1`) and VDA 5's acceptance rule."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy import stats

from scenarios.inspection import msa
from scenarios.inspection.verdict import Verdict, judge, q_mp


def test_type1_figures_by_hand():
    """25 readings of a reference part of 10.000 in a tolerance 9.9..10.1 (T = 0.2): the
    readings 10.000 +- 0.004 alternating, one at 10.006, so every figure is exact by hand:
    mean = 10.000 + 0.006/25 = 10.00024; Cg = 0.2 x 0.2 / (6 s); Cgk = (0.1 x 0.2 - |bias|)
    / (3 s); t = bias / (s / 5)."""
    x = np.array([10.004, 9.996] * 12 + [10.006])
    r = msa.type1(x, 10.0, 0.2, "x_mm", "mm")
    s = x.std(ddof=1)
    assert r.n == 25 and r.mean == pytest.approx(10.00024, abs=1e-12)
    assert r.bias == pytest.approx(0.00024, abs=1e-12)
    assert r.cg == pytest.approx(0.04 / (6 * s))
    assert r.cgk == pytest.approx((0.02 - 0.00024) / (3 * s))
    assert r.t == pytest.approx(0.00024 / (s / 5))
    assert r.p == pytest.approx(2 * stats.t.sf(r.t, 24))
    assert r.capable == (r.cg >= 1.33 and r.cgk >= 1.33)
    assert not r.bias_significant
    # a gauge that reads 0.006 high everywhere: capable spread, significant bias, lower Cgk
    b = msa.type1(x + 0.006, 10.0, 0.2, "x_mm", "mm")
    assert b.cg == pytest.approx(r.cg) and b.cgk < r.cgk and b.bias_significant
    with pytest.raises(ValueError, match="tolerance"):
        msa.type1(x, 10.0, 0.0, "x_mm", "mm")


#: A published Type-1 study with its data: the example JASP (the jaspQualityControl module,
#: https://github.com/jasp-stats/jaspQualityControl) ships as Type1InstrumentCapability.jasp,
#: its data in tests/testthat/Type1.csv ("Type 1 Study, Schweinfurt, Gauge: S-441-0,
#: 13-Nov-10, Reference = -4.0 um, Resolution = 0.1 um, Tolerance for dm is 15 um"; the help
#: page of that analysis cites Dodson et al., SKF's Statistical Process Control handbook, 2009),
#: 50 readings in um.
JASP_TYPE1 = [-4.0, -4.1, -4.1, -4.1, -4.1, -3.9, -3.9, -3.9, -4.1, -4.2,
              -3.9, -4.2, -4.0, -3.8, -3.9, -3.9, -3.9, -3.9, -4.6, -4.3,
              -3.9, -3.7, -3.7, -3.9, -4.0, -5.0, -3.9, -3.8, -3.7, -3.8,
              -3.7, -3.8, -3.6, -3.5, -3.6, -3.6, -3.4, -5.1, -3.5, -4.0,
              -4.5, -3.5, -5.1, -5.0, -3.5, -3.5, -3.5, -3.6, -3.6, -3.5]


def test_type1_equals_a_published_study():
    """JASP's printed figures for JASP_TYPE1 (tests/testthat/test-msaType1Gauge.R and
    test-example-Type1InstrumentCapability.R of jaspQualityControl), with its defaults K = 20 %
    of the tolerance and L = 6 standard deviations (Minitab's too, "Methods and formulas for
    Type 1 Gage Study", https://support.minitab.com/en-us/minitab/help-and-how-to/
    quality-and-process-improvement/measurement-system-analysis/how-to/gage-study/
    type-1-gage-study/methods-and-formulas/methods-and-formulas/): mean -3.946, s
    0.420014577006512, bias 0.054, t 0.909105737620188 on 49 degrees of freedom, p
    0.367744349288335, Cg 1.19, Cgk 1.15, %Var(repeatability) 16.8 and %Var(repeatability and
    bias) 17.43 (Minitab's K / Cg and K / Cgk, which pin Cg and Cgk to four digits)."""
    r = msa.type1(np.array(JASP_TYPE1), -4.0, 15.0, "dm", "um", pct=20.0, sigmas=6.0)
    assert r.n == 50
    assert round(r.mean, 3) == -3.946
    assert r.sd == pytest.approx(0.420014577006512, rel=1e-12)
    assert r.bias == pytest.approx(0.054, abs=1e-12)
    assert r.t == pytest.approx(0.909105737620188, rel=1e-12)
    assert r.p == pytest.approx(0.367744349288335, rel=1e-12)
    assert round(r.cg, 2) == 1.19 and round(r.cgk, 2) == 1.15
    assert round(100 * 0.20 / r.cg, 1) == 16.8 and round(100 * 0.20 / r.cgk, 2) == 17.43
    assert not r.capable and not r.bias_significant
    # the default is that convention; a company rule of L = 4 counts the spread as +-2 s, so
    # its Cg and Cgk are 6/4 of the figures above
    d = msa.type1(np.array(JASP_TYPE1), -4.0, 15.0, "dm", "um")
    assert d.sigmas == 6.0 and d.cg == r.cg and d.cgk == r.cgk
    f = msa.type1(np.array(JASP_TYPE1), -4.0, 15.0, "dm", "um", sigmas=4.0)
    assert f.cg == pytest.approx(1.5 * r.cg) and f.cgk == pytest.approx(1.5 * r.cgk)


@pytest.mark.parametrize(("error", "u", "iso", "vda"), [
    (0.5, 0.1, Verdict.PASS, Verdict.PASS),          # 0.5 + 0.2 <= 1: proven inside
    (0.9, 0.1, Verdict.INCONCLUSIVE, Verdict.FAIL),  # inside, but not by U: VDA 5 rejects
    (1.1, 0.1, Verdict.INCONCLUSIVE, Verdict.FAIL),
    (1.3, 0.1, Verdict.FAIL, Verdict.FAIL),          # proven outside
    (0.1, math.inf, Verdict.INCONCLUSIVE, Verdict.FAIL),
])
def test_vda5_accepts_only_inside_the_narrowed_tolerance(error, u, iso, vda):
    assert judge(error, u, 1.0, "iso14253-1", 2.0) == iso
    assert judge(error, u, 1.0, "vda5", 2.0) == vda
    assert q_mp(0.075, 1.0, 2.0) == pytest.approx(0.15)  # 2 U / T = 2 x 0.15 / 2


@pytest.mark.slow
def test_grr_type1_on_the_twin_and_from_its_records(tmp_path, capsys):
    """25 repeats of a twin reference part (1 scan each, an ideal sensor: about 20 s), then
    the same study read back from the records by its batch; a wrong batch lists the batches."""
    from scenarios.cli import main

    ref = tmp_path / "ref.toml"
    ref.write_text('unit = "REF-1"\n[reference]\ntilt_deg = 0.3\nyaw_deg = -0.2\n'
                   'x_mm = 2.0\n', encoding="utf-8")
    db = str(tmp_path / "t1.sqlite")
    code = main(["grr", "--type1", "--reference", str(ref), "--twin", "--db", db,
                 "--scans", "1", "--no-sensor-errors", "--json"])
    twin = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert code in (0, 1)
    axes = {a["axis"]: a for a in twin["axes"]}
    assert set(axes) == {"roll_deg", "tilt_deg", "yaw_deg", "x_mm"}
    assert all(a["n"] == 25 for a in axes.values())
    assert axes["tilt_deg"]["reference"] == 0.3 and axes["roll_deg"]["reference"] == 0.0
    # an ideal sensor: the twin's estimate is unbiased, so the mean is near the reference
    for a in axes.values():
        assert abs(a["bias"]) < 4 * a["sd"] / math.sqrt(a["n"]) + 1e-9, a

    assert main(["grr", "--type1", "--reference", str(ref), "--db", db, "--batch",
                 twin["batch"], "--json"]) == code
    again = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert again["axes"] == twin["axes"]

    assert main(["grr", "--type1", "--reference", str(ref), "--db", db, "--batch",
                 "nope"]) == 2
    err = capsys.readouterr().err
    assert "no records of batch 'nope'" in err and twin["batch"] in err and "25 records" in err
