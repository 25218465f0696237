"""align.posterior.moments: the consistent set's area and moments against a brute-force raster,
and the in-plane posterior's roll against the labels' geometry."""

from __future__ import annotations

import numpy as np
import pytest

from align.floats import plane_rows
from align.posterior import moments
from tests import naive

W2, H2 = 0.45, 0.27


def _edge_rays(rng, n_ring=5, step=0.009):
    """Rays of a few rings sampled every ``step`` m across a board at t = (0.01, -0.02):
    hits and misses near the four edges, with a random side-face widening."""
    t_true = np.array([0.01, -0.02])
    hits, misses = [], []
    z_rings = np.linspace(-0.33, 0.33, n_ring + 2)  # rings above and below the board too
    for z in z_rings + rng.uniform(-0.01, 0.01, len(z_rings)):
        x0 = rng.uniform(0, step)
        for x in np.arange(-0.52 + x0, 0.52, step):
            inside = abs(x + t_true[0]) <= W2 and abs(z + t_true[1]) <= H2
            (hits if inside else misses).append((x, 0.0, z))
    hits, misses = np.array(hits), np.array(misses)
    return hits, misses, rng.uniform(0, 1e-3, (len(hits), 4)), rng.uniform(0, 1e-3,
                                                                              (len(misses), 4))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_label_moments_match_a_raster(seed):
    rng = np.random.default_rng(seed)
    p_hit, p_miss, e_hit, e_miss = _edge_rays(rng)
    # extra misses at random near the corners: boxes that cut the hits' box partly
    corners = np.array([(sx * W2, 0.0, sz * H2) for sx in (-1, 1) for sz in (-1, 1)])
    extra = corners[rng.integers(0, 4, 6)] * 1.0 + np.column_stack(
        (rng.uniform(-0.04, 0.04, 6), np.zeros(6), rng.uniform(-0.04, 0.04, 6)))
    extra[:, 0] += np.sign(extra[:, 0]) * 0.02  # outside the board in x: a real miss
    p_miss = np.vstack((p_miss, extra))
    e_miss = np.vstack((e_miss, np.zeros((6, 4))))
    r0, r2 = np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 0.0, 1.0]])
    m = moments.label_moments(p_hit, p_miss, e_hit, e_miss, r0, r2, W2, H2)[0]
    a, mx, mz, vx, vz, cxz = naive.raster(p_hit, p_miss, e_hit, e_miss, W2, H2)
    assert m[0] > 0
    assert m[0] == pytest.approx(a, rel=0.005)
    got = np.array([m[1], m[2]]) / m[0]
    np.testing.assert_allclose(got, [mx, mz], atol=5e-5)
    var = np.array([m[3] / m[0] - got[0] ** 2, m[4] / m[0] - got[1] ** 2])
    np.testing.assert_allclose(var, [vx, vz], rtol=0.01, atol=1e-9)
    assert m[5] / m[0] - got[0] * got[1] == pytest.approx(cxz, abs=2e-8)


def test_inconsistent_labels_give_no_posterior():
    # a hit far to the left and another far to the right of a 0.9 m board: no position fits
    p_hit = np.array([[-0.6, 0.0, 0.0], [0.6, 0.0, 0.0]])
    labels = np.ones(2, dtype=np.int8)
    rolls = np.linspace(-0.01, 0.01, 21)
    assert moments.in_plane_posterior(np.array([0.0, 1.0, 0.0]), p_hit, labels,
                                       np.zeros((2, 4)), 0.9, 0.54, rolls) is None


def test_posterior_brackets_the_true_roll_and_position():
    # the rays' points on the plane y = 2.5 (normal e_y: roll 0 gives X = p_x, Z = p_z); the
    # board rolled by 0.5 deg and shifted: the posterior's mean is near the truth, within a
    # few of its standard deviations
    rng = np.random.default_rng(5)
    roll, t = np.deg2rad(0.5), np.array([0.012, -0.03])
    pts, lab = [], []
    for z in np.arange(-0.35, 0.35, 0.087) + 0.01:
        for x in np.arange(-0.55, 0.55, 0.0087) + rng.uniform(0, 0.0087):
            # board coordinates of this point for the true roll (R's rows at roll, n = e_y)
            bx = np.cos(roll) * x + np.sin(roll) * z + t[0]
            bz = -np.sin(roll) * x + np.cos(roll) * z + t[1]
            pts.append((x, 2.5, z))
            lab.append(1 if abs(bx) <= W2 and abs(bz) <= H2 else 0)
    pts, lab = np.array(pts), np.array(lab, dtype=np.int8)
    rolls = np.deg2rad(np.linspace(-1.5, 2.5, 401))
    post = moments.in_plane_posterior(np.array([0.0, 1.0, 0.0]), pts, lab,
                                       np.zeros((len(pts), 4)), 0.9, 0.54, rolls)
    assert post is not None
    sd = np.sqrt(np.diag(post.cov))
    err = post.mean - np.array([roll, t[0], t[1]])
    assert np.all(np.abs(err) < 4 * sd), (err, sd)
    assert sd[0] < np.deg2rad(0.5) and sd[1] < 0.005
    assert post.support[0] <= roll <= post.support[1]


def test_label_moments_over_a_roll_grid_match_roll_by_roll():
    # label_moments leaves out, per block of rolls, the labels that cannot bind anywhere in
    # it: a grid call must give exactly what each roll alone gives (a block of one roll), over
    # rolls wide enough that the blocks' bounds are loose, for a board off the plane's origin
    # (as seen from the LiDAR: points 2.5 m away) with random side-face widenings
    rng = np.random.default_rng(7)
    p_hit, p_miss, e_hit, e_miss = _edge_rays(rng)
    offset = np.array([0.3, 2.5, -0.1])
    p_hit, p_miss = p_hit + offset, p_miss + offset
    n = np.array([0.0, 1.0, 0.0])
    rolls = np.deg2rad(np.linspace(-3.0, 3.0, 301))
    r0, r2 = plane_rows(rolls, n)
    args = (p_hit, p_miss, e_hit, e_miss)
    grid = moments.label_moments(*args, r0, r2, W2, H2)
    one = np.vstack([moments.label_moments(*args, r0[k:k + 1], r2[k:k + 1], W2, H2)
                     for k in range(len(rolls))])
    assert np.count_nonzero(grid[:, 0]) > 10  # some rolls are consistent
    np.testing.assert_array_equal(grid, one)


def test_binding_labels_keep_every_label_when_the_rows_do_not_turn_rigidly():
    # binding_labels' bound holds for rows of R that rotate in one plane; rows that do not (a
    # grid whose r2 is not r0 x n) must leave no label out
    rng = np.random.default_rng(4)
    p_hit, p_miss, e_hit, e_miss = _edge_rays(rng)
    rolls = np.deg2rad(np.linspace(-1.0, 1.0, 41))
    r0, r2 = plane_rows(rolls, np.array([0.0, 1.0, 0.0]))
    lim_h, lim_m = moments.box_limits(e_hit, W2, H2), moments.box_limits(e_miss, W2, H2)
    hits, misses = moments.binding_labels(p_hit, p_miss, lim_h, lim_m, r0, r2)
    assert len(hits) < len(p_hit) and len(misses) < len(p_miss)  # rigid: some left out
    bent = r2.copy()
    bent[20] += 1e-6  # no longer unit, nor r0 x n
    hits, misses = moments.binding_labels(p_hit, p_miss, lim_h, lim_m, r0, bent)
    np.testing.assert_array_equal(hits, np.arange(len(p_hit)))
    np.testing.assert_array_equal(misses, np.arange(len(p_miss)))


def test_soft_hits_weigh_the_sets_without_them_as_a_raster_does():
    # two returns beside the right edge that may be a holder's: one cutting the board's
    # consistent positions in half, as likely off the board as on it (odds capped at 1), one
    # cutting less at odds 0.3 (it binds only once the first is off); one more below
    # `MIN_ODDS` stays a hard constraint. The exact sum over which of them are the board's must
    # match a raster of the product of their likelihoods
    rng = np.random.default_rng(3)
    p_hit, p_miss, e_hit, e_miss = _edge_rays(rng)
    zero_h, zero_m = np.zeros_like(e_hit), np.zeros_like(e_miss)
    _, mx, _, vx, _, _ = naive.raster(p_hit, p_miss, zero_h, zero_m, W2, H2)
    half = np.sqrt(3 * vx)  # the consistent t_x: about mx +- half
    extra = np.array([[W2 - mx, 0.0, 0.05], [W2 - mx - 0.5 * half, 0.0, -0.1]])
    p_hit = np.vstack((p_hit, extra))
    odds = np.zeros(len(p_hit))
    odds[-2:] = 4.0, 0.3
    odds[0] = 0.5 * moments.MIN_ODDS
    zero_h = np.zeros((len(p_hit), 4))
    r0, r2 = np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 0.0, 1.0]])
    soft = moments.soft_hits(odds)
    assert list(soft) == [len(p_hit) - 2, len(p_hit) - 1]
    got = moments.soft_moments(p_hit, p_miss, zero_h, zero_m, r0, r2, W2, H2, odds, soft)[0]
    want = naive.soft_raster(p_hit, p_miss, np.where(odds < moments.MIN_ODDS, 0.0, odds),
                              W2, H2)
    assert got[0] == pytest.approx(want[0], rel=0.005)
    np.testing.assert_allclose(got[1:3] / got[0], want[1:3] / want[0], atol=5e-5)
    np.testing.assert_allclose(got[3:] / got[0], want[3:] / want[0], rtol=0.01, atol=1e-8)
    # as hard labels they hold the board in the left half of its positions; as soft ones
    # the mean is pulled back towards the middle, and the set is wider
    hard = moments.label_moments(p_hit, p_miss, zero_h, zero_m, r0, r2, W2, H2)[0]
    assert hard[1] / hard[0] < mx - 0.3 * half
    assert hard[1] / hard[0] + 0.1 * half < got[1] / got[0] < mx
    assert got[3] / got[0] - (got[1] / got[0]) ** 2 > 1.5 * (hard[3] / hard[0]
                                                            - (hard[1] / hard[0]) ** 2)


def test_soft_hits_make_no_posterior_where_the_labels_allow_none():
    # a hit 12 mm past the right edge empties the set; its softness does not refill it (the
    # caller's stray rounds handle labels that contradict each other)
    rng = np.random.default_rng(3)
    p_hit, p_miss, _, _ = _edge_rays(rng)
    _, mx, _, _, _, _ = naive.raster(p_hit, p_miss, np.zeros((len(p_hit), 4)),
                                     np.zeros((len(p_miss), 4)), W2, H2)
    p_hit = np.vstack((p_hit, [[W2 - mx + 0.012, 0.0, 0.05]]))
    odds = np.zeros(len(p_hit))
    odds[-1] = 1.0
    r0, r2 = np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 0.0, 1.0]])
    args = (p_hit, p_miss, np.zeros((len(p_hit), 4)), np.zeros((len(p_miss), 4)), r0, r2, W2,
            H2)
    assert moments.label_moments(*args)[0, 0] == 0.0
    assert moments.soft_moments(*args, odds, moments.soft_hits(odds))[0, 0] == 0.0


def test_soft_moments_without_soft_hits_are_the_hard_ones():
    rng = np.random.default_rng(8)
    p_hit, p_miss, e_hit, e_miss = _edge_rays(rng)
    rolls = np.deg2rad(np.linspace(-1.0, 1.0, 41))
    r0, r2 = plane_rows(rolls, np.array([0.0, 1.0, 0.0]))
    odds = np.full(len(p_hit), 0.5 * moments.MIN_ODDS)
    odds[:3] = 0.5  # soft, but deep inside the board: they bind nowhere on the grid
    inner = (np.abs(p_hit[:, 0]) < 0.2) & (np.abs(p_hit[:, 2]) < 0.1)
    p_hit = np.vstack((p_hit[inner][:3], p_hit[~inner]))
    e_hit = np.vstack((e_hit[inner][:3], e_hit[~inner]))
    args = (p_hit, p_miss, e_hit, e_miss, r0, r2, W2, H2)
    np.testing.assert_array_equal(
        moments.soft_moments(*args, odds, moments.soft_hits(odds)),
        moments.label_moments(*args))
