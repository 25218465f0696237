"""The board's choice among the search's candidates (`align.choice`, issue 34): the decision on
its own (a table of fits), then on the twin with a second object beside the board."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

import align
import align.params
from align.choice import DECISIVE_LR, Candidate, decide, goodness, region_log_prior
from scenarios.station import Station
from twin.core.pose import Pose
from twin.sim.bench import BenchSim
from twin.sim.emulation import EmulationConfig
from twin.sim.params import BenchParams, SceneBox

NOISE = EmulationConfig(laser_offset_sigma=0.0)


def _fit(chi2_dof: float, dof: int, x: float = 0.0) -> align.PoseEstimate:
    """A passed fit as the pipeline reports it: the LiDAR 2.5 m in front of a board at x."""
    return align.PoseEstimate(align.Status.OK, "rays", Pose(x, -2.5, 0.0), np.eye(6) * 1e-8,
                              {"chi2_per_dof": chi2_dof, "dof": dof})


def _candidates(*fits: align.PoseEstimate) -> list[Candidate]:
    return [Candidate(k, np.arange(3), math.nan, f) for k, f in enumerate(fits)]


@pytest.mark.parametrize(
    ("fits", "chosen", "decisive"),
    [
        # the real scan the issue names: the search's first choice (a background surface) at
        # chi2/dof 1.30, the board 1.08, both passing their own checks: the board, decisively
        (((1.30, 700), (1.08, 700)), 1, True),
        # two fits the noise explains: no data can tell them apart
        (((1.01, 700), (0.98, 700)), 1, False),
        (((0.80, 700), (1.00, 700)), 0, False),  # better than the noise is no evidence
        # a failed candidate does not compete
        (((1.02, 700), None), 0, True),
    ],
)
def test_the_decision_is_the_likelihood_ratio(fits, chosen, decisive):
    ests = [align.PoseEstimate.failed(align.Status.PARTIAL_BOARD, "rays") if f is None
            else _fit(*f) for f in fits]
    d = decide(_candidates(*ests), align.Hints())
    assert d.chosen is not None and d.chosen.index == chosen
    assert d.decisive == decisive
    if d.runner_up is not None:
        lr = goodness(d.chosen.estimate) - goodness(d.runner_up.estimate)
        assert d.log10_lr == pytest.approx(lr / math.log(10))
        assert (10 ** d.log10_lr >= DECISIVE_LR) == decisive


def test_the_region_refuses_and_weighs():
    """A candidate beyond the station's radius never wins; inside, the prior weighs."""
    near, far = _fit(1.0, 700, x=0.0), _fit(1.0, 700, x=-1.2)
    # the LiDAR at (x, -2.5, 0) in {O} sees the board's centre at (-x, 2.5, 0) in {L}
    region = align.Hints(board_region=((0.0, 2.5, 0.0), 0.3))
    assert region_log_prior(Candidate(0, np.arange(3), 0.0, far).centre(), region) == -math.inf
    d = decide(_candidates(far, near), region)
    assert d.chosen is not None and d.chosen.index == 1 and d.decisive
    assert [c.index for c in d.outside_region] == [0]
    d = decide(_candidates(far), region)
    assert d.chosen is None and len(d.outside_region) == 1


def _twin_scans(clutter: tuple[SceneBox, ...], n: int = 3, seed: int = 1) -> list:
    sim = BenchSim(replace(BenchParams(), clutter=clutter), seed=seed, noise=NOISE)
    return [sim.scan() for _ in range(n)]


def _board_centre_in_lidar(scan) -> tuple[float, float, float]:
    pose = scan.meta["truth_pose"]
    c = -pose.rotation().T @ np.array([pose.x, pose.y, pose.z])
    return float(c[0]), float(c[1]), float(c[2])


#: A second panel of the board's own size and brightness 1.3 m to its right, the same distance
#: from the LiDAR: what no data can tell from the board.
TWIN_PANEL = SceneBox((1.3, 0.0, 0.5), (0.45, 0.01, 0.27), reflectivity=0.8)


@pytest.fixture(scope="module")
def panel_scans():
    return _twin_scans((TWIN_PANEL,))


def test_a_second_identical_panel_is_ambiguous_never_ok(panel_scans):
    for scan in panel_scans:
        est = align.estimate(scan)
        assert est.status == align.Status.AMBIGUOUS_BOARD, est.diagnostics
        assert est.pose is None
        reason = est.diagnostics["reason"]
        assert reason.count("candidate") == 2 and "position_tolerance_mm" in reason
    fused = align.estimate(panel_scans)
    assert fused.status == align.Status.AMBIGUOUS_BOARD


def test_the_stations_region_picks_the_board(panel_scans):
    truth = panel_scans[0].meta["truth_pose"].as_array()
    hints = align.Hints(board_region=(_board_centre_in_lidar(panel_scans[0]), 0.3))
    for scans in ([panel_scans[0]], panel_scans):
        est = align.estimate(scans, hints=hints)
        assert est.success, est.diagnostics
        assert np.all(np.abs(est.pose.as_array()[:3] - truth[:3]) < 4 * est.std[:3] + 1e-3)
        # the two panels, and the wall between them, seen past the board's edge, weighed too
        # (`align.search.board.BEHIND_CHOICE`): the region still picks the board
        assert est.diagnostics["board_candidates"] >= 2


def test_a_board_outside_the_region_is_refused(panel_scans):
    """The region 1 m below the board: neither panel is in it."""
    x, y, z = _board_centre_in_lidar(panel_scans[0])
    est = align.estimate(panel_scans[0], hints=align.Hints(board_region=((x, y, z - 1.0), 0.3)))
    assert est.status == align.Status.BOARD_OUTSIDE_REGION
    assert "300 mm of where the station puts it" in est.diagnostics["reason"]


def test_a_smaller_screen_beside_the_board_does_not_compete():
    """A monitor of half the board's size nearer the LiDAR: the board, ok."""
    monitor = SceneBox((1.0, -0.5, 0.5), (0.30, 0.03, 0.18), reflectivity=0.3)
    scans = _twin_scans((monitor,), n=2)
    truth = scans[0].meta["truth_pose"].as_array()
    for scan in scans:
        est = align.estimate(scan)
        assert est.success, est.diagnostics
        assert np.all(np.abs(est.pose.as_array()[:3] - truth[:3]) < 4 * est.std[:3] + 1e-3)


def test_the_station_states_its_region():
    """`Station.board_region`: the board's centre as the nominally mounted LiDAR sees it."""
    st = Station.model_validate({"board": {"position_tolerance_mm": 250.0},
                                 "mount": {"nominal": {"x_mm": 700.0, "y_mm": -2500.0,
                                                       "z_mm": 500.0}}})
    centre, radius = st.board_region(st.mount.nominal.to_pose())
    assert radius == pytest.approx(0.25)
    # the board at (0, 0, 0.5) m, the LiDAR at (0.7, -2.5, 0.5) looking along +Y
    assert centre == pytest.approx((-0.7, 2.5, 0.0))
    assert Station().board_region(st.mount.nominal.to_pose()) is None


def _steep_scans(n: int = 4) -> list:
    """The paper's board turned 35 deg and hung as a diamond (40 deg): seen obliquely."""
    params = replace(BenchParams(), board_yaw=np.deg2rad(35.0), board_roll=np.deg2rad(40.0))
    sim = BenchSim(params, seed=3, noise=NOISE)
    return [sim.scan() for _ in range(n)]


@pytest.fixture(scope="module")
def steep_scans():
    return _steep_scans()


def _normal_error(est, truth: np.ndarray) -> float:
    from align.geometry import plane_of_pose

    n_e, _ = plane_of_pose(est.pose.as_array())
    n_t, _ = plane_of_pose(truth)
    return float(np.arccos(min(1.0, abs(float(n_e @ n_t)))))


def test_the_size_the_rays_see_is_the_boards(steep_scans):
    """Every estimate reports the board's size as its rays see it; given right, it is the
    board's within its sigma and nothing moves (`size_freed` false)."""
    for scan in steep_scans:
        est = align.estimate(scan)
        d = est.diagnostics
        assert est.success and not d["size_freed"]
        assert abs(d["seen_width_m"] - 0.90) < 4 * d["seen_width_std_m"] + 2e-3
        assert abs(d["seen_height_m"] - 0.54) < 4 * d["seen_height_std_m"] + 2e-3


def test_a_size_given_3_percent_large_no_longer_leans_the_plane(steep_scans):
    """Issue 34's steep-incidence lean: a board given 927 x 556 mm for a 900 x 540 one turned
    the plane by 0.7-1.0 deg at 35 deg of incidence (the fit met the wider edges by
    foreshortening). The rays refuse that size, it is freed, and the normal is back within
    its sigma; the size seen is the true one."""
    wrong = align.BoardSpec(0.927, 0.556)
    for scan in steep_scans:
        truth = scan.meta["truth_pose"].as_array()
        est = align.estimate(scan, board=wrong)
        d = est.diagnostics
        assert est.success and d["size_freed"], d
        assert abs(d["seen_width_m"] - 0.90) < 4 * d["seen_width_std_m"] + 2e-3
        sd_normal = float(np.hypot(est.std[4], est.std[5]))
        assert _normal_error(est, truth) < 3 * sd_normal, (_normal_error(est, truth), sd_normal)
        held = align.estimate(scan, board=wrong,
                              params=replace(align.params.DEFAULT_PARAMS, size_refused_d2=1e9))
        assert _normal_error(held, truth) > _normal_error(est, truth)


def test_a_candidate_whose_size_is_unseen_earns_less():
    """The size term: of two fits alike, the one whose rays pin the known size wins; one whose
    rays say another size loses decisively."""
    def with_size(w: float, sd: float) -> align.PoseEstimate:
        est = _fit(1.0, 700)
        d2 = ((w - 0.9) ** 2) / (sd**2 + 1e-6)
        est.diagnostics.update(seen_width_m=w, seen_width_std_m=sd, seen_height_m=0.54,
                               seen_height_std_m=sd, size_mismatch_d2=d2)
        return est

    # vague: a rectangle the rays fit at any size within 20 cm (seen too obliquely, or in part)
    sharp, vague, other = with_size(0.9, 0.002), with_size(0.9, 0.2), with_size(0.95, 0.002)
    d = decide(_candidates(vague, sharp), align.Hints())
    assert d.chosen.index == 1 and d.decisive
    d = decide(_candidates(other, sharp), align.Hints())
    assert d.chosen.index == 1 and d.decisive


def test_a_board_of_another_size_than_given_is_not_vouched_for():
    """The paper's 900 x 540 mm board given 6 or 10 % too small or too large: the estimate is
    not ok (a board given 6-10 % small passed, x 26-44 mm and roll 1 deg off: the rectangle's
    edge sat inside the board with its outside hits under 3 %), and says the size given may be
    wrong; 3 % off (a drawing against a printed board, ranges read long) the pose is freed
    from the size given and stands. Seed 16, 6 % small: the first choice refused, the retry's
    next candidate, a piece of the same board whose start left the rest of it out as strays,
    passed (`align.api._same_object`)."""
    hints = align.Hints(edge_tolerance=(0.0, 0.0))
    for seed in (4, 5, 16):
        scan = BenchSim(seed=seed, noise=NOISE).scan()
        truth = scan.meta["truth_pose"].as_array()
        for f in (0.9, 0.94, 1.06, 1.1):
            est = align.estimate(scan, board=align.BoardSpec(0.9 * f, 0.54 * f), hints=hints)
            assert est.status == align.Status.PARTIAL_BOARD, (seed, f, est.diagnostics)
            if f in (0.94, 1.06):  # the edge sits inside or outside the board: the size named
                assert "size" in est.diagnostics["reason"], est.diagnostics["reason"]
        for f in (0.97, 1.03):
            est = align.estimate(scan, board=align.BoardSpec(0.9 * f, 0.54 * f), hints=hints)
            assert est.success and est.diagnostics["size_freed"], (seed, f, est.diagnostics)
            err = (est.pose.as_array() - truth) / est.std
            assert np.all(np.abs(err) < 4), (seed, f, err.round(1))


def test_an_inspection_states_the_boards_distance_from_the_station():
    """A line knows where its board is: the inspection's hints carry the board's distance from
    the nominally mounted LiDAR (the paper's bench: 2.5 m in front, 0.7 m to the side), so a
    board-sized panel hiding the board 1 m nearer is refused rather than passed for it."""
    from scenarios.inspection import mounting

    station = Station()
    at = mounting.nominal_pose(station)[0]
    assert station.board_distance(at) == pytest.approx(math.hypot(0.7, 2.5), abs=1e-3)
    assert station.board_distance(None) is None
    hints = align.Hints(expected_distance=station.board_distance(at))
    assert region_log_prior(np.array([-0.99, 1.30, -0.05]), hints) == -math.inf
    assert region_log_prior(np.array([-0.70, 2.50, 0.0]), hints) > -0.5
