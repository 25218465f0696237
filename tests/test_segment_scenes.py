"""The board search on the real twin among things that look like the board: a box's face of the
board's size a few centimetres behind it, beside it."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import align
from align.segment import find_board
from scenarios.study.protocol import pose_errors
from twin.sim.bench import BenchSim
from twin.sim.emulation import EmulationConfig
from twin.sim.params import BenchParams, SceneBox

SHARP = align.Hints(edge_tolerance=(0.0, 0.0))


@pytest.fixture(autouse=True)
def _quiet():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        yield


def _beside_a_box(seed: int) -> list:
    # a random scene's (bench_align --scenes, pose 0): a box turned by -83 deg shows a face
    # 0.55 m wide and 0.77 m tall (the board's size, turned upright), 7 cm behind the board's
    # face and just right of it; the board's own surround holds some of it within the plane's
    # band. The box outscored the board in 1 scan of 5 and took the estimate with it
    box = SceneBox((0.775, 0.31, 0.386), (0.145, 0.275, 0.386), yaw=-1.456, reflectivity=0.53)
    params = BenchParams(wall_distance=0.92, stand_offset=0.11, clutter=(box,),
                         mount_roll=0.0184, mount_tilt=-0.0299, mount_yaw=-0.0200)
    sim = BenchSim(params, seed=seed, noise=EmulationConfig(laser_offset_sigma=0.0))
    sim.move_to(x_m=0.0, yaw_rad=0.104)
    return [sim.scan() for _ in range(6)]


def test_a_board_sized_face_behind_and_beside_the_board_is_not_the_board():
    scans = _beside_a_box(11)
    truth = scans[0].meta["truth_pose"]
    board_range = float(np.hypot(truth.x, truth.y))
    for s in scans:
        est = align.estimate(s, hints=SHARP)
        assert est.success, est.diagnostics.get("reason")
        e, sd = pose_errors(est, truth)
        assert abs(e[0]) < 0.03 and abs(e[3]) < 4 * sd[3], (e, sd)
        # the search keeps the box as the next candidate: the estimate's check of every ray
        # against the known rectangle decides where the likeness scores are close
        seg = find_board(s, align.BoardSpec(), SHARP)
        chosen = [seg.board, *seg.alternatives][est.diagnostics.get("board_candidate", 0)]
        assert abs(float(np.mean(s.distance[chosen])) - board_range) < 0.06


def test_a_stand_post_just_behind_a_grazed_edge_is_not_the_board():
    # a random scene's (bench_align --scenes, pose 28): the stand's post 4 cm behind the
    # board's face, each of its returns within the noise of the plane, below a bottom edge that
    # a ring grazes. A laser that meets only the post has a handful of returns, too few to be
    # tested from each end as a group behind the plane; left as hits, the fit moved the bottom
    # edge onto the post (roll off by 13 deg, partial_board)
    from twin.sim.params import random_scene

    base = BenchParams(mount_roll=0.022768, mount_tilt=0.009979, mount_yaw=0.003385)
    params = random_scene(np.random.default_rng(1475316411), base, max_holders=0)
    sim = BenchSim(params, seed=45136754, noise=EmulationConfig(laser_offset_sigma=0.0))
    sim.move_to(x_m=0.0200, yaw_rad=np.deg2rad(4.8538))
    scans = [sim.scan() for _ in range(5)]
    truth = scans[0].meta["truth_pose"]
    for s in scans:
        est = align.estimate(s, hints=SHARP)
        assert est.success, est.diagnostics.get("reason")
        e, sd = pose_errors(est, truth)
        assert abs(e[3]) < max(4 * sd[3], np.deg2rad(0.5)), (np.rad2deg(e[3]), np.rad2deg(sd[3]))


def test_a_board_scored_below_a_box_far_behind_it_is_found_by_searching_again():
    # a random scene's (bench_align --scenes, pose 6): the board's main plane took in returns
    # beside it (a fifth of them off its rectangle) and scored below a box's face 0.9 m behind
    # it, and below a quarter of that face's score: not even a runner-up. The face's rays are
    # not the board's rectangle; the search redone without the face's returns finds the board
    # (2 of 5 scans were partial_board)
    from twin.sim.params import random_scene

    base = BenchParams(mount_roll=-0.0033490, mount_tilt=0.0486874, mount_yaw=0.0417023)
    params = random_scene(np.random.default_rng(1373317269), base, max_holders=0)
    sim = BenchSim(params, seed=396827229, noise=EmulationConfig(laser_offset_sigma=0.0,
                                                                 divergence=False))
    sim.move_to(x_m=-0.0152877, yaw_rad=np.deg2rad(-8.419314))
    scans = [sim.scan() for _ in range(5)]
    truth = scans[0].meta["truth_pose"]
    board_range = float(np.hypot(truth.x, truth.y))
    researched = boxed = 0
    for s in scans:
        est = align.estimate(s, hints=SHARP)
        assert est.success, est.diagnostics.get("reason")
        e, sd = pose_errors(est, truth)
        assert abs(e[3]) < max(4 * sd[3], np.deg2rad(0.5)), (np.rad2deg(e[3]), np.rad2deg(sd[3]))
        seg = find_board(s, align.BoardSpec(), SHARP)
        researched += est.diagnostics.get("board_candidate", 0) > len(seg.alternatives)
        boxed += float(np.mean(s.distance[seg.board])) > board_range + 0.5  # the box's face
    assert boxed >= 3 and researched >= 2


def test_a_board_whose_bottom_ring_the_clustering_left_out_is_regrown():
    # a random scene's (bench_align --scenes --divergence, pose 31, scan 3): the board's
    # cluster lacks its lowest ring, so the estimate never looked at the ring below it, saw no
    # miss beyond the bottom edge and reported partial_board. The cluster regrown onto the
    # rings either side (returns within the band of its plane) is the board
    from twin.sim.params import random_scene

    base = BenchParams(mount_roll=0.0016724, mount_tilt=-0.0333820, mount_yaw=-0.0483328)
    params = random_scene(np.random.default_rng(2091634011), base, max_holders=0)
    sim = BenchSim(params, seed=804135801, noise=EmulationConfig(laser_offset_sigma=0.0,
                                                                 divergence=True))
    sim.move_to(x_m=0.0219676, yaw_rad=np.deg2rad(-4.321948))
    s = [sim.scan() for _ in range(4)][3]
    truth = s.meta["truth_pose"]
    # the scene is what the test is about: a ring on the board below the cluster's rings
    from align.geometry import board_coordinates

    seg = find_board(s, align.BoardSpec(), align.Hints())
    x, z, lam = board_coordinates(truth.as_array(), s.origins(), s.directions())
    on_board = (s.distance > 0) & (np.abs(s.distance - lam) < 0.05) & (np.abs(x) < 0.45) & (
        np.abs(z) < 0.27)
    assert s.ring[on_board].min() < s.ring[seg.board].min()
    est = align.estimate(s)  # the default hints: the VLP-16's divergent beam
    assert est.success, est.diagnostics.get("reason")
    assert est.diagnostics["edges_seen"] == "lrbt" and est.diagnostics["board_candidate"] == 1
    e, sd = pose_errors(est, truth)
    assert abs(e[3]) < max(4 * sd[3], np.deg2rad(0.5)), (np.rad2deg(e[3]), np.rad2deg(sd[3]))
