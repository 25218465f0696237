"""align.posterior.hit_miss: the hit/miss posterior with the plane marginalised, on synthetic scans
whose labels are exact (a VLP-16's 16 rings, 0.2 deg azimuth steps, a board 2.5 m ahead), so
that the only errors are the ones the posterior must account for: the edges' sampling and the
plane's."""

from __future__ import annotations

import numpy as np
import pytest

from align.board import BoardSpec
from align.geometry import board_coordinates, plane_of_pose
from align.plane import fit as plane
from align.posterior.hit_miss import (
    LabelledRays,
    OffsetModel,
    gauss_hermite,
    label_posterior,
    laser_directions,
)

BOARD = BoardSpec()
#: The ranges' plane uncertainty of a single scan (tilt, yaw about 0.1 deg; distance 1.6 mm).
SD_PLANE = np.array([np.deg2rad(0.1), np.deg2rad(0.1), 1.6e-3])


def _pose(rng: np.random.Generator) -> np.ndarray:
    """A board 2.5 m ahead: x, z within +-30 mm, roll, tilt and yaw within +-3 deg."""
    return np.array([rng.uniform(-0.03, 0.03), -2.5, rng.uniform(-0.03, 0.03),
                     *np.deg2rad(rng.uniform(-3.0, 3.0, 3))])


def _scan(rng: np.random.Generator, theta: np.ndarray) -> LabelledRays:
    """Every ray of one rotation's 16 rings near the board, labelled exactly by the board at
    ``theta`` (a random start azimuth)."""
    el = np.deg2rad(np.arange(-15.0, 16.0, 2.0))
    az = np.deg2rad(np.arange(-14.0, 14.0, 0.2) + rng.uniform(0.0, 0.2))
    e, a = (v.ravel() for v in np.meshgrid(el, az, indexing="ij"))
    u = np.column_stack((np.cos(e) * np.sin(a), np.cos(e) * np.cos(a), np.sin(e)))
    o = np.zeros_like(u)
    x, z, lam = board_coordinates(theta, o, u)
    hit = (np.abs(x) <= BOARD.width / 2) & (np.abs(z) <= BOARD.height / 2) & (lam > 0)
    near = (np.abs(x) < BOARD.width / 2 + 0.05) & (np.abs(z) < BOARD.height / 2 + 0.1)
    return LabelledRays(o[near], u[near], hit[near].astype(np.int8), np.zeros((near.sum(), 4)))


def _plane_off(theta: np.ndarray, g: np.ndarray) -> tuple[np.ndarray, float]:
    """The true plane moved by g = (alpha, beta, d) as `label_posterior` moves its draws."""
    n, d = plane_of_pose(theta)
    e1, e2 = plane.tangent_basis(n)
    m = n + g[0] * e1 + g[1] * e2
    return m / np.linalg.norm(m), d + g[2]


def test_roll_x_z_within_their_stated_uncertainty():
    # the ranges' plane off by a draw from its own covariance, the start roll off by 0.3 deg: over
    # 200 scans the errors' chi-square per axis is about 1 (the plane's uncertainty carried
    # through, and no draw's posterior cut off by its roll grid)
    rng = np.random.default_rng(0)
    c_plane = np.diag(SD_PLANE**2)
    chi2 = []
    for _ in range(200):
        theta = _pose(rng)
        n, d = _plane_off(theta, rng.normal(0.0, SD_PLANE))
        start = theta.copy()
        start[3] += rng.normal(0.0, np.deg2rad(0.3))
        out = label_posterior(_scan(rng, theta), BOARD, start, np.deg2rad(0.3),
                              (n, d, c_plane), 1, rng)
        assert out is not None
        mean, cov = out
        idx = [3, 0, 2]
        chi2.append((mean - theta)[idx] ** 2 / np.diag(cov)[idx])
    assert np.mean(chi2, axis=0) == pytest.approx([1.0, 1.0, 1.0], abs=0.3)


def test_fused_pose_within_its_stated_uncertainty():
    # ten scans' labels (brackets ten times narrower, so the labels also pin the plane's
    # distance and yaw a little) and the plane off by a draw from a ten-scan covariance: every
    # axis's chi-square about 1 (at most 1 + 4 sigma of its sampling spread; the covariance may
    # be a little conservative) and no error beyond 5 sigma (a band of planes the first rule
    # cannot resolve was once 20-50 sigma off)
    rng = np.random.default_rng(3)
    sd = SD_PLANE / np.sqrt(10)
    c_plane = np.diag(sd**2)
    z = []
    for _ in range(80):
        theta = _pose(rng)
        parts = [_scan(rng, theta) for _ in range(10)]
        rays = LabelledRays(*(np.concatenate([getattr(p, f) for p in parts])
                              for f in ("origin", "direction", "label", "ext")))
        n, d = _plane_off(theta, rng.normal(0.0, sd))
        start = theta.copy()
        start[3] += rng.normal(0.0, np.deg2rad(0.03))
        out = label_posterior(rays, BOARD, start, np.deg2rad(0.03), (n, d, c_plane), 10, rng)
        assert out is not None
        mean, cov = out
        z.append((mean - theta) / np.sqrt(np.diag(cov)))
    chi2 = np.mean(np.square(z), axis=0)
    assert np.all(chi2 > 0.4) and np.all(chi2 < 1.0 + 4 * np.sqrt(2 / 80)), chi2
    assert np.max(np.abs(z)) < 5.0


def test_labels_that_rule_out_the_ranges_plane():
    # the ranges' plane 6 mm short: the board's hits at one side edge and misses at the other
    # are then closer together than the board is wide, for every roll. The posterior comes from
    # the plane draws the labels allow and still holds the truth.
    rng = np.random.default_rng(1)
    c_plane = np.diag(np.array([np.deg2rad(0.1), np.deg2rad(0.1), 3e-3]) ** 2)
    wide = np.deg2rad(np.linspace(-4.0, 4.0, 401))
    for _ in range(50):
        theta = _pose(rng)
        rays = _scan(rng, theta)
        n, d = _plane_off(theta, np.array([0.0, 0.0, -6e-3]))
        if rays.in_plane(n, d, BOARD, theta[3] + wide) is None:
            break
    else:
        pytest.fail("no seeded scene whose labels rule out a plane 6 mm short")
    out = label_posterior(rays, BOARD, theta, np.deg2rad(0.3), (n, d, c_plane), 1, rng)
    assert out is not None
    mean, cov = out
    err = (mean - theta)[[3, 0, 2, 1]]
    sd = np.sqrt(np.diag(cov))[[3, 0, 2, 1]]
    assert np.all(np.abs(err) < 4 * sd), (err, sd)
    # the labels moved the distance towards the truth
    assert abs(mean[1] - theta[1]) < 6e-3


def test_gauss_hermite_rule_integrates_a_gaussians_moments():
    # the rule's weights sum to 1 and reproduce the Gaussian's mean and covariance exactly
    centre = np.array([0.01, -0.02, 0.003])
    a = np.array([[1.0, 0.0, 0.0], [0.3, 2.0, 0.0], [-0.1, 0.2, 0.5]]) * 1e-3
    cov = a @ a.T
    nodes, log_q = gauss_hermite(centre, cov, 3)
    w = np.exp(log_q)
    assert nodes.shape == (27, 3)
    assert w.sum() == pytest.approx(1.0)
    np.testing.assert_allclose(w @ nodes, centre, atol=1e-15)
    dev = nodes - centre
    np.testing.assert_allclose((w[:, None] * dev).T @ dev, cov, atol=1e-15)


def test_per_laser_directions_span_the_plane_given_the_offset_beside_w():
    # with per-laser offsets the joint profile runs over the whole plane given b: w and two
    # directions independent of it under the ranges' conditional, one sigma each, the one the
    # offsets widen most first (here tilt: the noise alone holds it 10 times better)
    c_noise = np.diag([1e-7, 1e-7, 1e-6])
    lean = np.array([0.2, 1.0, 0.1]) * 1e-3
    c_cond = c_noise + np.outer(lean, lean) + np.diag([1e-9, 0.0, 1e-9])
    w = np.array([3e-4, 0.0, 1e-3])
    w /= np.sqrt(w @ np.linalg.solve(c_cond, w))
    offset = OffsetModel(0.0, np.zeros(3), 1e-6, c_noise=c_noise)
    axes = laser_directions(offset, c_cond, w)
    assert len(axes) == 2
    basis = np.column_stack([w, *axes])
    # independent and one sigma each: together they are c_cond
    np.testing.assert_allclose(basis @ basis.T, c_cond, rtol=1e-9, atol=1e-15)
    share = [1.0 - a @ np.linalg.solve(c_cond, c_noise) @ np.linalg.solve(c_cond, a)
             for a in axes]
    assert share[0] > 0.5 > share[1]
    assert abs(axes[0][1]) > 3 * abs(axes[0][0])  # mostly the lean: tilt
    # without per-laser offsets nothing more is profiled
    assert laser_directions(OffsetModel(0.0, np.zeros(3), 1e-6), c_cond, w) == []


def test_near_is_the_binding_masks_subset_and_split():
    """`LabelledRays.near` (compiled: `moments.binding_rays`) against its numpy version:
    board coordinates, `binding`'s masks, `select`, and the subset's own split into hits and
    misses, bit for bit, at poses about the labels' and off them, for reaches up to 4 deg;
    rays with origins off the centre (a laser's vertical offset)."""
    from align.geometry import lidar_up
    from align.posterior.hit_miss import binding

    rng = np.random.default_rng(12)
    for k in range(40):
        theta = _pose(rng)
        rays = _scan(rng, theta)
        if k % 2:
            o = rays.origin.copy()
            o[:, 2] = rng.choice([-0.0254, 0.0, 0.0127], len(o))
            rays = LabelledRays(o, rays.direction, rays.label, rays.ext + 1e-3 * rng.random(
                rays.ext.shape), rng.random(len(o)))
        ref = theta + rng.normal(size=6) * [0.01, 0.003, 0.01, 0.01, 0.003, 0.003]
        reach = float(rng.uniform(0.0, np.deg2rad(4.0)))
        got = rays.near(BOARD, ref, reach)
        x, z, _ = board_coordinates(ref, rays.origin, rays.direction)
        vx, vz = lidar_up(ref)
        arm = (0.5 * BOARD.diagonal + 0.2) * reach
        want = rays.select(binding(BOARD, x, z, rays.label, 0.02 + 0.08 * abs(vx) + arm,
                                   0.02 + 0.08 * abs(vz) + arm))
        assert 0 < len(want.label) < len(rays.label)
        for a, b in zip((got.origin, got.direction, got.label, got.ext, got.odds),
                        (want.origin, want.direction, want.label, want.ext, want.odds),
                        strict=True):
            np.testing.assert_array_equal(a, b)
        split = [np.ascontiguousarray(a[m], dtype=np.float64)
                 for m in (want.label == 1, want.label == 0)
                 for a in (want.origin, want.direction, want.ext)]
        for a, b in zip(got._split, split, strict=True):
            np.testing.assert_array_equal(a, b)
