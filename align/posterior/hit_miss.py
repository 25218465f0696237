"""The pose as the posterior mean given the ranges' plane and every hit/miss label.

For a plane, the posterior of roll, x and z given the labels is exact (`align.posterior.moments`:
uniform on the poses consistent with every label). The plane itself is uncertain (the ranges' fit,
`align.plane.fit.fit_rays`: n, d and the covariance C_g of g = (alpha, beta, d)), so it is
integrated out: each plane's in-plane posterior is weighted by the labels' evidence for it (the
consistent set's volume) and by the ranges' density. The labels thereby sharpen the plane a little
(a board of known width seen at the right distance), and they can rule a plane out: a distance a few
mm off puts a hit at one side edge and a miss at the other closer together than the board is wide.

The integral over g is a 3 x 3 x 3 Gauss-Hermite rule on the ranges' Gaussian: its error for the
smooth way the pose moves with the plane is far below that of random draws (two dozen importance
samples left 1.5 mm of Monte Carlo noise in x and 0.04 deg in tilt; the rule, under 0.2 mm and
0.01 deg). Where the labels rule out the ML plane the rule is centred on the nearest plane they
allow, the ranges' density put back in the weights. Where they allow only a band of planes
narrower than the rule's spacing (too few nodes, or all on one level of some direction: fused
scans, 0.3 % of them on the paper's protocol, were 20-50 sigma off in yaw), the rule is applied
again about the allowed nodes, a third as wide, up to twice; importance sampling in batches of
antithetic draws is the last resort.

The covariance is J C J^T + K P K^T: J = d pose / d g, fitted over the nodes (the plane's
uncertainty carried through the whole estimate); C the plane's covariance given the ranges and
the labels (C_g's precision plus the curvature of a quadratic fitted to the labels' log evidence
over the nodes; the nodes' weighted spread understates it where the labels cut the Gaussian); P
the posterior's covariance of (roll, x, z) given the plane (averaged over the nodes) and K =
d pose / d (roll, x, z) at a fixed plane. With a common range offset b as a nuisance, C is the
joint profile's instead (`_joint_profile`): the labels' evidence on a grid over b and a 3-point
rule over the one direction of the plane the least-squares fit says they couple with b (the
board's width ties distance to yaw), the ranges' conditional in the rest; with per-laser offsets
as well, a tensor of 3-point rules over every direction of the plane given b (they widen it in
tilt, where the labels hold it better than the ranges).
"""

from __future__ import annotations

import functools
import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

import align.symmetry as symmetry
from align.board import BoardSpec
from align.geometry import lidar_up, plane_of_pose, pose_from_plane, rotation
from align.plane.fit import tangent_basis
from align.posterior import moments
from align.posterior.moments import binding_rays

#: Rolls of each in-plane posterior's grid over the consistent ones.
FINE_ROLLS = 121
#: At most this many roll grids per plane, each wider on the side where its consistent rolls
#: ran off the last (the plane moves them).
GRID_TRIES = 3
#: Gauss-Hermite nodes per plane parameter, and at most this many rules, each a third as wide
#: about the planes the last one's labels allowed.
QUADRATURE_ORDER = 3
RULE_REFINEMENTS = 3
#: A rule whose nodes' weighted mean lies more than this many of its standard deviations from
#: its centre along one of its directions is placed again about that mean, at most `RECENTRES`
#: times (the 3-point rule's outer nodes are 1.7 of them out).
OFF_CENTRE = 1.0
RECENTRES = 2
#: Fewer planes than this consistent with the labels: importance sampling instead of the rule;
#: fewer after all its batches: no posterior (the caller's least-squares pose stands).
MIN_PLANES = 8
#: Importance sampling: draws per batch (antithetic pairs) and at most this many batches.
PLANE_SAMPLES = 24
PLANE_BATCHES = 4
#: Roll searched by a single scan's first pass, either side of the start, rad, and its step: a
#: least-squares fit caught in a wrong basin is a few degrees off.
SINGLE_SCAN_HALF = np.deg2rad(4.0)
SINGLE_SCAN_STEP = np.deg2rad(0.02)


@dataclass
class OffsetModel:
    """A common range offset b as a nuisance of the plane: the ranges' joint Gaussian of g = (alpha,
    beta, d) (about the ML plane, `align.plane.fit.fit_rays_offsets`) and b, given as b's estimate
    from the ranges ``b_hat``, its covariance with g ``c_gb`` (3,) and variance ``c_bb``;
    ``centre``, ``centre_std``: b and its sigma from a fit that saw the board's size (the least
    squares), where to look; ``slope``: that fit's d pose / d b (its covariance's regression, (6,)),
    the direction in which the labels trade the offset against the plane's other directions (None:
    not known); ``c_noise``: with per-laser offsets as random effects, the ranges' covariance of g
    given b from their noise alone (the per-laser offsets left out), which says in what direction
    those offsets widen the plane (None: none modelled). `label_posterior` fills in ``mean`` and
    ``std``: b's posterior given the ranges and the labels."""

    b_hat: float
    c_gb: np.ndarray
    c_bb: float
    centre: float = 0.0
    centre_std: float = 0.0
    slope: np.ndarray | None = None
    c_noise: np.ndarray | None = None
    mean: float | None = None
    std: float | None = None


#: The offset's profile (`_offset_profile`): points per grid, reach in the start's sigmas,
#: refinements about the allowed band when fewer than `PROFILE_MIN` points are allowed.
PROFILE_POINTS = 21
PROFILE_REACH = 5.0
PROFILE_REFINE = 3
PROFILE_MIN = 5
#: Rolls of the profile's grid (`_consistent_rolls`): a fused estimate's first pass has 201.
PROFILE_ROLLS = 201
#: The joint profile (`_joint_profile`) along the direction the labels couple with the
#: offset: fewer than `COUPLED_MIN` of its 3 Gauss-Hermite levels allowed, a grid of
#: `COUPLED_POINTS` levels over the band they allow instead, refined up to `COUPLED_REFINE`
#: times.
COUPLED_MIN = 3
COUPLED_POINTS = 7
COUPLED_REFINE = 2


@dataclass(frozen=True)
class LabelledRays:
    """The rays that carry edge information: origins and unit directions (M, 3) in {L}, labels
    (1 hit, 0 miss) and the plate's side face's widening of the left, right, bottom and top edge
    for each ray (M, 4), m. ``odds`` (M,): for a hit, how much likelier its return is off the
    board than on it (`moments.soft_moments`; None or 0: a hard constraint)."""

    origin: np.ndarray
    direction: np.ndarray
    label: np.ndarray
    ext: np.ndarray
    odds: np.ndarray | None = None

    def select(self, mask: np.ndarray) -> LabelledRays:
        return LabelledRays(self.origin[mask], self.direction[mask], self.label[mask],
                            self.ext[mask], None if self.odds is None else self.odds[mask])

    def near(self, board: BoardSpec, ref: np.ndarray, reach: float) -> LabelledRays:
        """The labels that can bind for rectangles whose roll, x and z differ from the pose
        ``ref``'s by at most ``reach`` rad and about 20 mm (100 mm across the rings, the
        LiDAR's up direction on the board: a ring spacing): a point as far from the plane's
        origin as the board's corners (plus 0.2 m) moves that far x the roll change."""
        vx, vz = lidar_up(ref)
        arm = (0.5 * board.diagonal + 0.2) * reach
        # `binding` of the rays' board coordinates, compiled (`binding_rays`: the same floats
        # and tests), its hits and misses apart: the subset's
        # split for the posterior's kernel taken from them, not from masks over it
        hits, misses = binding_rays(self.origin, self.direction, self.label,
                                    rotation(ref[3], ref[4], ref[5]), float(ref[0]),
                                    float(ref[1]), float(ref[2]), board.width / 2,
                                    board.height / 2, 0.02 + 0.08 * abs(vx) + arm,
                                    0.02 + 0.08 * abs(vz) + arm)
        out = self.select(np.sort(np.concatenate((hits, misses))))
        # `_split`'s value, as cached_property stores it (the instance's dict: the class is
        # frozen): the same arrays as the subset's masks would give
        out.__dict__["_split"] = tuple(
            np.ascontiguousarray(a[rows], dtype=np.float64) for rows in (hits, misses)
            for a in (self.origin, self.direction, self.ext))
        return out

    @functools.cached_property
    def _split(self) -> tuple[np.ndarray, ...]:
        """The hits' origins, directions and widenings, then the misses': contiguous float64,
        `moments.plane_posteriors`' arguments (split once, not per plane)."""
        hit, miss = self.label == 1, self.label == 0
        return tuple(np.ascontiguousarray(a[mask], dtype=np.float64) for mask in (hit, miss)
                     for a in (self.origin, self.direction, self.ext))

    @functools.cached_property
    def _hit_odds(self) -> np.ndarray:
        """The hits' odds, contiguous float64; empty when every label is hard."""
        if self.odds is None:
            return np.empty(0)
        return np.ascontiguousarray(self.odds[self.label == 1], dtype=np.float64)

    def posteriors(self, normals: np.ndarray, ds: np.ndarray, board: BoardSpec,
                   rolls: np.ndarray, roll_prior: tuple[float, float] | None = None
                   ) -> list[tuple[moments.InPlanePosterior, np.ndarray] | None]:
        """`in_plane` for each plane normals[i] . p = ds[i] ((P, 3), (P,)) in one compiled call,
        each with the pose (6,) of its posterior's mean (`_pose`); None where no roll on the
        grid is consistent with the labels. Each label's likelihood is
        `align.posterior.moments.label_moments`' (1 on the positions its box allows, else 0;
        a soft hit's ``odds`` off it, `moments.soft_moments`)."""
        weight = roll_weight(board, rolls, roll_prior)
        rows = moments.plane_posteriors(
            *self._split, np.ascontiguousarray(normals, dtype=np.float64),
            np.ascontiguousarray(ds, dtype=np.float64),
            np.ascontiguousarray(rolls, dtype=np.float64), weight, board.width / 2,
            board.height / 2, self._hit_odds)
        return [_unpack(row) if row[moments.OK] else None for row in rows]

    def in_plane(self, n: np.ndarray, d: float, board: BoardSpec, rolls: np.ndarray,
                 roll_prior: tuple[float, float] | None = None
                 ) -> moments.InPlanePosterior | None:
        """`moments.in_plane_posterior` for the plane n . p = d, with the roll prior
        (mean, 1-sigma, rad; compared modulo the board's symmetry) if given."""
        found = self.posteriors(np.asarray(n)[None, :], np.array([d]), board, rolls, roll_prior)[0]
        return None if found is None else found[0]


def roll_weight(board: BoardSpec, rolls: np.ndarray, roll_prior: tuple[float, float] | None
                ) -> np.ndarray:
    """The roll prior's density over ``rolls`` (mean, 1-sigma, rad; compared modulo the
    board's symmetry), unnormalised; empty for none (flat), as `moments.plane_posteriors`
    takes it."""
    if roll_prior is None:
        return np.empty(0)
    p = symmetry.period(board)
    dev = (rolls - roll_prior[0] + p / 2) % p - p / 2
    return np.exp(-0.5 * (dev / roll_prior[1]) ** 2)


def _unpack(row: np.ndarray) -> tuple[moments.InPlanePosterior, np.ndarray]:
    """One row of `moments.plane_posteriors`: the posterior and its pose."""
    k, own = moments, row.copy()  # one copy; the posterior and the pose are views of it
    post = moments.InPlanePosterior(own[k.MEAN:k.MEAN + 3], own[k.COV:k.COV + 9].reshape(3, 3),
                                     float(own[k.EVIDENCE]),
                                     (float(own[k.SUPPORT]), float(own[k.SUPPORT + 1])))
    return post, own[k.POSE:k.POSE + 6]


def binding(board: BoardSpec, x: np.ndarray, z: np.ndarray, lab: np.ndarray, mx: float,
            mz: float) -> np.ndarray:
    """The labels that can constrain a rectangle within (mx, mz) m of the one at which the
    rays' board coordinates are ``x``, ``z``: hits not deeper inside, misses not farther
    outside."""
    w2, h2 = board.width / 2, board.height / 2
    inner = (np.abs(x) < w2 - mx) & (np.abs(z) < h2 - mz)
    outer = (np.abs(x) > w2 + mx) | (np.abs(z) > h2 + mz)
    return ((lab == 1) & ~inner) | ((lab == 0) & ~outer)


def _pose(n: np.ndarray, d: float, q: np.ndarray) -> np.ndarray:
    """The pose (x, y, z, roll, tilt, yaw) of the plane n . p = d with roll, x, z = q."""
    th = pose_from_plane(n, d, q[0])
    th[0], th[2] = q[1], q[2]
    return th


def label_posterior(rays: LabelledRays, board: BoardSpec, theta: np.ndarray, sd_roll: float,
                    ml_plane: tuple[np.ndarray, float, np.ndarray], n_scans: int,
                    rng: np.random.Generator, roll_prior: tuple[float, float] | None = None,
                    offset: OffsetModel | None = None
                    ) -> tuple[np.ndarray, np.ndarray] | None:
    """The posterior mean pose and its covariance (6, 6), or None: too few planes explain the
    labels (blurred edges, a dropout at an edge).

    ``theta``, ``sd_roll``: a least-squares fit and its roll's standard deviation, only for where
    to look and how wide (``n_scans`` 1: `SINGLE_SCAN_HALF` of roll, wrong basins included).
    ``ml_plane``: the ranges' plane n, d and the covariance of (alpha, beta, d), `fit_rays`.
    ``rng``: for the planes tried when the labels rule out the ML plane and the nearest
    distances, and for the importance sampling fallback. ``roll_prior``: (mean, 1-sigma) of
    the roll, rad (`align.Hints.roll_prior`), multiplied into the posterior; None: flat.
    ``offset``: the ranges carry a common offset (``ml_plane``'s covariance includes it): the
    labels then hold the distance along the direction the offset moves the plane, which is
    first profiled jointly with the plane's direction the labels trade it against
    (`_joint_profile`; the band the labels allow can be far narrower than the offset's prior),
    the rule placed on the plane's posterior it gives and the covariance taken from it. Its
    posterior is written into ``offset``.
    """
    frame = _PlaneFrame.of(ml_plane)
    found = _consistent_rolls(rays, board, theta, sd_roll, frame, n_scans, rng, roll_prior,
                              offset)
    if found is None:
        return None
    centre, coarse, c_band, step = found
    grid = _FineGrid.about(rays, board, frame, centre, coarse, step, roll_prior)
    return _integrate(grid, frame, centre, c_band, offset, rng)


@dataclass(frozen=True)
class _PlaneFrame:
    """The ranges' plane (n0, d0), the covariance of (alpha, beta, d) about it and the tangent
    basis the small rotations alpha, beta turn its normal along (`fit_rays`')."""

    n0: np.ndarray
    d0: float
    c_plane: np.ndarray
    e1: np.ndarray
    e2: np.ndarray

    @classmethod
    def of(cls, ml_plane: tuple[np.ndarray, float, np.ndarray]) -> _PlaneFrame:
        n0, d0, c_plane = ml_plane
        return cls(n0, d0, c_plane, *tangent_basis(n0))

    def moved(self, g: np.ndarray) -> tuple[np.ndarray, float]:
        """The plane (n, d) at g = (alpha, beta, delta d) from (n0, d0)."""
        n = self.n0 + g[0] * self.e1 + g[1] * self.e2
        return n / np.linalg.norm(n), self.d0 + g[2]


def _consistent_rolls(rays: LabelledRays, board: BoardSpec, theta: np.ndarray, sd_roll: float,
                      frame: _PlaneFrame, n_scans: int, rng: np.random.Generator,
                      roll_prior: tuple[float, float] | None, offset: OffsetModel | None
                      ) -> tuple | None:
    """Step 1: where the rolls consistent with the labels lie: at the ML plane or, when the
    labels rule that out, at the nearest distance they allow (then at random planes); with an
    offset, at the joint profile's centre. (centre g, that plane's coarse posterior, the
    profile's covariance or None, the roll step) or None."""
    if n_scans == 1:
        half, step = SINGLE_SCAN_HALF, SINGLE_SCAN_STEP
    else:
        half = float(np.clip(10 * sd_roll, np.deg2rad(0.2), SINGLE_SCAN_HALF))
        step = half / 100
    wide = rays.near(board, theta, half)
    rolls = theta[3] + np.arange(-half, half + 0.5 * step, step)
    c_plane = frame.c_plane
    if offset is not None:
        # the rule's proposal: the plane's posterior from the joint profile of the offset and
        # the direction it trades against
        v = offset.c_gb / offset.c_bb
        c_cond = c_plane - np.outer(offset.c_gb, offset.c_gb) / offset.c_bb
        w = _coupled_direction(offset, theta, frame.n0, frame.d0, v, c_cond)
        axes = ([w] if w is not None else []) + laser_directions(offset, c_cond, w)
        # the profile's planes on a grid of `PROFILE_ROLLS` rolls, as a fused estimate's first
        # pass has them: a single scan's 0.02 deg steps over +-4 deg (401) made its some 650
        # planes cost 0.2 s; its roll's sigma is 0.1-0.3 deg, several steps of 0.04 deg
        p_rolls = (rolls if len(rolls) <= PROFILE_ROLLS
                   else np.linspace(rolls[0], rolls[-1], PROFILE_ROLLS))

        def in_planes(gs: list[np.ndarray]) -> list[moments.InPlanePosterior | None]:
            # a profile's planes in one compiled call: a single scan's integral tries some 650
            # (27 nodes with per-laser offsets); one call each cost 3 % more CPU (side by side)
            planes = [frame.moved(g) for g in gs]
            found = wide.posteriors(np.array([n for n, _ in planes]),
                                    np.array([d for _, d in planes]), board, p_rolls,
                                    roll_prior)
            return [None if f is None else f[0] for f in found]

        profile = _joint_profile(offset, v, axes, c_cond, in_planes)
        if profile is not None:
            centre, coarse, c_band = profile
            return centre, coarse, c_band, step
    # other distances k sigma away, the normal moved with them as the ranges correlate it
    # (a board seen obliquely: distance and tilt are strongly correlated, and a distance moved
    # alone would leave the ranges' ellipsoid by far more than k sigma); then random planes
    along_d = c_plane[:, 2] / np.sqrt(c_plane[2, 2])
    starts = [k * along_d for k in (0, 1, -1, 2, -2, 3, -3)]
    random = (rng.multivariate_normal(np.zeros(3), c_plane) for _ in range(PLANE_SAMPLES))
    for centre in itertools.chain(starts, random):
        coarse = wide.in_plane(*frame.moved(centre), board, rolls, roll_prior)
        if coarse is not None:
            return centre, coarse, None, step
    return None


class _FineGrid:
    """Step 2: each plane's posterior on a fine grid over the consistent rolls (a little wider),
    from the labels that can bind. Where a plane's consistent rolls run off the grid's end,
    that plane again on a grid wider on that side (evidence and moments are integrals: the
    planes need not share a grid)."""

    def __init__(self, rays: LabelledRays, board: BoardSpec, frame: _PlaneFrame,
                 base: np.ndarray, ref: np.ndarray, roll_prior: tuple[float, float] | None):
        self.rays, self.board, self.frame = rays, board, frame
        self.base, self.ref, self.roll_prior = base, ref, roll_prior
        self._subsets: dict[float, LabelledRays] = {}

    @classmethod
    def about(cls, rays: LabelledRays, board: BoardSpec, frame: _PlaneFrame,
              centre: np.ndarray, coarse: moments.InPlanePosterior, step: float,
              roll_prior: tuple[float, float] | None) -> _FineGrid:
        """The grid about the plane ``centre``'s ``coarse`` posterior (its support padded)."""
        lo, hi = coarse.support
        pad = max(2 * step, 0.25 * (hi - lo))
        base = np.linspace(lo - pad, hi + pad, FINE_ROLLS)
        return cls(rays, board, frame, base, _pose(*frame.moved(centre), coarse.mean),
                   roll_prior)

    def binding_for(self, rolls: np.ndarray) -> LabelledRays:
        """The labels that can bind over a grid's reach from the reference (cached per reach)."""
        reach = float(np.max(np.abs(rolls - self.ref[3])))
        if reach not in self._subsets:
            self._subsets[reach] = self.rays.near(self.board, self.ref, reach)
        return self._subsets[reach]

    def widened(self, found: tuple[moments.InPlanePosterior, np.ndarray] | None,
                n: np.ndarray, d: float) -> tuple[moments.InPlanePosterior, np.ndarray] | None:
        """A plane's posterior on the base grid again on wider grids while its rolls run off
        the end."""
        rolls = self.base
        for _ in range(GRID_TRIES - 1):
            if found is None:
                return None
            low, high = found[0].support[0] <= rolls[0], found[0].support[1] >= rolls[-1]
            if not (low or high):
                break
            span = rolls[-1] - rolls[0]
            rolls = np.linspace(rolls[0] - low * span, rolls[-1] + high * span, FINE_ROLLS)
            found = self.binding_for(rolls).posteriors(n[None, :], np.array([d]), self.board,
                                                       rolls, self.roll_prior)[0]
        return found

    def evaluate(self, planes: np.ndarray, log_q: np.ndarray) -> list[_Node]:
        """Every plane on the base grid in one call; the few that run off it one by one."""
        f = self.frame
        normals = f.n0 + planes[:, :1] * f.e1 + planes[:, 1:2] * f.e2
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        ds = f.d0 + planes[:, 2]
        nodes = []
        first = self.binding_for(self.base).posteriors(normals, ds, self.board, self.base,
                                                       self.roll_prior)
        for i, found in enumerate(first):
            found = self.widened(found, normals[i], float(ds[i]))
            if found is not None:
                nodes.append(_Node(planes[i], log_q[i], i, found[1], found[0]))
        return nodes


def _integrate(grid: _FineGrid, frame: _PlaneFrame, centre: np.ndarray,
               c_band: np.ndarray | None, offset: OffsetModel | None,
               rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray] | None:
    """Step 3: the integral over the plane: the rule about the centre. Where the labels allow a
    band of planes narrower than the rule's spacing (too few of its nodes, or all on one level
    of some direction), the rule again about the nodes they allowed, a third as wide; last,
    importance sampling in batches. The ranges' density over the rule's or sampler's goes into
    each node's weight. The rule's proposal is the ranges' Gaussian, or with an offset the
    plane's posterior from the joint profile (``c_band``)."""
    c_plane = frame.c_plane
    c_q = c_plane if c_band is None else c_band
    c_inv, q_inv = np.linalg.inv(c_plane), np.linalg.inv(c_q)

    def done(nodes: list[_Node]) -> tuple[np.ndarray, np.ndarray]:
        if c_band is None:
            return _moments(nodes, c_plane)
        # with an offset the labels' information is the joint profile's (exact in the plane's
        # directions it profiles: the offset's line, w and, with per-laser offsets, the way
        # they widen the plane); the rest is the ranges' given b. A quadratic fitted to the
        # labels' log evidence over the rule's nodes instead (as without an offset) sees a
        # band of flat evidence with cliffs: it put 2.3 mm of sigma on an offset known to
        # 0.7 mm, and roll's sigma twice its error
        mean, cov = _moments(nodes, c_band, given=True)
        _offset_posterior(offset, nodes, c_plane, c_band)
        return mean, cov

    m, scale = centre, 1.0
    recentred = 0
    for _ in range(RULE_REFINEMENTS + RECENTRES):
        planes, log_q = gauss_hermite(m, scale**2 * c_q, QUADRATURE_ORDER)
        nodes = grid.evaluate(planes, log_q + _log_density_ratio(planes, c_inv, m, scale, q_inv))
        if len(nodes) >= MIN_PLANES and _spans(nodes):
            # a rule whose weight sits at one side (the labels' evidence still rising at its
            # outer nodes) measures the band's slope, not its extent: its quadratic gave a
            # sigma a sixth of the error (per-laser offsets, tilt 8 sigma off). Again about
            # the weighted mean, as wide
            shift = _off_centre(nodes, m, scale**2 * c_q)
            if shift is None or recentred == RECENTRES:
                return done(nodes)
            m, recentred = shift, recentred + 1
            continue
        if not nodes:
            break
        m = _weights(nodes) @ np.array([nd.g for nd in nodes])
        scale /= 3.0
    nodes = []
    for _ in range(PLANE_BATCHES):
        half_batch = rng.multivariate_normal(np.zeros(3), c_q, PLANE_SAMPLES // 2)
        planes = centre + np.vstack((half_batch, -half_batch))
        nodes += grid.evaluate(planes, _log_density_ratio(planes, c_inv, centre, 1.0, q_inv))
        if len(nodes) >= MIN_PLANES:
            return done(nodes)
    return None


def _coupled_direction(offset: OffsetModel, theta: np.ndarray, n0: np.ndarray, d0: float,
                       v: np.ndarray, c_cond: np.ndarray) -> np.ndarray | None:
    """The direction w of the plane g = (alpha, beta, d) about (n0, d0), other than the offset's
    own line ``v``, along which the labels pull the plane as b moves: w = v - r, r the
    least-squares fit's d g / d b (its ``offset.slope`` mapped to the plane; the brackets hold
    the board's width, so a longer offset there also turns the plane in yaw), scaled to one
    sigma of the ranges' conditional ``c_cond`` (the plane given b). None: no slope, or the
    fit moves the plane exactly as the ranges do (nothing to couple)."""
    if offset.slope is None or not np.all(np.isfinite(offset.slope)):
        return None
    e1, e2 = tangent_basis(n0)

    def g_of(th: np.ndarray) -> np.ndarray:
        # the inverse of label_posterior's moved(g): n ~ n0 + alpha e1 + beta e2, d = d0 + g[2]
        n, d = plane_of_pose(th)
        return np.array([n @ e1 / (n @ n0), n @ e2 / (n @ n0), d - d0])

    h = 1e-4  # m of offset: the pose's response is linear far beyond it
    r = (g_of(theta + h * offset.slope) - g_of(theta - h * offset.slope)) / (2 * h)
    y = v - r
    m2 = float(y @ np.linalg.solve(c_cond, y))
    if not (np.isfinite(m2) and m2 > 0):
        return None
    return y / math.sqrt(m2)


def laser_directions(offset: OffsetModel, c_cond: np.ndarray, w: np.ndarray | None
                      ) -> list[np.ndarray]:
    """The plane's directions independent of ``w`` under the ranges' conditional ``c_cond``
    (the plane given b, per-laser offsets included), each one sigma of it, the one in which the
    per-laser offsets widen the plane most over the ranges' noise alone (``offset.c_noise``)
    first. Offsets that differ ring to ring lean the plane across the rings (tilt, with
    distance): the labels hold it there (the board's known height, its side edges across the
    rings) better than the ranges; left at the ranges' conditional, tilt's sigma was 1.3-1.5
    times its error. Empty: no per-laser offsets modelled."""
    if offset.c_noise is None:
        return []
    chol = np.linalg.cholesky(c_cond)
    # in the standardised plane (c_cond = I): the noise's share, the offsets' the rest
    a = np.linalg.solve(chol, np.linalg.solve(chol, offset.c_noise).T)
    basis = np.eye(3)
    if w is not None:
        om = np.linalg.solve(chol, w)  # unit: w is one sigma of c_cond
        basis = np.linalg.svd(om[None, :])[2][1:].T  # orthonormal, orthogonal to om
    share = basis.T @ (np.eye(3) - 0.5 * (a + a.T)) @ basis
    vecs = np.linalg.eigh(share)[1]
    return [chol @ (basis @ vecs[:, i]) for i in range(vecs.shape[1] - 1, -1, -1)]


def _joint_profile(offset: OffsetModel, v: np.ndarray, axes: list[np.ndarray],
                   c_cond: np.ndarray, in_planes: Callable
                   ) -> tuple[np.ndarray, moments.InPlanePosterior, np.ndarray] | None:
    """The labels' evidence over the offset b jointly with the plane's directions ``axes``
    they hold beyond the ranges: the one b trades against (w, `_coupled_direction`) and, with
    per-laser offsets, the rest (`laser_directions`). The plane is
    g = v (b - b_hat) + sum_k s_k a_k, each s_k the ranges' standard normal along a_k (given b,
    independent of it and of each other), integrated over the s_k by a tensor of 3-point
    Gauss-Hermite rules and over b by `_offset_profile` at each node. The band found along the
    one line s = 0 is conditional on s and too narrow where the labels couple b with w (yaw and
    distance in the board's width: fused, b's chi2 was 3.5 against it). ``c_cond``: the
    ranges' covariance of g given b (each a_k is one sigma of it). Returns the plane at the
    posterior mean, the most probable node's coarse in-plane posterior and the plane's
    posterior covariance (3, 3), or None where no plane explains the labels."""
    x, wt = _hermite(3)
    rule = list(zip(x, np.log(wt / wt.sum()), strict=True))
    levels = [rule for _ in axes]
    spacing = [float(x[1] - x[0]) for _ in axes]
    floor = [0.0 for _ in axes]
    profiles: dict[tuple[float, ...], tuple | None] = {}
    for _ in range(1 + COUPLED_REFINE):
        found = []
        for node in itertools.product(*levels):
            key = tuple(float(s) for s, _ in node)
            if key not in profiles:
                g0 = np.zeros(3)
                for s, a in zip(key, axes, strict=True):
                    g0 = g0 + s * a
                profiles[key] = _offset_profile(offset, v, in_planes, g0)
            prof = profiles[key]
            if prof is not None:
                found.append((key, sum(lw for _, lw in node) + prof[0], *prof[1:]))
        if not found:
            return None
        narrow = [k for k in range(len(axes)) if len({f[0][k] for f in found}) < COUPLED_MIN]
        if not narrow:
            break
        # the labels allow a band in s_k narrower than the levels' spacing (a near miss of the
        # board's width: one level left a sliver of 0.06 mm in b, and yaw 3.7 sigma off): a
        # uniform grid over it instead, the ranges' density times the spacing the weights,
        # the spacing's resolution a floor of s_k's variance
        for k in narrow:
            lo = min(f[0][k] for f in found) - spacing[k]
            hi = max(f[0][k] for f in found) + spacing[k]
            grid = np.linspace(lo, hi, COUPLED_POINTS + 2)[1:-1]
            spacing[k] = float(grid[1] - grid[0])
            levels[k] = [(float(g), -0.5 * g**2 + math.log(spacing[k])) for g in grid]
            floor[k] = spacing[k]**2 / 12
    # one contiguous array per axis (the sums below as without the per-laser axis)
    s_l = [np.array([f[0][k] for f in found]) for k in range(len(axes))]
    log_p = np.array([f[1] for f in found])
    p = np.exp(log_p - log_p.max())
    p /= p.sum()
    m_b = np.array([f[2] for f in found])
    v_b = np.array([f[3] for f in found])
    mean_b = float(p @ m_b)
    mean_s = [float(p @ s_l[k]) for k in range(len(axes))]
    var_b = float(p @ (v_b + m_b**2) - mean_b**2)
    cov_bs = [float(p @ (s_l[k] * m_b) - mean_b * mean_s[k]) for k in range(len(axes))]
    ridge, centre = v, v * (mean_b - offset.b_hat)
    for k, a in enumerate(axes):
        ridge = ridge + a * cov_bs[k] / var_b
        centre = centre + mean_s[k] * a
    best = found[int(np.argmax(log_p + np.log([f[5] for f in found])))][4]
    # the plane's covariance by the law of total variance over b: between offsets, b's
    # marginal variance along the way the plane's mean moves with it (the ridge: distance and
    # yaw together, as the board's width allows); given b, the profile's covariance of the
    # s_k in place of the ranges' (unit, independent), and the ranges' conditional in the
    # directions independent of the axes
    c_band = c_cond + var_b * np.outer(ridge, ridge)
    for k, j in itertools.product(range(len(axes)), repeat=2):
        c_sk = float(p @ (s_l[k] * s_l[j]) - mean_s[k] * mean_s[j])
        if k == j:
            c_sk += floor[k]
        c_sk -= cov_bs[k] * cov_bs[j] / var_b
        if k == j:
            c_sk -= 1.0  # the ranges' unit variance along a_k, in c_cond, replaced
        c_band += c_sk * np.outer(axes[k], axes[j])
    return centre, best, c_band


def _offset_profile(offset: OffsetModel, v: np.ndarray, in_planes: Callable, g0: np.ndarray
                    ) -> tuple[float, float, float, moments.InPlanePosterior, float] | None:
    """Where the labels put the offset along one line: the evidence of the planes
    g0 + v (b - b_hat) (the ranges' plane for offset b, moved by ``g0``) times the ranges'
    density of b, on a grid about the least-squares offset, refined about the band it allows.
    Returns the log of its integral over b (trapezoids over every b tried, those with no
    consistent pose at zero), b's mean and variance (m, m^2) on the line, the most probable
    plane's coarse in-plane posterior and its normalised weight, or None where no plane on
    the grid explains the labels. ``in_planes``: the coarse in-plane posteriors of a list of
    planes g (None where no roll is consistent), one compiled call for the list."""
    sd_prior = math.sqrt(offset.c_bb)
    sd = float(np.clip(offset.centre_std, 1e-4, sd_prior))
    lo, hi = offset.centre - PROFILE_REACH * sd, offset.centre + PROFILE_REACH * sd
    tried: dict[float, tuple[float, moments.InPlanePosterior | None]] = {}
    for _ in range(PROFILE_REFINE):
        bs = np.linspace(lo, hi, PROFILE_POINTS)
        posts = in_planes([g0 + v * (b - offset.b_hat) for b in bs])
        for b, post in zip(bs, posts, strict=True):
            ok = post is not None and post.evidence > 0
            tried[float(b)] = ((math.log(post.evidence) - 0.5 * (b - offset.b_hat)**2
                                / offset.c_bb) if ok else -math.inf, post if ok else None)
        step = bs[1] - bs[0]
        allowed = [b for b, (lw, _) in tried.items() if lw > -math.inf]
        inside = [b for b in allowed if lo <= b <= hi]
        if len(inside) >= PROFILE_MIN:
            break
        if not allowed:
            # nothing allowed: widen once to the prior's reach, then give up
            if hi - lo >= 2 * PROFILE_REACH * sd_prior:
                return None
            lo = offset.b_hat - PROFILE_REACH * sd_prior
            hi = offset.b_hat + PROFILE_REACH * sd_prior
            continue
        lo, hi = min(inside or allowed) - step, max(inside or allowed) + step
    b = np.array(sorted(tried))
    lw = np.array([tried[k][0] for k in b])
    if not np.isfinite(lw).any():
        return None
    top = lw.max()
    dens = np.exp(lw - top)
    # trapezoid weights on the union of the grids (a refinement is denser about the band)
    q = np.zeros(len(b))
    q[1:] += 0.5 * np.diff(b)
    q[:-1] += 0.5 * np.diff(b)
    mass = dens * q
    if len(b) == 1 or mass.sum() <= 0:
        mass = dens
    z = float(mass.sum())
    wn = mass / z
    mean = float(wn @ b)
    # the finest spacing is the resolution of the band's edges: its variance as a floor
    var = float(wn @ (b - mean) ** 2) + step**2 / 12
    i = int(np.argmax(dens))
    return top + math.log(z), mean, var, tried[float(b[i])][1], float(wn[i])


def _offset_posterior(offset: OffsetModel, nodes: list[_Node], c_plane: np.ndarray,
                      c_post: np.ndarray) -> None:
    """b's posterior, into ``offset``: b given a plane is the ranges' conditional (b_hat +
    k . g, k = C_gg^-1 C_gb; the labels see the plane, not b), averaged over the plane's
    posterior (the nodes' weights, its covariance ``c_post``)."""
    k = np.linalg.solve(c_plane, offset.c_gb)
    g = np.array([nd.g for nd in nodes])
    w = _weights(nodes)
    offset.mean = float(offset.b_hat + w @ (g @ k))
    var = offset.c_bb - offset.c_gb @ k + k @ c_post @ k
    offset.std = float(math.sqrt(max(var, 0.0)))


def _log_density_ratio(g: np.ndarray, c_inv: np.ndarray, m: np.ndarray, scale: float,
                       q_inv: np.ndarray | None = None) -> np.ndarray:
    """log N(g; 0, C) - log N(g; m, scale^2 Q), up to a constant (Q = C unless ``q_inv`` =
    Q^-1 is given): the ranges' density over the one the planes g were drawn from (or placed
    by a rule for)."""
    dev = g - m
    q_inv = c_inv if q_inv is None else q_inv
    return (-0.5 * np.einsum("ij,jk,ik->i", g, c_inv, g)
            + 0.5 * np.einsum("ij,jk,ik->i", dev, q_inv, dev) / scale**2)


def _off_centre(nodes: list[_Node], centre: np.ndarray, cov: np.ndarray) -> np.ndarray | None:
    """The nodes' weighted mean plane when it lies more than `OFF_CENTRE` of the rule's
    standard deviations (``cov``) from its ``centre`` along some direction of the rule, else
    None."""
    g = _weights(nodes) @ np.array([nd.g for nd in nodes])
    t = np.linalg.solve(np.linalg.cholesky(cov), g - centre)
    return g if np.max(np.abs(t)) > OFF_CENTRE else None


def _spans(nodes: list[_Node]) -> bool:
    """Whether the rule's nodes the labels allowed lie on two levels or more of every direction
    of its grid (else the J = d pose / d g fit and the band's extent are not determined)."""
    q = QUADRATURE_ORDER
    index = [nd.index for nd in nodes]
    # the grid's C order: level index // q^2 of the first direction, ... index % q of the last
    return all(len({i // q**a % q for i in index}) >= 2 for a in (2, 1, 0))


class _Node(NamedTuple):
    """One plane g of the integral: its log weight in the rule or sampler (with the ranges'
    density over theirs), the pose of its in-plane posterior's mean, and that posterior."""

    g: np.ndarray
    log_q: float
    index: int  # in its rule (the grid's C order) or sampler batch
    pose: np.ndarray
    post: moments.InPlanePosterior


def gauss_hermite(centre: np.ndarray, cov: np.ndarray, order: int
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The tensor Gauss-Hermite rule for N(centre, cov) in 3-D: nodes (order^3, 3) and the
    logs of their weights (which sum to 1)."""
    grid, log_q = _standard_rule(order)
    return centre + grid @ np.linalg.cholesky(cov).T, log_q.copy()


@functools.cache
def _standard_rule(order: int) -> tuple[np.ndarray, np.ndarray]:
    """`gauss_hermite`'s rule for N(0, I): nodes (order^3, 3) and log weights, read-only
    (computed once: the nodes' recurrence and the outer sums cost more than the rest of a rule)."""
    x, w = _hermite(order)
    grid = np.stack(np.meshgrid(x, x, x, indexing="ij"), axis=-1).reshape(-1, 3)
    log_w = np.log(w / w.sum())
    log_q = np.add.outer(np.add.outer(log_w, log_w), log_w).ravel()
    grid.flags.writeable = log_q.flags.writeable = False
    return grid, log_q


@functools.cache
def _hermite(order: int) -> tuple[np.ndarray, np.ndarray]:
    """The probabilists' Gauss-Hermite nodes and weights (`numpy.polynomial.hermite_e`), read-only
    and computed once."""
    x, w = np.polynomial.hermite_e.hermegauss(order)
    x.flags.writeable = w.flags.writeable = False
    return x, w


def _weights(nodes: list[_Node]) -> np.ndarray:
    """Each node's normalised weight: its log_q (rule or sampler, with the ranges' density)
    and the labels' evidence for its plane."""
    log_w = np.array([nd.log_q + np.log(nd.post.evidence) for nd in nodes])
    w = np.exp(log_w - log_w.max())
    return w / w.sum()


def _moments(nodes: list[_Node], c_plane: np.ndarray, given: bool = False
             ) -> tuple[np.ndarray, np.ndarray]:
    """The weighted mean of the nodes' poses and the covariance J C J^T + K P K^T (C: the
    plane's given the ranges ``c_plane`` and the labels, `_plane_posterior_cov`; with
    ``given``, ``c_plane`` is already the plane's posterior covariance)."""
    g = np.array([nd.g for nd in nodes])
    thetas = np.array([nd.pose for nd in nodes])
    w = _weights(nodes)
    mean = w @ thetas
    # J = d pose / d g, least squares over the nodes
    a = np.column_stack((np.ones(len(g)), g))
    j_g = np.linalg.lstsq(a, thetas, rcond=None)[0][1:].T
    # K = d pose / d (roll, x, z) at a fixed plane
    k = np.zeros((6, 3))
    h = 1e-6
    q = np.array([mean[3], mean[0], mean[2]])
    n, d = plane_of_pose(mean)
    k[:, 0] = (_pose(n, d, q + np.array([h, 0.0, 0.0])) - _pose(n, d, q)) / h
    k[0, 1] = k[2, 2] = 1.0
    within = np.einsum("s,sij->ij", w, np.array([nd.post.cov for nd in nodes]))
    c_post = (c_plane if given else
              _plane_posterior_cov(g, np.log([nd.post.evidence for nd in nodes]), c_plane))
    return mean, j_g @ c_post @ j_g.T + k @ within @ k.T


#: np.triu_indices(3), computed once; read-only.
_TRIU = np.triu_indices(3)
for _a in _TRIU:
    _a.flags.writeable = False


def _plane_posterior_cov(g: np.ndarray, log_ev: np.ndarray, c_plane: np.ndarray
                         ) -> np.ndarray:
    """The plane's covariance given the ranges and the labels: the labels' log evidence fitted
    as a quadratic in the standardised plane over the nodes, its curvature added to the ranges'
    precision (never below it). The ranges' covariance where the fit is not determined."""
    chol = np.linalg.cholesky(c_plane)
    xi = np.linalg.solve(chol, (g - g.mean(axis=0)).T).T
    i, j = _TRIU
    design = np.column_stack((np.ones(len(xi)), xi, xi[:, i] * xi[:, j]))
    if len(xi) < 2 * design.shape[1] or np.linalg.matrix_rank(design) < design.shape[1]:
        return c_plane
    coef = np.linalg.lstsq(design, log_ev, rcond=None)[0]
    h = np.zeros((3, 3))
    h[i, j] = coef[4:]
    h = -(h + h.T)  # -Hessian of the log evidence (the diagonal counted twice, as it must be)
    vals, vecs = np.linalg.eigh(np.eye(3) + h)
    prec = vecs @ np.diag(np.maximum(vals, 1.0)) @ vecs.T
    return chol @ np.linalg.inv(prec) @ chol.T
