"""The estimator on random scenes of the real twin (`twin.sim.params.random_scene`): what a
divergent beam straddling the board's edge returns before a dark or far wall, and a holder
flush with the board's plane beside an edge."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import align
from align.geometry import board_coordinates
from scenarios.study.protocol import pose_errors
from twin.sim.bench import BenchSim
from twin.sim.emulation import EmulationConfig
from twin.sim.params import BenchParams, random_scene


@pytest.fixture(autouse=True)
def _quiet():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        yield


def _dark_far_wall() -> list:
    # a random scene's (bench_align --scenes --divergence, pose 4): the wall 2.6 m behind the
    # board at reflectivity 0.21, an eighth of the board's echo energy per beam
    base = BenchParams(mount_roll=-0.0300381, mount_tilt=-0.0236410, mount_yaw=0.0321680)
    params = random_scene(np.random.default_rng(323523084), base, max_holders=0)
    sim = BenchSim(params, seed=152217472, noise=EmulationConfig(laser_offset_sigma=0.0,
                                                                 divergence=True))
    sim.move_to(x_m=-0.0139162, yaw_rad=np.deg2rad(-4.632693))
    return [sim.scan() for _ in range(5)]


def test_partial_returns_beyond_a_side_edge_keep_the_hit_miss_posterior():
    scans = _dark_far_wall()
    truth = scans[0].meta["truth_pose"]
    theta = truth.as_array()
    board = align.BoardSpec()
    err, beyond = [], 0
    for s in scans:
        # the scene is what the test is about: hits at the board's range beyond a side edge,
        # dim (a side part of the beam on the board), further out than the default side
        # tolerance (0.08 mrad)
        x, z, lam = board_coordinates(theta, s.origins(), s.directions())
        w2 = board.width / 2
        hit = (s.distance > 0) & (np.abs(s.distance - lam) < 0.05) & (np.abs(z) < board.height / 2)
        out = hit & (np.abs(x) > w2 + 0.3e-3 * lam) & (np.abs(x) < w2 + 0.02)
        inner = hit & (np.abs(x) < w2 - 0.05)
        assert np.all(s.intensity[out] < 0.5 * np.median(s.intensity[inner]))
        beyond += int(np.sum(out))
        est = align.estimate(s)  # the default hints: the VLP-16's divergent beam
        assert est.success, est.diagnostics.get("reason")
        # taken as hits the rectangle cannot hold at the default side tolerance, they emptied
        # the posterior in 3 of the 5 scans and pulled it 3 sigma off in the other two (roll
        # 0.55 deg RMS, the bound 0.29)
        assert est.diagnostics["label_posterior"]
        e, sd = pose_errors(est, truth)
        assert abs(e[3]) < 2.5 * sd[3], (np.rad2deg(e[3]), np.rad2deg(sd[3]))
        err.append(e[3])
    assert beyond >= 5
    assert np.rad2deg(np.sqrt(np.mean(np.square(err)))) < 0.3


def test_a_holder_flush_with_the_board_beside_a_side_edge_does_not_turn_roll():
    # a random scene's (bench_align --scenes --holders 4, pose 0), the sharp beam: a bracket
    # reaching 16 mm beyond the right edge, its face 15 mm behind the board's (within the
    # range noise), meets one laser; its hits extend that laser's run past the board's width,
    # and a rectangle turned by 0.9-1.4 deg took them in (no hit/miss posterior: the labels
    # disagree at the board's known width)
    base = BenchParams(mount_roll=0.0184130, mount_tilt=-0.0299160, mount_yaw=-0.0199541)
    params = random_scene(np.random.default_rng(168654340), base, max_holders=4)
    right = [h for h in params.holders if h.pos[0] + h.size[0] > params.board_width / 2]
    assert right and right[0].pos[1] - right[0].size[1] < 0.02
    sim = BenchSim(params, seed=305440497, noise=EmulationConfig(laser_offset_sigma=0.0,
                                                                 divergence=False))
    sim.move_to(x_m=0.0297481, yaw_rad=np.deg2rad(5.989322))
    scans = [sim.scan() for _ in range(5)]
    truth = scans[0].meta["truth_pose"]
    sharp = align.Hints(edge_tolerance=(0.0, 0.0))
    err = []
    for s in scans:
        est = align.estimate(s, hints=sharp)
        assert est.success, est.diagnostics.get("reason")
        assert est.diagnostics["label_posterior"]
        e, sd = pose_errors(est, truth)
        assert abs(e[3]) < 4 * sd[3], (np.rad2deg(e[3]), np.rad2deg(sd[3]))
        err.append(e[3])
    assert np.rad2deg(np.sqrt(np.mean(np.square(err)))) < 0.4


def _holder_scene(mount: tuple[float, float, float], scene_seed: int, scan_seed: int, x: float,
                  yaw_deg: float) -> tuple[BenchParams, list]:
    """Five sharp-beam scans of a random scene with holders (bench_align --scenes --holders 4,
    seed 2024: the pose's mount angles, stage position and seeds)."""
    base = BenchParams(mount_roll=mount[0], mount_tilt=mount[1], mount_yaw=mount[2])
    params = random_scene(np.random.default_rng(scene_seed), base, max_holders=4)
    sim = BenchSim(params, seed=scan_seed, noise=EmulationConfig(laser_offset_sigma=0.0,
                                                                 divergence=False))
    sim.move_to(x_m=x, yaw_rad=np.deg2rad(yaw_deg))
    return params, [sim.scan() for _ in range(5)]


def _roll_errors(scans: list) -> np.ndarray:
    """Each scan's roll error over its reported sigma; every estimate must succeed."""
    truth = scans[0].meta["truth_pose"]
    z = []
    for s in scans:
        est = align.estimate(s, hints=align.Hints(edge_tolerance=(0.0, 0.0)))
        assert est.success, est.diagnostics.get("reason")
        e, sd = pose_errors(est, truth)
        z.append((e[3], sd[3]))
    return np.array(z)


def test_a_holder_below_the_board_on_a_ring_that_misses_it_is_not_a_grazing_edge():
    # pose 7: a bracket reaching 37 mm below the bottom edge, its face 21 mm behind the board's
    # (within the range noise), meets the ring just below the board: 3-5 hits in the middle of
    # the bottom edge, which only a ring riding that edge within microns could give. A fit took
    # them for one and rolled the rectangle by 0.6-2.1 deg to ride them (4 of 5 scans)
    _, scans = _holder_scene((0.04246123, 0.00563728, -0.01343984), 984659277, 1463840930,
                             -0.00907365, 6.677941)
    from align.fit.labels import grazing_runs, labels_ordered
    from align.fit.rays import HIT, candidates_at
    from align.params import RaysParams
    from align.search.board import find_board

    board = align.BoardSpec()
    theta = scans[0].meta["truth_pose"].as_array()
    flagged_off, flagged_on = 0, 0
    for s in scans:
        seg = find_board(s, board, align.Hints())
        rays, coords, _ = candidates_at([s], [seg], theta, board, p=RaysParams())
        lab, order = labels_ordered(rays, coords[2], 0.014, p=RaysParams())
        out = grazing_runs(rays, lab, coords, coords[2], board, order, p=RaysParams())
        x, z = coords[0], coords[1]
        on = (np.abs(x) < board.width / 2) & (np.abs(z) < board.height / 2)
        assert np.all(lab[out] == HIT)
        flagged_on += int(np.sum(out & on))
        flagged_off += int(np.sum(out & ~on))
    assert flagged_on == 0  # none of the board's own hits
    assert flagged_off >= 10  # the holder's, in every scan
    z = _roll_errors(scans)
    assert np.all(np.abs(z[:, 0]) < 3 * z[:, 1]), np.rad2deg(z)
    assert np.rad2deg(np.sqrt(np.mean(z[:, 0] ** 2))) < 0.35


def test_a_ring_lengthened_by_a_holder_does_not_turn_the_fit_from_its_start():
    # pose 12: a bracket 34 mm beyond the right edge, its face 8 mm behind the board's and as
    # bright, lengthens one of the board's seven rings past its width. From a good start (roll
    # search 0.4 deg off) the fit turned the rectangle by 3.7 deg and shifted it half a ring
    # down to take those hits in, left the top rings outside and failed as `partial_board`
    params, scans = _holder_scene((-0.01862988, -0.00973907, 0.03761265), 779121434,
                                  981300171, 0.01297414, -9.730471)
    w2 = params.board_width / 2
    assert any(h.pos[0] + h.size[0] > w2 + 0.03 and h.pos[1] - h.size[1] < 0.01
               for h in params.holders)
    z = _roll_errors(scans)
    assert np.all(np.abs(z[:, 0]) < 3 * z[:, 1]), np.rad2deg(z)
    assert np.rad2deg(np.sqrt(np.mean(z[:, 0] ** 2))) < 0.35


def test_a_ring_that_crosses_the_bottom_edge_and_is_lengthened_at_a_side_is_told_by_the_side_line():
    # bench_align --scenes --holders 4 --seed 11, pose 11: a dark bracket 35 mm beyond the
    # right edge, its face 19 mm behind the board's, meets the lowest ring, which enters the
    # board through its bottom edge: its run is shorter than the board's width, and only the
    # line of the other rings' right ends shows its end 4 cm beyond the edge. A rectangle
    # rolled by 5 deg took it in (3 of 5 scans)
    _, scans = _holder_scene((-0.04587561, 0.01030360, 0.04144365), 1133864803, 408387001,
                             0.01830816, -9.461132)
    z = _roll_errors(scans)
    assert np.all(np.abs(z[:, 0]) < 3 * z[:, 1]), np.rad2deg(z)
    assert np.rad2deg(np.sqrt(np.mean(z[:, 0] ** 2))) < 0.35


def test_a_bright_hit_beside_a_side_edge_does_not_roll_a_confident_estimate():
    # seed 3, pose 30: a bright bracket (reflectivity 0.73) reaching 3 mm past the right edge,
    # its face 21 mm behind the board's, gives one ring a last hit no side line can tell from
    # the board's; as a hit the posterior held it inside the rectangle and rolled it by 0.8
    # deg at a sigma of 0.12 (7 sigma). It is brighter than any of the board's own
    from align.fit.labels import bright_ends, labels_ordered
    from align.fit.rays import candidates_at
    from align.params import RaysParams
    from align.search.board import find_board

    _, scans = _holder_scene((0.00170699, -0.03560768, -0.00589595), 317153660, 2071925616,
                             0.00389507, 7.455301)
    truth = scans[0].meta["truth_pose"]
    theta = truth.as_array()
    board = align.BoardSpec()
    w2, h2 = board.width / 2, board.height / 2
    seen = 0
    for s in scans:
        rays, coords, _ = candidates_at([s], [find_board(s, board, align.Hints())], theta,
                                         board, p=RaysParams())
        lab, order = labels_ordered(rays, coords[2], 0.014, p=RaysParams())
        x, z = coords[0], coords[1]
        inner = (np.abs(x) < w2 - 0.03) & (np.abs(z) < h2 - 0.03)
        out = bright_ends(rays, lab, s.intensity[rays.gidx], inner, order, p=RaysParams())
        assert not np.any(out & (np.abs(x) < w2) & (np.abs(z) < h2))  # none of the board's
        if not np.any(out):
            continue
        seen += 1
        est = align.estimate(s, hints=align.Hints(edge_tolerance=(0.0, 0.0)))
        e, sd = pose_errors(est, truth)
        assert abs(e[3]) < 3 * sd[3], (np.rad2deg(e[3]), np.rad2deg(sd[3]))
    assert seen >= 2


def test_the_plane_is_the_boards_not_one_through_the_board_and_the_stand_behind_it():
    # seed 3, pose 11: the stand's returns 4-7 cm behind the board below it share its cluster;
    # a plane tilted by 8 deg holds every board return within RANSAC's 4 cm and the stand's
    # besides, so it had the most inliers, and the fit from it failed as partial_board (2 of
    # 5 scans; the board's cluster was the third candidate tried). The truncated squared
    # distances (MSAC) prefer the board's
    from align.plane import fit as plane

    _, scans = _holder_scene((0.03674628, -0.03466357, 0.04862743), 1075524602, 2084259073,
                             0.00641303, 2.473855)
    z = _roll_errors(scans)
    assert np.rad2deg(np.sqrt(np.mean(z[:, 0] ** 2))) < 0.5
    # the mechanism, on a board and a stand of points drawn like the scene's: 570 on the
    # board (14 mm noise), 60 on a face 5 cm behind it below the board
    rng = np.random.default_rng(0)
    board = np.column_stack((rng.uniform(-0.45, 0.45, 570), 2.5 + rng.normal(0, 0.014, 570),
                             rng.uniform(-0.27, 0.27, 570)))
    stand = np.column_stack((rng.uniform(-0.3, 0.3, 60), 2.55 + rng.normal(0, 0.014, 60),
                             rng.uniform(-0.45, -0.28, 60)))
    pts = np.concatenate((board, stand))
    for truncated, tilted in ((True, False), (False, True)):
        n, _, _ = plane.ransac(pts, 0.04, np.random.default_rng(1), 100, truncated=truncated)
        tilt = np.rad2deg(np.arccos(abs(n[1])))
        assert (tilt > 2.0) == tilted, (truncated, tilt)


def test_a_bright_box_flush_with_a_side_edge_does_not_turn_the_rectangle_to_hold_it():
    # seed 9, pose 0: a bright box 3-6 cm behind the board, flush with its left edge on three
    # rings, joins its cluster; the roll search's rectangle turned by 20 deg holds both, every
    # start's fit contradicted some 30 labels, and one scan's roll erred by 12.5 deg at a sigma
    # of 0.36. The fit from the mount's nominal roll is tried as well when every start's
    # contradicts more than `RETRY_VIOLATIONS` labels
    _, scans = _holder_scene((0.03877241, -0.02232445, 0.01080165), 1965526454, 1965763840,
                             0.01296448, 5.550682)
    z = _roll_errors(scans)
    assert np.all(np.abs(np.rad2deg(z[:, 0])) < 0.5), np.rad2deg(z)


@pytest.mark.parametrize("mount, scene_seed, scan_seed, x, yaw_deg, which", [
    # seed 3, pose 30, scan 4: a holder's return 49 mm behind the plane (3.4 range sigmas),
    # 6 mm past the right edge, the last of its ring before the wall 1.25 m behind
    ((0.00170699, -0.03560768, -0.00589595), 317153660, 2071925616, 0.00389507, 7.455301, 4),
    # seed 3, pose 23, scan 1: one 50 mm behind, 2 mm past the left edge
    ((-0.03466662, 0.00131920, -0.00999092), 427688645, 423524080, -0.01002860, 3.306934, 1),
])
def test_one_holder_return_in_the_hit_band_does_not_pin_the_posterior(mount, scene_seed,
                                                                       scan_seed, x, yaw_deg,
                                                                       which):
    # as a hard label the posterior held the rectangle on it: roll off by -0.90 deg at a sigma
    # of 0.13 (6.8 sigma) and by 0.53 deg at 0.11 (5.1 sigma). Its range residual makes it a
    # soft label (`align.posterior.moments.soft_moments`), whose set without it outweighs the set
    # with it
    from align.params import RaysParams
    from align.posterior.moments import MIN_ODDS
    from align.posterior.rays import clutter_odds

    assert clutter_odds(np.array([0.049]), 0.014, p=RaysParams())[0] > 2 * MIN_ODDS
    _, scans = _holder_scene(mount, scene_seed, scan_seed, x, yaw_deg)
    z = _roll_errors(scans[which:which + 1])
    assert abs(z[0, 0]) < 3 * z[0, 1], np.rad2deg(z)


@pytest.mark.parametrize(("mount", "scene_seed", "scan_seed", "x", "yaw_deg", "scan"), [
    # bench_align --scenes --seed 7, pose 28: a box 2-4 cm behind the board beside its edge;
    # tilt 7.0, yaw 6.2 and x 6.2 sigmas off, all three well within 3 since
    ((-0.020246570768827684, 0.04831254748504994, -0.0035772231632951617), 193918404,
     394899472, 0.008113571033982794, 2.5620170972981366, 4),
    # --seed 4, pose 21: x and yaw 6 sigmas off
    ((0.0026527496047561955, 0.013591672894087869, -0.0015859840474401546), 733750288,
     2082485184, 0.02381434689674187, -7.740548893980039, 2),
])
def test_the_plane_the_posterior_holds_is_the_one_of_the_returns_inside_the_rectangle(
        mount, scene_seed, scan_seed, x, yaw_deg, scan):
    # the board's cluster, cut by a band about a first plane, kept the noise that leans
    # towards that plane, and the returns of a box's face within the band beside an edge: the
    # hit/miss posterior integrated over a plane whose own sigmas did not cover it. The plane
    # from every return inside the fitted rectangle does
    base = BenchParams(mount_roll=mount[0], mount_tilt=mount[1], mount_yaw=mount[2])
    params = random_scene(np.random.default_rng(scene_seed), base, max_holders=0)
    sim = BenchSim(params, seed=scan_seed, noise=EmulationConfig(laser_offset_sigma=0.0,
                                                                 divergence=False))
    sim.move_to(x_m=x, yaw_rad=np.deg2rad(yaw_deg))
    s = [sim.scan() for _ in range(scan + 1)][scan]
    est = align.estimate(s, hints=align.Hints(edge_tolerance=(0.0, 0.0)))
    assert est.success, est.diagnostics.get("reason")
    e, sd = pose_errors(est, s.meta["truth_pose"])
    for axis in (0, 3, 4, 5):  # x, roll, tilt, yaw
        assert abs(e[axis]) < 3 * sd[axis], (axis, e[axis] / sd[axis])
