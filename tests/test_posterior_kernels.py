"""The hit/miss posterior's compiled kernel (`align.posterior.moments.plane_posteriors`)
against the numpy version (`tests.naive.plane_posterior_row`: `in_plane_posterior` per plane,
then the pose of its mean), on synthetic VLP-16 scans whose labels are exact:
many planes about the true one in one call, with the plate's side face widening the edges, a
roll prior, and planes no roll explains. The same numbers to rounding (the kernel's sums run in
loop order, numpy's pairwise or in BLAS's order)."""

from __future__ import annotations

import numpy as np
import pytest

from align.board import BoardSpec
from align.floats import plane_rows, plane_rows_of
from align.geometry import board_coordinates, plane_of_pose
from align.plane import fit as plane
from align.posterior import moments
from align.posterior.hit_miss import LabelledRays
from tests import naive

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
    # the hits' origins, directions and widenings, then the misses'
    split = [np.ascontiguousarray(a[m], dtype=np.float64)
             for m in (rays.label == 1, rays.label == 0)
             for a in (rays.origin, rays.direction, rays.ext)]
    rows = moments.plane_posteriors(*split, normals, ds, rolls, weight,
                                     BOARD.width / 2, BOARD.height / 2, np.empty(0))
    assert rows.shape == (len(ds), moments.WIDTH)
    found = 0
    for row, n, d in zip(rows, normals, ds, strict=True):
        ref = naive.plane_posterior_row(rays, n, float(d), BOARD, rolls, weight if prior else None)
        if ref is None:
            assert row[moments.OK] == 0.0
            continue
        found += 1
        scale = np.maximum(np.abs(ref), 1e-6)  # covariances' entries of 1e-8: absolute
        np.testing.assert_allclose(row, ref, rtol=1e-10, atol=1e-12 * scale.max())
    assert found >= 8, found  # most planes near the true one are consistent
    assert rows[-1, moments.OK] == 0.0


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
        np.testing.assert_allclose(pose, naive.plane_pose(n, float(d), post.mean), rtol=1e-12,
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
    r0, r2 = plane_rows_of(np.cos(rolls), np.sin(rolls), n)
    for k, roll in enumerate(rolls):
        a0, a2 = plane_rows(rolls[k:k + 1], n)
        np.testing.assert_array_equal(r0[k], a0[0])
        np.testing.assert_array_equal(r2[k], a2[0])
        rot = rotation(*pose_from_plane(n, 2.0, roll)[3:])
        np.testing.assert_allclose(r0[k], rot[0], atol=1e-12)
        np.testing.assert_allclose(r2[k], rot[2], atol=1e-12)


@pytest.fixture(scope="module")
def twin_batches():
    """`moments.plane_posteriors`' real inputs: the default estimate of twin scans (the
    paper's yaw sweep's bench, divergence and mixed returns on, as the demo has them) at three
    stage yaws, every batch of planes it asks for, captured around the real kernel."""
    from align.api import estimate
    from scenarios import plans
    from scenarios.bench import SimBench
    from scenarios.runner import visit

    plan = plans.yaw_sweep(scans=2)
    bench = SimBench(seed=0)
    bench.home()
    batches = []
    kernel = moments.plane_posteriors

    def capture(*args):
        batches.append(args)
        return kernel(*args)

    moments.plane_posteriors = capture
    try:
        for i in (0, 10, 20):  # -10, 0 and +10 deg
            visit(bench, plan.references[i])
            bench.prepare(i, 0)
            for scan in bench.scans(2):
                estimate(scan)
    finally:
        moments.plane_posteriors = kernel
    assert len(batches) >= 6
    return batches


def test_label_moments_equal_every_label_on_twin_scans(twin_batches):
    # label_moments leaves out the labels that cannot bind (on the whole grid, then per block
    # of rolls): on every plane the estimate asked about, the same floats, bit for bit, as
    # every hit and miss at every roll
    planes = 0
    for (hit_o, hit_u, hit_ext, miss_o, miss_u, miss_ext, normals, ds, rolls, _, w2,
         h2, _) in twin_batches:
        for n, d in zip(normals, ds, strict=True):
            ph = moments.plane_points(hit_o, hit_u, n, d)
            pm = moments.plane_points(miss_o, miss_u, n, d)
            r0, r2 = plane_rows_of(np.cos(rolls), np.sin(rolls), n)
            got = moments.label_moments(ph, pm, hit_ext, miss_ext, r0, r2, w2, h2)
            ref = naive.moments_every_label(ph, pm, hit_ext, miss_ext, r0, r2, w2, h2)
            np.testing.assert_array_equal(got, ref)
            planes += 1
            hits, misses = moments.binding_labels(ph, pm, moments.box_limits(hit_ext, w2, h2),
                                                   moments.box_limits(miss_ext, w2, h2), r0, r2)
            assert len(hits) < len(ph) and len(misses) < len(pm)  # some are left out
    assert planes >= 60, planes


def test_soft_moments_equal_their_sum_over_every_label(twin_batches):
    # soft_moments reuses the binding labels its choice of soft hits found and, at the rolls
    # where a subset's hits' box is the whole set's, the whole set's moments: the same floats
    # as the sum over subsets of every label's moments. The estimate's own odds, and odds of
    # 0.5 on a few random hits (more subsets weighed, at rolls where they bind and where not)
    rng = np.random.default_rng(2)
    weighed = 0
    for (hit_o, hit_u, hit_ext, miss_o, miss_u, miss_ext, normals, ds, rolls, _, w2,
         h2, odds) in twin_batches:
        for variant in range(2):
            if variant:
                odds = np.zeros(len(hit_o))
                odds[rng.choice(len(hit_o), min(6, len(hit_o)), replace=False)] = 0.5
            if len(odds) == 0:
                continue
            soft = moments.soft_hits(odds)
            for n, d in list(zip(normals, ds, strict=True))[::4]:
                ph = moments.plane_points(hit_o, hit_u, n, d)
                pm = moments.plane_points(miss_o, miss_u, n, d)
                r0, r2 = plane_rows_of(np.cos(rolls), np.sin(rolls), n)
                got = moments.soft_moments(ph, pm, hit_ext, miss_ext, r0, r2, w2, h2, odds,
                                            soft)
                ref = naive.soft_every_label(ph, pm, hit_ext, miss_ext, r0, r2, w2, h2, odds, soft)
                np.testing.assert_array_equal(got, ref)
                hits, _ = moments.binding_labels(ph, pm, moments.box_limits(hit_ext, w2, h2),
                                                  moments.box_limits(miss_ext, w2, h2), r0, r2)
                weighed += len(moments.binding_soft(ph, pm, hit_ext,
                                                      moments.box_limits(miss_ext, w2, h2), r0,
                                                      r2, w2, h2, soft, hits)[0]) > 0
    assert weighed >= 10, weighed
