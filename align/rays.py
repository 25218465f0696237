"""method="rays": the ML plane along the rays plus the board rectangle fitted to hit/miss labels.

What a single flat board tells a LiDAR of a few rings (docs/align.md has the analysis):

- The plane (tilt, yaw, distance) comes from the ranges. We fit it by maximum likelihood along
  the rays (`align.plane.fit_rays`), which is unbiased on an obliquely seen board, unlike an
  orthogonal fit.
- Roll and the in-plane position (x, and z where the board's top or bottom edge falls between
  rings or a ring crosses it) come only from where rays hit or miss the board. Every fired ray
  near the board is intersected with the plane and labelled hit (a return on the plane), miss
  (no return, or one far behind) or unknown (a return in front of the board: an occluder).
  Along each laser's sequence of rays, sorted by azimuth (over all N scans when fusing: the
  start azimuth differs scan to scan, so the edge is sampled at new places and the bracket
  shrinks about as 1/N), each hit/miss transition brackets an edge crossing: the edge lies
  somewhere between the two rays, uniformly. The bracket's midpoint is a measurement of the
  edge with variance (bracket width)^2 / 12 plus a small blur for the random part of mixed
  returns. Where several transitions crowd together (a beam straddling the edge gives mixed
  returns that flicker), the zone is reduced to the one step that misclassifies the fewest rays
  (ties widen the bracket): the blur is modelled, not ignored.
- Both kinds of measurement enter one Gauss-Newton fit of the six pose parameters (range
  residuals only from hits safely inside the rectangle: mixed returns at the edges pull ranges
  towards the wall). That fit finds the basin and is the fallback.
- The estimate itself is the posterior mean (`align.label_posterior`): for a plane, the poses
  consistent with every hit/miss label form a set whose volume and moments are exact
  (`align.feasible`); a dozen uniform brackets hold roll, and their intersection is narrower
  than the least-squares midpoints say. The ranges' plane is integrated out (a Gauss-Hermite
  rule, each plane weighted by the labels' evidence), and a single scan's roll is searched over
  +-4 deg, so a fit caught in a wrong basin is corrected. Mixed returns of a divergent beam are
  allowed for by a tolerance on every label (`Hints.edge_tolerance`). Where no pose explains
  the labels (a dropout at an edge), the least-squares fit stands.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from align import feasible, plane
from align.board import BoardSpec
from align.geometry import board_coordinates, pose_from_plane, rotation
from align.label_posterior import LabelledRays, label_posterior
from align.result import Hints, PoseEstimate, Status
from align.segment import Segmentation, consecutive_ring_block
from twin.core.pose import Pose
from twin.core.scan import Scan

#: A return within this distance of the plane (along the ray) is a hit on the board, m. The
#: nearest thing behind the paper's board (its stand) is 0.15 m behind it; the noise is 14 mm.
LABEL_TOLERANCE = 0.07
#: Range residuals only from hits at least this far inside the rectangle, m (beam footprint
#: 3 mrad x 2.6 m = 8 mm, half of it plus the azimuth step).
EDGE_MARGIN = 0.015
#: Consecutive transitions closer than this (in azimuth, rad) form one mixed zone.
ZONE_AZIMUTH = np.deg2rad(0.5)
#: Neighbours farther apart than this in azimuth bracket nothing (a dropped firing), rad.
MAX_GAP = np.deg2rad(0.7)
#: A hit farther than this outside the rectangle (after the z profile) is not the board, m.
STRAY = 0.04
#: 1-sigma of a top/bottom edge crossing across the ring (the ring's height), m.
EDGE_BLUR_Z = 2.0e-3
#: Rays considered: within this of the rectangle's side edges (board coordinates), m ...
WINDOW = 0.12
#: ... and of its top and bottom edges: one ring spacing (2 deg at 2.6 m = 91 mm) plus the lean
#: of a rolled ring, not more (the board's stand, 5 cm in front of the plane, sits lower), m.
WINDOW_Z = 0.13


@dataclass
class _Rays:
    """The candidate rays of all scans, in one set."""

    origin: np.ndarray  # (M, 3) m, {L}
    direction: np.ndarray  # (M, 3)
    distance: np.ndarray  # (M,) m, 0 = no return
    laser: np.ndarray  # (M,)
    azimuth: np.ndarray  # (M,) rad, unwrapped around the board
    ring: np.ndarray
    gidx: np.ndarray  # index into the concatenation of the scans


def _unwrap(az: np.ndarray, c: float) -> np.ndarray:
    return (az - c + np.pi) % (2 * np.pi) - np.pi


def _candidates(scans: list[Scan], segs: list[Segmentation], theta: np.ndarray,
                board: BoardSpec) -> _Rays:
    """Every fired ray (hit or not) near the board's rectangle, from all scans."""
    parts = []
    offset = 0
    for s, g in zip(scans, segs, strict=True):
        az_b = s.azimuth[g.board]
        c = float(np.angle(np.mean(np.exp(1j * az_b))))
        rel_b = _unwrap(az_b, c)
        # wide enough for the whole board even if only part of it returned (a dark patch, an
        # occluder): the rectangle must not extend where no ray was looked at
        margin = board.width / max(float(np.median(s.distance[g.board])), 0.5)
        lo, hi = rel_b.min() - margin, rel_b.max() + margin
        ring_of_laser = s.lasers.ring_of_laser
        rings = ring_of_laser[s.laser_id[g.board]]
        # the lasers of the board's rings and one more on each side (a table, not Scan.ring)
        near_ring = np.arange(s.lasers.n_lasers)
        near_ring = (near_ring >= int(rings.min()) - 1) & (near_ring <= int(rings.max()) + 1)
        idx = np.flatnonzero(near_ring[ring_of_laser][s.laser_id])
        rel = _unwrap(s.azimuth[idx], c)
        win = (rel >= lo) & (rel <= hi)
        idx = idx[win]
        sub = s.select(idx)
        parts.append((sub.origins(), sub.directions(), sub.distance, sub.laser_id,
                      rel[win] + c, sub.ring, idx + offset))
        offset += len(s)
    cat = [np.concatenate(p) for p in zip(*parts, strict=True)]
    rays = _Rays(*cat)
    x, z, lam = board_coordinates(theta, rays.origin, rays.direction)
    keep = (lam > 0) & (np.abs(x) < board.width / 2 + WINDOW) & \
        (np.abs(z) < board.height / 2 + WINDOW_Z)
    return _Rays(*(a[keep] for a in cat))


def _labels(rays: _Rays, lam: np.ndarray) -> np.ndarray:
    """1 hit on the board, 0 miss (no return or far behind), -1 unknown (something in front)."""
    lab = np.zeros(len(lam), dtype=np.int8)
    ret = rays.distance > 0
    res = rays.distance - lam
    lab[ret & (np.abs(res) <= LABEL_TOLERANCE)] = 1
    lab[ret & (res < -LABEL_TOLERANCE)] = -1
    return lab


def _brackets(rays: _Rays, lab: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Hit/miss brackets along each laser: pairs (hit-side ray, miss-side ray) of indices."""
    order = np.lexsort((rays.azimuth, rays.laser))
    ls, az, lb = rays.laser[order], rays.azimuth[order], lab[order]
    link = (ls[1:] == ls[:-1]) & (np.diff(az) < MAX_GAP) & (lb[1:] >= 0) & (lb[:-1] >= 0)
    trans = np.flatnonzero(link & (lb[1:] != lb[:-1]))
    hits, misses = [], []
    i = 0
    while i < len(trans):
        # grow a zone of transitions that follow each other closely on the same laser
        j = i
        while (j + 1 < len(trans) and np.all(link[trans[j]:trans[j + 1] + 1])
               and az[trans[j + 1]] - az[trans[j]] < ZONE_AZIMUTH):
            j += 1
        a, b = trans[i], trans[j] + 1  # zone spans sorted rays a..b
        left, right = lb[a], lb[b]
        i = j + 1
        if left == right:
            continue  # in and out again: no net crossing (a grazing ring, a flicker)
        z = lb[a:b + 1]
        # split after position s: errors = wrong labels left of it + wrong labels right of it
        wrong_left = np.cumsum(z != left)[:-1]
        wrong_right = np.cumsum((z != right)[::-1])[::-1][1:]
        err = wrong_left + wrong_right
        best = np.flatnonzero(err == err.min())
        p, q = a + best[0], a + best[-1] + 1  # the bracket: rays p and q
        h, m = (p, q) if left == 1 else (q, p)
        hits.append(order[h])
        misses.append(order[m])
    return np.array(hits, dtype=np.int64), np.array(misses, dtype=np.int64)


def _vertical_brackets(rays: _Rays, lab: np.ndarray, x: np.ndarray, x_c: float
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Ring-to-ring brackets of the top and bottom edges at the board's central column.

    For each ring, the ray nearest the column X = x_c; going up from the lowest ring that hits,
    the first ring that misses brackets the top edge with the ring below it (and likewise down).
    One bracket per edge for all scans: the rings sit at the same heights in every scan.
    """
    rings = np.unique(rays.ring)
    col = {}
    for r in rings:
        m = np.flatnonzero((rays.ring == r) & (lab >= 0))
        if len(m):
            col[int(r)] = int(m[np.argmin(np.abs(x[m] - x_c))])
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


def _coords(rot: np.ndarray, theta: np.ndarray, o: np.ndarray, u: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Board coordinates X, Z of rays (origins o, directions u in {L}) and their directions in
    {O}, for the rotation ``rot`` of pose ``theta``."""
    d = u @ rot.T
    oo = o @ rot.T + theta[:3]
    lam = -oo[:, 1] / d[:, 1]
    return oo[:, 0] + lam * d[:, 0], oo[:, 2] + lam * d[:, 2], d


class _Model:
    """Whitened residuals of the joint fit for a pose theta."""

    def __init__(self, rays: _Rays, lab: np.ndarray, bh: np.ndarray, bm: np.ndarray,
                 board: BoardSpec, sigma_r: float, blur: float) -> None:
        self.rays, self.lab, self.board = rays, lab, board
        self.bh, self.bm = bh, bm
        self.sigma_r, self.blur = sigma_r, blur
        # a ring's height on the board is known less well than a position along it: the beam
        # is 1.5 mrad tall (4 mm at 2.6 m) and the laser's elevation is only nominal
        self.blur_z = max(blur, EDGE_BLUR_Z)
        self.use_range = np.zeros(len(lab), dtype=bool)
        self._range = (np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))
        self._bh = (rays.origin[bh], rays.direction[bh])
        self._bm = (rays.origin[bm], rays.direction[bm])
        self.edge_kind = np.zeros(len(bh), dtype=np.int8)  # 0 skip, 1 vertical edge, 2 horizontal
        self.edge_sign = np.zeros(len(bh))
        self.edge_sd = np.ones(len(bh))
        self._cache_edges()

    def _cache_edges(self) -> None:
        """The used brackets' rays, signs and sigmas, contiguous (the fit only reads these)."""
        use = self.edge_kind > 0
        self._ubh = (self._bh[0][use], self._bh[1][use])
        self._ubm = (self._bm[0][use], self._bm[1][use])
        self._usign, self._usd = self.edge_sign[use], self.edge_sd[use]
        self._uvert = (self.edge_kind == 1)[use]

    def assign(self, theta: np.ndarray) -> None:
        """Which hits feed the range residuals: those safely inside the rectangle."""
        w2, h2 = self.board.width / 2, self.board.height / 2
        x, z, lam = board_coordinates(theta, self.rays.origin, self.rays.direction)
        inside = (np.abs(x) < w2 - EDGE_MARGIN) & (np.abs(z) < h2 - EDGE_MARGIN)
        res = self.rays.distance - lam
        self.use_range = (self.lab == 1) & inside & (np.abs(res) < 4 * self.sigma_r)
        # the fit only ever looks at these rays: keep them contiguous
        r = self.rays
        self._range = (r.origin[self.use_range], r.direction[self.use_range],
                       r.distance[self.use_range])

    def classify(self, theta: np.ndarray, guard: float, crossings: bool = True) -> None:
        """Fix which edge each bracket measures, for pose ``theta``; drop the ambiguous ones.

        The line through a bracket's hit and miss meets the side edge X = +-W/2 (on the side it
        heads to) at some height z_at: well within the board's height (by ``guard``, m: the
        pose's own uncertainty there) the bracket measures that side edge; well beyond it,
        the top or bottom edge; in between (a bracket at a corner) it could be either and is
        left out. Assignments stay fixed during a fit: switching them inside Gauss-Newton
        makes the cost jump and traps the fit in wrong basins.
        """
        x, z, _ = board_coordinates(theta, self.rays.origin, self.rays.direction)
        kind, sign, sd = self._edges(x[self.bh], z[self.bh], x[self.bm], z[self.bm], guard)
        if not crossings:  # leave out rings crossing the top or bottom edge (sharp in z)
            kind = np.where((kind == 2) & (sd < 0.01), 0, kind).astype(np.int8)
        self.edge_kind, self.edge_sign, self.edge_sd = kind, sign, sd
        self._cache_edges()

    def _edges(self, xh, zh, xm, zm, guard: float = 0.0):
        """Edge kind (1 side, 2 top or bottom, 0 left out), sign and sigma (m) of brackets.

        sigma = sqrt(width^2 / 12 + blur^2), width = the bracket's extent across its edge.
        """
        w2, h2 = self.board.width / 2, self.board.height / 2
        dx, dz = xm - xh, zm - zh
        with np.errstate(divide="ignore", invalid="ignore"):
            z_at = np.abs(zh + (np.sign(dx) * w2 - xh) * dz / dx)
        z_at = np.where(np.isfinite(z_at), z_at, np.inf)
        vert = z_at <= h2
        kind = np.where(vert, 1, 2).astype(np.int8)
        kind = np.where((np.abs(z_at - h2) < guard) | ((dx == 0) & (dz == 0)), 0, kind)
        # which side: that of the miss (a ring crossing the top edge runs almost level, so
        # the sign of its tiny height change says nothing)
        sign = np.where(vert, np.sign(xm), np.sign(zm))
        width = np.where(vert, dx, dz)
        sd = np.sqrt(width**2 / 12 + np.where(vert, self.blur, self.blur_z) ** 2)
        return kind, sign, sd

    def _width(self, theta: np.ndarray) -> np.ndarray:
        """Each bracket's extent across its edge (m) at pose theta."""
        x, z, _ = board_coordinates(theta, self.rays.origin, self.rays.direction)
        return np.where(self.edge_kind == 1, x[self.bm] - x[self.bh], z[self.bm] - z[self.bh])

    def profile_z(self, theta: np.ndarray, dz: np.ndarray, tol: float = 3e-3) -> np.ndarray:
        """A cost for the pose shifted by each of ``dz`` in z (m): label violations first.

        A z shift moves every board coordinate Z by the same amount and leaves the ranges
        alone, so the profile is cheap. The cost counts hits outside the rectangle and misses
        inside it (more than ``tol`` from its edge), then adds the brackets' squared
        residuals with their edges reassigned for each shift.
        """
        x, z, _ = board_coordinates(theta, self.rays.origin, self.rays.direction)
        w2, h2 = self.board.width / 2, self.board.height / 2
        hit, miss = self.lab == 1, self.lab == 0
        n = len(dz)

        def count_in(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
            """For each shift, how many intervals (lo, hi) contain it (interval counting)."""
            a = np.searchsorted(dz, lo, side="right")
            b = np.searchsorted(dz, hi, side="left")
            c = np.bincount(a, minlength=n + 1) - np.bincount(np.maximum(b, a), minlength=n + 1)
            return np.cumsum(c)[:n]

        # a hit violates when |z + s| > h2 + tol (or it is outside in x at any shift); a miss
        # within the side edges violates when |z + s| < h2 - tol
        zh = z[hit & (np.abs(x) <= w2 + tol)]
        viol = np.count_nonzero(hit & (np.abs(x) > w2 + tol)) + len(zh) - count_in(
            -h2 - tol - zh, h2 + tol - zh)
        zm = z[miss & (np.abs(x) < w2 - tol)]
        viol = viol + count_in(-h2 + tol - zm, h2 - tol - zm)
        xh, xm = x[self.bh][:, None], x[self.bm][:, None]
        zh, zm = z[self.bh][:, None] + dz[None, :], z[self.bm][:, None] + dz[None, :]
        kind, sign, sd = self._edges(xh, zh, xm, zm)
        e = np.where(kind == 1, sign * w2 - 0.5 * (xh + xm), sign * h2 - 0.5 * (zh + zm))
        cost = np.sum(np.where(kind > 0, (e / sd) ** 2, 0.0), axis=0)
        return 1e6 * viol + cost

    def residuals(self, theta: np.ndarray) -> np.ndarray:
        """Whitened residuals: ranges of the interior hits, then the used brackets."""
        rot = rotation(theta[3], theta[4], theta[5])
        o_r, u_r, d_r = self._range
        lam = -(o_r @ rot[1] + theta[1]) / (u_r @ rot[1])
        rr = (d_r - lam) / self.sigma_r
        xh, zh, dh = _coords(rot, theta, *self._ubh)
        xm, zm, _ = _coords(rot, theta, *self._ubm)
        sgn = self._usign
        mid_x = 0.5 * (xh + xm)
        mid_z = 0.5 * (zh + zm)
        # the plate's side face: a ray heading inwards (against the edge's outward side) that
        # passes the front edge by less than thickness x (its lateral over forward direction)
        # still hits the board, so that edge sits that much further out for it
        t = self.board.thickness
        ext_x = t * np.maximum(0.0, -sgn * dh[:, 0] / dh[:, 1])
        ext_z = t * np.maximum(0.0, -sgn * dh[:, 2] / dh[:, 1])
        e = np.where(self._uvert, sgn * (self.board.width / 2 + ext_x) - mid_x,
                     sgn * (self.board.height / 2 + ext_z) - mid_z)
        re = e / self._usd
        return np.concatenate((rr, re))

    def jacobian(self, theta: np.ndarray, f0: np.ndarray) -> np.ndarray:
        """d residuals / d theta: translations analytically, rotations by forward differences.

        X = o.r0 + t_x + lam u.r0, Z = o.r2 + t_z + lam u.r2, lam = -(o.r1 + t_y) / u.r1 (r_k
        the rows of R): t_x and t_z move X and Z one for one; t_y moves lam by -1 / u.r1.
        """
        rot = rotation(theta[3], theta[4], theta[5])
        vert = self._uvert
        j = np.empty((len(f0), 6))
        u_r = self._range[1]
        nr = len(u_r)
        j[:nr, 0] = 0.0
        j[:nr, 1] = (1.0 / (u_r @ rot[1])) / self.sigma_r  # -(d lam / d t_y) / sigma
        j[:nr, 2] = 0.0
        sd = self._usd

        def d_dty(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            dlam = -1.0 / (u @ rot[1])
            return dlam * (u @ rot[0]), dlam * (u @ rot[2])

        xh_t, zh_t = d_dty(self._ubh[1])
        xm_t, zm_t = d_dty(self._ubm[1])
        j[nr:, 0] = np.where(vert, -1.0, 0.0) / sd
        j[nr:, 2] = np.where(vert, 0.0, -1.0) / sd
        j[nr:, 1] = -0.5 * np.where(vert, xh_t + xm_t, zh_t + zm_t) / sd
        for i in range(3, 6):
            t = theta.copy()
            t[i] += 1e-7
            j[:, i] = (self.residuals(t) - f0) / 1e-7
        return j


def _gauss_newton(model: _Model, theta: np.ndarray, max_iter: int = 30
                  ) -> tuple[np.ndarray, np.ndarray, bool, int]:
    """Levenberg-Marquardt on the whitened residuals.

    The bracket assignment and the set of range residuals stay fixed during one call (they are
    chosen for the start pose), so the cost is one smooth function and the steps decrease it.
    Converged when every step is below a hundredth of the parameter's standard deviation.
    """
    converged = False
    it = 0
    lam = 1e-6
    model.assign(theta)
    f = model.residuals(theta)
    cost = f @ f
    j = model.jacobian(theta, f)
    for it in range(1, max_iter + 1):
        a = j.T @ j
        g = j.T @ f
        sd = np.sqrt(np.clip(np.diag(np.linalg.pinv(a)), 1e-18, None))
        while True:
            step = np.linalg.solve(a + lam * np.diag(np.diag(a)) + 1e-12 * np.eye(6), -g)
            f_new = model.residuals(theta + step)
            c_new = f_new @ f_new
            if c_new <= cost * (1 + 1e-12):
                break
            lam *= 10
            if lam > 1e8:
                return theta, j, bool(np.all(np.abs(step) < 1e-2 * sd)), it
        theta, f, cost = theta + step, f_new, c_new
        lam = max(lam / 10, 1e-9)
        j = model.jacobian(theta, f)
        if np.all(np.abs(step) < 1e-2 * sd + 1e-10):
            converged = True
            break
    return theta, j, converged, it


def _initial_roll(x: np.ndarray, z: np.ndarray, ring: np.ndarray) -> float:
    """Roll from the leftmost and rightmost return of each ring (Theil-Sen, both sides).

    ``x``, ``z``: board coordinates computed with roll 0. A ring that crosses the top or bottom
    edge ends on that edge rather than on a side, so its extremes sit inside the side edges:
    the median of pairwise slopes over rings within 25 mm of the widest ring resists them. A
    positive roll leans the side edges so that X grows downwards (dX/dZ = -tan roll).
    """
    zs, xl, xr = [], [], []
    for r in np.unique(ring):
        m = ring == r
        if m.sum() >= 3:
            zs.append(np.median(z[m]))
            xl.append(x[m].min())
            xr.append(x[m].max())
    if len(zs) < 2:
        return 0.0
    zs, xl, xr = np.array(zs), np.array(xl), np.array(xr)
    slopes = []
    for xs in (xl, xr):
        edge = np.abs(xs - np.median(xs))
        full = np.flatnonzero(edge <= np.sort(edge)[min(1, len(edge) - 1)] + 0.025)
        for i in full:
            for k in full:
                if zs[k] - zs[i] > 0.05:
                    slopes.append((xs[k] - xs[i]) / (zs[k] - zs[i]))
    if not slopes:
        return 0.0
    return float(-np.arctan(np.median(slopes)))


def _staged_fit(model: _Model, theta: np.ndarray, dz: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, bool, int, float]:
    """Fit in stages; returns (theta, J, converged, iterations, chi2 per degree of freedom).

    First without the top/bottom crossings: roll and x from the side edges alone, so that a
    poor start cannot lock z and roll into a wrong pair of crossings; then with them, the
    bracket assignment redone with a tighter corner guard; a z profile after each stage, and a
    last fit if that profile moved z.
    """
    iters = 0
    for guard, crossings in ((0.005, False), (0.002, True)):
        model.classify(theta, guard, crossings)
        theta, j, conv, it = _gauss_newton(model, theta)
        iters += it
        theta = theta.copy()
        shift = dz[np.argmin(model.profile_z(theta, dz))]
        theta[2] += shift
    if abs(shift) > 0.0015:  # the profile moved z by more than its 1 mm grid: refit
        model.classify(theta, 0.002, True)
        theta, j, conv, it = _gauss_newton(model, theta)
        iters += it
    f = model.residuals(theta)
    return theta, j, conv, iters, float(f @ f / max(len(f) - 6, 1))


def _ray_points(model: _Model, theta: np.ndarray, tolerance: tuple[float, float]
                ) -> LabelledRays:
    """The rays that carry edge information, for `align.label_posterior`. Misses well inside
    and hits well outside the rectangle at ``theta`` are left out (dropouts, strays). A hit may
    lie up to ``tolerance`` (rad seen from the LiDAR: across the side edges, across the top and
    bottom edges) outside the rectangle and a miss as far inside it (`Hints.edge_tolerance`)."""
    rays, board = model.rays, model.board
    x, z, lam = board_coordinates(theta, rays.origin, rays.direction)
    lab = model.lab
    w2, h2, margin = board.width / 2, board.height / 2, feasible.OUTLIER_MARGIN
    inner = (np.abs(x) < w2 - margin) & (np.abs(z) < h2 - margin)
    outer = (np.abs(x) > w2 + margin) | (np.abs(z) > h2 + margin)
    use = ((lab == 1) & ~outer) | ((lab == 0) & ~inner)
    u = rays.direction[use]
    # the plate's side faces, seen by rays heading inwards past an edge (as `_Model.residuals`)
    rot = rotation(theta[3], theta[4], theta[5])
    dn = u @ rot.T
    ratio_x, ratio_z = dn[:, 0] / dn[:, 1], dn[:, 2] / dn[:, 1]
    ext = board.thickness * np.maximum(0.0, np.column_stack((ratio_x, -ratio_x, ratio_z,
                                                             -ratio_z)))
    lab = lab[use]
    per_edge = np.repeat(np.asarray(tolerance, dtype=float), 2)  # left, right, bottom, top
    ext += (lam[use] * np.where(lab == 1, 1.0, -1.0))[:, None] * per_edge
    return LabelledRays(rays.origin[use], u, lab, ext)


def _build_model(rays: _Rays, lab: np.ndarray, theta: np.ndarray, board: BoardSpec,
                 sigma_r: float, blur: float) -> _Model:
    """Brackets along the rings and between rings at the board's centre column, as a model."""
    x, _, _ = board_coordinates(theta, rays.origin, rays.direction)
    bh, bm = _brackets(rays, lab)
    vh, vm = _vertical_brackets(rays, lab, x, 0.0)
    return _Model(rays, lab, np.concatenate((bh, vh)), np.concatenate((bm, vm)), board,
                  sigma_r, blur)


#: Returns farther than this many sigma from the plane are not the board's face (the stand, a
#: mixed return at an edge); the variance of a unit Gaussian cut there (1 - 2 c phi(c) /
#: (2 Phi(c) - 1)) corrects the noise estimated from the rest.
TRIM = 2.5
TRIMMED_VARIANCE = 1.0 - 2.0 * TRIM * math.exp(-TRIM**2 / 2) / math.sqrt(2 * math.pi) / math.erf(
    TRIM / math.sqrt(2))


#: The least range noise assumed, m: a noise-free simulation (or one return per ring) still gets
#: a plane of finite uncertainty.
RANGE_SIGMA_FLOOR = 1e-3


def estimate_rays(scans: list[Scan], segs: list[Segmentation], board: BoardSpec,
                  hints: Hints) -> PoseEstimate:
    """Joint estimate from one or more scans of a static pose (their board clusters found)."""
    t0 = time.perf_counter()
    rng = np.random.default_rng(hints.seed)
    pts = [np.column_stack((s.x[g.board], s.y[g.board], s.z[g.board])) for s, g in
           zip(scans, segs, strict=True)]
    # robust start: RANSAC on the first scan's cluster
    n, d, _ = plane.ransac(pts[0], 0.04, rng, 100)
    # ML plane along the rays, all scans' returns within the RANSAC band
    o_l, u_l, r_l, k_l = [], [], [], []
    for s, g, p in zip(scans, segs, pts, strict=True):
        near = np.abs(p @ n - d) < 0.05
        sub = s.select(g.board[near])
        o_l.append(sub.origins())
        u_l.append(sub.directions())
        r_l.append(sub.distance)
        k_l.append(sub.ring)
    o_all, u_all, r_all = np.concatenate(o_l), np.concatenate(u_l), np.concatenate(r_l)
    ring_all = np.concatenate(k_l)
    n, d, _, sigma = plane.fit_rays(r_all, o_all, u_all, n, d)
    keep = np.abs(r_all - plane.predicted_range(n, d, o_all, u_all)) < TRIM * sigma
    n, d, _, sigma = plane.fit_rays(r_all[keep], o_all[keep], u_all[keep], n, d)
    # the board's rings hold many returns; the few that leak in from the stand (its base is
    # 5 cm in front of the board) sit on other rings: keep rings with a quarter of the most
    # and the board's rings are consecutive: keep the consecutive block with the most returns
    # (the stand's base, a parallel face 5 cm in front, lights up a ring or two below a gap)
    keep &= np.isin(ring_all, consecutive_ring_block(ring_all[keep]))
    n, d, c_plane, sigma = plane.fit_rays(r_all[keep], o_all[keep], u_all[keep], n, d,
                                          sigma_floor=RANGE_SIGMA_FLOOR)
    # the range noise: the user's, or the residuals' (a trimmed sample's understate it: undone
    # for Gaussian noise); the plane's covariance scaled to it
    sigma_r = hints.range_sigma or sigma / math.sqrt(TRIMMED_VARIANCE)
    ml_plane = (n, d, c_plane * (sigma_r / sigma) ** 2)
    t_plane = time.perf_counter()

    # initial pose: the plane; roll from the cluster's side edges; centred on the cluster
    ring_all = ring_all[keep]
    o_k, u_k = o_all[keep], u_all[keep]
    theta = pose_from_plane(n, d, 0.0)
    x, z, _ = board_coordinates(theta, o_k, u_k)
    theta = pose_from_plane(n, d, _initial_roll(x, z, ring_all))
    x, z, _ = board_coordinates(theta, o_k, u_k)
    # x, z shift the rays' board coordinates one for one (the plane does not depend on them)
    theta[0] -= 0.5 * (x.max() + x.min())
    theta[2] -= 0.5 * (z.max() + z.min())
    rays = _candidates(scans, segs, theta, board)
    x, z, lam = board_coordinates(theta, rays.origin, rays.direction)
    lab = _labels(rays, lam)
    hit = lab == 1
    rings_hit = np.unique(rays.ring[hit])
    if len(rings_hit) < 3:
        return PoseEstimate.failed(Status.TOO_FEW_RINGS, "rays", rings=len(rings_hit),
                                   reason=f"the board spans {len(rings_hit)} rings; 3 needed")

    dz = np.arange(-0.06, 0.0605, 0.001)
    model = _build_model(rays, lab, theta, board, sigma_r, hints.edge_blur)
    # z is the weakly known coordinate (rings are 2 deg apart) and a ring that crosses the top or
    # bottom edge pins it down sharply, but only once its bracket is matched to the right edge.
    # So: profile z over more than a ring spacing (label violations first); then returns far
    # outside the rectangle are not the board (the stand's base is level with the plane a ring
    # or two below it): mark them unknown and rebuild the brackets; profile again; fix the
    # bracket assignments leaving out those at corners, fit; reassign tighter, refit.
    theta[2] += dz[np.argmin(model.profile_z(theta, dz))]
    x, z, _ = board_coordinates(theta, rays.origin, rays.direction)
    stray = (lab == 1) & ((np.abs(x) > board.width / 2 + STRAY) |
                          (np.abs(z) > board.height / 2 + STRAY))
    if np.any(stray):
        lab = lab.copy()
        lab[stray] = -1
        model = _build_model(rays, lab, theta, board, sigma_r, hints.edge_blur)
        theta[2] += dz[np.argmin(model.profile_z(theta, dz))]
    iters = 0
    theta, j, conv, iters, chi2 = _staged_fit(model, theta, dz)
    if chi2 > 1.5:
        # a misfit (roll started too far off and a pair of top/bottom crossings held it there):
        # restart from other rolls and keep the best
        for droll in np.deg2rad([-2.0, -1.0, 1.0, 2.0]):
            start = theta.copy()
            start[3] += droll
            cand = _staged_fit(model, start, dz)
            if cand[4] < chi2:
                theta, j, conv, it, chi2 = cand
                iters += it
        model.classify(theta, 0.002, True)  # the state of the kept fit, for the diagnostics
        model.assign(theta)
    cov = np.linalg.pinv(j.T @ j)
    post = label_posterior(_ray_points(model, theta, hints.edge_tolerance), board, theta,
                           float(np.sqrt(max(cov[3, 3], 0.0))), ml_plane, len(scans), rng)
    if post is not None:
        theta, cov = post
        model.classify(theta, 0.002, True)  # the diagnostics below describe this pose
        model.assign(theta)
    t_fit = time.perf_counter()

    # what was seen: both side edges on at least two rings, nothing in front of the board
    x, z, lam = board_coordinates(theta, rays.origin, rays.direction)
    k, sgn = model.edge_kind, model.edge_sign
    n_left = int(np.sum((k == 1) & (sgn < 0)))
    n_right = int(np.sum((k == 1) & (sgn > 0)))
    n_top = int(np.sum((k == 2) & (sgn > 0)))
    n_bottom = int(np.sum((k == 2) & (sgn < 0)))
    w2, h2 = board.width / 2, board.height / 2
    inside = (np.abs(x) < w2) & (np.abs(z) < h2)
    occluded = int(np.sum(inside & (lab == -1)))
    inside_miss = int(np.sum(inside & (np.abs(x) < w2 - 0.02) & (np.abs(z) < h2 - 0.02) &
                             (lab == 0)))
    diag = {
        "rings": len(rings_hit), "rays": len(lab), "hits": int(hit.sum()),
        "range_residuals": int(model.use_range.sum()), "brackets": int(np.sum(k > 0)),
        "edges_left": n_left, "edges_right": n_right, "edges_top": n_top,
        "edges_bottom": n_bottom, "occluded_rays": occluded, "inside_misses": inside_miss,
        "range_sigma_m": sigma_r, "iterations": iters,
        "chi2_per_dof": float(np.sum(model.residuals(theta) ** 2) / max(len(j) - 6, 1)),
    }
    outside_hits = int(np.sum((lab == 1) & ((np.abs(x) > w2 + 0.02) | (np.abs(z) > h2 + 0.02))))
    diag["outside_hits"] = outside_hits
    status = Status.OK
    n_inside = max(int(np.sum(inside)), 1)
    n_hit = max(int(hit.sum()), 1)
    if (n_left < 2 or n_right < 2 or occluded > 0.03 * n_inside or inside_miss > 0.03 * n_inside
            or outside_hits > 0.03 * n_hit or diag["chi2_per_dof"] > 3.0
            or model.use_range.sum() < 0.5 * n_hit):
        # the known rectangle does not explain what was seen: part of the board is hidden,
        # dark or outside the field of view (or something board-like is not the board)
        status = Status.PARTIAL_BOARD
        diag["reason"] = ("the board's rectangle is not fully seen: side edges on "
                          f"{n_left}/{n_right} rings, {occluded} rays blocked in front, "
                          f"{inside_miss} misses inside, {outside_hits} hits outside, "
                          f"chi2/dof {diag['chi2_per_dof']:.1f}")
    elif not conv:
        status = Status.NOT_CONVERGED
    used = {"board": rays.gidx[model.use_range],
            "features": np.stack((rays.gidx[model.bh[k > 0]], rays.gidx[model.bm[k > 0]]), axis=1)}
    timings = {"plane": t_plane - t0, "fit": t_fit - t_plane}
    return PoseEstimate(status, "rays", Pose.from_array(theta), cov, diag, used, timings)
