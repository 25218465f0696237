"""The least-squares fit of the pose from a start: profile across the rings, strays left out,
staged Gauss-Newton (`fit_from`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from align.board import BoardSpec
from align.fit.bracket_kernels import contradicted
from align.fit.labels import bright_ends, grazing_runs, labels_ordered
from align.fit.lsq_kernels import lm_fit
from align.fit.model import JACOBIAN_STEP, Model, build_model
from align.fit.rays import HIT, MISS, UNKNOWN, candidates_at
from align.fit.sides import Sides, overhanging, side_widening
from align.params import RaysParams
from align.result import Hints
from align.search.result import Segmentation
from twin.core.scan import Scan


def gauss_newton(model: Model, theta: np.ndarray, max_iter: int = 30
                  ) -> tuple[np.ndarray, np.ndarray, bool, int]:
    """Levenberg-Marquardt on the whitened residuals.

    The bracket assignment and the set of range residuals stay fixed during one call (they are
    chosen for the start pose), so the cost is one smooth function and the steps decrease it.
    Converged when every step is below a hundredth of the parameter's standard deviation.
    With ``model.offset_prior`` the common range offset is a seventh parameter (its prior one
    more residual): the ranges alone cannot tell it from the distance, the brackets (the
    board's known size) can. The Jacobian returned then has seven columns.
    """
    model.assign(theta)
    fit_b = model.offset_prior is not None
    b0, sb = model.offset_prior if fit_b else (0.0, 1.0)
    o_r, u_r, d_r, offset, sigma_r, *edges = model._fit_arrays()
    # the whole loop compiled (`lm_fit`): a step is a dozen small array operations, whose
    # per-call overhead would outweigh their arithmetic
    p, j, converged, it = lm_fit(np.asarray(theta, dtype=np.float64), fit_b, offset,
                                 float(b0), float(sb), o_r, u_r, d_r, sigma_r, *edges,
                                 JACOBIAN_STEP, max_iter)
    if fit_b:
        model.offset = float(p[6])
    return p[:6], j, bool(converged), int(it)


def _gross_brackets(model: Model, theta: np.ndarray, *, p: RaysParams) -> np.ndarray:
    """The brackets (a mask over all of the model's) the fit at ``theta`` misses by more than
    `p.gross` sigma."""
    f = model.residuals(theta)
    out = np.zeros(len(model.bh), dtype=bool)
    out[np.flatnonzero(model.edge_kind > 0)[np.abs(f[len(model._range[0]):]) > p.gross]] = True
    return out


def staged_fit(model: Model, theta: np.ndarray, ds: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, bool, int, float]:
    """Fit in stages; returns (theta, J, converged, iterations, chi2 per degree of freedom).

    First without the grazing crossings (rings crossing a level board's top or bottom edge):
    roll and x from the edges the rings cross steeply, so that a poor start cannot lock z and
    roll into a wrong pair of crossings; then with them, the bracket assignment redone with a
    tighter corner guard; a profile across the rings (`Model.profile`) after each stage, and
    a last fit if that profile moved the rectangle.
    """
    iters = 0
    for guard, crossings in ((0.005, False), (0.002, True)):
        model.classify(theta, guard, crossings)
        theta, j, conv, it = gauss_newton(model, theta)
        iters += it
        moved = model.shift(theta, ds)
        shift = float(np.hypot(moved[0] - theta[0], moved[2] - theta[2]))
        theta = moved
    if shift > 0.0015:  # the profile moved the rectangle by more than its 1 mm grid: refit
        model.classify(theta, 0.002, True)
        theta, j, conv, it = gauss_newton(model, theta)
        iters += it
    f = model.residuals(theta)
    return theta, j, conv, iters, float(f @ f / max(len(f) - 6, 1))


@dataclass
class Fit:
    """The least-squares fit from one start pose."""

    theta: np.ndarray
    j: np.ndarray
    conv: bool
    iters: int
    chi2: float
    model: Model
    rings: np.ndarray  # the rings with hits
    violations: int  # labels it contradicts by more than 1 cm (`_contradicted`)


def fit_from(scans: list[Scan], segs: list[Segmentation], theta: np.ndarray, board: BoardSpec,
             sigma_r: float, hints: Hints, ds: np.ndarray,
             offset: tuple[float, tuple[float, float] | None] = (0.0, None), *,
             p: RaysParams) -> Fit | None:
    """The joint least-squares fit from the start pose ``theta``; None: fewer than 3 rings hit.

    The position across the rings is the weakly known one (rings are 2 deg apart) and a ring
    that crosses an edge at a grazing angle pins it down sharply, but only once its bracket is
    matched to the right edge. So: profile across the rings over more than a ring spacing
    (label violations first); then returns far outside the rectangle are not the board (the
    stand's base is level with the plane a ring or two below it): mark them unknown and rebuild
    the brackets; profile again; fix the bracket assignments leaving out those at corners, fit;
    reassign tighter, refit (`staged_fit`).
    """
    found = _start_labels(scans, segs, theta, board, sigma_r, offset, p=p)
    if found is None:
        return None
    rays, coords, spacing, lab, rings_hit = found
    # the profile and the stray margin grow with the rings' spacing on the board: the start
    # can be off by half of it (a far board, one tilted away)
    reach = max(float(ds[-1]), p.profile_spacings * spacing)
    ds = np.arange(-reach, reach + 0.5e-3, 1e-3)
    stray_margin = max(p.stray, p.stray_spacings * spacing)
    model = build_model(rays, lab, theta, board, sigma_r, hints.edge_blur, offset=offset,
                         coords=coords, p=p)
    theta = model.shift(theta, ds)
    coords = model.coords(theta)
    x, z = coords[0], coords[1]
    stray = (lab == HIT) & ((np.abs(x) > board.width / 2 + stray_margin) |
                            (np.abs(z) > board.height / 2 + stray_margin))
    if np.any(stray):
        lab = lab.copy()
        lab[stray] = UNKNOWN
        model = build_model(rays, lab, theta, board, sigma_r, hints.edge_blur, like=model,
                             coords=coords, p=p)
        theta = model.shift(theta, ds)
    theta, j, conv, iters, chi2 = staged_fit(model, theta, ds)
    for _ in range(2):
        # a bracket the fit misses by many sigma is not the board's edge: a stray's (a post
        # just behind the board's edge, within the label tolerance of its plane, on a ring
        # that never crosses the board): left out of the fit, which is redone. The labels stay
        # (the hit/miss posterior judges them).
        gross = _gross_brackets(model, theta, p=p)
        if not np.any(gross):
            break
        model.excluded |= gross
        theta, j, conv, it, chi2 = staged_fit(model, theta, ds)
        iters += it
    if chi2 > 1.5:
        theta, j, conv, iters, chi2 = _other_rolls(model, theta, ds, (theta, j, conv, iters, chi2))
    return Fit(theta, j, conv, iters, chi2, model, rings_hit, _contradicted(model, theta))


def _start_labels(scans: list[Scan], segs: list[Segmentation], theta: np.ndarray,
                  board: BoardSpec, sigma_r: float,
                  offset: tuple[float, tuple[float, float] | None], *, p: RaysParams
                  ) -> tuple | None:
    """The rays near the board at the start pose ``theta`` and their labels, with the hits
    that are not the board's taken as unknown: (rays, board coordinates, ring spacing, labels,
    rings hit), or None: fewer than 3 rings hit."""
    rays, coords, spacing = candidates_at(scans, segs, theta, board, p=p)
    expected = coords[2] + offset[0]  # the range expected, offset included
    lab, order = labels_ordered(rays, expected, sigma_r, p=p)  # order: by scan, laser, azimuth
    # things just behind the board beside its edges, within the range noise of its plane: a
    # few cm of hits on a ring that passes the board, and rings lengthened past a side edge.
    # Left out before the brackets are drawn (a rectangle turned to reach them, as a fit from
    # there finds it, locks onto grazing crossings degrees off); judged again by the hit/miss
    # posterior's labels at the fitted pose (`ray_points`)
    w2, h2, margin = board.width / 2, board.height / 2, p.outlier_margin
    inner = (np.abs(coords[0]) < w2 - margin) & (np.abs(coords[1]) < h2 - margin)
    intensity = np.concatenate([s.intensity for s in scans])[rays.gidx]
    lab[bright_ends(rays, lab, intensity, inner, order, p=p)] = UNKNOWN
    ext = side_widening(rays.direction, theta, board)
    sides = Sides.of(coords[0], coords[1], lab, rays.laser, ext, board, p=p)
    grazing = grazing_runs(rays, lab, coords, expected, board, order, sides, p=p)
    if np.any(grazing):
        lab[grazing] = UNKNOWN
        sides = None  # its lasers' ends may have changed
    lab[overhanging(coords[0], coords[1], lab, rays.laser, ext, board, sides, p=p)] = UNKNOWN
    rings_hit = np.unique(rays.ring[lab == HIT])
    if len(rings_hit) < 3:
        return None
    return rays, coords, spacing, lab, rings_hit


def _other_rolls(model: Model, theta: np.ndarray, ds: np.ndarray, fit: tuple) -> tuple:
    """A misfit (roll started too far off and a pair of grazing crossings held it there):
    restarts from other rolls; the best ``fit`` (theta, j, conv, iterations, chi2) kept, and
    the model left in its state."""
    theta, j, conv, iters, chi2 = fit
    kept_offset = model.offset
    for droll in np.deg2rad([-2.0, -1.0, 1.0, 2.0]):
        start = theta.copy()
        start[3] += droll
        cand = staged_fit(model, start, ds)
        if cand[4] < chi2:
            theta, j, conv, it, chi2 = cand
            iters += it
            kept_offset = model.offset
    model.offset = kept_offset
    model.classify(theta, 0.002, True)  # the state of the kept fit, for the diagnostics
    model.assign(theta)
    return theta, j, conv, iters, chi2


def _contradicted(model: Model, theta: np.ndarray, margin: float = 0.01) -> int:
    """How many hits lie outside the rectangle at ``theta`` and misses inside it, by more than
    ``margin`` (m)."""
    x, z, _ = model.coords(theta)
    # one compiled pass over the rays (`contradicted`)
    return int(contradicted(x, z, model.lab, HIT, MISS, model.board.width / 2,
                            model.board.height / 2, margin))
