"""method="rays": the ML plane along the rays plus the board rectangle fitted to hit/miss labels.

The pipeline, one step per stage (docs/align.md says what each does and why):
plane (`align.plane`) -> starts (`align.fit.starts`) -> fit (`align.fit.lsq`) -> plane refit
inside the fitted rectangle -> hit/miss posterior (`align.posterior`) -> result.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace

import numpy as np

import align.symmetry as symmetry
from align.board import BoardSpec
from align.fit.label_kernels import seen_counts
from align.fit.labels import hit_band
from align.fit.lsq import Fit, fit_from, staged_fit
from align.fit.model import Model, build_model
from align.fit.rays import DROPOUT, HIT, MISS, UNKNOWN, rays_of
from align.fit.size import seen_size, size_mismatch
from align.fit.starts import held_by, start_at, starts_on
from align.geometry import (
    board_centre,
    in_plane_rotation,
    plane_of_pose,
    pose_from_plane,
    unwrap,
)
from align.params import RaysParams
from align.plane.fit import fit_rays, fit_rays_offsets, predicted_range, ransac
from align.posterior.hit_miss import OffsetModel, label_posterior
from align.posterior.rays import (
    pose_per_plane,
    ray_points,
    violation,
)
from align.rays.plane_steps import (
    inside_returns,
    plane_moved,
    range_plane,
    start_band,
)
from align.result import Hints, PoseEstimate, Status
from align.search.board import FLAT_BAND
from align.search.cluster_kernels import in_ring_block
from align.search.result import Segmentation
from align.search.rings import on_board_rings
from align.search.roll import FINE_REACH, RollStart
from twin.core.pose import Pose
from twin.core.scan import Scan


def estimate_rays(scans: list[Scan], segs: list[Segmentation], board: BoardSpec,
                  hints: Hints, *, p: RaysParams) -> PoseEstimate:
    """Joint estimate from one or more scans of a static pose (their board clusters found)."""
    t0 = time.perf_counter()
    rng = np.random.default_rng(hints.seed)
    p = p.for_firing_step(firing_step(scans[0]))
    plane = board_plane(scans, segs, board, hints, rng, p=p)
    t_plane = time.perf_counter()
    starts = roll_starts(plane, board, hints, p=p)
    fit = best_fit(scans, segs, plane, starts, board, hints, p=p)
    if fit is None:
        return PoseEstimate.failed(Status.TOO_FEW_RINGS, "rays", rings=0,
                                   reason="the board spans fewer than 3 rings; 3 needed")
    plane = plane_inside(plane, fit, segs[0].by_plane, board, hints, p=p)
    solution = hit_miss_posterior(scans, plane, fit, board, hints, rng, p=p)
    timings = {"plane": t_plane - t0, "fit": time.perf_counter() - t_plane}
    return outcome(solution, fit, len(starts), plane.sigma_r, board, timings, p=p)


def firing_step(scan: Scan) -> float:
    """The azimuth between two firings of the least fired laser, rad: the median step between
    its firings sorted by azimuth (0 if it fired once), so that a scan cut to a window or out
    of firing order says the same. A PandarQT128's middle lasers fire every 0.8 deg, half as
    often as its others; the VLP-16's every 0.2 deg."""
    counts = np.bincount(scan.laser_id, minlength=scan.lasers.n_lasers)
    if not np.any(counts):
        return 0.0
    least = int(np.argmin(np.where(counts > 0, counts, np.iinfo(counts.dtype).max)))
    steps = np.diff(np.sort(scan.azimuth[scan.laser_id == least]))
    steps = steps[steps > 0]
    return float(np.median(steps)) if len(steps) else 0.0


#: The fewest rays a plane is fitted to (three points fix a plane).
MIN_PLANE_RAYS = 3


@dataclass(frozen=True)
class BoardRays:
    """The board's returns as rays, from all scans: origins, directions, ranges, rings, which of
    them the plane holds (``keep``), and how many are the first scan's (``first``)."""

    origin: np.ndarray
    direction: np.ndarray
    distance: np.ndarray
    ring: np.ndarray
    keep: np.ndarray
    first: int


@dataclass(frozen=True)
class Plane:
    """The board's plane from the ranges, as the later steps use it."""

    n: np.ndarray
    d: float
    rays: BoardRays
    sigma_r: float  # the range noise, m
    ml: tuple  # (n, d, covariance) the hit/miss posterior integrates over
    offset_model: OffsetModel | None  # the common range offset's, when estimated
    offset_start: tuple  # the offset's start for the least-squares fit
    cluster: tuple[np.ndarray, float]  # the cluster's (n, d), before an offset moved it
    starts: list[RollStart] | None  # the roll search's on this plane, when already made


def board_plane(scans: list[Scan], segs: list[Segmentation], board: BoardSpec, hints: Hints,
                rng: np.random.Generator, *, p: RaysParams) -> Plane:
    """Step 1: the ML plane along the rays of the board's returns (`fit_rays`), from
    a RANSAC start; with the ranges' offsets as nuisance parameters where the hints say so."""
    rays, n, d = _board_rays(scans, segs, rng, p=p)
    o, u, r = rays.origin, rays.direction, rays.distance
    n, d, c_plane, sigma, keep = _plane_of_rays(rays, n, d, p=p)
    # start poses: the plane at the rolls where the board's returns fit the rectangle, each
    # centred on the returns. A flat thing a few cm behind the board beside or below it (a
    # box, a cabinet's side, the stand's face) joins its cluster and turns the plane by
    # degrees to pass between both; the rectangle the search finds then leaves it out, and
    # the plane is fitted again to what that rectangle holds
    starts, looked_at = starts_on(o, u, keep, rays.first, n, d, board, hints, p=p)
    held = (keep & held_by(o, u, n, d, starts[0], board, p=p)
            if starts and starts[0].left_out > p.spill * looked_at else None)
    # a rectangle that holds fewer returns than a plane needs is no refit's start: a candidate
    # whose plane the rays barely meet (a few returns of the floor, the rays at grazing
    # incidence: the rectangle found kilometres away) raised here, an empty fit
    if held is not None and np.count_nonzero(held) >= MIN_PLANE_RAYS:
        keep = held
        n, d, _, sigma = fit_rays(r[keep], o[keep], u[keep], n, d)
        trimmed = keep & (np.abs(r - predicted_range(n, d, o, u)) < p.trim * sigma)
        keep = trimmed if np.count_nonzero(trimmed) >= MIN_PLANE_RAYS else keep
        n, d, c_plane, sigma = fit_rays(r[keep], o[keep], u[keep], n, d,
                                        sigma_floor=p.range_sigma_floor)
        starts = None
    rays = replace(rays, keep=keep)
    # the range noise: the user's, or the residuals' (a trimmed sample's understate it: undone
    # for Gaussian noise); the plane's covariance scaled to it
    sigma_r = hints.range_sigma or sigma / math.sqrt(p.trimmed_variance)
    n1, d1, ml_plane, offset_model, offset_start = range_plane(
        r[keep], o[keep], u[keep], rays.ring[keep], n, d, c_plane, sigma, sigma_r, hints, p=p)
    return Plane(n1, d1, rays, sigma_r, ml_plane, offset_model, offset_start, (n, d), starts)


def _board_rays(scans: list[Scan], segs: list[Segmentation], rng: np.random.Generator, *,
                p: RaysParams
                ) -> tuple[BoardRays, np.ndarray, float]:
    """The rays of the board's returns within a band about a RANSAC plane of the first scan's
    (the band `start_band`), and that plane (n, d); of a noisy unit's, the returns of the
    cluster's rings within the azimuths each spans in it (`ring_spans`), not the cluster's
    alone."""
    # the plane from the board's own rings: the cluster may reach the stand's face a ring or
    # two below, coplanar within the bands below (it biased tilt by 0.04 deg fused on the
    # paper's bench)
    board_idx = [on_board_rings(s, g.board) for s, g in zip(scans, segs, strict=True)]
    # robust start: RANSAC on the first scan's cluster, and the band about it from its spread
    first = scans[0].points(board_idx[0])
    n, d, _ = ransac(first, 0.04, rng, 100, truncated=True)
    dev = np.abs(first @ n - d)
    band = start_band(dev, p=p)
    spread = 1.4826 * float(np.median(dev))  # the ranges' sigma, robust
    if spread > 0 and FLAT_BAND / spread < p.pool_cut_sigmas:
        # a noisy unit: the search's band cut its noise (`p.pool_cut_sigmas`)
        board_idx = [ring_spans(s, i) for s, i in zip(scans, board_idx, strict=True)]
    pts = [s.points(i) for s, i in zip(scans, board_idx, strict=True)]
    o_l, u_l, r_l, k_l = [], [], [], []
    for s, i, pt in zip(scans, board_idx, pts, strict=True):
        near = i[np.abs(pt @ n - d) < band]
        lid = s.laser_id[near]
        o, u = rays_of(s, near, lid)
        o_l.append(o)
        u_l.append(u)
        r_l.append(s.distance[near])
        k_l.append(s.lasers.ring_of_laser[lid])
    rays = BoardRays(np.concatenate(o_l), np.concatenate(u_l), np.concatenate(r_l),
                     np.concatenate(k_l), np.ones(sum(map(len, r_l)), dtype=bool), len(o_l[0]))
    return rays, n, d


def ring_spans(scan: Scan, idx: np.ndarray) -> np.ndarray:
    """The returns of ``scan`` on the rings of the returns ``idx`` within the azimuths each of
    those rings spans in ``idx`` (ascending indices; ``idx``'s own among them)."""
    if not len(idx):
        return idx
    centre = float(np.angle(np.mean(np.exp(1j * scan.azimuth[idx]))))
    ring_of = scan.lasers.ring_of_laser
    rings = ring_of[scan.laser_id[idx]]
    rel = unwrap(scan.azimuth[idx], centre)
    n_rings = int(ring_of.max()) + 1
    lo = np.full(n_rings, np.inf)
    hi = np.full(n_rings, -np.inf)
    np.minimum.at(lo, rings, rel)
    np.maximum.at(hi, rings, rel)
    ring_all = ring_of[scan.laser_id]
    rel_all = unwrap(scan.azimuth, centre)
    inside = (scan.distance > 0) & (rel_all >= lo[ring_all]) & (rel_all <= hi[ring_all])
    return np.union1d(idx, np.flatnonzero(inside))


def _plane_of_rays(rays: BoardRays, n: np.ndarray, d: float, *, p: RaysParams
                   ) -> tuple[np.ndarray, float, np.ndarray, float, np.ndarray]:
    """The ML plane along ``rays`` from (n, d): trimmed at `p.trim` sigma, on the consecutive
    block of rings that holds the most returns; (n, d, covariance, residuals' sigma, kept)."""
    o, u, r = rays.origin, rays.direction, rays.distance
    n, d, _, sigma = fit_rays(r, o, u, n, d)
    keep = np.abs(r - predicted_range(n, d, o, u)) < p.trim * sigma
    n, d, _, sigma = fit_rays(r[keep], o[keep], u[keep], n, d)
    # the board's rings hold many returns; the few that leak in from the stand (its base is
    # 5 cm in front of the board) sit on other rings: the board's rings are consecutive: keep
    # the consecutive block with the most returns (the stand's base, a parallel face 5 cm in
    # front, lights up a ring or two below a gap)
    keep &= in_ring_block(rays.ring, keep)
    n, d, c_plane, sigma = fit_rays(r[keep], o[keep], u[keep], n, d,
                                    sigma_floor=p.range_sigma_floor)
    return n, d, c_plane, sigma, keep


def roll_starts(plane: Plane, board: BoardSpec, hints: Hints, *, p: RaysParams) -> list[RollStart]:
    """Step 2: the fit's start poses, the roll search's on the plane (searched again where the
    plane moved since: refitted without a neighbour, or with the ranges' offsets)."""
    if (plane.starts is not None and plane.offset_start[1] is None
            and hints.laser_offset_sigma <= 0):
        return plane.starts
    rays = plane.rays
    return starts_on(rays.origin, rays.direction, rays.keep, rays.first, plane.n, plane.d, board,
                   hints, p=p)[0]


def _shifts() -> np.ndarray:
    """The shifts across the rings the fit's profile starts from, m."""
    return np.arange(-0.06, 0.0605, 0.001)


def best_fit(scans: list[Scan], segs: list[Segmentation], plane: Plane,
             starts: list[RollStart], board: BoardSpec, hints: Hints, *, p: RaysParams
             ) -> Fit | None:
    """Step 3: the least-squares fit from each start (`align.fit.lsq.fit_from`); the one that
    contradicts the fewest labels wins (the chi2 of a fit that had to leave its brackets out
    says little), then the lower chi2. None: fewer than 3 rings hit from every start."""

    def fit_at(st: RollStart) -> Fit | None:
        theta = pose_from_plane(plane.n, plane.d, st.roll)
        theta[0], theta[2] = st.t_x, st.t_z
        return fit_from(scans, segs, theta, board, plane.sigma_r, hints, _shifts(),
                        plane.offset_start, p=p)

    def better(fit: Fit | None, best: Fit | None) -> bool:
        return fit is not None and (best is None or (fit.violations, fit.chi2) <
                                    (best.violations, best.chi2))

    best = None
    for st in starts:
        fit = fit_at(st)
        if better(fit, best):
            best = fit
    level = hints.roll_prior[0] if hints.roll_prior is not None else 0.0
    if best is not None and best.violations > p.retry_violations and all(
            abs(st.roll - level) > FINE_REACH for st in starts):
        # every start's fit contradicts many labels: the search's rectangle may have turned to
        # hold something beside the board (a bright box flush with an edge a few cm behind it,
        # 20 deg): the fit from the mount's nominal roll as well
        rays = plane.rays
        fit = fit_at(start_at(rays.origin, rays.direction, rays.keep, rays.first, plane.n,
                               plane.d, board, level))
        if better(fit, best):
            best = fit
    return best


def plane_inside(plane: Plane, fit: Fit, by_plane: bool, board: BoardSpec, hints: Hints, *,
                 p: RaysParams
                 ) -> Plane:
    """Step 4: the plane checked against every return inside the fitted rectangle, none beyond
    it; that plane where it differs from the cluster's by more than chance (`plane_moved`) or
    the cluster's returns were chosen by a band about a plane (``by_plane``: the plane-first
    search's), else ``plane`` as it was.

    The cluster's returns were cut by a band about a first plane, which keeps the noise that
    leans towards that plane (on random scenes the truth was 4-7 of the plane's sigmas off in
    some scans; tilt, yaw and x chi2 1.3); and a box's face or a holder a few cm behind the
    board beside an edge, within the band on the board's rings, is in the cluster and leans
    the plane. Only beyond chance: the posterior is sensitive to its plane at a tenth of a
    sigma (one scan in 800 on the paper's bench went 2 deg off with the other for no better
    reason). A rectangle that holds less than half the cluster's returns is not the board's:
    the result's checks say so, on the first plane."""
    model, theta = fit.model, fit.theta
    held = inside_returns(model.rays, theta, model.offset, board, model.coords(theta), p=p)
    if np.count_nonzero(held) < 0.5 * np.count_nonzero(plane.rays.keep):
        return plane
    rays_ = model.rays
    r_in, o_in, u_in = rays_.distance[held], rays_.origin[held], rays_.direction[held]
    n_in, d_in, _, s_in = fit_rays(r_in, o_in, u_in, plane.n, plane.d)
    k_in = np.abs(r_in - predicted_range(n_in, d_in, o_in, u_in)) < p.trim * s_in
    n_in, d_in, c_in, s_in = fit_rays(r_in[k_in], o_in[k_in], u_in[k_in], n_in, d_in,
                                      sigma_floor=p.range_sigma_floor)
    if not (by_plane or plane_moved(plane.cluster, (n_in, d_in, c_in), p=p)):
        return plane
    rays = BoardRays(o_in, u_in, r_in, rays_.ring[held], k_in, plane.rays.first)
    n, d, ml_plane, offset_model, _ = range_plane(
        r_in[k_in], o_in[k_in], u_in[k_in], rays.ring[k_in], n_in, d_in, c_in, s_in,
        plane.sigma_r, hints, p=p)
    return replace(plane, n=n, d=d, rays=rays, ml=ml_plane, offset_model=offset_model)


@dataclass(frozen=True)
class Solution:
    """The pose after the hit/miss posterior (or the least-squares fit where it found none)."""

    theta: np.ndarray
    cov: np.ndarray
    model: Model
    j: np.ndarray  # the least-squares fit's Jacobian
    conv: bool
    iters: int
    dropped: int  # labels left out as strays
    posterior: bool  # whether the hit/miss posterior held
    offset: float  # the common range offset, m
    offset_diag: dict


def hit_miss_posterior(scans: list[Scan], plane: Plane, fit: Fit, board: BoardSpec,
                       hints: Hints, rng: np.random.Generator, *, p: RaysParams) -> Solution:
    """Step 5: the hit/miss posterior (`align.posterior`) about the fit. Where a few labels make
    it empty (returns near the board's plane from something beside it: the stand's base at a
    corner of a rolled board, a hand; a dropout at an edge), the labels the least-squares pose
    violates are left out (unknown), the fit redone without them and the posterior tried
    again (`_stray_rounds`); where none holds, the least-squares fit stands."""
    post, theta, j, conv, model, cov, dropped, iters = _stray_rounds(scans, plane, fit, board,
                                                                     hints, rng, p=p)
    offset_model = plane.offset_model
    if post is not None:
        theta, cov = post
        model.classify(theta, 0.002, True)  # the diagnostics describe this pose
        model.assign(theta)
    elif hints.laser_offset_sigma > 0:
        # the least-squares fit's covariance knows the ranges' noise (and the common offset it
        # fits), not the per-laser offsets: their share of the plane's covariance is added
        prior = hints.range_offset_prior or (0.0, p.offset_known)
        rays, keep = plane.rays, plane.rays.keep
        c_common = fit_rays_offsets(rays.distance[keep], rays.origin[keep],
                                    rays.direction[keep], rays.ring[keep], plane.n, plane.d,
                                    plane.sigma_r, prior, 0.0, 1)[2]
        j_p = pose_per_plane(theta, plane.n, plane.d)
        cov = cov + j_p @ (plane.ml[2] - c_common) @ j_p.T
    offset_diag, b = {}, model.offset
    if offset_model is not None:
        if post is not None and offset_model.mean is not None:
            b, b_sd = offset_model.mean, offset_model.std
        else:  # the least-squares fit's
            b, b_sd = model.offset, offset_model.centre_std
        offset_diag = {"range_offset_m": float(b), "range_offset_std_m": float(b_sd),
                       "range_offset_lsq_m": float(model.offset),
                       "range_offset_lsq_std_m": float(offset_model.centre_std)}
    return Solution(theta, cov, model, j, conv, iters, dropped, post is not None, b, offset_diag)


def _stray_rounds(scans: list[Scan], plane: Plane, fit: Fit, board: BoardSpec, hints: Hints,
                  rng: np.random.Generator, *, p: RaysParams) -> tuple:
    """The posterior, leaving out the labels the least-squares pose violates for up to
    `p.stray_rounds` rounds: (posterior or None, theta, j, conv, model, covariance,
                                       labels left
    out, iterations)."""
    theta, j, conv, iters, model = fit.theta, fit.j, fit.conv, fit.iters, fit.model
    offset_model, cov = plane.offset_model, None
    dropped = 0
    intensity = np.concatenate([s.intensity for s in scans])  # indexed as the rays' gidx
    for _ in range(p.stray_rounds):
        # the least-squares covariance (7 x 7 when the offset is fitted: pose, offset) where
        # the posterior reads it (fused scans' roll reach, the offset's centre) or where it
        # stands instead of the posterior
        cov_ls = (np.linalg.pinv(j.T @ j) if len(scans) > 1 or offset_model is not None
                  else None)
        _centre_offset(offset_model, model, cov_ls, slope=True)
        labelled, idx = ray_points(model, theta, hints.edge_tolerance,
                                   intensity[model.rays.gidx], hints.partial_edge_tolerance, p=p)
        # a single scan's posterior searches a fixed reach of roll: no roll sigma needed
        sd_roll = (float(np.sqrt(max(cov_ls[3, 3], 0.0))) if cov_ls is not None else math.nan)
        post = label_posterior(labelled, board, theta, sd_roll, plane.ml, len(scans), rng,
                               hints.roll_prior, offset_model)
        if post is not None:
            break
        if cov_ls is None:
            cov_ls = np.linalg.pinv(j.T @ j)
        cov = cov_ls[:6, :6]
        if not dropped:
            first = (theta, j, conv, model, cov, cov_ls)
        bad = idx[violation(labelled, board, theta) > p.stray_violation]
        limit = max(p.max_strays, p.max_stray_fraction * len(idx))
        if len(bad) == 0 or dropped + len(bad) > limit:
            break
        dropped += len(bad)
        lab = model.lab.copy()
        lab[bad] = UNKNOWN
        model = build_model(model.rays, lab, theta, board, plane.sigma_r, hints.edge_blur,
                            like=model, p=p)
        theta, j, conv, it, _ = staged_fit(model, theta, _shifts())
        iters += it
    if post is None and dropped:
        # leaving them out did not make the labels agree: they were not strays but the
        # board's own labels that a least-squares pose in a wrong basin violates (a ring
        # grazing an edge); each round moved it further (2 deg of roll, seen on a random
        # scene), so the first fit stands
        theta, j, conv, model, cov, cov_ls = first
        dropped = 0
        _centre_offset(offset_model, model, cov_ls, slope=False)
    return post, theta, j, conv, model, cov, dropped, iters


def _centre_offset(offset_model: OffsetModel | None, model: Model, cov_ls: np.ndarray | None,
                   slope: bool) -> None:
    """The common offset's centre for the posterior: the least-squares fit's, with its sigma
    and (``slope``) how the least-squares pose moves with the offset when the brackets (the
    board's size) hold it: the direction the labels trade distance against yaw and x."""
    if offset_model is None:
        return
    offset_model.centre = model.offset
    offset_model.centre_std = float(np.sqrt(cov_ls[6, 6])) if len(cov_ls) > 6 else 0.0
    if slope:
        offset_model.slope = (cov_ls[:6, 6] / cov_ls[6, 6] if len(cov_ls) > 6
                              and cov_ls[6, 6] > 0 else None)


def outcome(sol: Solution, fit: Fit, n_starts: int, sigma_r: float, board: BoardSpec,
            timings: dict, *, p: RaysParams) -> PoseEstimate:
    """Step 6: the result: what was seen (every edge, nothing in front of the board) and the
    status it earns; the pose in its canonical form under the board's symmetry."""
    model, theta = sol.model, sol.theta
    rays, lab = model.rays, model.lab
    k = model.edge_kind
    seen = _seen(sol, sigma_r, board, p=p)
    diag = {
        "rings": len(fit.rings), "rays": len(lab), "hits": int(np.sum(lab == HIT)),
        "range_residuals": int(model.use_range.sum()), "brackets": int(np.sum(k > 0)),
        **{key: seen.pop(key) for key in ("edges_left", "edges_right", "edges_top",
                                          "edges_bottom", "occluded_rays", "inside_misses",
                                          "dropouts")},
        "starts": n_starts, "strays_dropped": sol.dropped, "label_posterior": sol.posterior,
        "in_plane_rotation_rad": in_plane_rotation(theta), "range_sigma_m": sigma_r,
        "iterations": sol.iters, **sol.offset_diag,
        "chi2_per_dof": float(np.sum(model.residuals(theta) ** 2) / max(len(sol.j) - 6, 1)),
        "dof": max(len(sol.j) - 6, 1),
        "outside_hits": seen.pop("outside_hits"),
    }
    theta, cov = _size_checked(model, theta, sol.cov, board, diag, p=p)
    diag["incidence_rad"] = _incidence(theta)
    status, reason = _status(diag, seen, model, sol.conv, p=p)
    if reason:
        diag["reason"] = reason
    used = {"board": rays.gidx[model.use_range],
            "features": np.stack((rays.gidx[model.bh[k > 0]], rays.gidx[model.bm[k > 0]]), axis=1)}
    theta, cov = symmetry.canonical(theta, board, cov)
    return PoseEstimate(status, "rays", Pose.from_array(theta), cov, diag, used, timings)


def _size_checked(model: Model, theta: np.ndarray, cov: np.ndarray, board: BoardSpec,
                  diag: dict, *, p: RaysParams) -> tuple[np.ndarray, np.ndarray]:
    """The size the rays see (`align.fit.size`) into ``diag``; where it refuses the size given
    (`p.size_refused_d2`), the pose where the rays put it with the size freed, and its wider
    covariance; else (theta, cov) as they were."""
    size = seen_size(model, theta)
    if size is None:
        return theta, cov
    d2 = size_mismatch(size, board.width, board.height, board.size_std)
    sd_w, sd_h = size.std
    diag.update(seen_width_m=size.width, seen_width_std_m=float(sd_w),
                seen_height_m=size.height, seen_height_std_m=float(sd_h),
                size_mismatch_d2=d2, size_freed=d2 > p.size_refused_d2)
    if d2 <= p.size_refused_d2:
        return theta, cov
    theta = theta + size.pose_step
    diag["in_plane_rotation_rad"] = in_plane_rotation(theta)
    return theta, cov + size.pose_cov


def _not_the_board(diag: dict, board: BoardSpec, *, p: RaysParams) -> str:
    """Why a rectangle that may explain its rays is not vouched for as the board, or "": seen
    edge-on (`p.max_incidence`); a size the rays hold off the one given (`p.size_refused_ratio`);
    or hits beyond an edge, or misses inside it, with no hit/miss pair across that edge while
    two or more cross the opposite one (across a level board's top and bottom edges one pair
    is usual, none at one of them happens on a true board). A board given 6-10 % small or
    large passed so, x 26-58 mm off; a cabinet's face, 7-10 % off its size."""
    if diag["incidence_rad"] > p.max_incidence:
        return (f"the board would be seen at {np.degrees(diag['incidence_rad']):.0f} deg of "
                f"incidence, beyond the {np.degrees(p.max_incidence):.0f} deg at which a board "
                "is measured: an object seen edge-on, not the board facing the LiDAR")
    off = _size_off(diag, board)
    if diag.get("size_freed") and off > p.size_refused_ratio:
        return (f"the rays see a {1e3 * diag['seen_width_m']:.0f} x "
                f"{1e3 * diag['seen_height_m']:.0f} mm rectangle, not the "
                f"{1e3 * board.width:.0f} x {1e3 * board.height:.0f} mm given "
                f"({100 * off:.0f} % off): another object, or the board's size given wrong "
                "(--board-mm, board.width_mm and height_mm)")
    outside_hits, inside_miss = diag["outside_hits"], diag["inside_misses"]
    per_edge = [diag[f"edges_{n}"] for n in ("left", "right", "bottom", "top")]
    bare = [i for i in range(4) if per_edge[i] == 0 and per_edge[i ^ 1] >= 2]
    if (outside_hits or inside_miss) and bare:
        unbracketed = "/".join(("left", "right", "bottom", "top")[i] for i in bare)
        return (f"{outside_hits} hits outside the board's rectangle, {inside_miss} misses "
                f"inside it and no hit/miss pair across its {unbracketed} edge: the rays do "
                "not put the board's edge there (is the board's size given right? --board-mm, "
                "board.width_mm and height_mm)")
    return ""


def _size_off(diag: dict, board: BoardSpec) -> float:
    """The largest relative difference of the seen size from the size given (0: none seen)."""
    if "seen_width_m" not in diag:
        return 0.0
    return max(abs(diag["seen_width_m"] / board.width - 1.0),
               abs(diag["seen_height_m"] / board.height - 1.0))


def _incidence(theta: np.ndarray) -> float:
    """The angle between the line of sight to the board's centre and the board's normal, rad."""
    normal, _ = plane_of_pose(theta)
    centre = board_centre(theta)
    cos_i = abs(float(normal @ centre)) / max(float(np.linalg.norm(centre)), 1e-9)
    return float(np.arccos(min(cos_i, 1.0)))


def _seen(sol: Solution, sigma_r: float, board: BoardSpec, *, p: RaysParams) -> dict:
    """The brackets per edge and, in one compiled pass (`seen_counts`), every edge seen, the
    rays blocked (a return in front of the board where the board is: not a stray left out),
    the dropouts and misses inside and the hits outside."""
    model = sol.model
    x, z, lam = model.coords(sol.theta)
    k, sgn = model.edge_kind, model.edge_sign
    seen, n_inside, occluded, dropouts, inside_miss, outside_hits = seen_counts(
        x, z, lam, model.lab, model.rays.distance, float(sol.offset), hit_band(sigma_r, p=p),
        board.width / 2, board.height / 2, p.window, 0.02, HIT, MISS, DROPOUT)
    return {"edges_left": int(np.sum((k == 1) & (sgn < 0))),
            "edges_right": int(np.sum((k == 1) & (sgn > 0))),
            "edges_top": int(np.sum((k == 2) & (sgn > 0))),
            "edges_bottom": int(np.sum((k == 2) & (sgn < 0))),
            "occluded_rays": occluded, "inside_misses": inside_miss, "dropouts": dropouts,
            "outside_hits": outside_hits, "inside_rays": n_inside,
            "seen": tuple(bool(v) for v in seen)}


def _status(diag: dict, seen: dict, model: Model, conv: bool, *, p: RaysParams) -> tuple[Status,
                                                                                         str]:
    """ok, or partial_board where the known rectangle does not explain what was seen (part of
    the board hidden, dark or outside the field of view, or something board-like that is not
    the board), or not_converged; and the reason."""
    n_inside = max(seen["inside_rays"], 1)
    seen = seen["seen"]
    n_hit = max(diag["hits"], 1)
    diag["edges_seen"] = "".join("lrbt"[i] for i in range(4) if seen[i])
    not_it = _not_the_board(diag, model.board, p=p)
    if not_it:
        # the rectangle is not this object's: nor is a piece of the same object
        # (`align.api._other_candidates`)
        diag["not_the_board"] = True
        return Status.PARTIAL_BOARD, not_it
    occluded, inside_miss = diag["occluded_rays"], diag["inside_misses"]
    outside_hits, brackets = diag["outside_hits"], diag["brackets"]
    if (not all(seen) or brackets < p.min_brackets
            or occluded > 0.03 * n_inside or inside_miss > 0.03 * n_inside
            or outside_hits > 0.03 * n_hit or diag["chi2_per_dof"] > 3.0
            or model.use_range.sum() < 0.5 * n_hit):
        missing = "/".join(n for n, ok in zip(("left", "right", "bottom", "top"), seen,
                                              strict=True) if not ok)
        return Status.PARTIAL_BOARD, (
            "the board's rectangle is not fully seen: "
            + (f"nothing seen beyond its {missing} edge, " if missing else "")
            + f"{brackets} edge brackets (left/right/bottom/top {diag['edges_left']}/"
            f"{diag['edges_right']}/{diag['edges_bottom']}/{diag['edges_top']}), {occluded} "
            f"rays blocked in front, {inside_miss} misses inside, {outside_hits} hits outside, "
            f"chi2/dof {diag['chi2_per_dof']:.1f}")
    return (Status.NOT_CONVERGED if not conv else Status.OK), ""
