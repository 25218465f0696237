"""The pose fit's compiled kernels (align/fit/*_kernels.py) against their numpy references
(tests/naive.py): the same numbers bit for bit (they only compare, count and copy numpy's
floats), on the joint fit's models of real scans (the five ACFR chessboard captures) and a
twin scan."""

from __future__ import annotations

import numpy as np
import pytest

import align
from align.board import BoardSpec
from align.fit.bracket_kernels import board_spans, contradicted
from align.fit.brackets import (
    hit_miss_brackets,
    rays_between_hits,
    vertical_brackets,
)
from align.fit.labels import behind_ends, bright_ends, grazing_runs, labels_ordered
from align.fit.lsq import gauss_newton
from align.fit.model import Model
from align.fit.rays import DROPOUT, HIT, MISS, UNKNOWN, Rays
from align.fit.sides import Sides, side_lines, side_widening
from align.floats import plane_rows
from align.geometry import board_coordinates, lidar_up, unwrap
from align.params import RaysParams
from align.posterior.rays import ray_points
from align.search.roll_kernels import window_sweep
from tests import naive
from tests.conftest import DATA_DIR
from tests.test_rays_kernels import ACFR_BOARD, _model
from twin.lidar.pcd import read_pcd_scans
from twin.sim.bench import BenchSim

#: The method's tuning, as the estimate uses it by default.
P = RaysParams()


@pytest.fixture(scope="module")
def models() -> list[tuple[Model, np.ndarray]]:
    hints = align.Hints(expected_distance=1.8)
    out = [_model(read_pcd_scans(p)[0], ACFR_BOARD, hints)
           for p in sorted((DATA_DIR / "acfr-vlp16").glob("pose*_full.pcd"))]
    out.append(_model(BenchSim(seed=3).scan(), align.BoardSpec(), align.Hints()))
    return out


def test_profile_matches_numpy_on_real_scans(models):
    rng = np.random.default_rng(11)
    for model, theta in models:
        ds = np.arange(-0.08, 0.0805, 1e-3)
        for k in range(4):
            t = theta + (rng.normal(size=6) * [5e-3, 5e-3, 5e-3, 1e-2, 1e-2, 1e-2] if k else 0)
            for tol in (3e-3, 0.0):
                np.testing.assert_array_equal(model.profile(t, ds, tol),
                                              naive.profile(model, t, ds, tol))


def test_profile_best_is_the_profiles_first_minimum(models):
    """`profile_best` (the brackets costed only where they can decide) against np.argmin of
    the whole profile: poses off by up to a few cm and degrees, the profile's own tolerance
    and none, sharp and blurred edges (bracket costs far above the 1e6 of a violation),
    shifts with ties and a coarse grid."""
    from align.fit.bracket_kernels import profile_best, profile_cost, violations

    rng = np.random.default_rng(23)
    for model, theta in models:
        w2, h2 = model.board.width / 2, model.board.height / 2
        hits, misses = np.flatnonzero(model.lab == HIT), np.flatnonzero(model.lab == MISS)
        for k in range(12):
            t = theta + (rng.normal(size=6) * [2e-2, 5e-3, 2e-2, 3e-2, 1e-2, 1e-2] if k else 0)
            x, z, _ = model.coords(t)
            vx, vz = lidar_up(t)
            for ds in (np.arange(-0.08, 0.0805, 1e-3), np.arange(-0.06, 0.061, 0.02),
                       np.zeros(5)):
                for tol, blur in ((3e-3, model.blur_edges), (0.0, (0.0, 0.0)),
                                  (3e-3, (1e-5, 2e-5))):
                    args = (x, z, hits, misses, model.bh, model.bm, ds, vx, vz, w2, h2, tol,
                            *blur)
                    assert profile_best(*args) == int(np.argmin(profile_cost(*args)))
    # synthetic: brackets a micrometre wide, whose cost at a wrong shift outweighs many
    # violations, so that the least cost lies at a shift with more of them; and exact ties
    wins_elsewhere = 0
    for k in range(300):
        n = 200
        x, z = rng.uniform(-0.6, 0.6, n), rng.uniform(-0.4, 0.4, n)
        hits = np.flatnonzero(rng.random(n) < 0.5)
        misses = np.setdiff1d(np.arange(n), hits)
        nb = int(rng.integers(0, 6))
        bh, bm = rng.choice(n, nb), rng.choice(n, nb)
        x[bm] = x[bh] + rng.choice([1e-6, 1e-3, 0.0], nb)
        z[bm] = z[bh] + rng.choice([1e-6, 0.0], nb)
        ds = np.round(np.arange(-0.06, 0.0605, 0.005), 3) if k % 2 else np.arange(-0.06, 0.061,
                                                                                  0.001)
        args = (x, z, hits, misses, bh, bm, ds, 0.1 * rng.normal(), 1.0, 0.45, 0.27,
                3e-3, 1e-7 * (k % 3), 1e-7)
        cost = profile_cost(*args)
        want = int(np.argmin(cost))
        viol = violations(*args[:4], *args[6:12])
        wins_elsewhere += viol[want] > viol.min()
        assert profile_best(*args) == want
    assert wins_elsewhere > 0  # the case the bound exists for was met


def test_brackets_match_numpy_on_real_scans(models):
    rng = np.random.default_rng(5)
    for model, _ in models:
        lab = model.lab.copy()
        for k in range(5):
            if k in (1, 2):  # flicker: labels flipped at random make zones of mixed returns
                flip = rng.random(len(lab)) < 0.05 * k
                lab = np.where(flip & (lab >= 0), 1 - lab, lab).astype(lab.dtype)
            if k >= 3:  # dropouts (skipped) and unknowns (unlinked) among them
                odd = rng.random(len(lab)) < 0.04
                lab = np.where(odd, DROPOUT if k == 3 else UNKNOWN,
                               lab).astype(lab.dtype)
            got = hit_miss_brackets(model.rays, lab, p=P)
            want = naive.hit_miss_brackets(model.rays, lab)
            assert len(got[0]) > 0
            np.testing.assert_array_equal(got[0], want[0])
            np.testing.assert_array_equal(got[1], want[1])


def _board_points(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Returns on a 0.6 x 0.45 m board 2.6 m ahead, on a few rings, with a few strays."""
    normal = np.array([0.1, 0.99, -0.05])
    normal /= np.linalg.norm(normal)
    e1 = np.cross(normal, [0.0, 0.0, 1.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    u = rng.uniform(-0.3, 0.3, n)
    v = rng.choice(np.linspace(-0.2, 0.2, 6), n) + rng.normal(0, 1e-3, n)
    pts = 2.6 * normal + u[:, None] * e1 + v[:, None] * e2
    pts[:3] += 0.2  # strays
    return pts, normal


def test_window_sweep_matches_sorting_every_roll():
    rng = np.random.default_rng(3)
    board = BoardSpec()
    for n, step in ((150, np.deg2rad(1.0)), (1000, np.deg2rad(0.1)), (7, np.deg2rad(5.0))):
        pts, normal = _board_points(rng, n)
        rolls = np.arange(-np.pi / 2, np.pi / 2, step)
        r0, r2 = plane_rows(rolls, normal)
        whole = 0
        for p in (pts, pts[3:]):  # with strays, and without: rolls the window holds whole
            for coords, length in ((p @ r0.T, board.width + 0.02),
                                   (p @ r2.T, board.height + 0.02)):
                got, want = window_sweep(coords, length), naive.window_fit(coords, length)
                np.testing.assert_array_equal(got[0], want[0])
                np.testing.assert_array_equal(got[1], want[1])
                whole += int(np.sum(got[0] == len(p)))
        assert whole > 0
    # ties, a single point, none
    coords = np.repeat(np.array([[0.0, 1.0, 1.0, 2.0]]).T, 3, axis=1)
    for c in (coords, coords[:1], coords[:0]):
        got, want = window_sweep(c, 1.0), naive.window_fit(c, 1.0)
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_array_equal(got[1], want[1])


def test_rotation_kernel_is_geometry_rotation_bit_for_bit():
    from align.fit.lsq_kernels import jacobian_rotations
    from align.floats import rotation as rotation_kernel
    from align.geometry import rotation

    rng = np.random.default_rng(2)
    for _ in range(2000):
        t = rng.uniform(-4.0, 4.0, 3) * rng.choice([1e-6, 1e-2, 1.0])
        np.testing.assert_array_equal(rotation_kernel(*t), rotation(*t))
    theta = np.array([0.1, -2.6, 0.05, 0.02, -0.01, 0.2])
    rots = jacobian_rotations(theta, 1e-7)
    for k in range(3):
        t = theta.copy()
        t[3 + k] += 1e-7
        np.testing.assert_array_equal(rots[1 + k], rotation(t[3], t[4], t[5]))


def test_inverse_diagonal_is_pinvs_where_well_conditioned(models):
    from align.fit.lsq_kernels import inverse_diagonal

    for model, theta in models:
        f = model.residuals(theta)
        j = model.jacobian(theta, f)
        a = j.T @ j
        diag, ok = inverse_diagonal(a)
        assert ok
        np.testing.assert_allclose(diag, np.diag(np.linalg.pinv(a)), rtol=1e-12, atol=0)
        # a parameter no residual sees: singular, left to pinv (`lm_fit`)
        a0 = a.copy()
        a0[0, :] = a0[:, 0] = 0.0
        assert not inverse_diagonal(a0)[1]  # `lm_fit` then takes pinv's
    # nearly singular (condition 1e14): not trusted either
    assert not inverse_diagonal(np.diag([1.0, 1e-14]))[1]


def test_behind_ends_match_numpy_on_real_scans(models):
    rng = np.random.default_rng(9)
    sigma_r = 0.01
    for model, _ in models:
        rays, lab = model.rays, model.lab
        marked = 0
        for k in range(4):
            res = rng.normal(0.0, sigma_r, len(lab))
            # things just behind the board: a laser's first or last hits, or a short laser
            # whole, 2-5 cm behind
            hit = np.flatnonzero(lab == HIT)
            order = hit[np.lexsort((rays.azimuth[hit], rays.laser[hit], rays.scan[hit]))]
            key = rays.scan[order].astype(np.int64) * 256 + rays.laser[order]
            for grp in np.split(order, np.flatnonzero(key[1:] != key[:-1]) + 1):
                if rng.random() < 0.5:
                    w = int(rng.integers(1, 12))
                    part = grp[:w] if rng.random() < 0.5 else grp[-w:]
                    res[part] += rng.uniform(0.02, 0.05)
            if k == 3:
                # short groups, tested whole: each laser keeps its first 3-8 hits only, some of
                # them all behind
                lab = lab.copy()
                for grp in np.split(order, np.flatnonzero(key[1:] != key[:-1]) + 1):
                    keep = int(rng.integers(3, 9))
                    lab[grp[keep:]] = MISS
                    if rng.random() < 0.5:
                        res[grp[:keep]] += 0.03
            got = behind_ends(rays, lab, res, sigma_r, p=P)
            np.testing.assert_array_equal(got, naive.behind_ends(rays, lab, res, sigma_r))
            marked += int(got.sum())
        assert marked > 0


def test_vertical_brackets_match_numpy_on_real_scans(models):
    rng = np.random.default_rng(4)
    found = 0
    for model, theta in models:
        rays = model.rays
        x, z, _ = board_coordinates(theta, rays.origin, rays.direction)
        vx, vz = lidar_up(theta)
        off = np.abs(vz * x - vx * z)
        for k in range(6):
            lab = model.lab.copy()
            if k:  # rings dropped (unknown), ties of the offsets, labels flipped
                lab[np.isin(rays.ring, rng.choice(np.unique(rays.ring), k))] = UNKNOWN
                off = np.round(off, 2) if k == 2 else off
                lab = np.where(rng.random(len(lab)) < 0.05 * k, 1 - lab, lab).astype(lab.dtype)
            got = vertical_brackets(rays, lab, off)
            want = naive.vertical_brackets(rays, lab, off)
            np.testing.assert_array_equal(got[0], want[0])
            np.testing.assert_array_equal(got[1], want[1])
            found += len(got[0])
    assert found > 0
    empty = vertical_brackets(rays, np.full(len(rays.ring), MISS,
                                                      dtype=np.int8), off)
    assert len(empty[0]) == 0 and empty[0].dtype == np.int64


def test_window_firings_match_numpy_on_real_scans():
    from align.fit.label_kernels import window_firings

    scans = [read_pcd_scans(p)[0] for p in sorted((DATA_DIR / "acfr-vlp16").glob("pose*_full.pcd"))]
    scans.append(BenchSim(seed=3).scan())
    rng = np.random.default_rng(8)
    for s in scans:
        ring_of_laser = s.lasers.ring_of_laser
        for c in (0.0, np.pi - 1e-3, -np.pi, 2.0, float(rng.uniform(-np.pi, np.pi))):
            lo, hi = sorted(rng.uniform(-np.pi, np.pi, 2))
            r_lo = int(rng.integers(-1, 8))
            r_hi = r_lo + int(rng.integers(0, 9))
            near = np.arange(s.lasers.n_lasers)
            near = (near >= r_lo) & (near <= r_hi)
            want = np.flatnonzero(near[ring_of_laser][s.laser_id])
            rel = unwrap(s.azimuth[want], c)
            win = (rel >= lo) & (rel <= hi)
            idx, got_rel = window_firings(s.azimuth, s.laser_id, ring_of_laser, c, lo, hi,
                                          r_lo, r_hi)
            np.testing.assert_array_equal(idx, want[win])
            np.testing.assert_array_equal(got_rel, rel[win])


def test_window_rays_are_board_coordinates_bit_for_bit():
    """`window_rays` against `board_coordinates` and numpy's mask over every fired ray of real
    and twin scans (origins with and without vertical offsets), at poses about the board's
    and far from it."""
    from align.fit.label_kernels import window_rays
    from align.geometry import rotation

    scans = [read_pcd_scans(p)[0] for p in sorted((DATA_DIR / "acfr-vlp16").glob("pose*_full.pcd"))]
    scans.append(BenchSim(seed=3).scan())
    rng = np.random.default_rng(9)
    kept = 0
    for s in scans:
        o, u = s.origins(), s.directions()
        for k in range(6):
            theta = np.array([0.0, -2.5, 0.0, 0.0, 0.0, 0.0]) + rng.normal(size=6) * [
                0.1, 0.5, 0.1, 0.3, 0.1, 1.0]
            half_w, half_h = 0.45 + 0.1 * k, 0.27 + 0.1 * k
            x, z, lam = board_coordinates(theta, o, u)
            want = np.flatnonzero((lam > 0) & (np.abs(x) < half_w) & (np.abs(z) < half_h))
            idx, gx, gz, glam = window_rays(o, u, rotation(*theta[3:]), *theta[:3], half_w,
                                            half_h)
            np.testing.assert_array_equal(idx, want)
            np.testing.assert_array_equal(gx, x[want])
            np.testing.assert_array_equal(gz, z[want])
            np.testing.assert_array_equal(glam, lam[want])
            kept += len(want)
    assert kept > 10_000


#: (hit x, z; miss x, z) in board coordinates of the paper's board (0.9 x 0.54 m), the edge
#: `classify_edges` gives the bracket with a 2 mm corner guard, and why.
CLASSIFY_TABLE = [
    ((0.445, 0.10, 0.454, 0.10), 1, "a level ring leaving the right edge"),
    ((-0.445, -0.20, -0.454, -0.20), 1, "a level ring leaving the left edge"),
    ((0.10, 0.268, 0.10, 0.275), 2, "a ring crossing the top edge steeply"),
    ((-0.350, 0.2671, -0.3509, 0.26713), 2,
     "a ring grazing the top edge 10 cm from a corner: its line meets the side edge at the "
     "corner (pose 120 of bench_align --offsets --poses 160)"),
    ((-0.350, 0.2351, -0.3509, 0.23513), 2, "the same ring from a start 3 cm low"),
    ((0.446, 0.2685, 0.452, 0.2685), 0, "at a corner: either edge"),
]


@pytest.mark.parametrize("bracket, kind, why", CLASSIFY_TABLE,
                         ids=[why.split(":")[0] for _, _, why in CLASSIFY_TABLE])
def test_classify_edges_table(bracket, kind, why):
    from align.fit.bracket_kernels import classify_edges

    xh, zh, xm, zm = bracket
    got, sign, _ = classify_edges(np.array([xh, xm]), np.array([zh, zm]), np.array([0]),
                                  np.array([1]), 0.45, 0.27, 0.002, 0.003, 0.002, True,
                                  P.grazing, np.zeros(1, dtype=bool))
    assert got[0] == kind, why
    # the edge's side: that of the miss, across the edge it measures
    if kind:
        assert sign[0] == np.sign(xm if kind == 1 else zm), why


def test_classify_matches_numpy_on_real_scans(models):
    rng = np.random.default_rng(6)
    for model, theta in models:
        kept = model.excluded.copy()
        for k in range(4):
            t = theta + (rng.normal(size=6) * [5e-3, 5e-3, 5e-3, 1e-2, 1e-2, 1e-2] if k else 0)
            model.excluded = rng.random(len(model.bh)) < 0.1 * k
            for guard, crossings in ((0.005, False), (0.002, True), (0.05, False)):
                want = naive.classify(model, t, guard, crossings)
                model.classify(t, guard, crossings)
                assert model.edge_kind.dtype == np.int8
                for got, ref in zip((model.edge_kind, model.edge_sign, model.edge_sd), want,
                                    strict=True):
                    np.testing.assert_array_equal(got, ref)
        model.excluded = kept
        model.classify(theta, 0.002, True)
        model.assign(theta)


def test_residual_copies_are_kernels_bit_for_bit(models):
    """`residuals_into` (`lm_fit` calls it) is `fit_residuals`' residuals, bit
    for bit, at the estimate and off it, with a range offset. (The Jacobian has one version,
    `jacobian_into`, held against numpy's in tests/test_rays_kernels.py.)"""
    from align.fit.lsq_kernels import residuals_into
    from align.floats import rotation

    for model, theta in models:
        for dt in (np.zeros(6), np.array([3e-3, -5e-3, 2e-3, 1e-2, -4e-3, 6e-3])):
            t = theta + dt
            model.offset = 0.02
            f = model.residuals(t)
            o_r, u_r, d_r, offset, sigma_r, *edges = model._fit_arrays()
            got = np.empty(len(f))
            residuals_into(t, rotation(t[3], t[4], t[5]), o_r, u_r, d_r, offset, sigma_r,
                            *edges, got)
            np.testing.assert_array_equal(got, f)
            model.offset = 0.0


@pytest.mark.parametrize("prior", [None, (0.01, 0.02)])
def test_lm_fit_matches_the_python_loop(models, prior):
    """`lm_fit` (`align.fit.lsq.gauss_newton`) takes the python loop's steps: the same
    iterations and convergence, the pose, offset and Jacobian to rounding (its normal equations
    are summed in another order than BLAS's), from the estimate and from starts moved off it."""
    for model, theta in models:
        for dt in (np.zeros(6), np.array([4e-3, -6e-3, 3e-3, 1.5e-2, -5e-3, 8e-3])):
            start = theta + dt
            results = []
            for fit in (naive.gauss_newton, gauss_newton):
                model.offset, model.offset_prior = 0.0, prior
                results.append((*fit(model, start.copy()), model.offset))
            (p0, j0, c0, i0, b0), (p1, j1, c1, i1, b1) = results
            assert (c1, i1) == (c0, i0)
            np.testing.assert_allclose(p1, p0, rtol=0, atol=1e-9)
            np.testing.assert_allclose(b1, b0, rtol=0, atol=1e-9)
            np.testing.assert_allclose(j1, j0, rtol=1e-6, atol=1e-6 * np.abs(j0).max())
            model.offset, model.offset_prior = 0.0, None


def test_ray_plane_fit_matches_numpy_on_real_scans(models):
    """`plane.fit_rays` (`ray_plane_fit`) against its numpy loop on the models'
    interior hits, from the estimate's plane and from one tilted off it, and a start facing
    away (the flip): the plane and sigma to rounding, the covariance to 1e-9 of itself."""
    from align.geometry import plane_of_pose
    from align.plane import fit as plane

    for model, theta in models:
        use = model.use_range
        r, o, u = model.rays.distance[use], model.rays.origin[use], model.rays.direction[use]
        n, d = plane_of_pose(theta)
        for n0, d0, floor in ((n, d, 0.0), (n + np.array([0.03, -0.02, 0.01]), d + 0.05, 0.0),
                              (-n, -d, 0.02)):
            got, want = plane.fit_rays(r, o, u, n0, d0, sigma_floor=floor), naive.fit_rays(
                r, o, u, n0, d0, sigma_floor=floor)
            np.testing.assert_allclose(got[0], want[0], rtol=0, atol=1e-12)
            assert abs(got[1] - want[1]) < 1e-12
            scale = np.abs(want[2]).max()
            np.testing.assert_allclose(got[2], want[2], rtol=1e-9, atol=1e-9 * scale)
            assert abs(got[3] - want[3]) < 1e-12 * max(want[3], 1e-3)


def test_between_hits_match_numpy_on_real_scans(models):
    """`rays_between_hits` (`between_hits`) against its numpy version, on the
    models' labels and on labels with random hits dropped (dropout-like gaps) and added."""
    rng = np.random.default_rng(11)
    for model, _ in models:
        rays = model.rays
        for k in range(3):
            lab = model.lab.copy()
            if k == 1:
                lab[(lab == HIT) & (rng.random(len(lab)) < 0.2)] = MISS
            if k == 2:
                lab[rng.random(len(lab)) < 0.1] = HIT
            want = naive.rays_between_hits(rays, lab)
            np.testing.assert_array_equal(rays_between_hits(rays, lab), want)
            order = np.lexsort((rays.azimuth, rays.laser, rays.scan))
            np.testing.assert_array_equal(rays_between_hits(rays, lab, order), want)
            assert want.any()
    empty = Rays(*(a[:0] for a in vars(models[0][0].rays).values()))
    assert len(rays_between_hits(empty, np.zeros(0, dtype=np.int8))) == 0


def test_board_spans_match_numpy_on_real_scans(models):
    """`board_spans` (the brackets' span of each laser) against its numpy version: the models'
    labels, with hits dropped at random (runs split, ties of equal runs), and none."""
    rng = np.random.default_rng(12)
    for model, _ in models:
        rays = model.rays
        order = np.lexsort((rays.azimuth, rays.laser))
        for k in range(4):
            lab = model.lab.copy()
            if k == 1:
                lab[(lab == HIT) & (rng.random(len(lab)) < 0.3)] = MISS
            if k == 2:
                lab[rng.random(len(lab)) < 0.5] = HIT
            if k == 3:
                lab[:] = MISS
            ls, az, lb = rays.laser[order], rays.azimuth[order], lab[order]
            got = board_spans(ls, az, lb == HIT, P.zone_azimuth)
            want = naive.board_spans(ls, az, lb)
            for g, w in zip(got, want, strict=True):
                np.testing.assert_array_equal(g, w)
        # equal runs on one laser: the later wins
        ls = np.zeros(7, dtype=rays.laser.dtype)
        az = np.array([0.0, 0.001, 0.1, 0.101, 0.2, 0.201, 0.3])
        lb = np.array([1, 1, 0, 1, 1, 0, 1], dtype=np.int8)
        got = board_spans(ls, az, lb == HIT, P.zone_azimuth)
        for g, w in zip(got, naive.board_spans(ls, az, lb), strict=True):
            np.testing.assert_array_equal(g, w)


def test_assign_matches_numpy_on_real_scans(models):
    """`Model.assign` (`range_rays`) against its numpy version, at the estimate and
    off it, with a range offset."""
    for model, theta in models:
        for dt, offset in ((np.zeros(6), 0.0), (np.array([0.01, 0.004, -0.01, 0.02, 0, 0]), 0.01)):
            model.offset = offset
            model.assign(theta + dt)
            want = naive.assign(model, theta + dt)
            np.testing.assert_array_equal(model.use_range, want[0])
            for g, w in zip(model._range, want[1:], strict=True):
                np.testing.assert_array_equal(g, w)
            assert want[0].any()
        model.offset = 0.0
        model.assign(theta)


def test_model_coords_are_board_coordinates_bit_for_bit(models):
    """`Model.coords` reuses the rotation's products for a pose moved in the plane only: the
    same bits as `board_coordinates` there, after a new rotation, and after a new t_y."""
    for model, theta in models:
        model._coords = model._products = None
        vx, vz = lidar_up(theta)
        poses = [theta]
        for s in (0.004, -0.013, 0.0):
            t = theta.copy()
            t[0] += s * vx
            t[2] += s * vz
            poses.append(t)
        poses += [theta + np.array([0, 0, 0, 1e-3, 0, 0]), theta + np.array([0, 2e-3, 0, 0, 0, 0]),
                  theta + np.array([5e-3, 0, -4e-3, 0, 0, 0]), theta]
        for t in poses:
            got = model.coords(t)
            for g, w in zip(got, board_coordinates(t, model.rays.origin, model.rays.direction),
                            strict=True):
                np.testing.assert_array_equal(g, w)


def test_used_edges_and_contradicted_match_numpy_on_real_scans(models):
    """`Model._cache_edges` (`used_edges`) and the fit's count of contradicted labels
    (`contradicted`, at the model's coordinates) against their numpy versions, for both
    corner guards and with and without the grazing crossings, at the estimate and off it."""
    for model, theta in models:
        for guard, crossings, dt in ((0.005, False, 0.0), (0.002, True, 0.0),
                                     (0.002, True, 0.02)):
            t = theta + np.array([dt, 0, -dt, dt, 0, 0])
            model.classify(t, guard, crossings)
            use = model.edge_kind > 0
            assert use.any()
            want = (model._bh[0][use], model._bh[1][use], model._bm[0][use], model._bm[1][use],
                    model.edge_sign[use], model.edge_sd[use], (model.edge_kind == 1)[use])
            got = (*model._ubh, *model._ubm, model._usign, model._usd, model._uvert)
            for g, w in zip(got, want, strict=True):
                assert g.dtype == w.dtype
                np.testing.assert_array_equal(g, w)
            for margin in (0.0, 0.01, 0.05):
                x, z, _ = board_coordinates(t, model.rays.origin, model.rays.direction)
                w2, h2 = model.board.width / 2, model.board.height / 2
                out = (np.abs(x) > w2 + margin) | (np.abs(z) > h2 + margin)
                deep = (np.abs(x) < w2 - margin) & (np.abs(z) < h2 - margin)
                lab = model.lab
                count = int(np.sum((lab == HIT) & out)
                            + np.sum((lab == MISS) & deep))
                xs, zs, _ = model.coords(t)
                assert contradicted(xs, zs, lab, HIT, MISS, w2, h2, margin) == count
        model.classify(theta, 0.002, True)


def test_numpy_mean_is_np_mean_bit_for_bit():
    """`label_kernels.numpy_mean` (the short groups' mean in `behind_groups`) is np.mean of the
    gathered values bit for bit, for every size up to 128."""
    from align.fit.label_kernels import numpy_mean

    rng = np.random.default_rng(13)
    res = rng.normal(0.0, 0.01, 400) + rng.choice([0.0, 0.03], 400)
    for n in range(1, 129):
        for _ in range(20):
            idx = rng.choice(len(res), n, replace=False)
            assert numpy_mean(res, idx) == float(res[idx].mean())


def test_laser_ends_match_numpy_on_real_scans(models):
    """`laser_ends` (`Sides.of`) against the lexsorts and diffs it replaced: the fit's
    poses and others a few cm and degrees off, the side faces of a 3 mm plate and of none,
    labels flipped at random, and ties (x quantised to 5 mm)."""
    from align.fit.label_kernels import laser_ends

    rng = np.random.default_rng(31)
    compared = 0
    for model, theta in models:
        board = model.board
        for k in range(8):
            t = theta + (rng.normal(size=6) * [2e-2, 5e-3, 2e-2, 3e-2, 1e-2, 1e-2] if k else 0)
            x, z, _ = model.coords(t)
            if k % 4 == 3:
                x = np.round(x / 0.005) * 0.005
            lab = model.lab.copy()
            if k % 2:
                flip = rng.random(len(lab)) < 0.1
                lab = np.where(flip & (lab >= 0), 1 - lab, lab).astype(lab.dtype)
            ext = side_widening(model.rays.direction, t, replace_thickness(board, k))
            want = naive.laser_ends(x, z, lab, model.rays.laser, ext, board)
            w2, h2, margin = board.width / 2, board.height / 2, P.outlier_margin
            got = laser_ends(x, z, lab, model.rays.laser, ext, HIT, w2 + margin,
                             h2 + margin)
            if want is None:
                assert len(got[3]) < 3
                continue
            for g, w in zip(got, want, strict=True):
                np.testing.assert_array_equal(g, w)
            compared += 1
    assert compared > 30


def replace_thickness(board: BoardSpec, k: int) -> BoardSpec:
    """``board`` with a 3 mm plate for even ``k``, none for odd."""
    return BoardSpec(board.width, board.height, thickness=0.003 if k % 2 == 0 else 0.0)


def test_kth_smallest_is_np_partitions():
    """`kth_smallest` (`laser_ends`' median step) against np.partition: random, rounded
    (ties), constant, sorted and reversed values, one to two thousand of them."""
    from align.fit.label_kernels import kth_smallest

    rng = np.random.default_rng(4)
    for trial in range(3000):
        n = int(rng.integers(1, 60)) if trial % 2 else int(rng.integers(1, 2000))
        a = [rng.random(n), np.round(rng.random(n), 1), np.zeros(n), np.sort(rng.random(n)),
             np.sort(rng.random(n))[::-1].copy()][trial % 5]
        k = int(rng.integers(0, n))
        assert kth_smallest(a.copy(), k) == np.partition(a, k)[k]


def test_grazing_runs_match_numpy_on_real_scans(models):
    """`grazing_runs` (its runs compiled: `hit_runs`) against the numpy version: the
    models' labels, and labels flipped at random (short runs of hits beside misses and
    returns behind, some grazing), with and without the side lines, at poses off the fit's."""
    from align.fit.label_kernels import hit_runs

    rng = np.random.default_rng(17)
    runs = flagged = 0
    for model, theta in models:
        rays, board = model.rays, model.board
        order = np.lexsort((rays.azimuth, rays.laser, rays.scan))
        for k in range(10):
            t = theta + (rng.normal(size=6) * [1e-2, 5e-3, 1e-2, 2e-2, 5e-3, 5e-3] if k else 0)
            coords = board_coordinates(t, rays.origin, rays.direction)
            lab = model.lab.copy()
            if k % 2:
                flip = rng.random(len(lab)) < 0.08 * (k % 4)
                lab = np.where(flip, rng.choice([-1, 0, 1], len(lab)), lab).astype(lab.dtype)
            expected = coords[2] + (0.02 if k % 3 == 0 else 0.0)
            ext = side_widening(rays.direction, t, board)
            for sides in (None, Sides.of(coords[0], coords[1], lab, rays.laser, ext,
                                                   board, p=P)):
                got = grazing_runs(rays, lab, coords, expected, board, order, sides, p=P)
                want = naive.grazing_runs(rays, lab, coords, expected, board, order, sides)
                np.testing.assert_array_equal(got, want)
                flagged += int(np.any(want))
            runs += len(hit_runs(order, lab, rays.laser, rays.scan, rays.azimuth,
                                 rays.distance, expected, P.max_gap, HIT,
                                 MISS, UNKNOWN)[0])
    assert runs > 200 and flagged > 0, (runs, flagged)


def test_side_faces_match_numpy_on_real_scans():
    """`side_faces` (`side_widening`) against u @ rot.T and numpy's elementwise steps, bit
    for bit: every fired ray of real and twin scans, any number of them (one row takes
    numpy's matrix-vector kernel), at poses about the board's; rays along the plane (a
    division by zero) as numpy gives them."""
    from align.fit.label_kernels import side_faces
    from align.geometry import rotation

    scans = [read_pcd_scans(p)[0] for p in sorted((DATA_DIR / "acfr-vlp16").glob("pose*_full.pcd"))]
    scans.append(BenchSim(seed=3).scan())
    rng = np.random.default_rng(13)
    for s in scans:
        u_all = s.directions()
        for k in range(12):
            theta = rng.normal(size=6) * [0.1, 0.5, 0.1, 0.3, 0.1, 1.0]
            m = [len(u_all), 1, 2, 3, 5, 17, 64][k % 7]
            u = u_all if m == len(u_all) else u_all[rng.choice(len(u_all), m)]
            if k == 11:  # rays along the plane (no rotation): divisions by zero
                theta[3:] = 0.0
                u = u.copy()
                u[0], u[1] = (1.0, 0.0, 0.0), (0.0, 0.0, 0.0)
            with np.errstate(divide="ignore", invalid="ignore"):
                want = naive.side_faces(u, theta, 0.003)
            np.testing.assert_array_equal(side_faces(u, rotation(*theta[3:]), 0.003), want)


def test_side_lines_match_numpy():
    """`align.fit.sides.side_lines` (compiled around numpy's normal equations) against the numpy
    version, bit for bit: lasers' ends of a rolled board with noise, holders' ends beyond a
    side, rings leaving through the top or bottom (ends well inside), too few ends."""
    rng = np.random.default_rng(21)
    w2 = 0.45
    found = dropped = 0
    for _ in range(3000):
        n = int(rng.integers(2, 16))
        z = np.sort(rng.uniform(-0.27, 0.27, n))
        slope = rng.normal() * 0.05
        ends = np.column_stack((-w2 + slope * z + rng.normal(size=n) * 0.004, z,
                                w2 + slope * z + rng.normal(size=n) * 0.004, z))
        for _ in range(int(rng.integers(0, 3))):  # a holder beyond, or a ring leaving early
            i, c = int(rng.integers(n)), int(rng.choice([0, 2]))
            ends[i, c] += (1 if c == 2 else -1) * rng.choice([0.01, 0.03, -0.02, -0.06])
        tol, inward = 0.006 + 0.002 * rng.random(), 0.015 + 0.01 * rng.random()
        want = naive.side_lines(ends, w2, tol, inward)
        got = side_lines(ends, w2, tol, inward, p=P)
        assert got == want
        found += want is not None
        dropped += want is not None and want != naive.side_lines(ends, w2, 1.0, 1.0)
    assert found > 1000 and dropped > 100, (found, dropped)


def test_lidar_up_is_the_rotations_column_bit_for_bit():
    """`geometry.lidar_up` (R's entries without the 3 x 3 array) against its definition from
    `geometry.rotation`: the same floats, including a LiDAR looking along the plane."""
    import math

    from align.geometry import rotation

    rng = np.random.default_rng(3)
    for k in range(20000):
        theta = rng.normal(size=6) * (3.0 if k % 2 else 0.05)
        if k % 7 == 0:
            theta[4] = np.pi / 2
        r = rotation(theta[3], theta[4], theta[5])
        nv = math.hypot(r[0, 2], r[2, 2])
        want = (0.0, 1.0) if nv < 1e-9 else (float(r[0, 2] / nv), float(r[2, 2] / nv))
        assert lidar_up(theta) == want


def test_normal_equations_in_registers_are_the_loops():
    """`normal_equations` of six columns (its sums in registers) against the loop over the
    array it replaced: the same floats, the products added in the same order."""
    from align.fit.lsq_kernels import normal_equations

    rng = np.random.default_rng(5)
    for n in (0, 1, 7, 555):
        for cols in (6, 7):
            j = rng.normal(size=(n, cols)) * rng.lognormal(size=cols) * 1e3
            f = rng.normal(size=n)
            loop = naive.normal_equations(j, f)
            for got, want in zip(normal_equations(j, f), loop, strict=True):
                np.testing.assert_array_equal(got, want)


def test_window_pool_is_the_scans_selected_rays():
    """`window_pool` (`align.fit.rays`' candidate pool) against `window_firings` and `Scan.select`'s
    origins, directions, ranges, lasers and rings, bit for bit, on real and twin scans, with
    and without the lasers' vertical and horizontal offsets applied (the sine and cosine of the
    azimuth are numba's: the C library's, as numpy's)."""
    from dataclasses import replace

    from align.fit.label_kernels import window_firings, window_pool

    scans = [read_pcd_scans(p)[0] for p in sorted((DATA_DIR / "acfr-vlp16").glob("pose*_full.pcd"))]
    scans.append(BenchSim(seed=3).scan())
    # an Ouster's lasers: origins off the beam by up to 1.2 mm (horizontal offsets)
    from twin.core.lasers import LaserTable

    lt = scans[-1].lasers
    h = np.random.default_rng(23).uniform(-1.2e-3, 1.2e-3, lt.n_lasers)
    scans.append(replace(scans[-1], lasers=LaserTable(lt.model, lt.elevation, lt.vertical_offset,
                                                      lt.azimuth_offset, h)))
    scans += [replace(s, vertical_offsets_applied=False) for s in scans[-2:]]
    rng = np.random.default_rng(19)
    for s in scans:
        lasers = s.lasers
        offset_z = (np.array(lasers.vertical_offset) if s.vertical_offsets_applied
                    else np.zeros(lasers.n_lasers))
        offset_h = (np.array(lasers.horizontal_offset) if s.vertical_offsets_applied
                    else np.zeros(lasers.n_lasers))
        for c in (0.0, np.pi - 1e-3, float(rng.uniform(-np.pi, np.pi))):
            lo, hi = sorted(rng.uniform(-np.pi, np.pi, 2))
            r_lo = int(rng.integers(-1, 8))
            r_hi = r_lo + int(rng.integers(0, 9))
            idx, rel = window_firings(s.azimuth, s.laser_id, lasers.ring_of_laser, c, lo, hi,
                                      r_lo, r_hi)
            sub = s.select(idx)
            want = (idx, sub.origins(), sub.directions(), sub.distance, sub.laser_id, rel + c,
                    sub.ring)
            got = window_pool(s.azimuth, s.laser_id, s.distance, lasers.ring_of_laser,
                              np.cos(lasers.elevation), np.sin(lasers.elevation), offset_z,
                              offset_h, c, lo, hi, r_lo, r_hi)
            for g, w in zip(got, want, strict=True):
                np.testing.assert_array_equal(g, w)
                assert g.dtype == w.dtype


def test_pool_rows_are_numpys_gathers(models):
    """`pool_rows` (`candidates_at`'s rows of the pool) against numpy's fancy indexing
    of each field, values and dtypes."""
    from align.fit.label_kernels import pool_rows

    rng = np.random.default_rng(29)
    for model, _ in models:
        r = model.rays
        fields = (r.origin, r.direction, r.distance, r.laser, r.azimuth, r.ring, r.gidx, r.scan)
        for size in (0, 1, len(r.distance) // 2):
            keep = np.sort(rng.choice(len(r.distance), size, replace=False))
            for got, a in zip(pool_rows(keep, *fields), fields, strict=True):
                np.testing.assert_array_equal(got, a[keep])
                assert got.dtype == a.dtype


def test_the_warm_up_compiles_the_fits_and_the_posteriors_kernels():
    """`scenarios.warmup` (run by make setup) leaves none of the kernels the default
    estimate calls in the fit's, the posterior's and the plane's kernel modules (and the
    search's the fit calls) for a command to compile. (The others are compiled into these.)"""
    from align.fit import bracket_kernels, label_kernels, lsq_kernels
    from align.plane import kernels as plane_kernels
    from align.posterior import moments
    from align.search import cluster_kernels, roll_kernels
    from scenarios.warmup import warm_up

    warm_up()
    called = {
        label_kernels: ("window_pool", "window_rays", "pool_rows", "laser_ends", "side_faces",
                        "side_ends", "line_excess", "hit_runs", "ray_products",
                        "shifted_coords", "behind_groups", "range_rays", "edge_labels",
                        "range_labels", "bright_limit", "seen_counts"),
        bracket_kernels: ("laser_brackets", "profile_best", "between_hits", "column_brackets",
                          "classify_edges", "used_edges", "contradicted"),
        lsq_kernels: ("lm_fit", "fit_residuals"),
        roll_kernels: ("window_sweep_pair",),
        moments: ("plane_posteriors", "binding_rays"),
        plane_kernels: ("msac_best", "lsq_plane", "ray_plane_fit"),
        cluster_kernels: ("in_ring_block",),
    }
    missing = [f"{mod.__name__}.{name}" for mod, names in called.items() for name in names
               if not getattr(mod, name).signatures]
    assert missing == []


def test_ray_points_match_numpy_on_real_scans(models):
    """`ray_points` (its labels and allowances compiled: `edge_labels`) against the
    numpy version, bit for bit: sharp and divergent tolerances, partial tolerances, random
    intensities (dim hits, an even and an odd number of reference hits: np.median's mean of
    the middle two) and none, at the fit's pose and off it."""
    rng = np.random.default_rng(37)
    partials, parities = 0, set()
    for model, theta in models:
        n = len(model.lab)
        for k in range(8):
            t = theta + (rng.normal(size=6) * [5e-3, 2e-3, 5e-3, 5e-3, 2e-3, 2e-3] if k else 0)
            tolerance = ((0.0, 0.0), (8e-5, 5e-4), (0.0, 5e-4), (3e-4, 0.0))[k % 4]
            partial = (1e-3, 1.5e-3) if k % 3 else (0.0, 0.0)
            intensity = None if k == 5 else rng.integers(0, 256 if k % 2 else 60, n).astype(
                np.uint8)
            if intensity is not None and k == 6:  # an odd number of reference hits
                intensity[:] = 40
            got = ray_points(model, t, tolerance, intensity, partial, p=P)
            want = naive.ray_points(model, t, tolerance, intensity, partial)
            for a, b in zip((got[0].origin, got[0].direction, got[0].label, got[0].ext,
                             got[0].odds, got[1]),
                            (want[0].origin, want[0].direction, want[0].label, want[0].ext,
                             want[0].odds, want[1]), strict=True):
                np.testing.assert_array_equal(a, b)
            if intensity is not None:
                x, z, _ = board_coordinates(t, model.rays.origin, model.rays.direction)
                inner = (np.abs(x) < model.board.width / 2 - 0.03) & (
                    np.abs(z) < model.board.height / 2 - 0.03)
                partials += int(np.any(naive.partial_hits(model.lab, intensity, inner)))
                parities.add(int(np.count_nonzero((model.lab == HIT) & inner)) % 2)
    assert partials > 10 and parities == {0, 1}


def test_labels_and_bright_ends_match_numpy_on_real_scans(models):
    """`labels_ordered` (`range_labels`) and `bright_ends` (`bright_limit`) against the
    numpy versions: ranges off the plane by up to the label tolerance and more, several range
    sigmas, intensities with bright holders at the ends of the rings and without."""
    rng = np.random.default_rng(41)
    bright = 0
    for model, theta in models:
        rays = model.rays
        _, _, lam = board_coordinates(theta, rays.origin, rays.direction)
        for k in range(6):
            lam_k = lam + rng.normal(size=len(lam)) * (0.02 if k % 2 else 0.002)
            sigma_r = (0.003, 0.014, 0.03)[k % 3]
            lab = labels_ordered(rays, lam_k, sigma_r, p=P)[0]
            np.testing.assert_array_equal(lab, naive.labels(rays, lam_k, sigma_r))
            order = np.lexsort((rays.azimuth, rays.laser, rays.scan))
            intensity = rng.integers(20, 60, len(lab)).astype(np.uint8)
            if k % 2:  # a bright holder at a ring's ends, and a few bright returns
                hits = order[lab[order] == HIT]
                intensity[hits[:2]] = intensity[hits[-1]] = 250
                intensity[rng.random(len(lab)) < 0.004] = 250
            inner = rng.random(len(lab)) < 0.7
            got = bright_ends(rays, lab, intensity, inner, order, p=P)
            np.testing.assert_array_equal(got, naive.bright_ends(rays, lab, intensity,
                                                                     inner, order))
            bright += int(np.any(got))
    assert bright > 0


def test_seen_counts_match_numpy_on_real_scans(models):
    """`seen_counts` (the estimate's account of what was seen) against
    `tests.naive.edges_seen` and numpy's masks: the models' labels, with misses,
    dropouts and returns in front put in at random, at poses off the fit's (edges unseen, rays
    blocked)."""
    from align.fit.label_kernels import seen_counts

    rng = np.random.default_rng(43)
    for model, theta in models:
        rays, board = model.rays, model.board
        w2, h2 = board.width / 2, board.height / 2
        for k in range(8):
            t = theta + (rng.normal(size=6) * [3e-2, 1e-2, 3e-2, 3e-2, 1e-2, 1e-2] if k else 0)
            x, z, lam = board_coordinates(t, rays.origin, rays.direction)
            lab = model.lab.copy()
            if k % 2:
                lab = np.where(rng.random(len(lab)) < 0.05, rng.choice(
                    [MISS, DROPOUT, HIT], len(lab)), lab).astype(
                    lab.dtype)
            distance = rays.distance - (0.2 if k % 3 == 0 else 0.0) * (rng.random(len(lab))
                                                                        < 0.1)
            b, front = 0.003 * k, 0.04
            inside = (np.abs(x) < w2) & (np.abs(z) < h2)
            want = (naive.edges_seen(x, z, lab, board), int(np.sum(inside)),
                    int(np.sum(inside & (distance > 0) & (distance - b - lam < -front))),
                    int(np.sum(inside & (lab == DROPOUT))),
                    int(np.sum(inside & (np.abs(x) < w2 - 0.02) & (np.abs(z) < h2 - 0.02)
                               & (lab == MISS))),
                    int(np.sum((lab == HIT) & ((np.abs(x) > w2 + 0.02)
                                                        | (np.abs(z) > h2 + 0.02)))))
            got = seen_counts(x, z, lam, lab, distance, b, front, w2, h2, P.window,
                              0.02, HIT, MISS, DROPOUT)
            assert tuple(bool(v) for v in got[0]) == want[0]
            assert got[1:] == want[1:]
