"""method="rays": the ML plane along the rays plus the board rectangle fitted to hit/miss labels.

The pipeline, one step per stage (docs/align.md says what each does and why):
plane (`align.plane`) -> starts (`align.fit.starts`) -> fit (`align.fit.lsq`) -> plane refit
inside the fitted rectangle -> hit/miss posterior (`align.posterior`) -> result.
"""

from __future__ import annotations

import math
import time

import numpy as np

import align.symmetry as symmetry
from align.board import BoardSpec
from align.fit.label_kernels import seen_counts
from align.fit.labels import _hit_band
from align.fit.lsq import _fit, _staged_fit
from align.fit.model import _build_model
from align.fit.rays import DROPOUT, HIT, MISS, UNKNOWN, WINDOW, _rays_of
from align.fit.starts import RETRY_VIOLATIONS, SPILL, _held, _start_at, _starts
from align.geometry import in_plane_rotation, pose_from_plane
from align.plane.fit import fit_rays, fit_rays_offsets, predicted_range, ransac
from align.posterior.hit_miss import label_posterior
from align.posterior.rays import (
    MAX_STRAY_FRACTION,
    MAX_STRAYS,
    STRAY_ROUNDS,
    STRAY_VIOLATION,
    _pose_per_plane,
    _ray_points,
    _violation,
)
from align.rays.plane_steps import (
    OFFSET_KNOWN,
    RANGE_SIGMA_FLOOR,
    TRIM,
    TRIMMED_VARIANCE,
    _inside_returns,
    _plane_moved,
    _range_plane,
    _start_band,
)
from align.result import Hints, PoseEstimate, Status
from align.search.cluster_kernels import in_ring_block
from align.search.result import Segmentation
from align.search.rings import on_board_rings
from align.search.roll import FINE_REACH
from twin.core.pose import Pose
from twin.core.scan import Scan


def estimate_rays(scans: list[Scan], segs: list[Segmentation], board: BoardSpec,
                  hints: Hints) -> PoseEstimate:
    """Joint estimate from one or more scans of a static pose (their board clusters found)."""
    t0 = time.perf_counter()
    rng = np.random.default_rng(hints.seed)
    # the plane from the board's own rings: the cluster may reach the stand's face a ring or
    # two below, coplanar within the bands below (it biased tilt by 0.04 deg fused on the
    # paper's bench)
    board_idx = [on_board_rings(s, g.board) for s, g in zip(scans, segs, strict=True)]
    pts = [np.column_stack((s.x[i], s.y[i], s.z[i])) for s, i in
           zip(scans, board_idx, strict=True)]
    # robust start: RANSAC on the first scan's cluster
    n, d, _ = ransac(pts[0], 0.04, rng, 100, truncated=True)
    band = _start_band(np.abs(pts[0] @ n - d))
    # ML plane along the rays, all scans' returns within the RANSAC band
    o_l, u_l, r_l, k_l = [], [], [], []
    for s, i, p in zip(scans, board_idx, pts, strict=True):
        near = i[np.abs(p @ n - d) < band]
        lid = s.laser_id[near]
        o, u = _rays_of(s, near, lid)
        o_l.append(o)
        u_l.append(u)
        r_l.append(s.distance[near])
        k_l.append(s.lasers.ring_of_laser[lid])
    o_all, u_all, r_all = np.concatenate(o_l), np.concatenate(u_l), np.concatenate(r_l)
    ring_all = np.concatenate(k_l)
    n, d, _, sigma = fit_rays(r_all, o_all, u_all, n, d)
    keep = np.abs(r_all - predicted_range(n, d, o_all, u_all)) < TRIM * sigma
    n, d, _, sigma = fit_rays(r_all[keep], o_all[keep], u_all[keep], n, d)
    # the board's rings hold many returns; the few that leak in from the stand (its base is
    # 5 cm in front of the board) sit on other rings: keep rings with a quarter of the most
    # and the board's rings are consecutive: keep the consecutive block with the most returns
    # (the stand's base, a parallel face 5 cm in front, lights up a ring or two below a gap)
    keep &= in_ring_block(ring_all, keep)  # np.isin(ring, segment.consecutive_ring_block(...))
    n, d, c_plane, sigma = fit_rays(r_all[keep], o_all[keep], u_all[keep], n, d,
                                          sigma_floor=RANGE_SIGMA_FLOOR)
    # start poses: the plane at the rolls where the board's returns fit the rectangle, each
    # centred on the returns. A flat thing a few cm behind the board beside or below it (a
    # box, a cabinet's side, the stand's face) joins its cluster and turns the plane by
    # degrees to pass between both; the rectangle the search finds then leaves it out, and
    # the plane is fitted again to what that rectangle holds
    starts, looked_at = _starts(o_all, u_all, keep, len(o_l[0]), n, d, board, hints)
    if starts and starts[0].left_out > SPILL * looked_at:
        keep &= _held(o_all, u_all, n, d, starts[0], board)
        n, d, _, sigma = fit_rays(r_all[keep], o_all[keep], u_all[keep], n, d)
        keep &= np.abs(r_all - predicted_range(n, d, o_all, u_all)) < TRIM * sigma
        n, d, c_plane, sigma = fit_rays(r_all[keep], o_all[keep], u_all[keep], n, d,
                                              sigma_floor=RANGE_SIGMA_FLOOR)
        starts = None
    # the range noise: the user's, or the residuals' (a trimmed sample's understate it: undone
    # for Gaussian noise); the plane's covariance scaled to it
    sigma_r = hints.range_sigma or sigma / math.sqrt(TRIMMED_VARIANCE)
    first_plane = (n, d)  # the cluster's (before any offset moves it), for `_plane_moved`
    n, d, ml_plane, offset_model, offset_start = _range_plane(
        r_all[keep], o_all[keep], u_all[keep], ring_all[keep], n, d, c_plane, sigma, sigma_r,
        hints)
    t_plane = time.perf_counter()

    if starts is None or offset_start[1] is not None or hints.laser_offset_sigma > 0:
        # the plane moved since (refitted without a neighbour, or with the ranges' offsets)
        starts = _starts(o_all, u_all, keep, len(o_l[0]), n, d, board, hints)[0]
    ds = np.arange(-0.06, 0.0605, 0.001)
    best = None
    for st in starts:
        theta = pose_from_plane(n, d, st.roll)
        theta[0], theta[2] = st.t_x, st.t_z
        fit = _fit(scans, segs, theta, board, sigma_r, hints, ds, offset_start)
        # the start whose fit contradicts the fewest labels wins (the chi2 of a fit that had
        # to leave its brackets out says little), then the lower chi2
        if fit is not None and (best is None or (fit.violations, fit.chi2) <
                                (best.violations, best.chi2)):
            best = fit
    level = hints.roll_prior[0] if hints.roll_prior is not None else 0.0
    if best is not None and best.violations > RETRY_VIOLATIONS and all(
            abs(st.roll - level) > FINE_REACH for st in starts):
        # every start's fit contradicts many labels: the search's rectangle may have turned to
        # hold something beside the board (a bright box flush with an edge a few cm behind it,
        # 20 deg): the fit from the mount's nominal roll as well
        st = _start_at(o_all, u_all, keep, len(o_l[0]), n, d, board, level)
        theta = pose_from_plane(n, d, st.roll)
        theta[0], theta[2] = st.t_x, st.t_z
        fit = _fit(scans, segs, theta, board, sigma_r, hints, ds, offset_start)
        if fit is not None and (fit.violations, fit.chi2) < (best.violations, best.chi2):
            best = fit
    if best is None:
        return PoseEstimate.failed(Status.TOO_FEW_RINGS, "rays", rings=0,
                                   reason="the board spans fewer than 3 rings; 3 needed")
    theta, j, conv, iters, model = best.theta, best.j, best.conv, best.iters, best.model
    rings_hit = best.rings
    # the plane checked against every return inside the fitted rectangle, none beyond it. The
    # cluster's returns were cut by a band about a first plane, which keeps the noise that
    # leans towards that plane (on random scenes the truth was 4-7 of the plane's sigmas off
    # in some scans; tilt, yaw and x chi2 1.3); and a box's face or a holder a few cm behind
    # the board beside an edge, within the band on the board's rings, is in the cluster and
    # leans the plane. Where the two planes differ by more than chance, or the cluster's
    # returns were chosen by a band about a plane (`Segmentation.by_plane`: the plane-first
    # search's), the posterior integrates over the rectangle's; else over the cluster's, as
    # it was (the posterior is sensitive to its plane at a tenth of a sigma: one scan in 800
    # on the paper's bench went 2 deg off with the other for no better reason). (A rectangle
    # that holds less than half the cluster's returns is not the board's: the checks below
    # say so, on the first plane)
    held = _inside_returns(model.rays, theta, model.offset, board, model.coords(theta))
    if np.count_nonzero(held) >= 0.5 * np.count_nonzero(keep):
        rays_ = model.rays
        r_in, o_in, u_in = rays_.distance[held], rays_.origin[held], rays_.direction[held]
        n_in, d_in, _, s_in = fit_rays(r_in, o_in, u_in, n, d)
        k_in = np.abs(r_in - predicted_range(n_in, d_in, o_in, u_in)) < TRIM * s_in
        n_in, d_in, c_in, s_in = fit_rays(r_in[k_in], o_in[k_in], u_in[k_in], n_in,
                                                d_in, sigma_floor=RANGE_SIGMA_FLOOR)
        if segs[0].by_plane or _plane_moved(first_plane, (n_in, d_in, c_in)):
            r_all, o_all, u_all, keep = r_in, o_in, u_in, k_in
            ring_all = rays_.ring[held]
            n, d, ml_plane, offset_model, _ = _range_plane(
                r_all[keep], o_all[keep], u_all[keep], ring_all[keep], n_in, d_in, c_in, s_in,
                sigma_r, hints)
    # the hit/miss posterior. Where a few labels make it empty (returns near the board's plane
    # from something beside it: the stand's base at a corner of a rolled board, a hand; a
    # dropout at an edge), the labels the least-squares pose violates are left out (unknown),
    # the fit redone without them and the posterior tried again
    dropped = 0
    intensity = np.concatenate([s.intensity for s in scans])  # indexed as the rays' gidx
    for _ in range(STRAY_ROUNDS):
        # the least-squares covariance (7 x 7 when the offset is fitted: pose, offset) where
        # the posterior reads it (fused scans' roll reach, the offset's centre) or where it
        # stands instead of the posterior (below)
        cov_ls = (np.linalg.pinv(j.T @ j) if len(scans) > 1 or offset_model is not None
                  else None)
        if offset_model is not None:
            offset_model.centre = model.offset
            offset_model.centre_std = float(np.sqrt(cov_ls[6, 6])) if len(cov_ls) > 6 else 0.0
            # how the least-squares pose moves with the offset when the brackets (the board's
            # size) hold it: the direction the labels trade distance against yaw and x
            offset_model.slope = (cov_ls[:6, 6] / cov_ls[6, 6] if len(cov_ls) > 6
                                  and cov_ls[6, 6] > 0 else None)
        labelled, idx = _ray_points(model, theta, hints.edge_tolerance,
                                    intensity[model.rays.gidx], hints.partial_edge_tolerance)
        # a single scan's posterior searches a fixed reach of roll: no roll sigma needed
        sd_roll = (float(np.sqrt(max(cov_ls[3, 3], 0.0))) if cov_ls is not None else math.nan)
        post = label_posterior(labelled, board, theta, sd_roll, ml_plane, len(scans), rng,
                               hints.roll_prior, offset_model)
        if post is not None:
            break
        if cov_ls is None:
            cov_ls = np.linalg.pinv(j.T @ j)
        cov = cov_ls[:6, :6]
        if not dropped:
            first = (theta, j, conv, model, cov, cov_ls)
        bad = idx[_violation(labelled, board, theta) > STRAY_VIOLATION]
        limit = max(MAX_STRAYS, MAX_STRAY_FRACTION * len(idx))
        if len(bad) == 0 or dropped + len(bad) > limit:
            break
        dropped += len(bad)
        lab = model.lab.copy()
        lab[bad] = UNKNOWN
        model = _build_model(model.rays, lab, theta, board, sigma_r, hints.edge_blur, like=model)
        theta, j, conv, it, _ = _staged_fit(model, theta, ds)
        iters += it
    if post is None and dropped:
        # leaving them out did not make the labels agree: they were not strays but the
        # board's own labels that a least-squares pose in a wrong basin violates (a ring
        # grazing an edge); each round moved it further (2 deg of roll, seen on a random
        # scene), so the first fit stands
        theta, j, conv, model, cov, cov_ls = first
        dropped = 0
        if offset_model is not None:
            offset_model.centre = model.offset
            offset_model.centre_std = float(np.sqrt(cov_ls[6, 6])) if len(cov_ls) > 6 else 0.0
    rays, lab = model.rays, model.lab
    hit = lab == HIT
    if post is not None:
        theta, cov = post
        model.classify(theta, 0.002, True)  # the diagnostics below describe this pose
        model.assign(theta)
    elif hints.laser_offset_sigma > 0:
        # the least-squares fit's covariance knows the ranges' noise (and the common offset it
        # fits), not the per-laser offsets: their share of the plane's covariance is added
        prior = hints.range_offset_prior or (0.0, OFFSET_KNOWN)
        c_common = fit_rays_offsets(r_all[keep], o_all[keep], u_all[keep],
                                          ring_all[keep], n, d, sigma_r, prior, 0.0, 1)[2]
        j_p = _pose_per_plane(theta, n, d)
        cov = cov + j_p @ (ml_plane[2] - c_common) @ j_p.T
    offset_diag, b = {}, model.offset
    if offset_model is not None:
        if post is not None and offset_model.mean is not None:
            b, b_sd = offset_model.mean, offset_model.std
        else:  # the least-squares fit's
            b, b_sd = model.offset, offset_model.centre_std
        offset_diag = {"range_offset_m": float(b), "range_offset_std_m": float(b_sd),
                       "range_offset_lsq_m": float(model.offset),
                       "range_offset_lsq_std_m": float(offset_model.centre_std)}
    t_fit = time.perf_counter()

    # what was seen: every edge, nothing in front of the board
    x, z, lam = model.coords(theta)
    k, sgn = model.edge_kind, model.edge_sign
    n_left = int(np.sum((k == 1) & (sgn < 0)))
    n_right = int(np.sum((k == 1) & (sgn > 0)))
    n_top = int(np.sum((k == 2) & (sgn > 0)))
    n_bottom = int(np.sum((k == 2) & (sgn < 0)))
    w2, h2 = board.width / 2, board.height / 2
    # every edge seen (`_edges_seen`), the rays inside the rectangle, those blocked (a return
    # in front of the board where the board is: not a stray left out), the dropouts and misses
    # inside and the hits outside: one compiled pass (`align.fit_kernels.seen_counts`)
    seen, n_inside, occluded, dropouts, inside_miss, outside_hits = seen_counts(
        x, z, lam, lab, rays.distance, float(b), _hit_band(sigma_r), w2, h2, WINDOW, 0.02,
        HIT, MISS, DROPOUT)
    seen = tuple(bool(v) for v in seen)
    diag = {
        "rings": len(rings_hit), "rays": len(lab), "hits": int(hit.sum()),
        "range_residuals": int(model.use_range.sum()), "brackets": int(np.sum(k > 0)),
        "edges_left": n_left, "edges_right": n_right, "edges_top": n_top,
        "edges_bottom": n_bottom, "occluded_rays": occluded, "inside_misses": inside_miss,
        "dropouts": dropouts, "starts": len(starts), "strays_dropped": dropped,
        "label_posterior": post is not None,
        "in_plane_rotation_rad": in_plane_rotation(theta),
        "range_sigma_m": sigma_r, "iterations": iters, **offset_diag,
        "chi2_per_dof": float(np.sum(model.residuals(theta) ** 2) / max(len(j) - 6, 1)),
    }
    diag["outside_hits"] = outside_hits
    status = Status.OK
    n_inside = max(n_inside, 1)
    n_hit = max(int(hit.sum()), 1)
    diag["edges_seen"] = "".join("lrbt"[i] for i in range(4) if seen[i])
    if (not all(seen) or int(np.sum(k > 0)) < MIN_BRACKETS
            or occluded > 0.03 * n_inside or inside_miss > 0.03 * n_inside
            or outside_hits > 0.03 * n_hit or diag["chi2_per_dof"] > 3.0
            or model.use_range.sum() < 0.5 * n_hit):
        # the known rectangle does not explain what was seen: part of the board is hidden,
        # dark or outside the field of view (or something board-like is not the board)
        status = Status.PARTIAL_BOARD
        missing = "/".join(n for n, ok in zip(("left", "right", "bottom", "top"), seen,
                                              strict=True) if not ok)
        diag["reason"] = ("the board's rectangle is not fully seen: "
                          + (f"nothing seen beyond its {missing} edge, " if missing else "")
                          + f"{int(np.sum(k > 0))} edge brackets (left/right/bottom/top "
                          f"{n_left}/{n_right}/{n_bottom}/{n_top}), {occluded} rays blocked in "
                          f"front, {inside_miss} misses inside, {outside_hits} hits outside, "
                          f"chi2/dof {diag['chi2_per_dof']:.1f}")
    elif not conv:
        status = Status.NOT_CONVERGED
    used = {"board": rays.gidx[model.use_range],
            "features": np.stack((rays.gidx[model.bh[k > 0]], rays.gidx[model.bm[k > 0]]), axis=1)}
    timings = {"plane": t_plane - t0, "fit": t_fit - t_plane}
    theta, cov = symmetry.canonical(theta, board, cov)
    return PoseEstimate(status, "rays", Pose.from_array(theta), cov, diag, used, timings)


#: At least this many hit/miss brackets (3 in-plane unknowns: roll, x, z, and one to spare).
MIN_BRACKETS = 4


def _edges_seen(x: np.ndarray, z: np.ndarray, lab: np.ndarray, board: BoardSpec
                ) -> tuple[bool, bool, bool, bool]:
    """Whether the LiDAR looked beyond each edge (left, right, bottom, top) and saw no board
    there: a miss just outside it (within `WINDOW`), alongside it. An edge beyond the field of
    view, behind an occluder or on a dark patch that returns nothing has none: the rectangle
    could extend there, so the board is not wholly seen."""
    w2, h2 = board.width / 2, board.height / 2
    miss = lab == MISS
    along_x, along_z = np.abs(z) <= h2, np.abs(x) <= w2
    out = []
    for c, half, along, side in ((x, w2, along_x, -1), (x, w2, along_x, 1),
                                 (z, h2, along_z, -1), (z, h2, along_z, 1)):
        beyond = (side * c > half) & (side * c < half + WINDOW)
        out.append(bool(np.any(miss & along & beyond)))
    return tuple(out)
