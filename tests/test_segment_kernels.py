"""The compiled segmentation kernels (`align.kernels`) against plain numpy references, on real
scans: the same clusters, the same label numbers, the same statistics bit for bit (so the same
board chosen: `find_board` sees the clustering through nothing else).

The references are the numpy versions the kernels replaced (docs/align.md, "Where the time
goes"), kept here so that a change to either side shows as a difference.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

import align
from align import segment
from align.board import BoardSpec
from align.segment import (
    BRIDGE,
    CLUSTER_RADIUS_MIN,
    CLUSTER_RADIUS_PER_M,
    FILL_MARGIN,
    FLAT_BAND,
    LONG_RUN,
    MAX_AZIMUTH_GAP,
    SURROUND,
    unwrap,
    ring_radius_scale,
)
from tests.conftest import DATA_DIR
from twin.core.scan import Scan
from twin.lidar.capture import open_pcap, read_capture
from twin.lidar.pcd import read_pcd_scans

ACFR_BOARD = align.BoardSpec(0.61, 0.85, thickness=0.0)


def union_find_reference(n: int, a: np.ndarray, b: np.ndarray) -> tuple[int, np.ndarray]:
    """Connected components of a small graph (n nodes, edges a-b): (count, label per node).

    Minimum-label propagation with pointer jumping, vectorised: each node ends with the
    smallest node of its component; labels number the components in that order.
    """
    if len(a) > 20000:
        g = coo_matrix((np.ones(len(a), dtype=np.int8), (a, b)), shape=(n, n))
        return connected_components(g, directed=False)
    lab = np.arange(n)
    while True:
        new = lab.copy()
        np.minimum.at(new, a, lab[b])
        np.minimum.at(new, b, lab[a])
        new = new[new]
        if np.array_equal(new, lab):
            break
        lab = new
    _, lab = np.unique(lab, return_inverse=True)
    return int(lab.max()) + 1 if n else 0, lab


def labels_grid_reference(scan: Scan, grid: tuple[int, int], ok: np.ndarray, board_diagonal: float,
                 short_side: float) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """`segment._labels_grid` as numpy passes (the version before the compiled kernel)."""
    k0, m = grid
    nl = scan.lasers.n_lasers
    sl = slice(k0, k0 + nl * m)
    x, y, z = (a[sl].reshape(m, nl) for a in (scan.x, scan.y, scan.z))
    dist, az, okg = (a[sl].reshape(m, nl) for a in (scan.distance, scan.azimuth, ok))
    thr = np.maximum(CLUSTER_RADIUS_PER_M * dist, CLUSTER_RADIUS_MIN)
    thr *= thr
    ring_scale = ring_radius_scale(scan) ** 2

    def close(sa, sb, x=x, y=y, z=z, thr=thr, okg=okg, scale=1.0) -> np.ndarray:
        d2 = x[sa] - x[sb]
        d2 *= d2
        t = y[sa] - y[sb]
        t *= t
        d2 += t
        t = z[sa] - z[sb]
        t *= t
        d2 += t
        c = d2 < scale * np.minimum(thr[sa], thr[sb])
        c &= okg[sa]
        c &= okg[sb]
        return c

    # along each ring: each return and the laser's next return. Neighbouring firings join when
    # closer than the threshold; across firings without a return (a dark patch of the board
    # that drops out: a chessboard's black squares) when nothing else returned in between, the
    # ranges agree within the threshold and the gap is under `BRIDGE` of the board's smaller
    # side (a lost firing is not a gap in the surface). Laser-major order: a laser's firings
    # are contiguous.
    okf = okg.T.ravel()
    pos = np.flatnonzero(okf)
    n_run_max = len(pos)
    if n_run_max == 0:
        return np.full(len(scan), -1, dtype=np.int64), {
            k: np.zeros(0) for k in ("count", "distance", "rings")}
    xf, yf, zf, df = (a.T.ravel()[pos] for a in (x, y, z, dist))
    thr_f = thr.T.ravel()[pos]
    a, b = pos[:-1], pos[1:]
    d2 = (xf[1:] - xf[:-1]) ** 2 + (yf[1:] - yf[:-1]) ** 2 + (zf[1:] - zf[:-1]) ** 2
    t2 = np.minimum(thr_f[1:], thr_f[:-1])
    returned = np.cumsum(dist.T.ravel() > 0)  # returns of any kind up to each firing
    empty_between = returned[b - 1] - returned[a] == 0
    bridge2 = max(t2.max(initial=0.0), (BRIDGE * short_side) ** 2)
    link = (a // m == b // m) & np.where(
        b - a == 1, d2 < t2,
        empty_between & ((df[1:] - df[:-1]) ** 2 < t2) & (d2 < np.maximum(t2, bridge2)))
    start_flag = np.concatenate(([True], ~link))  # per return: does it start a run?
    run_of = np.cumsum(start_flag) - 1  # run id of each return
    n_run = int(run_of[-1]) + 1
    starts = pos[start_flag]
    ends = pos[np.concatenate((~link, [True]))]
    run = np.full(nl * m, -1, dtype=np.int64)
    run[pos] = run_of
    run = run.reshape(nl, m)  # run id of each firing (laser, sequence); -1 without a return
    # adjacent rings = the lasers of consecutive elevations: column pairs (la, lb)
    laser_of_ring = scan.lasers.laser_of_ring
    la, lb = laser_of_ring[:-1], laser_of_ring[1:]
    # columns in ring order once (one gather per array), then ring neighbours are slices
    lr = laser_of_ring.astype(np.intp)
    lv = close(np.s_[:, :-1], np.s_[:, 1:], x[:, lr], y[:, lr], z[:, lr], thr[:, lr],
               okg[:, lr], scale=ring_scale)  # (m, nl - 1)
    ra_l, rb_l = [run[la].T[lv]], [run[lb].T[lv]]
    daz_w = np.abs((az[0] - az[-1] + np.pi) % (2 * np.pi) - np.pi)
    wrap = close(np.s_[-1], np.s_[0]) & (daz_w < MAX_AZIMUTH_GAP)
    ra_l.append(run[:, -1][wrap])
    rb_l.append(run[:, 0][wrap])
    ra, rb = np.concatenate(ra_l), np.concatenate(rb_l)
    sums = (np.bincount(run_of, minlength=n_run).astype(np.float64),
            np.bincount(run_of, df, minlength=n_run))
    # a run longer than the board (the floor's ring, a wall) joins nothing: otherwise the board,
    # its stand and the floor ring at the stand's foot chain into one cluster
    laser_s, seq_s = np.divmod(starts, m)
    span = (az[ends % m, ends // m] - az[seq_s, laser_s]) % (2 * np.pi)
    long_run = span * sums[1] / np.maximum(sums[0], 1) > LONG_RUN * board_diagonal
    keep = ~(long_run[ra] | long_run[rb])
    n_comp, comp = union_find_reference(n_run, ra[keep], rb[keep])
    cnt = np.bincount(comp, sums[0], n_comp)
    ring_hit = np.zeros((n_comp, nl), dtype=bool)
    ring_hit[comp, scan.lasers.ring_of_laser[laser_s]] = True
    stats = {"count": cnt, "distance": np.bincount(comp, sums[1], n_comp) / np.maximum(cnt, 1),
             "rings": ring_hit.sum(axis=1)}
    labels = np.full(len(scan), -1, dtype=np.int64)  # -1: no cluster (or outside the grid)
    comp_x = np.append(comp, -1)  # run -1 (and firings without a return): label -1
    labels[sl].reshape(m, nl)[...] = comp_x[np.where(okg, run.T, -1)]
    return labels, stats


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
    """The returns `segment.find_board` clusters."""
    m = scan.valid & (scan.distance >= hints.min_distance)
    if hints.expected_distance is not None:
        m &= np.abs(scan.distance - hints.expected_distance) <= board.diagonal + 0.5
    return m


def test_grid_clusters_match_the_numpy_reference_on_real_scans(real_scans):
    """Labels and statistics of the compiled clustering equal the numpy passes' exactly, on
    every real scan, for the search region find_board uses and for every return."""
    compared = 0
    for scan, board, hints in real_scans:
        grid = segment._grid(scan)
        assert grid is not None  # both captures are on the sensor's firing grid
        short = min(board.width, board.height)
        for ok in (search_mask(scan, board, hints), scan.valid):
            want_labels, want = labels_grid_reference(scan, grid, ok, board.diagonal, short)
            got_labels, got = segment._labels_grid(scan, grid, ok, board.diagonal, short)
            np.testing.assert_array_equal(got_labels, want_labels)
            for key in ("count", "distance", "rings"):
                assert got[key].dtype == want[key].dtype, key
                np.testing.assert_array_equal(got[key], want[key], err_msg=key)
            compared += int(want["count"].size)
    assert compared > 100  # the scans had clusters to compare



def rectangle_fit_reference(scan: Scan, sel: np.ndarray, board: BoardSpec
                  ) -> tuple[float, float, float]:
    """`segment.rectangle_fit` before its compiled parts (`best_roll`, `rectangle_rays`)."""
    from align.feasible import plane_rows
    from align.plane import fit_lsq
    from align.roll_search import COARSE_STEP, TOLERANCE, left_out, subsample

    points = scan.xyz[sel]
    if len(points) < 3:
        return 0.0, 0.0, 0.0
    n, d = fit_lsq(points)
    p = subsample(points - (points @ n - d)[:, None] * n, 300)
    rolls = np.arange(-np.pi / 2, np.pi / 2, COARSE_STEP)
    grow = TOLERANCE + 0.5 * board.diagonal * np.sin(0.5 * COARSE_STEP)
    left, tx, tz = left_out(p, n, board, rolls, grow)
    best = int(np.argmin(left))
    held = float(1.0 - left[best] / (2 * len(p)))
    # the rays around the cluster (its rings, its azimuths and a board's width more)
    ring = scan.ring
    az0 = float(np.angle(np.mean(np.exp(1j * scan.azimuth[sel]))))
    rel = unwrap(scan.azimuth, az0)
    span = np.abs(unwrap(scan.azimuth[sel], az0)).max() + board.diagonal / max(d, 0.5)
    near = np.flatnonzero((np.abs(rel) <= span) & (ring >= ring[sel].min())
                          & (ring <= ring[sel].max()))
    sub = scan.select(near)  # the rays of the few rings near the cluster, not the scan's
    u, o = sub.directions(), sub.origins()
    un = u @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = (d - o @ n) / un
    q = o + lam[:, None] * u
    r0, r2 = plane_rows(rolls[best:best + 1], n)
    x, z = q @ r0[0] + tx[best], q @ r2[0] + tz[best]
    inside = (lam > 0) & (np.abs(x) < board.width / 2 - FILL_MARGIN) & (
        np.abs(z) < board.height / 2 - FILL_MARGIN)
    dist = scan.distance[near]
    ret = (lam > 0) & (dist > 0)
    on_plane = ret & (np.abs(dist - lam) <= FLAT_BAND)
    # a return off the plane inside the rectangle, behind it or in front, is unexplained
    n_on, n_off = int(np.sum(inside & on_plane)), int(np.sum(inside & ret & ~on_plane))
    fill = n_on / (n_on + n_off) if n_on + n_off else 0.0
    beyond = np.maximum(np.abs(x) - board.width / 2, np.abs(z) - board.height / 2)
    band = ret & (beyond > SURROUND[0]) & (beyond < SURROUND[1])
    free = 1.0 - float(np.sum(band & on_plane)) / max(int(band.sum()), 1)
    return held, fill, free


def test_rectangle_fit_matches_the_numpy_reference_on_real_clusters(real_scans):
    """held, fill and free of every real cluster the board search weighs (each candidate's
    planes) equal the numpy reference's exactly."""
    weighed = 0
    for scan, board, hints in real_scans:
        labels, st = segment.cluster(scan, search_mask(scan, board, hints), board.diagonal,
                                     min(board.width, board.height))
        rng = np.random.default_rng(0)
        for lab in np.flatnonzero((st["count"] >= 20) & (st["rings"] >= 2)):
            rest = np.flatnonzero(labels == lab)
            for _ in range(segment.PLANES_PER_CLUSTER):
                if len(rest) < 3:
                    break
                on = segment.planar_part(scan.xyz[rest], rng)
                sel, rest = rest[on], rest[~on]
                if len(sel) < 3:
                    continue
                assert segment.rectangle_fit(scan, sel, board) == rectangle_fit_reference(
                    scan, sel, board)
                weighed += 1
    assert weighed > 50


def test_best_roll_is_the_argmin_of_left_out_on_awkward_point_sets():
    """`best_roll` against `roll_search._left_out` and `np.argmin` where its bound is put to
    the test: points on a coarse lattice (many equal counts across rolls: the first of equal
    minima), strays far off the plane or far along it, a handful of points, clusters much
    larger than the box."""
    from align.feasible import plane_rows
    from align.kernels import best_roll
    from align.roll_search import COARSE_STEP, TOLERANCE, left_out

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
    """`kernels.ransac` against `plane.ransac` on every real cluster of three returns or more,
    the same generator state: the same normal, distance and inliers (bit for bit on this
    machine's BLAS; at worst a point within 1e-15 m of the band's edge could differ)."""
    from align import kernels, plane

    compared = 0
    for scan, board, hints in real_scans:
        labels, st = segment.cluster(scan, search_mask(scan, board, hints), board.diagonal,
                                     min(board.width, board.height))
        for lab in np.flatnonzero(st["count"] >= 3):
            pts = scan.xyz[labels == lab]
            for seed in (0, 1):
                n0, d0, in0 = plane.ransac(pts, segment.FLAT_BAND, np.random.default_rng(seed),
                                           segment.PLANE_HYPOTHESES)
                n1, d1, in1 = kernels.ransac(pts, segment.FLAT_BAND,
                                             np.random.default_rng(seed),
                                             segment.PLANE_HYPOTHESES)
                np.testing.assert_array_equal(in1, in0)
                np.testing.assert_array_equal(n1, n0)
                assert d1 == d0
                compared += 1
    assert compared > 100
    with pytest.raises(ValueError):
        kernels.ransac(np.zeros((5, 3)), 0.04, np.random.default_rng(0), 10)


def test_the_warm_up_compiles_every_estimator_kernel():
    """`scenarios.warmup` (run by make setup) leaves no kernel of `align.kernels` for a
    command to compile: each one the estimator calls has its signature after it. (The helpers
    with a leading underscore are compiled into their callers.)"""
    from numba.core.registry import CPUDispatcher

    from align import kernels
    from scenarios.warmup import warm_up

    warm_up()
    public = {name: f for name, f in vars(kernels).items()
              if isinstance(f, CPUDispatcher) and not name.startswith("_")}
    assert {"grid_clusters", "best_roll", "rectangle_rays", "ransac_best", "plane_band",
            "in_ring_block", "corner_points", "corner_residuals", "corner_jacobian",
            "cluster_members", "in_firing_order", "fit_residuals"} <= set(public)
    assert [name for name, f in public.items() if not f.signatures] == []


def test_in_ring_block_is_isin_of_the_consecutive_ring_block():
    """`kernels.in_ring_block` against np.isin of `segment.consecutive_ring_block` (the board's
    rings for `on_board_rings` and the paper's method): random ring lists with gaps, ties
    between blocks, nothing counted, and the real clusters' rings."""
    from align.kernels import in_ring_block

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
        want = np.isin(rings, segment.consecutive_ring_block(rings[counted]))
        np.testing.assert_array_equal(in_ring_block(rings, counted), want)


def feature_points_reference(points: np.ndarray, n: np.ndarray, d: float
                             ) -> tuple[np.ndarray, np.ndarray]:
    """`paper.feature_points` as numpy calls (the version before `kernels.corner_points`)."""
    from align.paper import plane_axes

    proj = points - np.outer(points @ n - d, n)
    h, v = plane_axes(n)
    u, w = proj @ h, proj @ v
    corners_uv = [(u.min(), w.max()), (u.max(), w.max()), (u.min(), w.min()), (u.max(), w.min())]
    idx = np.array([int(np.argmin((u - cu) ** 2 + (w - cw) ** 2)) for cu, cw in corners_uv])
    return proj[idx], idx


def test_corner_points_match_the_numpy_reference_on_real_clusters(real_scans):
    """The paper's feature points from the compiled pass equal the numpy version's bit for bit
    (the same points, the same projections) on every real cluster's main plane, and on a few
    of its points."""
    from align import kernels
    from align.paper import feature_points

    compared = 0
    for scan, board, hints in real_scans:
        labels, st = segment.cluster(scan, search_mask(scan, board, hints), board.diagonal,
                                     min(board.width, board.height))
        for lab in np.flatnonzero(st["count"] >= 10):
            pts = scan.xyz[labels == lab]
            n, d, inl = kernels.ransac(pts, 0.03, np.random.default_rng(0), 50)
            for sub in (pts[inl], pts[inl][:4], pts[::3]):
                want_p, want_i = feature_points_reference(sub, n, d)
                got_p, got_i = feature_points(sub, n, d)
                np.testing.assert_array_equal(got_i, want_i)
                np.testing.assert_array_equal(got_p, want_p)
                compared += 1
    assert compared > 100


def test_corner_residuals_and_jacobian_match_numpy():
    """The paper's corner residuals and their Jacobian (`kernels.corner_residuals`,
    `corner_jacobian`) equal the numpy expressions they replaced, bit for bit, at random poses
    and corner sets (as the Levenberg-Marquardt of `paper.levenberg_marquardt` meets them)."""
    from align.geometry import rotation
    from align.kernels import corner_jacobian, corner_residuals

    def residuals(beta, p_l, p_o):
        r = rotation(beta[3], beta[4], beta[5])
        return (p_o - (p_l @ r.T + beta[:3])).ravel()

    def jacobian(beta, p_l, p_o):
        j = np.empty((p_l.size, 6))
        j[:, :3] = np.tile(-np.eye(3), (len(p_l), 1))
        f0 = residuals(beta, p_l, p_o)
        for k in range(3, 6):
            b = beta.copy()
            b[k] += 1e-7
            j[:, k] = (residuals(b, p_l, p_o) - f0) / 1e-7
        return j

    rng = np.random.default_rng(22)
    p_o = align.BoardSpec().corners()
    for _ in range(300):
        beta = np.concatenate((rng.normal(0, 1, 3), rng.normal(0, 0.2, 3)))
        p_l = rng.normal(0, 1, (4, 3)) + np.array([0.0, 2.5, 0.0])
        np.testing.assert_array_equal(corner_residuals(beta, p_l, p_o),
                                      residuals(beta, p_l, p_o))
        want = jacobian(beta, p_l, p_o)
        got = corner_jacobian(beta, p_l, p_o)
        np.testing.assert_array_equal(got, want)
        assert np.array_equal(np.signbit(got), np.signbit(want))


def test_rel_azimuth_is_unwrap_bit_for_bit():
    """The compiled pass's relative azimuth (`kernels._rel_azimuth`, its remainder's shortcuts)
    against `segment._unwrap`, on random azimuths and centres and at the shortcuts' edges."""
    from align.kernels import _rel_azimuth

    rng = np.random.default_rng(23)
    two_pi = 2 * np.pi
    edges = np.array([0.0, two_pi, 2 * two_pi, -two_pi]) - np.pi
    az = np.concatenate((rng.uniform(-10, 20, 3000), rng.uniform(0, two_pi, 3000),
                         np.nextafter(edges, np.inf), np.nextafter(edges, -np.inf), edges))
    for centre in (*rng.uniform(-np.pi, np.pi, 5), 0.0, np.pi, -np.pi):
        want = unwrap(az, centre)
        taken = np.zeros(1, dtype=np.int64)
        got = np.array([_rel_azimuth(a, centre, taken) for a in az])
        assert np.array_equal(got, want) and np.array_equal(np.signbit(got), np.signbit(want))
        assert 0 < taken[0] < len(az) // 2  # the remainder only outside the shortcuts


def test_cluster_members_match_the_stable_argsort_on_real_scans(real_scans):
    """`kernels.cluster_members` against the numpy grouping `find_board` used (a stable argsort
    of the candidates' labels and a searchsorted), for the board search's candidates and for
    every cluster of each real scan."""
    from align.kernels import cluster_members

    for scan, board, hints in real_scans:
        labels, st = segment.cluster(scan, search_mask(scan, board, hints), board.diagonal,
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
    from align.kernels import in_firing_order

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
    """`kernels.centre` (the mean and the centred points of `plane.fit_lsq`) against
    points.mean(axis=0) and points - mean, bit for bit, on runs of returns of every length
    from 1 to a few thousand."""
    from align.kernels import centre

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
    """`kernels.total_variance` against the numpy expression `segment._board_score` used (per
    coordinate c = c - c.sum() / N, then (c * c).sum() / N, summed): numpy's pairwise sums
    reproduced for every length from a few returns to a whole scan (blocks of 8, of 128 and
    the halving above), on the real scans' coordinates."""
    from align.kernels import total_variance

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
