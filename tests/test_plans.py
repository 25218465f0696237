"""Plans: the paper's defaults, Monte Carlo seeding, repeatability approaches, TOML sweeps."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from scenarios import plans
from scenarios.plans import Plan, PlanError, Reference


def test_yaw_sweep_is_the_papers_first_test():
    p = plans.yaw_sweep()
    assert p.kind == "yaw" and p.scans == 100 and len(p) == 21
    yaws = [r.yaw_deg for r in p.references]
    assert yaws == pytest.approx(np.arange(-10, 11, 1.0), abs=1e-12)
    assert p.references[10].yaw_rad == 0.0  # exactly zero: the relative report's baseline
    assert all(r.x_m == 0.0 and r.mount is None for r in p.references)
    assert p.total_scans == 2100


def test_x_sweep_is_the_papers_second_test():
    p = plans.x_sweep()
    assert [round(r.x_mm, 9) for r in p.references] == list(range(-30, 31, 5))
    assert all(r.yaw_rad == 0.0 for r in p.references)
    assert p.scans == 100


def test_grid_visits_every_pair_once_in_a_serpentine():
    p = plans.grid(yaw_deg=[-1, 0, 1], x_mm=[-5, 5], scans=3)
    pairs = [(round(r.yaw_deg, 9), round(r.x_mm, 9)) for r in p.references]
    assert sorted(pairs) == sorted((y, x) for y in (-1, 0, 1) for x in (-5, 5))
    # The second row runs backwards, so the rotation stage never swings the whole range back.
    assert pairs[2][0] == pairs[3][0]
    assert len(plans.grid()) == 21 * 13


def test_monte_carlo_is_seeded_and_within_bounds():
    a = plans.monte_carlo(poses=50, seed=7)
    b = plans.monte_carlo(poses=50, seed=7)
    c = plans.monte_carlo(poses=50, seed=8)
    assert a.to_dict() == b.to_dict()
    assert a.to_dict() != c.to_dict()
    assert a.scans == 50
    mounts = np.array([[r.mount[k] for k in plans.MOUNT_KEYS] for r in a.references])
    assert np.all(np.abs(mounts[:, :3]) <= 3.0) and np.all(np.abs(mounts[:, 3]) <= 30.0)
    # Uniform draws fill the box, not a corner of it.
    assert mounts[:, :3].std() > 1.2 and mounts[:, 3].std() > 12
    assert all(r.yaw_rad == 0 and r.x_m == 0 for r in a.references)
    assert len(plans.monte_carlo()) == 200


def test_repeatability_approaches_from_alternate_sides():
    p = plans.repeatability(yaw_deg=2.0, x_mm=10.0, repeats=4, scans=5)
    assert len(p) == 4
    assert {(round(r.yaw_deg, 9), round(r.x_mm, 9)) for r in p.references} == {(2.0, 10.0)}
    sides = [np.sign(r.via.yaw_rad - r.yaw_rad) for r in p.references]
    assert sides == [1, -1, 1, -1]


def test_plan_round_trips_through_its_dict():
    p = plans.repeatability(repeats=3, scans=2)
    q = Plan.from_dict(p.to_dict())
    assert q == p
    mc = plans.monte_carlo(poses=3)
    assert Plan.from_dict(mc.to_dict()) == mc


def test_with_scans_and_build():
    assert plans.build("yaw", scans=7).scans == 7
    assert plans.build("montecarlo", poses=4, seed=1).to_dict() == \
        plans.monte_carlo(poses=4, seed=1).to_dict()
    with pytest.raises(PlanError, match="unknown scenario"):
        plans.build("spiral")


def test_empty_or_bad_plans_are_refused():
    with pytest.raises(PlanError):
        Plan("empty", "yaw", (), 10)
    with pytest.raises(PlanError):
        Plan("zero", "yaw", (Reference(),), 0)
    with pytest.raises(PlanError):
        plans.steps(0, 1, 0)
    with pytest.raises(PlanError):
        plans.steps(1, 0, 0.5)


def test_steps_include_the_end_without_float_drift():
    assert list(plans.steps(-3, 3, 0.5)) == [x / 2 for x in range(-6, 7)]
    assert len(plans.steps(0, 0.3, 0.1)) == 4


def test_toml_axes(tmp_path: Path):
    f = tmp_path / "fine.toml"
    f.write_text('name = "fine yaw"\nscans = 12\nmethod = "paper"\nseed = 3\n'
                 "yaw_deg = { start = -1, stop = 1, step = 0.5 }\nx_mm = [0, 10]\n")
    p = plans.from_toml(f)
    assert p.name == "fine yaw" and p.scans == 12 and p.kind == "grid" and len(p) == 10
    assert p.settings["method"] == "paper" and p.settings["seed"] == 3
    assert {round(r.x_mm, 9) for r in p.references} == {0.0, 10.0}


def test_toml_references_with_mount(tmp_path: Path):
    f = tmp_path / "refs.toml"
    f.write_text("scans = 5\n[mount]\nroll_deg = 1.5\n"
                 "[[reference]]\nyaw_deg = 2\nx_mm = -5\nlabel = 'left'\n"
                 "[[reference]]\nyaw_deg = -2\n[reference.mount]\ntilt_deg = -1\n")
    p = plans.from_toml(f)
    assert len(p) == 2 and p.kind == "toml"
    assert p.references[0].label == "left"
    assert p.references[0].yaw_rad == pytest.approx(math.radians(2))
    assert p.references[0].mount["roll_deg"] == 1.5
    assert p.references[1].mount == {"roll_deg": 0.0, "tilt_deg": -1.0, "yaw_deg": 0.0,
                                     "x_mm": 0.0}


@pytest.mark.parametrize("text, match", [
    ("scans = 0\n", "scans must be a whole number 1.."),
    ("yaw_deg = 'ten'\n", "yaw_deg"),
    ("bogus = 1\n", "unknown keys"),
    ("yaw_deg = { start = 1, stop = 0, step = 1 }\n", "below start"),
    ("yaw_deg = 1\n[[reference]]\nyaw_deg = 2\n", "not both"),
    ("[mount]\nspin_deg = 1\n", "unknown keys"),
    ("yaw_deg = [", "not valid TOML"),
])
def test_toml_errors_are_clear(tmp_path: Path, text: str, match: str):
    f = tmp_path / "bad.toml"
    f.write_text(text)
    with pytest.raises(PlanError, match=match):
        plans.from_toml(f)


def test_missing_toml_file(tmp_path: Path):
    with pytest.raises(PlanError, match="no such plan file"):
        plans.build(str(tmp_path / "nope.toml"))


def test_references_beyond_travel():
    p = plans.yaw_sweep(start_deg=-20, stop_deg=20, step_deg=10, scans=1)
    beyond = [i for i, _ in plans.references_beyond(
        p, (math.radians(-15), math.radians(15)), (-0.05, 0.05))]
    assert beyond == [0, 4]
    rep = plans.repeatability(yaw_deg=14, repeats=2, approach_deg=2, scans=1)
    assert [i for i, _ in plans.references_beyond(
        rep, (math.radians(-15), math.radians(15)), (-0.05, 0.05))] == [0]
