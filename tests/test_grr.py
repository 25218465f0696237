"""The station's measurement-system studies: the gauge R&R's ANOVA against statsmodels, its
figures and intervals on studies of known components, on the twin (the figures move the right
way with the noise and the tolerance), bias across units and linearity."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from scenarios import station as stations
from scenarios.commands.grr import grr_report
from scenarios.inspection import msa, studies
from scenarios.inspection.records import Records

REPO = Path(__file__).resolve().parents[1]


def study(rng: np.random.Generator, p: int, o: int, r: int, sd: dict[str, float]) -> np.ndarray:
    return (rng.normal(0, sd["PV"], (p, 1, 1)) + rng.normal(0, sd["A"], (1, o, 1))
            + rng.normal(0, sd["PA"], (p, o, 1)) + rng.normal(0, sd["EV"], (p, o, r)))


def test_balanced_sums_of_squares_are_statsmodels_anova():
    y = study(np.random.default_rng(3), 7, 3, 3, {"PV": 1.0, "A": 0.3, "PA": 0.2, "EV": 0.1})
    ss, dfs = msa.balanced_ss(y)
    ss_sm, dfs_sm = msa.anova_table(y)
    assert np.allclose(ss, ss_sm, rtol=1e-9) and np.array_equal(dfs, dfs_sm)


def test_figures_of_a_known_study_and_their_intervals_cover():
    """Studies drawn with known components (10 x 3 x 2, AIAG's usual design): the 95 %
    intervals of sigma_GRR and sigma_EV cover the truth about 95 % of the time (binomial
    bounds at 0.1 %); %GRR against the tolerance scales as 1 / tolerance exactly."""
    sd = {"PV": 0.5, "A": 0.05, "PA": 0.03, "EV": 0.06}
    true_grr = np.sqrt(sd["A"] ** 2 + sd["PA"] ** 2 + sd["EV"] ** 2)
    rng = np.random.default_rng(5)
    n, hits_grr, hits_ev = 120, 0, 0
    for i in range(n):
        g = msa.gauge_rr(study(rng, 10, 3, 2, sd), "tilt_deg", "deg", 2.0, n_boot=500, seed=i)
        lo, hi = g.ci["sigma_GRR"]
        hits_grr += lo <= true_grr <= hi
        lo, hi = g.ci["sigma_EV"]
        hits_ev += lo <= sd["EV"] <= hi
    lo_n, hi_n = stats.binom.ppf([0.0005, 0.9995], n, 0.95)
    assert lo_n <= hits_grr <= hi_n, hits_grr
    assert lo_n <= hits_ev <= hi_n, hits_ev
    y = study(rng, 10, 3, 2, sd)
    a = msa.gauge_rr(y, "tilt_deg", "deg", 2.0)
    b = msa.gauge_rr(y, "tilt_deg", "deg", 4.0)
    assert np.isclose(b.pct_tolerance["GRR"], a.pct_tolerance["GRR"] / 2)
    assert a.ndc == int(np.floor(1.41 * a.sigma["PV"] / a.sigma["GRR"]))
    assert msa.acceptance(9.9) == "acceptable" and msa.acceptance(25) == "marginal"
    assert msa.acceptance(31) == "not acceptable"


def test_an_unbalanced_record_set_is_refused_naming_what_is_missing():
    rows = [{"unit": u, "operator": o, "status": "ok", "err_tilt": 0.01}
            for u, o in (("a", "ann"), ("a", "ann"), ("a", "bob"), ("a", "bob"), ("b", "ann"),
                         ("b", "ann"))]
    with pytest.raises(studies.StudyError, match="b by bob"):
        studies.grr_data(rows, "tilt")


def test_bias_and_linearity_recover_a_known_gauge():
    rng = np.random.default_rng(2)
    ref = np.repeat([-1.5, -0.75, 0.0, 0.75, 1.5], 6)
    meas = 0.05 + 1.02 * ref + rng.normal(0, 0.01, len(ref))
    lin = msa.linearity(ref, meas, "yaw_deg", "deg")
    assert lin.slope_ci[0] < 0.02 < lin.slope_ci[1] and lin.slope_p < 1e-6
    assert lin.intercept_ci[0] < 0.05 < lin.intercept_ci[1]
    b = msa.bias_across_units(rng.normal(0.1, 0.3, 400), np.full(400, 0.1), "tilt_deg", "deg")
    assert b.mean_ci[0] < 0.1 < b.mean_ci[1]
    assert abs(b.system_sigma - np.sqrt(0.3 ** 2 + 0.1 ** 2 - 0.1 ** 2)) < 0.05
    assert 8 < b.chi2 < 12


@pytest.mark.slow
def test_twin_grr_moves_the_right_way_with_noise_and_tolerance(tmp_path: Path):
    """A small twin study (4 parts x 2 re-mountings x 2 trials of 4 scans), with the twin's
    14 mm range noise and with 28 mm: the repeatability grows with the noise (yaw and x scale
    with it; tilt's has a part that does not: 0.163 deg at 14 mm, 0.187 at 28, by the two
    levels about 0.15 deg that does not scale. It passed 1.4 x at 28 mm only while the search's
    4 cm band leaned a noisy unit's plane: 0.234 deg, 0.456 with seed 2); %GRR against a
    tolerance twice as wide is half."""
    st = stations.default()
    wide = st.model_copy(update={"tolerances": st.tolerances.model_copy(update={
        "roll_deg": 2.0, "tilt_deg": 2.0, "yaw_deg": 2.0, "x_mm": 20.0})})
    figures = {}
    with Records.open(tmp_path / "grr.sqlite", create=True) as rec:
        for noise in (14.0, 28.0):
            batch = studies.run_grr_twin(st, rec, parts=4, appraisers=2, trials=2, seed=1,
                                         scans=4, range_noise_mm=noise)
            rows = rec.rows("WHERE batch = ?", (batch,))
            assert sum(r["status"] == "ok" for r in rows) == 16
            figures[noise] = {g.axis: g for g in grr_report(rows, st, 0.95)}
        wide_fig = {g.axis: g for g in grr_report(rows, wide, 0.95)}
    for axis in ("x_mm", "yaw_deg"):
        assert figures[28.0][axis].sigma["EV"] > 1.4 * figures[14.0][axis].sigma["EV"], axis
    for axis in ("roll_deg", "tilt_deg"):
        assert figures[28.0][axis].sigma["EV"] > figures[14.0][axis].sigma["EV"], axis
    for axis, g in figures[28.0].items():
        assert np.isclose(wide_fig[axis].pct_tolerance["GRR"], g.pct_tolerance["GRR"] / 2)
        assert set(g.ci) >= {"sigma_GRR", "pct_tolerance_GRR", "ndc"}


@pytest.mark.slow
def test_grr_command_on_the_twin_and_from_records(tmp_path: Path):
    env = {**os.environ, "PYTHONPATH": str(REPO)}

    def cli(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "scenarios.cli", *args], cwd=tmp_path,
                              env=env, capture_output=True, text=True, timeout=600)
    r = cli("grr", "--twin", "--parts", "3", "--appraisers", "2", "--trials", "2", "--scans",
            "3", "--db", "g.sqlite", "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert [a["axis"] for a in out["axes"]] == ["x_mm", "roll_deg", "tilt_deg", "yaw_deg"]
    assert all(a["acceptance"] in ("acceptable", "marginal", "not acceptable")
               for a in out["axes"])
    again = cli("grr", "--db", "g.sqlite", "--batch", out["batch"])  # the same records, read
    assert again.returncode == 0 and "%GRR tol" in again.stdout
    with Records.open(tmp_path / "g.sqlite") as rec:
        assert rec.count() == 12  # resumed, not repeated
        assert {r["operator"] for r in rec.rows()} == {"mount-1", "mount-2"}
    r = cli("grr", "--linearity", "--bench", "sim", "--yaw-refs-deg=-1,0,1",
            "--x-refs-mm=-10,0,10", "--repeats", "2", "--scans", "3", "--json")
    assert r.returncode == 0, r.stderr
    assert "linearity: 12/12 measurements" in r.stderr  # its progress, beside the JSON
    lin = {a["axis"]: a for a in json.loads(r.stdout)["axes"]}
    # The twin's stages are exact: the gauge follows them (slope near 0, the bias near 0).
    assert abs(lin["yaw_deg"]["slope"]) < 0.1 and abs(lin["x_mm"]["slope"]) < 0.2
    r = cli("grr", "--db", "none.sqlite")
    assert r.returncode == 2 and "no inspection records" in r.stderr
