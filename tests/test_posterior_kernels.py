"""The hit/miss posterior's compiled kernel (`align.feasible.plane_posteriors`) against
the numpy version it replaced (`align.feasible.in_plane_posterior` per plane, then
`align.label_posterior._pose` of its mean), on synthetic VLP-16 scans whose labels are exact:
many planes about the true one in one call, with the plate's side face widening the edges, a
roll prior, and planes no roll explains. The same numbers to rounding (the kernel's sums run in
loop order, numpy's pairwise or in BLAS's order)."""

from __future__ import annotations

import numpy as np
import pytest

from align import feasible, plane
from align.board import BoardSpec
from align.geometry import board_coordinates, plane_of_pose
from align.label_posterior import LabelledRays, _pose

BOARD = BoardSpec()


def _scan(rng: np.random.Generator, theta: np.ndarray) -> LabelledRays:
    """One rotation's 16 rings near a board at ``theta``, labelled exactly, each ray's edges
    widened by up to 2 mm (the side face) and labelled by the widened board."""
    el = np.deg2rad(np.arange(-15.0, 16.0, 2.0))
    az = np.deg2rad(np.arange(-25.0, 25.0, 0.2) + rng.uniform(0.0, 0.2))
    e, a = (v.ravel() for v in np.meshgrid(el, az, indexing="ij"))
    u = np.column_stack((np.cos(e) * np.sin(a), np.cos(e) * np.cos(a), np.sin(e)))
    o = rng.normal(0.0, 0.01, u.shape)  # the lasers' origins off the centre
    x, z, lam = board_coordinates(theta, o, u)
    w2, h2 = BOARD.width / 2, BOARD.height / 2
    ext = rng.uniform(0.0, 2e-3, (len(u), 4))  # left, right, bottom, top
    hit = ((-w2 - ext[:, 0] <= x) & (x <= w2 + ext[:, 1]) & (-h2 - ext[:, 2] <= z)
           & (z <= h2 + ext[:, 3]) & (lam > 0))
    near = (np.abs(x) < w2 + 0.05) & (np.abs(z) < h2 + 0.1)
    return LabelledRays(o[near], u[near], hit[near].astype(np.int8), ext[near])


def _planes(rng: np.random.Generator, theta: np.ndarray, count: int
            ) -> tuple[np.ndarray, np.ndarray]:
    """``count`` planes about the board's at ``theta``: 0.03 deg and 1 mm of spread."""
    n0, d0 = plane_of_pose(theta)
    e1, e2 = plane.tangent_basis(n0)
    g = rng.normal(0.0, 1.0, (count, 3)) * np.array([np.deg2rad(0.03), np.deg2rad(0.03), 1e-3])
    n = n0 + g[:, :1] * e1 + g[:, 1:2] * e2
    return n / np.linalg.norm(n, axis=1, keepdims=True), d0 + g[:, 2]


def _reference(rays: LabelledRays, n: np.ndarray, d: float, rolls: np.ndarray,
               weight: np.ndarray | None) -> np.ndarray | None:
    """One plane's row as the numpy code computed it."""
    lam = (d - rays.origin @ n) / (rays.direction @ n)
    points = rays.origin + lam[:, None] * rays.direction
    post = feasible.in_plane_posterior(n, points, rays.label, rays.ext, BOARD.width,
                                       BOARD.height, rolls, weight)
    if post is None:
        return None
    return np.concatenate(([1.0], post.mean, post.cov.ravel(), [post.evidence],
                           post.support, _pose(n, d, post.mean)))


@pytest.mark.parametrize(("seed", "dist", "prior"), [(0, 1.5, False), (1, 2.5, True),
                                                     (2, 4.0, False), (3, 2.0, True)])
def test_plane_posteriors_match_the_numpy_version(seed, dist, prior):
    rng = np.random.default_rng(seed)
    theta = np.array([rng.uniform(-0.03, 0.03), -dist, rng.uniform(-0.03, 0.03),
                      *np.deg2rad(rng.uniform(-3.0, 3.0, 3))])
    rays = _scan(rng, theta)
    normals, ds = _planes(rng, theta, 12)
    # a plane a tenth short: the hits at one side edge and the misses at the other closer
    # together than the board is wide, no roll consistent
    normals = np.vstack((normals, plane_of_pose(theta)[0]))
    ds = np.append(ds, -0.9 * theta[1])
    rolls = theta[3] + np.deg2rad(np.linspace(-0.6, 0.6, 121))
    weight = (np.exp(-0.5 * ((rolls - theta[3]) / np.deg2rad(0.2)) ** 2) if prior
              else np.empty(0))
    rows = feasible.plane_posteriors(*rays._split, normals, ds, rolls, weight,
                                              BOARD.width / 2, BOARD.height / 2)
    assert rows.shape == (len(ds), feasible.WIDTH)
    found = 0
    for row, n, d in zip(rows, normals, ds, strict=True):
        ref = _reference(rays, n, float(d), rolls, weight if prior else None)
        if ref is None:
            assert row[feasible.OK] == 0.0
            continue
        found += 1
        scale = np.maximum(np.abs(ref), 1e-6)  # covariances' entries of 1e-8: absolute
        np.testing.assert_allclose(row, ref, rtol=1e-10, atol=1e-12 * scale.max())
    assert found >= 8, found  # most planes near the true one are consistent
    assert rows[-1, feasible.OK] == 0.0


def test_in_plane_is_the_kernels_single_plane():
    # LabelledRays.in_plane (one plane) and .posteriors (many) give the same posterior
    rng = np.random.default_rng(5)
    theta = np.array([0.01, -2.0, -0.01, *np.deg2rad([1.0, -2.0, 2.5])])
    rays = _scan(rng, theta)
    normals, ds = _planes(rng, theta, 4)
    rolls = theta[3] + np.deg2rad(np.linspace(-1.0, 1.0, 201))
    many = rays.posteriors(normals, ds, BOARD, rolls, (theta[3], np.deg2rad(0.5)))
    for (post, pose), n, d in zip(many, normals, ds, strict=True):
        one = rays.in_plane(n, float(d), BOARD, rolls, (theta[3], np.deg2rad(0.5)))
        np.testing.assert_array_equal(one.mean, post.mean)
        np.testing.assert_array_equal(one.cov, post.cov)
        assert one.evidence == post.evidence and one.support == post.support
        np.testing.assert_allclose(pose, _pose(n, float(d), post.mean), rtol=1e-12,
                                   atol=1e-15)


def test_rows_from_the_grids_trig_match_roll_by_roll_and_the_rotation():
    # plane_posteriors builds each plane's rows from the grid's cosines and sines computed
    # once: the same floats as computing them roll by roll (a grid of one roll), and the rows
    # of the rotation `align.geometry.pose_from_plane` gives, to rounding
    from align.geometry import pose_from_plane, rotation

    rng = np.random.default_rng(3)
    rolls = np.sort(rng.uniform(-np.pi / 2, np.pi / 2, 101))
    n = np.array([0.05, 0.99, -0.08])
    n /= np.linalg.norm(n)
    r0, r2 = feasible._rows_of(np.cos(rolls), np.sin(rolls), n)
    for k, roll in enumerate(rolls):
        a0, a2 = feasible._rows_kernel(rolls[k:k + 1], n)
        np.testing.assert_array_equal(r0[k], a0[0])
        np.testing.assert_array_equal(r2[k], a2[0])
        rot = rotation(*pose_from_plane(n, 2.0, roll)[3:])
        np.testing.assert_allclose(r0[k], rot[0], atol=1e-12)
        np.testing.assert_allclose(r2[k], rot[2], atol=1e-12)
