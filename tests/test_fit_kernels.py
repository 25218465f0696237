"""The pose fit's compiled kernels (`align.fit_kernels`) against the numpy versions they
replaced: the same numbers bit for bit (they only compare, count and copy numpy's floats), on
the joint fit's models of real scans (the five ACFR chessboard captures) and a twin scan."""

from __future__ import annotations

import numpy as np
import pytest

import align
from align import rays as rays_mod
from align import roll_search
from align.board import BoardSpec
from align.feasible import plane_rows
from align.fit_kernels import window_sweep
from align.geometry import board_coordinates, lidar_up
from tests.conftest import DATA_DIR
from tests.test_rays_kernels import ACFR_BOARD, _model
from twin.lidar.pcd import read_pcd_scans
from twin.sim.bench import BenchSim


@pytest.fixture(scope="module")
def models() -> list[tuple[rays_mod._Model, np.ndarray]]:
    hints = align.Hints(expected_distance=1.8)
    out = [_model(read_pcd_scans(p)[0], ACFR_BOARD, hints)
           for p in sorted((DATA_DIR / "acfr-vlp16").glob("pose*_full.pcd"))]
    out.append(_model(BenchSim(seed=3).scan(), align.BoardSpec(), align.Hints()))
    return out


def profile_reference(model: rays_mod._Model, theta: np.ndarray, ds: np.ndarray,
                      tol: float = 3e-3) -> np.ndarray:
    """`Model.profile` as numpy calls (before the kernel)."""
    x, z, _ = board_coordinates(theta, model.rays.origin, model.rays.direction)
    vx, vz = lidar_up(theta)
    w2, h2 = model.board.width / 2, model.board.height / 2
    hit, miss = model.lab == rays_mod.HIT, model.lab == rays_mod.MISS
    n = len(ds)

    def count_in(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        a = np.searchsorted(ds, lo, side="right")
        b = np.searchsorted(ds, hi, side="left")
        c = np.bincount(a, minlength=n + 1) - np.bincount(np.maximum(b, a), minlength=n + 1)
        return np.cumsum(c)[:n]

    def inside(c: np.ndarray, v: float, half: float) -> tuple[np.ndarray, np.ndarray]:
        if abs(v) < 1e-12:
            full = np.abs(c) < half
            return np.where(full, -np.inf, np.inf), np.where(full, np.inf, -np.inf)
        a, b = (-half - c) / v, (half - c) / v
        return np.minimum(a, b), np.maximum(a, b)

    def both(xs, zs, grow):
        lo1, hi1 = inside(xs, vx, w2 + grow)
        lo2, hi2 = inside(zs, vz, h2 + grow)
        return np.maximum(lo1, lo2), np.minimum(hi1, hi2)

    lo, hi = both(x[hit], z[hit], tol)
    viol = np.count_nonzero(hit) - count_in(lo, hi)
    lo, hi = both(x[miss], z[miss], -tol)
    viol = viol + count_in(lo, hi)
    sh = ds[None, :]
    xh, xm = x[model.bh][:, None] + sh * vx, x[model.bm][:, None] + sh * vx
    zh, zm = z[model.bh][:, None] + sh * vz, z[model.bm][:, None] + sh * vz
    kind, sign, sd = model._edges(xh, zh, xm, zm)
    e = np.where(kind == 1, sign * w2 - 0.5 * (xh + xm), sign * h2 - 0.5 * (zh + zm))
    cost = np.sum(np.where(kind > 0, (e / sd) ** 2, 0.0), axis=0)
    return 1e6 * viol + cost


def brackets_reference(rays: rays_mod._Rays, lab: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`rays._brackets` with its walk over the transitions in python (before the kernel)."""
    order = np.lexsort((rays.azimuth, rays.laser))
    order = order[lab[order] != rays_mod.DROPOUT]
    ls, az, lb = rays.laser[order], rays.azimuth[order], lab[order]
    link = ((ls[1:] == ls[:-1]) & (np.diff(az) < rays_mod.MAX_GAP) & (lb[1:] >= 0)
            & (lb[:-1] >= 0))
    trans = np.flatnonzero(link & (lb[1:] != lb[:-1]))
    first_hit, last_hit = board_spans_reference(ls, az, lb)
    hits, misses = [], []
    i = 0
    while i < len(trans):
        j = i
        while (j + 1 < len(trans) and np.all(link[trans[j]:trans[j + 1] + 1])
               and az[trans[j + 1]] - az[trans[j]] < rays_mod.ZONE_AZIMUTH):
            j += 1
        a, b = trans[i], trans[j] + 1
        left, right = lb[a], lb[b]
        i = j + 1
        if left == right:
            continue
        f, g = first_hit[ls[a]], last_hit[ls[a]]
        if not (a < f <= b or a <= g < b):
            continue
        z = lb[a:b + 1]
        err = np.cumsum(z != left)[:-1] + np.cumsum((z != right)[::-1])[::-1][1:]
        best = np.flatnonzero(err == err.min())
        p, q = a + best[0], a + best[-1] + 1
        h, m = (p, q) if left == 1 else (q, p)
        hits.append(order[h])
        misses.append(order[m])
    return np.array(hits, dtype=np.int64), np.array(misses, dtype=np.int64)


def test_profile_matches_numpy_on_real_scans(models):
    rng = np.random.default_rng(11)
    for model, theta in models:
        ds = np.arange(-0.08, 0.0805, 1e-3)
        for k in range(4):
            t = theta + (rng.normal(size=6) * [5e-3, 5e-3, 5e-3, 1e-2, 1e-2, 1e-2] if k else 0)
            for tol in (3e-3, 0.0):
                np.testing.assert_array_equal(model.profile(t, ds, tol),
                                              profile_reference(model, t, ds, tol))


def test_profile_best_is_the_profiles_first_minimum(models):
    """`profile_best` (the brackets costed only where they can decide) against np.argmin of
    the whole profile: poses off by up to a few cm and degrees, the profile's own tolerance
    and none, sharp and blurred edges (bracket costs far above the 1e6 of a violation),
    shifts with ties and a coarse grid."""
    from align.fit_kernels import _violations, profile_best, profile_cost

    rng = np.random.default_rng(23)
    for model, theta in models:
        w2, h2 = model.board.width / 2, model.board.height / 2
        for k in range(12):
            t = theta + (rng.normal(size=6) * [2e-2, 5e-3, 2e-2, 3e-2, 1e-2, 1e-2] if k else 0)
            x, z, _ = model.coords(t)
            vx, vz = lidar_up(t)
            for ds in (np.arange(-0.08, 0.0805, 1e-3), np.arange(-0.06, 0.061, 0.02),
                       np.zeros(5)):
                for tol, blur in ((3e-3, model.blur_edges), (0.0, (0.0, 0.0)),
                                  (3e-3, (1e-5, 2e-5))):
                    args = (x, z, model._hits, model._misses, model.bh, model.bm, ds, vx, vz,
                            w2, h2, tol, *blur)
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
        viol = _violations(*args[:4], *args[6:12])
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
                lab = np.where(odd, rays_mod.DROPOUT if k == 3 else rays_mod.UNKNOWN,
                               lab).astype(lab.dtype)
            got, want = rays_mod._brackets(model.rays, lab), brackets_reference(model.rays, lab)
            assert len(got[0]) > 0
            np.testing.assert_array_equal(got[0], want[0])
            np.testing.assert_array_equal(got[1], want[1])


def window_fit_reference(coords: np.ndarray, length: float) -> tuple[np.ndarray, np.ndarray]:
    """`roll_search._window_fit` before the kernel: every column sorted afresh, then slid."""
    rows = np.ascontiguousarray(coords.T)
    rows.sort(axis=1)
    return roll_search._slide(rows, length)


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
                got, want = window_sweep(coords, length), window_fit_reference(coords, length)
                np.testing.assert_array_equal(got[0], want[0])
                np.testing.assert_array_equal(got[1], want[1])
                whole += int(np.sum(got[0] == len(p)))
        assert whole > 0
    # ties, a single point, none
    coords = np.repeat(np.array([[0.0, 1.0, 1.0, 2.0]]).T, 3, axis=1)
    for c in (coords, coords[:1], coords[:0]):
        got, want = window_sweep(c, 1.0), window_fit_reference(c, 1.0)
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_array_equal(got[1], want[1])


def test_rotation_kernel_is_geometry_rotation_bit_for_bit():
    from align.fit_kernels import jacobian_rotations
    from align.fit_kernels import rotation as rotation_kernel
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
    from align.fit_kernels import inverse_diagonal

    for model, theta in models:
        f = model.residuals(theta)
        j = model.jacobian(theta, f)
        a = j.T @ j
        diag, ok = inverse_diagonal(a)
        assert ok
        np.testing.assert_allclose(diag, np.diag(np.linalg.pinv(a)), rtol=1e-12, atol=0)
        # a parameter no residual sees: singular, left to pinv (rays._inverse_diagonal)
        a0 = a.copy()
        a0[0, :] = a0[:, 0] = 0.0
        assert not inverse_diagonal(a0)[1]  # `lm_fit` then takes pinv's
    # nearly singular (condition 1e14): not trusted either
    assert not inverse_diagonal(np.diag([1.0, 1e-14]))[1]


def behind_ends_reference(rays: rays_mod._Rays, lab: np.ndarray, res: np.ndarray,
                          sigma_r: float) -> np.ndarray:
    """`rays._behind_ends` with its loop over the lasers in python (before the kernel)."""
    import math

    out = np.zeros(len(lab), dtype=bool)
    hit = np.flatnonzero(lab == rays_mod.HIT)
    order = hit[np.lexsort((rays.azimuth[hit], rays.laser[hit], rays.scan[hit]))]
    key = rays.scan[order].astype(np.int64) * 256 + rays.laser[order]
    run, sig, least = rays_mod.BEHIND_RUN, rays_mod.BEHIND_SIGMAS, rays_mod.BEHIND_MIN
    for grp in np.split(order, np.flatnonzero(key[1:] != key[:-1]) + 1):
        n = len(grp)
        if n < run:
            continue
        if n < 3 * run:
            mean = float(res[grp].mean())
            if mean > least and mean * math.sqrt(n) > sig * sigma_r:
                out[grp] = True
            continue
        reach = min(rays_mod.BEHIND_REACH, n // 3)
        for seq in (grp[:reach], grp[::-1][:reach]):
            m = np.arange(1, len(seq) + 1)
            mean = np.cumsum(res[seq]) / m
            ok = (m >= run) & (mean > least) & (mean * np.sqrt(m) > sig * sigma_r)
            if np.any(ok):
                out[seq[:int(np.flatnonzero(ok)[-1]) + 1]] = True
    return out


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
            hit = np.flatnonzero(lab == rays_mod.HIT)
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
                    lab[grp[keep:]] = rays_mod.MISS
                    if rng.random() < 0.5:
                        res[grp[:keep]] += 0.03
            got = rays_mod._behind_ends(rays, lab, res, sigma_r)
            np.testing.assert_array_equal(got, behind_ends_reference(rays, lab, res, sigma_r))
            marked += int(got.sum())
        assert marked > 0


def vertical_brackets_reference(rays: rays_mod._Rays, lab: np.ndarray, off: np.ndarray
                                ) -> tuple[np.ndarray, np.ndarray]:
    """`rays._vertical_brackets` with its dictionary of rings (before the kernel)."""
    col = {}
    for r in np.unique(rays.ring):
        m = np.flatnonzero((rays.ring == r) & (lab >= 0))
        if len(m):
            col[int(r)] = int(m[np.argmin(off[m])])
    hit_rings = [r for r in col if lab[col[r]] == 1]
    hits, misses = [], []
    if not hit_rings:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    top, bottom = max(hit_rings), min(hit_rings)
    if top + 1 in col and lab[col[top + 1]] == 0:
        hits.append(col[top])
        misses.append(col[top + 1])
    if bottom - 1 in col and lab[col[bottom - 1]] == 0:
        hits.append(col[bottom])
        misses.append(col[bottom - 1])
    return np.array(hits, dtype=np.int64), np.array(misses, dtype=np.int64)


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
                lab[np.isin(rays.ring, rng.choice(np.unique(rays.ring), k))] = rays_mod.UNKNOWN
                off = np.round(off, 2) if k == 2 else off
                lab = np.where(rng.random(len(lab)) < 0.05 * k, 1 - lab, lab).astype(lab.dtype)
            got = rays_mod._vertical_brackets(rays, lab, off)
            want = vertical_brackets_reference(rays, lab, off)
            np.testing.assert_array_equal(got[0], want[0])
            np.testing.assert_array_equal(got[1], want[1])
            found += len(got[0])
    assert found > 0
    empty = rays_mod._vertical_brackets(rays, np.full(len(rays.ring), rays_mod.MISS,
                                                      dtype=np.int8), off)
    assert len(empty[0]) == 0 and empty[0].dtype == np.int64


def test_window_firings_match_numpy_on_real_scans():
    from align.fit_kernels import window_firings

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
            rel = rays_mod._unwrap(s.azimuth[want], c)
            win = (rel >= lo) & (rel <= hi)
            idx, got_rel = window_firings(s.azimuth, s.laser_id, ring_of_laser, c, lo, hi,
                                          r_lo, r_hi)
            np.testing.assert_array_equal(idx, want[win])
            np.testing.assert_array_equal(got_rel, rel[win])


def test_window_rays_are_board_coordinates_bit_for_bit():
    """`window_rays` against `board_coordinates` and numpy's mask over every fired ray of real
    and twin scans (origins with and without vertical offsets), at poses about the board's
    and far from it."""
    from align.fit_kernels import window_rays
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


def classify_reference(model: rays_mod._Model, theta: np.ndarray, guard: float,
                       crossings: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`Model.classify`'s kinds, signs and sigmas as numpy calls (before the kernel)."""
    x, z, _ = board_coordinates(theta, model.rays.origin, model.rays.direction)
    model.set_blur(theta)
    xh, zh, xm, zm = x[model.bh], z[model.bh], x[model.bm], z[model.bm]
    kind, sign, sd = model._edges(xh, zh, xm, zm, guard)
    if not crossings:
        across = np.abs(np.where(kind == 1, xm - xh, zm - zh))
        along = np.abs(np.where(kind == 1, zm - zh, xm - xh))
        kind = np.where((kind > 0) & (across < rays_mod.GRAZING * along), 0, kind).astype(np.int8)
    return np.where(model.excluded, 0, kind).astype(np.int8), sign, sd


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
    from align.fit_kernels import classify_edges

    xh, zh, xm, zm = bracket
    got, sign, _ = classify_edges(np.array([xh, xm]), np.array([zh, zm]), np.array([0]),
                                  np.array([1]), 0.45, 0.27, 0.002, 0.003, 0.002, True,
                                  rays_mod.GRAZING, np.zeros(1, dtype=bool))
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
                want = classify_reference(model, t, guard, crossings)
                model.classify(t, guard, crossings)
                assert model.edge_kind.dtype == np.int8
                for got, ref in zip((model.edge_kind, model.edge_sign, model.edge_sd), want,
                                    strict=True):
                    np.testing.assert_array_equal(got, ref)
        model.excluded = kept
        model.classify(theta, 0.002, True)
        model.assign(theta)


def test_residual_copies_are_kernels_bit_for_bit(models):
    """`fit_kernels`' copy of the residuals (`lm_fit` calls it) is `align.kernels`' own, bit
    for bit, at the estimate and off it, with a range offset. (The Jacobian has one version,
    `jacobian_into`, held against numpy's in tests/test_rays_kernels.py.)"""
    from align.fit_kernels import _residuals_into, rotation

    for model, theta in models:
        for dt in (np.zeros(6), np.array([3e-3, -5e-3, 2e-3, 1e-2, -4e-3, 6e-3])):
            t = theta + dt
            model.offset = 0.02
            f = model.residuals(t)
            o_r, u_r, d_r, offset, sigma_r, *edges = model._fit_arrays()
            got = np.empty(len(f))
            _residuals_into(t, rotation(t[3], t[4], t[5]), o_r, u_r, d_r, offset, sigma_r,
                            *edges, got)
            np.testing.assert_array_equal(got, f)
            model.offset = 0.0


def gauss_newton_reference(model: rays_mod._Model, theta: np.ndarray, max_iter: int = 30
                           ) -> tuple[np.ndarray, np.ndarray, bool, int]:
    """`rays._gauss_newton` as a python loop of numpy calls (before `lm_fit`)."""
    from align.fit_kernels import inverse_diagonal

    converged = False
    it = 0
    lam = 1e-6
    model.assign(theta)
    fit_b = model.offset_prior is not None
    n_p = 7 if fit_b else 6

    def res(p: np.ndarray) -> np.ndarray:
        if not fit_b:
            return model.residuals(p)
        model.offset = float(p[6])
        b0, sb = model.offset_prior
        return np.concatenate((model.residuals(p[:6]), [(p[6] - b0) / sb]))

    def jac(p: np.ndarray, f: np.ndarray) -> np.ndarray:
        if not fit_b:
            return model.jacobian(p, f)
        model.offset = float(p[6])
        j = np.zeros((len(f), 7))
        j[:-1, :6] = model.jacobian(p[:6], f[:-1])
        j[:len(model._range[0]), 6] = -1.0 / model.sigma_r
        j[-1, 6] = 1.0 / model.offset_prior[1]
        return j

    def inv_diag(a: np.ndarray) -> np.ndarray:
        diag, ok = inverse_diagonal(a)
        return diag if ok else np.diag(np.linalg.pinv(a))

    p = np.append(theta, model.offset) if fit_b else theta
    f = res(p)
    cost = f @ f
    j = jac(p, f)
    for it in range(1, max_iter + 1):
        a = j.T @ j
        g = j.T @ f
        sd = np.sqrt(np.clip(inv_diag(a), 1e-18, None))
        while True:
            step = np.linalg.solve(a + lam * np.diag(np.diag(a)) + 1e-12 * np.eye(n_p), -g)
            f_new = res(p + step)
            c_new = f_new @ f_new
            if c_new <= cost * (1 + 1e-12):
                break
            lam *= 10
            if lam > 1e8:
                if fit_b:
                    model.offset = float(p[6])
                return p[:6], j, bool(np.all(np.abs(step) < 1e-2 * sd)), it
        p, f, cost = p + step, f_new, c_new
        lam = max(lam / 10, 1e-9)
        j = jac(p, f)
        if np.all(np.abs(step) < 1e-2 * sd + 1e-10):
            converged = True
            break
    if fit_b:
        model.offset = float(p[6])
    return p[:6], j, converged, it


@pytest.mark.parametrize("prior", [None, (0.01, 0.02)])
def test_lm_fit_matches_the_python_loop(models, prior):
    """`lm_fit` (`rays._gauss_newton`) takes the python loop's steps: the same iterations and
    convergence, the pose, offset and Jacobian to rounding (its normal equations are summed in
    another order than BLAS's), from the estimate and from starts moved off it."""
    for model, theta in models:
        for dt in (np.zeros(6), np.array([4e-3, -6e-3, 3e-3, 1.5e-2, -5e-3, 8e-3])):
            start = theta + dt
            results = []
            for fit in (gauss_newton_reference, rays_mod._gauss_newton):
                model.offset, model.offset_prior = 0.0, prior
                results.append((*fit(model, start.copy()), model.offset))
            (p0, j0, c0, i0, b0), (p1, j1, c1, i1, b1) = results
            assert (c1, i1) == (c0, i0)
            np.testing.assert_allclose(p1, p0, rtol=0, atol=1e-9)
            np.testing.assert_allclose(b1, b0, rtol=0, atol=1e-9)
            np.testing.assert_allclose(j1, j0, rtol=1e-6, atol=1e-6 * np.abs(j0).max())
            model.offset, model.offset_prior = 0.0, None


def fit_rays_reference(ranges: np.ndarray, origins: np.ndarray, dirs: np.ndarray,
                       n0: np.ndarray, d0: float, iterations: int = 8, tol: float = 1e-9,
                       sigma_floor: float = 0.0) -> tuple[np.ndarray, float, np.ndarray, float]:
    """`plane.fit_rays` as numpy calls (before `ray_plane_fit`)."""
    from align.plane import predicted_range, tangent_basis

    n, d = n0 / np.linalg.norm(n0), float(d0)
    for _ in range(iterations):
        e1, e2 = tangent_basis(n)
        un = dirs @ n
        pred = (d - origins @ n) / un
        res = ranges - pred
        j = np.empty((len(ranges), 3))
        j[:, 0] = -(origins @ e1 + pred * (dirs @ e1)) / un
        j[:, 1] = -(origins @ e2 + pred * (dirs @ e2)) / un
        j[:, 2] = 1.0 / un
        step, *_ = np.linalg.lstsq(j, res, rcond=None)
        n = n + step[0] * e1 + step[1] * e2
        n /= np.linalg.norm(n)
        d += step[2]
        if np.max(np.abs(step)) < tol:
            break
    res = ranges - predicted_range(n, d, origins, dirs)
    sigma = max(float(np.sqrt(res @ res / max(len(ranges) - 3, 1))), sigma_floor)
    cov = sigma**2 * np.linalg.pinv(j.T @ j)
    if d < 0:
        n, d = -n, -d
        flip = np.array([-1.0, 1.0, -1.0])
        cov = cov * np.outer(flip, flip)
    return n, d, cov, sigma


def test_ray_plane_fit_matches_numpy_on_real_scans(models):
    """`plane.fit_rays` (`fit_kernels.ray_plane_fit`) against its numpy loop on the models'
    interior hits, from the estimate's plane and from one tilted off it, and a start facing
    away (the flip): the plane and sigma to rounding, the covariance to 1e-9 of itself."""
    from align import plane
    from align.geometry import plane_of_pose

    for model, theta in models:
        use = model.use_range
        r, o, u = model.rays.distance[use], model.rays.origin[use], model.rays.direction[use]
        n, d = plane_of_pose(theta)
        for n0, d0, floor in ((n, d, 0.0), (n + np.array([0.03, -0.02, 0.01]), d + 0.05, 0.0),
                              (-n, -d, 0.02)):
            got, want = plane.fit_rays(r, o, u, n0, d0, sigma_floor=floor), fit_rays_reference(
                r, o, u, n0, d0, sigma_floor=floor)
            np.testing.assert_allclose(got[0], want[0], rtol=0, atol=1e-12)
            assert abs(got[1] - want[1]) < 1e-12
            scale = np.abs(want[2]).max()
            np.testing.assert_allclose(got[2], want[2], rtol=1e-9, atol=1e-9 * scale)
            assert abs(got[3] - want[3]) < 1e-12 * max(want[3], 1e-3)


def between_hits_reference(rays: rays_mod._Rays, lab: np.ndarray) -> np.ndarray:
    """`rays._between_hits` as numpy cumsums over the sorted rays (before the kernel)."""
    order = np.lexsort((rays.azimuth, rays.laser, rays.scan))
    key = rays.scan[order].astype(np.int64) * 256 + rays.laser[order]
    group = np.concatenate(([0], np.cumsum(key[1:] != key[:-1])))
    is_hit = (lab[order] == rays_mod.HIT).astype(np.int64)
    cum = np.cumsum(is_hit)
    first = np.concatenate(([0], np.flatnonzero(key[1:] != key[:-1]) + 1))
    before = cum - is_hit - (cum[first] - is_hit[first])[group]
    total = np.bincount(group, is_hit)[group]
    out = np.zeros(len(lab), dtype=bool)
    out[order] = (before >= 1) & (total - before - is_hit >= 1)
    return out


def test_between_hits_match_numpy_on_real_scans(models):
    """`rays._between_hits` (`fit_kernels.between_hits`) against its numpy version, on the
    models' labels and on labels with random hits dropped (dropout-like gaps) and added."""
    rng = np.random.default_rng(11)
    for model, _ in models:
        rays = model.rays
        for k in range(3):
            lab = model.lab.copy()
            if k == 1:
                lab[(lab == rays_mod.HIT) & (rng.random(len(lab)) < 0.2)] = rays_mod.MISS
            if k == 2:
                lab[rng.random(len(lab)) < 0.1] = rays_mod.HIT
            want = between_hits_reference(rays, lab)
            np.testing.assert_array_equal(rays_mod._between_hits(rays, lab), want)
            order = np.lexsort((rays.azimuth, rays.laser, rays.scan))
            np.testing.assert_array_equal(rays_mod._between_hits(rays, lab, order), want)
            assert want.any()
    empty = rays_mod._Rays(*(a[:0] for a in vars(models[0][0].rays).values()))
    assert len(rays_mod._between_hits(empty, np.zeros(0, dtype=np.int8))) == 0


def board_spans_reference(ls: np.ndarray, az: np.ndarray, lb: np.ndarray
                          ) -> tuple[np.ndarray, np.ndarray]:
    """`rays._board_spans` as numpy runs sorted by size (before the kernel)."""
    n_l = int(ls.max()) + 1 if len(ls) else 0
    first, last = np.full(n_l, -1), np.full(n_l, -1)
    pos = np.flatnonzero(lb == rays_mod.HIT)
    if not len(pos):
        return first, last
    new_run = np.concatenate(([True], (ls[pos[1:]] != ls[pos[:-1]])
                              | (az[pos[1:]] - az[pos[:-1]] > rays_mod.ZONE_AZIMUTH)))
    run = np.cumsum(new_run) - 1
    size = np.bincount(run)
    starts = pos[new_run]
    ends = pos[np.concatenate((new_run[1:], [True]))]
    best = np.full(n_l, -1)
    for r in np.argsort(size, kind="stable"):
        best[ls[starts[r]]] = r
    have = best >= 0
    first[have], last[have] = starts[best[have]], ends[best[have]]
    return first, last


def test_board_spans_match_numpy_on_real_scans(models):
    """`rays._board_spans` (`fit_kernels.board_spans`) against its numpy version: the models'
    labels, with hits dropped at random (runs split, ties of equal runs), and none."""
    rng = np.random.default_rng(12)
    for model, _ in models:
        rays = model.rays
        order = np.lexsort((rays.azimuth, rays.laser))
        for k in range(4):
            lab = model.lab.copy()
            if k == 1:
                lab[(lab == rays_mod.HIT) & (rng.random(len(lab)) < 0.3)] = rays_mod.MISS
            if k == 2:
                lab[rng.random(len(lab)) < 0.5] = rays_mod.HIT
            if k == 3:
                lab[:] = rays_mod.MISS
            ls, az, lb = rays.laser[order], rays.azimuth[order], lab[order]
            got, want = rays_mod._board_spans(ls, az, lb), board_spans_reference(ls, az, lb)
            for g, w in zip(got, want, strict=True):
                np.testing.assert_array_equal(g, w)
        # equal runs on one laser: the later wins
        ls = np.zeros(7, dtype=rays.laser.dtype)
        az = np.array([0.0, 0.001, 0.1, 0.101, 0.2, 0.201, 0.3])
        lb = np.array([1, 1, 0, 1, 1, 0, 1], dtype=np.int8)
        for g, w in zip(rays_mod._board_spans(ls, az, lb), board_spans_reference(ls, az, lb),
                        strict=True):
            np.testing.assert_array_equal(g, w)


def assign_reference(model: rays_mod._Model, theta: np.ndarray) -> tuple[np.ndarray, ...]:
    """`Model.assign`'s mask and rays as numpy masks and gathers (before the kernel)."""
    w2, h2 = model.board.width / 2, model.board.height / 2
    x, z, lam = board_coordinates(theta, model.rays.origin, model.rays.direction)
    inside = (np.abs(x) < w2 - rays_mod.EDGE_MARGIN) & (np.abs(z) < h2 - rays_mod.EDGE_MARGIN)
    res = model.rays.distance - model.offset - lam
    use = (model.lab == 1) & inside & (np.abs(res) < 4 * model.sigma_r)
    r = model.rays
    return use, r.origin[use], r.direction[use], r.distance[use]


def test_assign_matches_numpy_on_real_scans(models):
    """`Model.assign` (`fit_kernels.range_rays`) against its numpy version, at the estimate and
    off it, with a range offset."""
    for model, theta in models:
        for dt, offset in ((np.zeros(6), 0.0), (np.array([0.01, 0.004, -0.01, 0.02, 0, 0]), 0.01)):
            model.offset = offset
            model.assign(theta + dt)
            want = assign_reference(model, theta + dt)
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
    """`Model._cache_edges` (`fit_kernels.used_edges`) and `rays._contradicted`
    (`fit_kernels.contradicted`) against their numpy versions, for both corner guards and with
    and without the grazing crossings, at the estimate and off it."""
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
                count = int(np.sum((lab == rays_mod.HIT) & out)
                            + np.sum((lab == rays_mod.MISS) & deep))
                assert rays_mod._contradicted(model, t, margin) == count
        model.classify(theta, 0.002, True)


def test_numpy_mean_is_np_mean_bit_for_bit():
    """`fit_kernels._numpy_mean` (the short groups' mean in `behind_groups`) is np.mean of the
    gathered values bit for bit, for every size up to 128."""
    from align.fit_kernels import _numpy_mean

    rng = np.random.default_rng(13)
    res = rng.normal(0.0, 0.01, 400) + rng.choice([0.0, 0.03], 400)
    for n in range(1, 129):
        for _ in range(20):
            idx = rng.choice(len(res), n, replace=False)
            assert _numpy_mean(res, idx) == float(res[idx].mean())


def sides_reference(x, z, lab, laser, ext, board):
    """`rays._Sides.of`'s ends as numpy calls (before `laser_ends`): hit, x_l, x_r, the
    lasers' leftmost and rightmost hits, their ends and the median step; None below 3
    lasers."""
    w2, h2, margin = board.width / 2, board.height / 2, rays_mod.feasible.OUTLIER_MARGIN
    hit = (lab == rays_mod.HIT) & (np.abs(z) < h2 + margin) & (np.abs(x) < w2 + margin)
    x_l, x_r = x + ext[:, 0], x - ext[:, 1]
    idx = np.flatnonzero(hit)
    by_l = idx[np.lexsort((x_l[idx], laser[idx]))]
    by_r = idx[np.lexsort((-x_r[idx], laser[idx]))]
    first = np.flatnonzero(np.diff(np.concatenate(([-1], laser[by_l]))))
    if len(first) < 3:
        return None
    il, ir = by_l[first], by_r[first]
    ends = np.column_stack((x_l[il], z[il], x_r[ir], z[ir]))
    dx = np.abs(np.diff(x[by_l]))[np.diff(laser[by_l]) == 0]
    step = float(np.partition(dx, len(dx) // 2)[len(dx) // 2]) if len(dx) else 0.0
    return hit, x_l, x_r, il, ir, ends, step


def test_laser_ends_match_numpy_on_real_scans(models):
    """`laser_ends` (`rays._Sides.of`) against the lexsorts and diffs it replaced: the fit's
    poses and others a few cm and degrees off, the side faces of a 3 mm plate and of none,
    labels flipped at random, and ties (x quantised to 5 mm)."""
    from align.fit_kernels import laser_ends

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
            ext = rays_mod._side_faces(model.rays.direction, t, replace_thickness(board, k))
            want = sides_reference(x, z, lab, model.rays.laser, ext, board)
            w2, h2, margin = board.width / 2, board.height / 2, rays_mod.feasible.OUTLIER_MARGIN
            got = laser_ends(x, z, lab, model.rays.laser, ext, rays_mod.HIT, w2 + margin,
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
    """`_kth_smallest` (`laser_ends`' median step) against np.partition: random, rounded
    (ties), constant, sorted and reversed values, one to two thousand of them."""
    from align.fit_kernels import _kth_smallest

    rng = np.random.default_rng(4)
    for trial in range(3000):
        n = int(rng.integers(1, 60)) if trial % 2 else int(rng.integers(1, 2000))
        a = [rng.random(n), np.round(rng.random(n), 1), np.zeros(n), np.sort(rng.random(n)),
             np.sort(rng.random(n))[::-1].copy()][trial % 5]
        k = int(rng.integers(0, n))
        assert _kth_smallest(a.copy(), k) == np.partition(a, k)[k]


def grazing_reference(rays, lab, coords, expected, board, order, sides=None):
    """`rays._grazing_runs` as numpy calls (before `hit_runs`)."""
    HIT, MISS, UNKNOWN = rays_mod.HIT, rays_mod.MISS, rays_mod.UNKNOWN
    x, z = coords[0][order], coords[1][order]
    lb, az = lab[order], rays.azimuth[order]
    same = (rays.laser[order][1:] == rays.laser[order][:-1]) & (
        rays.scan[order][1:] == rays.scan[order][:-1]) & (np.diff(az) < rays_mod.MAX_GAP)
    hit = lb == HIT
    behind = (rays.distance[order] > 0) & (rays.distance[order] > expected[order])
    beside = (lb == MISS) | ((lb == UNKNOWN) & behind)
    starts = np.flatnonzero(hit & ~np.concatenate(([False], same & hit[:-1])))
    ends = np.flatnonzero(hit & ~np.concatenate((same & hit[1:], [False])))
    out = np.zeros(len(lab), dtype=bool)
    w2, h2, margin = board.width / 2, board.height / 2, rays_mod.feasible.OUTLIER_MARGIN
    corners = np.array([(-w2, -h2), (w2, -h2), (-w2, h2), (w2, h2)])
    n = len(lb)
    seen = (starts > 0) & (ends < n - 1)
    starts, ends = starts[seen], ends[seen]
    ok = same[starts - 1] & same[ends] & beside[starts - 1] & beside[ends + 1]
    spans = np.hypot(x[ends + 1] - x[starts - 1], z[ends + 1] - z[starts - 1])
    ok &= spans < min(board.width, board.height)
    for a, b, span in zip(starts[ok], ends[ok], spans[ok], strict=True):
        xs, zs = x[a:b + 1], z[a:b + 1]
        if np.all((np.abs(xs) < w2 - margin) & (np.abs(zs) < h2 - margin)):
            continue
        if sides is not None and sides.lines is not None:
            if sides.reaches(xs, zs):
                continue
        elif np.min(np.hypot(xs[:, None] - corners[:, 0], zs[:, None] - corners[:, 1])) < \
                span + rays_mod.CORNER_REACH:
            continue
        cx, cz = x[b + 1] - x[a - 1], z[b + 1] - z[a - 1]
        sag = np.max(np.abs((xs - x[a - 1]) * cz - (zs - z[a - 1]) * cx)) / span
        if sag < rays_mod.GRAZE_SAG:
            out[order[a:b + 1]] = True
    return out


def test_grazing_runs_match_numpy_on_real_scans(models):
    """`rays._grazing_runs` (its runs compiled: `hit_runs`) against the numpy version: the
    models' labels, and labels flipped at random (short runs of hits beside misses and
    returns behind, some grazing), with and without the side lines, at poses off the fit's."""
    from align.fit_kernels import hit_runs

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
            ext = rays_mod._side_faces(rays.direction, t, board)
            for sides in (None, rays_mod._Sides.of(coords[0], coords[1], lab, rays.laser, ext,
                                                   board)):
                got = rays_mod._grazing_runs(rays, lab, coords, expected, board, order, sides)
                want = grazing_reference(rays, lab, coords, expected, board, order, sides)
                np.testing.assert_array_equal(got, want)
                flagged += int(np.any(want))
            runs += len(hit_runs(order, lab, rays.laser, rays.scan, rays.azimuth,
                                 rays.distance, expected, rays_mod.MAX_GAP, rays_mod.HIT,
                                 rays_mod.MISS, rays_mod.UNKNOWN)[0])
    assert runs > 200 and flagged > 0, (runs, flagged)


def test_side_faces_match_numpy_on_real_scans():
    """`side_faces` (`rays._side_faces`) against u @ rot.T and numpy's elementwise steps, bit
    for bit: every fired ray of real and twin scans, any number of them (one row takes
    numpy's matrix-vector kernel), at poses about the board's; rays along the plane (a
    division by zero) as numpy gives them."""
    from align.fit_kernels import side_faces
    from align.geometry import rotation

    def reference(u, theta, thickness):
        rot = rotation(theta[3], theta[4], theta[5])
        dn = u @ rot.T
        ratio_x, ratio_z = dn[:, 0] / dn[:, 1], dn[:, 2] / dn[:, 1]
        return thickness * np.maximum(0.0, np.column_stack((ratio_x, -ratio_x, ratio_z,
                                                            -ratio_z)))

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
                want = reference(u, theta, 0.003)
            np.testing.assert_array_equal(side_faces(u, rotation(*theta[3:]), 0.003), want)


def side_lines_reference(ends, w2, tol, inward):
    """`rays._side_lines` as numpy calls (before `side_ends`, `line_excess`)."""
    reach, side_ends_min, line_ends_min = (rays_mod.EDGE_REACH, rays_mod.SIDE_ENDS,
                                           rays_mod.LINE_ENDS)
    left = np.flatnonzero(ends[:, 0] < -w2 + reach)
    right = np.flatnonzero(ends[:, 2] > w2 - reach)
    xs = np.concatenate((ends[left, 0], ends[right, 2]))
    zs = np.concatenate((ends[left, 1], ends[right, 3]))
    side = np.concatenate((np.zeros(len(left)), np.ones(len(right))))
    out_sign = 2.0 * side - 1.0
    keep = np.ones(len(xs), dtype=bool)
    a = np.column_stack((1.0 - side, side, zs))
    while True:
        n_r = int(np.count_nonzero(keep & (side == 1)))
        if n_r < side_ends_min or int(np.count_nonzero(keep)) - n_r < side_ends_min or \
                int(np.count_nonzero(keep)) < line_ends_min:
            return None
        ak = a[keep]
        coef = np.linalg.solve(ak.T @ ak, ak.T @ xs[keep])
        beyond = (xs - a @ coef) * out_sign
        excess = np.where(keep, np.maximum(np.maximum(beyond - tol, -beyond - inward), 0.0),
                          0.0)
        worst = int(np.argmax(excess))
        if excess[worst] <= 0.0:
            return float(coef[0]), float(coef[1]), float(coef[2])
        keep[worst] = False


def test_side_lines_match_numpy():
    """`rays._side_lines` (compiled around numpy's normal equations) against the numpy
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
        want = side_lines_reference(ends, w2, tol, inward)
        got = rays_mod._side_lines(ends, w2, tol, inward)
        assert got == want
        found += want is not None
        dropped += want is not None and want != side_lines_reference(ends, w2, 1.0, 1.0)
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
    """`_normal_equations` of six columns (its sums in registers) against the loop over the
    array it replaced: the same floats, the products added in the same order."""
    from numba import njit

    from align.fit_kernels import _normal_equations

    @njit
    def loop(j, f):
        n_p = j.shape[1]
        a, g = np.zeros((n_p, n_p)), np.zeros(n_p)
        for i in range(j.shape[0]):
            for r in range(n_p):
                jr = j[i, r]
                g[r] += jr * f[i]
                for c in range(r + 1):
                    a[r, c] += jr * j[i, c]
        for r in range(n_p):
            for c in range(r):
                a[c, r] = a[r, c]
        return a, g

    rng = np.random.default_rng(5)
    for n in (0, 1, 7, 555):
        for cols in (6, 7):
            j = rng.normal(size=(n, cols)) * rng.lognormal(size=cols) * 1e3
            f = rng.normal(size=n)
            for got, want in zip(_normal_equations(j, f), loop(j, f), strict=True):
                np.testing.assert_array_equal(got, want)


def test_window_pool_is_the_scans_selected_rays():
    """`window_pool` (`rays._candidate_pool`) against `window_firings` and `Scan.select`'s
    origins, directions, ranges, lasers and rings, bit for bit, on real and twin scans, with
    and without the lasers' vertical offsets applied (the sine and cosine of the azimuth are
    numba's: the C library's, as numpy's)."""
    from dataclasses import replace

    from align.fit_kernels import window_firings, window_pool

    scans = [read_pcd_scans(p)[0] for p in sorted((DATA_DIR / "acfr-vlp16").glob("pose*_full.pcd"))]
    scans.append(BenchSim(seed=3).scan())
    scans += [replace(s, vertical_offsets_applied=False) for s in scans[-2:]]
    rng = np.random.default_rng(19)
    for s in scans:
        lasers = s.lasers
        offset_z = (np.array(lasers.vertical_offset) if s.vertical_offsets_applied
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
                              np.cos(lasers.elevation), np.sin(lasers.elevation), offset_z, c,
                              lo, hi, r_lo, r_hi)
            for g, w in zip(got, want, strict=True):
                np.testing.assert_array_equal(g, w)
                assert g.dtype == w.dtype


def test_pool_rows_are_numpys_gathers(models):
    """`pool_rows` (`rays._candidates_at`'s rows of the pool) against numpy's fancy indexing
    of each field, values and dtypes."""
    from align.fit_kernels import pool_rows

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
    estimate calls in `align.fit_kernels`, `align.feasible` and `align.kernels` (the rays'
    RANSAC) for a command to compile. (The others are compiled into these, or serve the
    tests' numpy references.)"""
    from align import feasible, fit_kernels, kernels
    from scenarios.warmup import warm_up

    warm_up()
    called = {
        fit_kernels: ("window_pool", "window_rays", "pool_rows", "laser_ends", "side_faces",
                      "side_ends", "line_excess", "hit_runs", "laser_brackets", "binding_rays",
                      "ray_products", "shifted_coords", "profile_best", "window_sweep_pair",
                      "lm_fit", "ray_plane_fit", "behind_groups", "between_hits",
                      "column_brackets", "classify_edges", "range_rays", "used_edges",
                      "contradicted", "edge_labels", "range_labels", "bright_limit",
                      "seen_counts"),
        feasible: ("plane_posteriors",),
        kernels: ("msac_best", "in_ring_block", "lsq_plane", "fit_residuals"),
    }
    missing = [f"{mod.__name__}.{name}" for mod, names in called.items() for name in names
               if not getattr(mod, name).signatures]
    assert missing == []


def ray_points_reference(model, theta, tolerance, intensity=None, partial=(0.0, 0.0)):
    """`rays._ray_points` as numpy calls (before `edge_labels`)."""
    rays, board = model.rays, model.board
    x, z, lam = board_coordinates(theta, rays.origin, rays.direction)
    lab = model.lab
    w2, h2, margin = board.width / 2, board.height / 2, rays_mod.feasible.OUTLIER_MARGIN
    inner = (np.abs(x) < w2 - margin) & (np.abs(z) < h2 - margin)
    outer = (np.abs(x) > w2 + margin) | (np.abs(z) > h2 + margin)
    use = ((lab == 1) & ~outer) | ((lab == 0) & ~inner)
    u = rays.direction
    ext = rays_mod._side_faces(u, theta, board)
    vx, vz = lidar_up(theta)
    t_h, t_v = np.full(len(lab), tolerance[0]), np.full(len(lab), tolerance[1])
    if intensity is not None:
        part = rays_mod._partial_hits(lab, intensity, inner)
        t_h[part] = max(tolerance[0], partial[0]) if tolerance[0] > 0 else 0.0
        t_v[part] = max(tolerance[1], partial[1]) if tolerance[1] > 0 else 0.0
    per_x, per_z = np.hypot(t_h * vz, t_v * vx), np.hypot(t_h * vx, t_v * vz)
    per_edge = np.column_stack((per_x, per_x, per_z, per_z))
    ext += (lam * np.where(lab == 1, 1.0, -1.0))[:, None] * per_edge
    use &= ~rays_mod._overhanging(x, z, lab, rays.laser, ext, board)
    odds = rays_mod._clutter_odds(rays.distance[use] - model.offset - lam[use], model.sigma_r)
    return (rays_mod.LabelledRays(rays.origin[use], u[use], lab[use], ext[use],
                                  odds * (lab[use] == rays_mod.HIT)), np.flatnonzero(use))


def test_ray_points_match_numpy_on_real_scans(models):
    """`rays._ray_points` (its labels and allowances compiled: `edge_labels`) against the
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
            got = rays_mod._ray_points(model, t, tolerance, intensity, partial)
            want = ray_points_reference(model, t, tolerance, intensity, partial)
            for a, b in zip((got[0].origin, got[0].direction, got[0].label, got[0].ext,
                             got[0].odds, got[1]),
                            (want[0].origin, want[0].direction, want[0].label, want[0].ext,
                             want[0].odds, want[1]), strict=True):
                np.testing.assert_array_equal(a, b)
            if intensity is not None:
                x, z, _ = board_coordinates(t, model.rays.origin, model.rays.direction)
                inner = (np.abs(x) < model.board.width / 2 - 0.03) & (
                    np.abs(z) < model.board.height / 2 - 0.03)
                partials += int(np.any(rays_mod._partial_hits(model.lab, intensity, inner)))
                parities.add(int(np.count_nonzero((model.lab == rays_mod.HIT) & inner)) % 2)
    assert partials > 10 and parities == {0, 1}


def labels_reference(rays, lam, sigma_r):
    """`rays._labels` as numpy calls (before `range_labels`)."""
    lab = np.zeros(len(lam), dtype=np.int8)
    ret = rays.distance > 0
    res = rays.distance - lam
    near = rays_mod._hit_band(sigma_r)
    lab[ret & (np.abs(res) <= near)] = rays_mod.HIT
    lab[ret & ((res < -near) | ((res > near) & (res <= rays_mod.LABEL_TOLERANCE)))] = \
        rays_mod.UNKNOWN
    order = np.lexsort((rays.azimuth, rays.laser, rays.scan))
    lab[rays_mod._behind_ends(rays, lab, res, sigma_r, order)] = rays_mod.UNKNOWN
    inner = rays_mod._between_hits(rays, lab, order) & ~ret
    hits = int(np.count_nonzero(lab == rays_mod.HIT))
    if np.count_nonzero(inner) >= max(rays_mod.MIN_DROPOUTS, rays_mod.DROPOUT_FRACTION * hits):
        lab[~ret] = rays_mod.DROPOUT
    return lab


def bright_ends_reference(rays, lab, intensity, inner, order):
    """`rays._bright_ends` as numpy calls (before `bright_limit`)."""
    import itertools

    out = np.zeros(len(lab), dtype=bool)
    ref = intensity[(lab == rays_mod.HIT) & inner]
    if len(ref) < rays_mod.BRIGHT_REFERENCE:
        return out
    hits = order[lab[order] == rays_mod.HIT]
    k = int(0.99 * (len(ref) - 1))
    odd = intensity[hits] > rays_mod.BRIGHT_RATIO * float(np.partition(ref, k)[k])
    if not np.any(odd):
        return out
    key = rays.scan[hits].astype(np.int64) * 256 + rays.laser[hits]
    bounds = np.flatnonzero(np.diff(np.concatenate(([-1], key, [-1]))))
    for a, b in itertools.pairwise(bounds):
        if not (odd[a] or odd[b - 1]):
            continue
        i = a
        while i < b and odd[i]:
            i += 1
        j = b
        while j > i and odd[j - 1]:
            j -= 1
        out[hits[a:i]] = True
        out[hits[j:b]] = True
    return out


def test_labels_and_bright_ends_match_numpy_on_real_scans(models):
    """`rays._labels` (`range_labels`) and `rays._bright_ends` (`bright_limit`) against the
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
            lab = rays_mod._labels(rays, lam_k, sigma_r)
            np.testing.assert_array_equal(lab, labels_reference(rays, lam_k, sigma_r))
            order = np.lexsort((rays.azimuth, rays.laser, rays.scan))
            intensity = rng.integers(20, 60, len(lab)).astype(np.uint8)
            if k % 2:  # a bright holder at a ring's ends, and a few bright returns
                hits = order[lab[order] == rays_mod.HIT]
                intensity[hits[:2]] = intensity[hits[-1]] = 250
                intensity[rng.random(len(lab)) < 0.004] = 250
            inner = rng.random(len(lab)) < 0.7
            got = rays_mod._bright_ends(rays, lab, intensity, inner, order)
            np.testing.assert_array_equal(got, bright_ends_reference(rays, lab, intensity,
                                                                     inner, order))
            bright += int(np.any(got))
    assert bright > 0


def test_seen_counts_match_numpy_on_real_scans(models):
    """`seen_counts` (the estimate's account of what was seen) against `rays._edges_seen` and
    numpy's masks: the models' labels, with misses, dropouts and returns in front put in at
    random, at poses off the fit's (edges unseen, rays blocked)."""
    from align.fit_kernels import seen_counts

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
                    [rays_mod.MISS, rays_mod.DROPOUT, rays_mod.HIT], len(lab)), lab).astype(
                    lab.dtype)
            distance = rays.distance - (0.2 if k % 3 == 0 else 0.0) * (rng.random(len(lab))
                                                                        < 0.1)
            b, front = 0.003 * k, 0.04
            inside = (np.abs(x) < w2) & (np.abs(z) < h2)
            want = (rays_mod._edges_seen(x, z, lab, board), int(np.sum(inside)),
                    int(np.sum(inside & (distance > 0) & (distance - b - lam < -front))),
                    int(np.sum(inside & (lab == rays_mod.DROPOUT))),
                    int(np.sum(inside & (np.abs(x) < w2 - 0.02) & (np.abs(z) < h2 - 0.02)
                               & (lab == rays_mod.MISS))),
                    int(np.sum((lab == rays_mod.HIT) & ((np.abs(x) > w2 + 0.02)
                                                        | (np.abs(z) > h2 + 0.02)))))
            got = seen_counts(x, z, lam, lab, distance, b, front, w2, h2, rays_mod.WINDOW,
                              0.02, rays_mod.HIT, rays_mod.MISS, rays_mod.DROPOUT)
            assert tuple(bool(v) for v in got[0]) == want[0]
            assert got[1:] == want[1:]
