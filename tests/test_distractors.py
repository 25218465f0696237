"""Distractors on the twin (`twin.sim.distractors`, issue 34): each placement puts its object
where it says (in the LiDAR's view, the board's centre ray clear), the same seed the same
scene, and the estimator never reports an ok pose of the wrong object (one scene per kind, real
MuJoCo, real estimator; `benchmarks/bench_align.py --distractors` is the count)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

import align
from twin.sim import distractors as dz
from twin.sim.bench import BenchSim
from twin.sim.emulation import EmulationConfig
from twin.sim.params import BenchParams, SceneBox

SHARP = EmulationConfig(laser_offset_sigma=0.0, divergence=False)
HINTS = align.Hints(edge_tolerance=(0.0, 0.0))  # the sharp beam the twin has
BOARDS = {"level": BenchParams(), "diamond": dz.diamond(BenchParams())}


def _scene(board: str, kind: str, placement: str, seed: int = 0
           ) -> tuple[BenchParams, dz.Distractor, tuple[np.ndarray, np.ndarray]]:
    params = BOARDS[board]
    lidar = dz.lidar_in_world(params)
    d = dz.place(kind, placement, np.random.default_rng(seed), params, lidar[0])
    return dz.with_distractor(dz.room_for(params, d), d), d, lidar


def _centre_l(pose) -> np.ndarray:
    return -pose.rotation().T @ np.array([pose.x, pose.y, pose.z])


def test_a_box_without_roll_is_built_as_before_and_a_rolled_one_turns():
    box = SceneBox((0.0, 0.0, 0.5), (0.4, 0.01, 0.2), yaw=0.3)
    np.testing.assert_array_equal(box.quat(), [np.cos(0.15), 0.0, 0.0, np.sin(0.15)])
    q = SceneBox((0.0, 0.0, 0.5), (0.4, 0.01, 0.2), roll=math.pi / 4).quat()
    np.testing.assert_allclose(q, [np.cos(math.pi / 8), 0.0, np.sin(math.pi / 8), 0.0],
                               atol=1e-15)


def test_the_same_seed_places_the_same_distractor():
    params = BOARDS["level"]
    sensor = dz.lidar_in_world(params)[0]
    for kind in dz.KINDS:
        for placement in dz.PLACEMENTS:
            a, b, c = (dz.place(kind, placement, np.random.default_rng(s), params, sensor)
                       for s in (7, 7, 8))
            assert a == b
            assert a.boxes[0] != c.boxes[0]


@pytest.mark.parametrize("board", list(BOARDS))
def test_every_placement_puts_its_distractor_where_it_says(board):
    """In view (the scan's returns on it), the board's centre ray meets the board, and the
    distance and side each placement names."""
    for kind in dz.KINDS:
        for placement in dz.PLACEMENTS:
            params, d, lidar = _scene(board, kind, placement, seed=3)
            sight = dz.Sight.of(params, lidar[0])
            face = np.asarray(d.centre)
            along = float((face - sight.sensor) @ sight.ahead)
            across = float((face - sight.sensor) @ sight.right)
            if placement == "front":
                assert along < 0.85 * sight.distance
            elif placement == "beside":
                assert abs(along - sight.distance) <= 0.1 + 1e-9
                assert abs(across) > sight.half_width + 0.3
            elif placement == "behind":
                assert sight.distance + 0.3 - 1e-9 <= along <= sight.distance + 1.5 + 1e-9
            else:
                assert along < 0.75 * sight.distance
                # wholly clear of the board's silhouette
                assert abs(math.atan2(across, along)) > sight.half_angle
            sim = BenchSim(params, seed=1, noise=SHARP)
            board_geom = sim.physics.model.geom("board").id
            box_geoms = {sim.physics.model.geom(f"clutter_{len(params.clutter) - k - 1}").id
                         for k in range(len(d.boxes))}
            pos, _ = sim.physics.lidar_pose_world()
            ray = sight.board - pos
            _, gid, _ = sim.caster.multiray(pos, (ray / np.linalg.norm(ray))[None, :])
            assert gid[0] == board_geom, (kind, placement)
            assert not box_geoms & {int(gid[0])}
            s = sim.scan()
            m = s.distance > 0
            seen = dz.returns_on(np.column_stack([s.x[m], s.y[m], s.z[m]]),
                                 sim.physics.lidar_pose_world(), d.boxes[0])
            assert seen >= 20, (kind, placement, seen)


#: One scene per kind, where each is hardest short of hiding the board's centre: a second panel
#: beside and behind it, a door and a cabinet nearer, a whiteboard beside it, a monitor in
#: front (hiding part of the board); and what is expected of them with the distance stated.
CASES = [("level", "panel", "beside", "right"), ("diamond", "panel", "behind", "right"),
         ("level", "door", "nearer", "right"), ("diamond", "whiteboard", "beside", "right"),
         ("level", "monitor", "front", "partial_board"), ("diamond", "cabinet", "nearer", "right")]


def _verdict(est: align.PoseEstimate, centre: np.ndarray) -> str:
    if not est.success:
        return str(est.status)
    return "right" if np.linalg.norm(_centre_l(est.pose) - centre) < 0.1 else "WRONG"


@pytest.mark.parametrize(("board", "kind", "placement", "stated"), CASES)
def test_no_ok_of_the_wrong_object(board, kind, placement, stated):
    """Never WRONG; with the distance stated, the board (or, hidden in part, no pose); a second
    panel of the board's size without it: ambiguous, as two identical panels must be."""
    params, _, _ = _scene(board, kind, placement, seed=1)
    sim = BenchSim(params, seed=2, noise=SHARP)
    for _ in range(2):
        scan = sim.scan()
        centre = _centre_l(scan.meta["truth_pose"])
        bare = _verdict(align.estimate(scan, hints=HINTS), centre)
        told = _verdict(align.estimate(scan, hints=replace(
            HINTS, expected_distance=float(np.linalg.norm(centre)))), centre)
        assert "WRONG" not in (bare, told)
        assert told == stated
        if kind == "panel":
            assert bare == "ambiguous_board"


def test_a_panel_in_front_hiding_part_of_the_board_is_not_vouched_for():
    """A board-sized panel in front of the board hides part of it: the board's candidate fails
    partial_board, the panel's passes. Weighed only among those that passed, the panel was
    reported ok (issue 34's finding); partly hidden, the board is a rival the rays cannot rule
    out, and the panel 1 m nearer than the distance stated is refused."""
    params, _, _ = _scene("level", "panel", "front", seed=1)
    scan = BenchSim(params, seed=2, noise=SHARP).scan()
    centre = _centre_l(scan.meta["truth_pose"])
    est = align.estimate(scan, hints=replace(HINTS,
                                             expected_distance=float(np.linalg.norm(centre))))
    assert not est.success or np.linalg.norm(_centre_l(est.pose) - centre) < 0.1


@pytest.mark.parametrize("seed", [0, 2, 3])
def test_without_a_stated_distance_a_panel_hiding_half_the_board_is_not_vouched_for(seed):
    """No distance stated, a board-sized panel in front hiding part of a level board: the
    board's half scored a few hundredths of the panel's score (its rectangle half filled), the
    search dropped it, and the panel alone passed ok (these three scenes: WRONG before
    `align.search.board.BEHIND_CHOICE`). Kept as a candidate, it is the panel's rival."""
    params, _, _ = _scene("level", "panel", "front", seed=seed)
    scan = BenchSim(params, seed=2, noise=SHARP).scan()
    centre = _centre_l(scan.meta["truth_pose"])
    assert _verdict(align.estimate(scan, hints=HINTS), centre) == "ambiguous_board"


def test_a_candidate_whose_plane_the_rays_barely_meet_fails_and_does_not_raise():
    """A door in front of the board (the benchmark's first draw, level door front, scene 1):
    the retry's candidates included a few returns of the floor whose plane the rays met at
    grazing incidence, the roll search's rectangle found kilometres away, and the plane's
    refit to the none it held raised (numpy LinAlgError: arrays cannot be empty). A status,
    never an exception: here the board hidden in part."""
    from scenarios.study.protocol import random_pose
    from twin.sim.params import random_scene

    rng = np.random.default_rng([2024, 0])
    for _ in range(2):  # the benchmark's second scene of the level board
        params, x, _ = random_pose(rng, base=BenchParams())
        params = random_scene(np.random.default_rng(rng.integers(2**31)), params,
                              max_holders=0)
        seed = int(rng.integers(2**31))
    door = SceneBox((-0.3357523843123709, -0.8008355519068472, 1.0), (0.45, 0.02, 1.0),
                    yaw=0.16929339979364005, reflectivity=0.379463668906178)
    sim = BenchSim(replace(params, clutter=(*params.clutter, door)), seed=seed, noise=SHARP)
    sim.move_to(x_m=x, yaw_rad=0.0)
    scan = sim.scan()
    centre = _centre_l(scan.meta["truth_pose"])
    est = align.estimate(scan, hints=replace(HINTS,
                                             expected_distance=float(np.linalg.norm(centre))))
    assert _verdict(est, centre) == "partial_board", est.diagnostics
