"""The board search's, the plane's and the paper's compiled kernels against plain numpy
references (tests/naive.py), on real scans: the same clusters, the same label numbers, the same
statistics bit for bit (so the same board chosen: `find_board` sees the clustering through
nothing else). A change to either side shows as a difference.
"""

from __future__ import annotations

import numpy as np
import pytest

import align
from align.baselines.kernels import corner_jacobian, corner_residuals
from align.baselines.paper import feature_points
from align.floats import plane_rows
from align.geometry import unwrap
from align.plane.fit import ransac
from align.search.board import (
    FLAT_BAND,
    PLANE_HYPOTHESES,
    PLANES_PER_CLUSTER,
    planar_part,
    rectangle_fit,
)
from align.search.cluster_kernels import (
    cluster_members,
    in_firing_order,
    in_ring_block,
    total_variance,
)
from align.search.clusters import (
    cluster,
    firing_grid,
    labels_grid,
)
from align.search.rings import consecutive_ring_block
from align.search.roll import COARSE_STEP, TOLERANCE, left_out
from align.search.roll_kernels import best_roll, rel_azimuth
from tests import naive
from tests.conftest import DATA_DIR
from twin.core.scan import Scan
from twin.lidar.capture import open_pcap, read_capture
from twin.lidar.pcd import read_pcd_scans

ACFR_BOARD = align.BoardSpec(0.61, 0.85, thickness=0.0)


@pytest.fixture(scope="module")
def real_scans() -> list[tuple[Scan, align.BoardSpec, align.Hints]]:
    """The five ACFR chessboard scans (a VLP-16 in a lab, a board held up) and the sample
    capture's rotations (a VLP-16 in a street, no board), with the board each is searched for."""
    acfr = [(read_pcd_scans(p)[0], ACFR_BOARD, align.Hints(expected_distance=1.8))
            for p in sorted((DATA_DIR / "acfr-vlp16").glob("pose*_full.pcd"))]
    street = [(s, align.BoardSpec(), align.Hints()) for s in read_capture(
        open_pcap(DATA_DIR / "vlp16-strongest-10hz.pcap"), cut_azimuth=None).scans]
    assert len(acfr) == 5 and street
    return acfr + street


def search_mask(scan: Scan, board: align.BoardSpec, hints: align.Hints) -> np.ndarray:
    """The returns `align.search.board.find_board` clusters."""
    m = scan.valid & (scan.distance >= hints.min_distance)
    if hints.expected_distance is not None:
        m &= np.abs(scan.distance - hints.expected_distance) <= board.diagonal + 0.5
    return m


def test_grid_clusters_match_the_numpy_reference_on_real_scans(real_scans):
    """Labels and statistics of the compiled clustering equal the numpy passes' exactly, on
    every real scan, for the search region find_board uses and for every return."""
    compared = 0
    for scan, board, hints in real_scans:
        grid = firing_grid(scan)
        assert grid is not None  # both captures are on the sensor's firing grid
        short = min(board.width, board.height)
        for ok in (search_mask(scan, board, hints), scan.valid):
            want_labels, want = naive.labels_grid(scan, grid, ok, board.diagonal, short)
            got_labels, got = labels_grid(scan, grid, ok, board.diagonal, short)
            np.testing.assert_array_equal(got_labels, want_labels)
            for key in ("count", "distance", "rings"):
                assert got[key].dtype == want[key].dtype, key
                np.testing.assert_array_equal(got[key], want[key], err_msg=key)
            compared += int(want["count"].size)
    assert compared > 100  # the scans had clusters to compare


def test_rectangle_fit_matches_the_numpy_reference_on_real_clusters(real_scans):
    """held, fill and free of every real cluster the board search weighs (each candidate's
    planes) equal the numpy reference's exactly."""
    weighed = 0
    for scan, board, hints in real_scans:
        labels, st = cluster(scan, search_mask(scan, board, hints), board.diagonal,
                                     min(board.width, board.height))
        rng = np.random.default_rng(0)
        for lab in np.flatnonzero((st["count"] >= 20) & (st["rings"] >= 2)):
            rest = np.flatnonzero(labels == lab)
            for _ in range(PLANES_PER_CLUSTER):
                if len(rest) < 3:
                    break
                on = planar_part(scan.xyz[rest], rng)
                sel, rest = rest[on], rest[~on]
                if len(sel) < 3:
                    continue
                assert rectangle_fit(scan, sel, board) == naive.rectangle_fit(
                    scan, sel, board)
                weighed += 1
    assert weighed > 50


def test_best_roll_is_the_argmin_of_left_out_on_awkward_point_sets():
    """`best_roll` against `left_out` and `np.argmin` where its bound is put to
    the test: points on a coarse lattice (many equal counts across rolls: the first of equal
    minima), strays far off the plane or far along it, a handful of points, clusters much
    larger than the box."""
    board = align.BoardSpec()
    rolls = np.arange(-np.pi / 2, np.pi / 2, COARSE_STEP)
    grow = TOLERANCE + 0.5 * board.diagonal * np.sin(0.5 * COARSE_STEP)
    rng = np.random.default_rng(20)
    for case in range(200):
        n = rng.normal(size=3)
        n[1] = abs(n[1]) + 2.0
        n /= np.linalg.norm(n)
        e1 = np.cross(n, [0.0, 0.0, 1.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(n, e1)
        size = rng.uniform(0.2, 2.5, 2)
        uv = rng.uniform(-0.5, 0.5, (int(rng.integers(3, 300)), 2)) * size
        if case % 3 == 0:
            uv = np.round(uv / 0.05) * 0.05
        c, s = np.cos(rng.uniform(0, np.pi)), np.sin(rng.uniform(0, np.pi))
        uv = uv @ np.array([[c, s], [-s, c]])
        p = rng.uniform(0.5, 20.0) * n + uv[:, :1] * e1 + uv[:, 1:] * e2
        if case % 2:
            p[:3] += rng.normal(size=(min(3, len(p)), 3))
        if case % 5 == 4:  # a stray far off: the histogram bounds' exact fallback
            p[-1] += 30.0 * e1
        left, tx, tz = left_out(p, n, board, rolls, grow)
        b = int(np.argmin(left))
        r0, r2 = plane_rows(rolls, n)
        got = best_roll(p, r0, r2, board.width + 2 * grow, board.height + 2 * grow)
        assert got == (b, int(left[b]), float(tx[b]), float(tz[b])), case


def test_ransac_gives_plane_ransacs_plane_on_real_clusters(real_scans):
    """`ransac` (scored by `ransac_best`) against numpy's scoring of the same draws
    (`tests.naive.ransac`) on every real cluster of three returns or more, the same generator
    state: the same normal, distance and inliers (bit for bit on this machine's BLAS; at worst
    a point within 1e-15 m of the band's edge could differ)."""
    compared = 0
    for scan, board, hints in real_scans:
        labels, st = cluster(scan, search_mask(scan, board, hints), board.diagonal,
                                     min(board.width, board.height))
        for lab in np.flatnonzero(st["count"] >= 3):
            pts = scan.xyz[labels == lab]
            for seed in (0, 1):
                n0, d0, in0 = naive.ransac(pts, FLAT_BAND, np.random.default_rng(seed),
                                           PLANE_HYPOTHESES)
                n1, d1, in1 = ransac(pts, FLAT_BAND, np.random.default_rng(seed),
                                     PLANE_HYPOTHESES)
                np.testing.assert_array_equal(in1, in0)
                np.testing.assert_array_equal(n1, n0)
                assert d1 == d0
                compared += 1
    assert compared > 100
    with pytest.raises(ValueError):
        ransac(np.zeros((5, 3)), 0.04, np.random.default_rng(0), 10)


def test_the_warm_up_compiles_every_estimator_kernel():
    """`scenarios.warmup` (run by make setup) leaves no kernel of the board search, the plane
    and the baselines for a command to compile: each one the estimator calls has its signature
    after it. (The helpers with a leading underscore, and the leaf's `align.floats` that a module
    imports, are compiled into their callers.)"""
    from numba.core.registry import CPUDispatcher

    from align.baselines import kernels as baseline_kernels
    from align.fit import lsq_kernels
    from align.plane import kernels as plane_kernels
    from align.search import cluster_kernels, roll_kernels
    from scenarios.warmup import warm_up

    warm_up()
    public = {name: f for mod in (cluster_kernels, plane_kernels, baseline_kernels)
              for name, f in vars(mod).items()
              if isinstance(f, CPUDispatcher) and not name.startswith("_")
              and f.py_func.__module__ == mod.__name__}  # the leaf's, imported: inlined
    public |= {"best_roll": roll_kernels.best_roll, "rectangle_rays": roll_kernels.rectangle_rays,
               "fit_residuals": lsq_kernels.fit_residuals}
    assert {"grid_clusters", "best_roll", "rectangle_rays", "ransac_best", "plane_band",
            "in_ring_block", "corner_points", "corner_residuals", "corner_jacobian",
            "cluster_members", "in_firing_order", "fit_residuals"} <= set(public)
    assert [name for name, f in public.items() if not f.signatures] == []


def test_in_ring_block_is_isin_of_the_consecutive_ring_block():
    """`in_ring_block` against np.isin of `consecutive_ring_block` (the board's
    rings for `on_board_rings` and the paper's method): random ring lists with gaps, ties
    between blocks, nothing counted, and the real clusters' rings."""
    rng = np.random.default_rng(21)
    cases = []
    for _ in range(300):
        k = int(rng.integers(0, 60))
        rings = rng.choice(rng.permutation(16)[:int(rng.integers(1, 17))], size=k).astype(
            np.uint8)
        cases.append((rings, rng.random(k) < rng.uniform(0.3, 1.0)))
    cases.append((np.array([0, 0, 2, 2, 5], dtype=np.uint8), np.ones(5, dtype=bool)))  # a tie
    cases.append((np.array([3, 4], dtype=np.uint8), np.zeros(2, dtype=bool)))
    for rings, counted in cases:
        want = np.isin(rings, consecutive_ring_block(rings[counted]))
        np.testing.assert_array_equal(in_ring_block(rings, counted), want)


def test_corner_points_match_the_numpy_reference_on_real_clusters(real_scans):
    """The paper's feature points from the compiled pass equal the numpy version's bit for bit
    (the same points, the same projections) on every real cluster's main plane, and on a few
    of its points."""
    compared = 0
    for scan, board, hints in real_scans:
        labels, st = cluster(scan, search_mask(scan, board, hints), board.diagonal,
                                     min(board.width, board.height))
        for lab in np.flatnonzero(st["count"] >= 10):
            pts = scan.xyz[labels == lab]
            n, d, inl = ransac(pts, 0.03, np.random.default_rng(0), 50)
            for sub in (pts[inl], pts[inl][:4], pts[::3]):
                want_p, want_i = naive.feature_points(sub, n, d)
                got_p, got_i = feature_points(sub, n, d)
                np.testing.assert_array_equal(got_i, want_i)
                np.testing.assert_array_equal(got_p, want_p)
                compared += 1
    assert compared > 100


def test_corner_residuals_and_jacobian_match_numpy():
    """The paper's corner residuals and their Jacobian (`kernels.corner_residuals`,
    `corner_jacobian`) equal the numpy expressions they replaced, bit for bit, at random poses
    and corner sets (as the Levenberg-Marquardt of `paper.levenberg_marquardt` meets them)."""
    rng = np.random.default_rng(22)
    p_o = align.BoardSpec().corners()
    for _ in range(300):
        beta = np.concatenate((rng.normal(0, 1, 3), rng.normal(0, 0.2, 3)))
        p_l = rng.normal(0, 1, (4, 3)) + np.array([0.0, 2.5, 0.0])
        np.testing.assert_array_equal(corner_residuals(beta, p_l, p_o),
                                      naive.corner_residuals(beta, p_l, p_o))
        want = naive.corner_jacobian(beta, p_l, p_o)
        got = corner_jacobian(beta, p_l, p_o)
        np.testing.assert_array_equal(got, want)
        assert np.array_equal(np.signbit(got), np.signbit(want))


def test_rel_azimuth_is_unwrap_bit_for_bit():
    """The compiled pass's relative azimuth (`roll_kernels.rel_azimuth`, its remainder's shortcuts)
    against `align.geometry.unwrap`, on random azimuths and centres and at the shortcuts' edges."""
    rng = np.random.default_rng(23)
    two_pi = 2 * np.pi
    edges = np.array([0.0, two_pi, 2 * two_pi, -two_pi]) - np.pi
    az = np.concatenate((rng.uniform(-10, 20, 3000), rng.uniform(0, two_pi, 3000),
                         np.nextafter(edges, np.inf), np.nextafter(edges, -np.inf), edges))
    for centre in (*rng.uniform(-np.pi, np.pi, 5), 0.0, np.pi, -np.pi):
        want = unwrap(az, centre)
        taken = np.zeros(1, dtype=np.int64)
        got = np.array([rel_azimuth(a, centre, taken) for a in az])
        assert np.array_equal(got, want) and np.array_equal(np.signbit(got), np.signbit(want))
        assert 0 < taken[0] < len(az) // 2  # the remainder only outside the shortcuts


def test_cluster_members_match_the_stable_argsort_on_real_scans(real_scans):
    """`kernels.cluster_members` against the numpy grouping `find_board` used (a stable argsort
    of the candidates' labels and a searchsorted), for the board search's candidates and for
    every cluster of each real scan."""
    for scan, board, hints in real_scans:
        labels, st = cluster(scan, search_mask(scan, board, hints), board.diagonal,
                                     min(board.width, board.height))
        for cand in (st["count"] >= 20, st["count"] > 0, np.zeros(len(st["count"]), bool)):
            ids = np.flatnonzero(cand)
            is_cand = np.zeros(len(cand) + 1, dtype=bool)
            is_cand[ids + 1] = True
            want = np.flatnonzero(is_cand[labels + 1])
            want = want[np.argsort(labels[want], kind="stable")]
            want_bounds = np.searchsorted(labels[want], np.append(ids, len(cand)))
            got, got_bounds = cluster_members(labels, cand)
            np.testing.assert_array_equal(got, want)
            np.testing.assert_array_equal(got_bounds, want_bounds)


def test_in_firing_order_is_the_grids_comparison(real_scans):
    """`kernels.in_firing_order` against the (sequences, lasers) comparison with np.arange it
    replaced, on the real scans as they are and with a firing dropped or two lasers swapped."""
    rng = np.random.default_rng(24)
    for scan, _, _ in real_scans:
        nl = scan.lasers.n_lasers
        ids = [scan.laser_id, np.delete(scan.laser_id, int(rng.integers(nl, len(scan))))]
        swapped = scan.laser_id.copy()
        k = int(rng.integers(0, len(scan) - 1))
        swapped[[k, k + 1]] = swapped[[k + 1, k]]
        ids.append(swapped)
        for lid in ids:
            k0 = int(np.argmax(lid[:nl] == 0))
            m = (len(lid) - k0) // nl
            grid = lid[k0:k0 + nl * m].reshape(m, nl)
            want = np.array_equal(grid, np.broadcast_to(np.arange(nl, dtype=lid.dtype),
                                                        grid.shape))
            assert in_firing_order(lid, k0, m, nl) == want


def test_centre_is_numpys_mean_and_difference_on_real_clusters(real_scans):
    """`centre` (the mean and the centred points of `plane.fit_lsq`) against
    points.mean(axis=0) and points - mean, bit for bit, on runs of returns of every length
    from 1 to a few thousand."""
    from align.baselines.kernels import centre

    rng = np.random.default_rng(3)
    for scan, _, _ in real_scans:
        xyz = scan.xyz[scan.valid]
        for n in (1, 2, 3, 7, 64, 299, 586, 1000, 4001):
            i0 = int(rng.integers(0, max(len(xyz) - n, 1)))
            p = np.ascontiguousarray(xyz[i0:i0 + n])
            c, out = centre(p)
            np.testing.assert_array_equal(c, p.mean(axis=0))
            np.testing.assert_array_equal(out, p - p.mean(axis=0))


def test_total_variance_is_the_numpy_sums_bit_for_bit(real_scans):
    """`total_variance` against the numpy expression `board_score` used (per
    coordinate c = c - c.sum() / N, then (c * c).sum() / N, summed): numpy's pairwise sums
    reproduced for every length from a few returns to a whole scan (blocks of 8, of 128 and
    the halving above), on the real scans' coordinates."""
    rng = np.random.default_rng(5)
    for scan, _, _ in real_scans[:3]:
        valid = np.flatnonzero(scan.valid)
        for n in (*range(1, 140), 255, 256, 257, 586, 1000, 4097, len(valid)):
            sel = np.sort(rng.choice(valid, min(n, len(valid)), replace=False))
            want = 0.0
            for c in (scan.x[sel], scan.y[sel], scan.z[sel]):
                c = c - c.sum() / len(c)
                want += float((c * c).sum()) / len(c)
            assert total_variance(scan.x, scan.y, scan.z, sel) == want, n
