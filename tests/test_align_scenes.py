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
