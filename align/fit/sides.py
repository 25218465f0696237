"""The side edges as two parallel lines through the lasers' ends, and hits beyond them that are
not the board's (a thing just behind it, beside an edge)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from align.board import BoardSpec
from align.fit.label_kernels import laser_ends, line_excess, side_ends, side_faces
from align.fit.rays import HIT
from align.geometry import rotation
from align.params import RaysParams


def side_widening(u: np.ndarray, theta: np.ndarray, board: BoardSpec) -> np.ndarray:
    """(M, 4) how far past the left, right, bottom and top edge (m) the rays with directions
    ``u`` still hit the plate at ``theta``: its side faces, seen by rays heading inwards past
    an edge (as `Model.residuals`)."""
    # compiled (`side_faces`: the floats of u @ rot.T, the ratios, np.maximum and the product)
    return side_faces(np.ascontiguousarray(u, dtype=np.float64),
                      rotation(theta[3], theta[4], theta[5]), float(board.thickness))


def overhanging(x: np.ndarray, z: np.ndarray, lab: np.ndarray, laser: np.ndarray,
                 ext: np.ndarray, board: BoardSpec, sides: Sides | None = None, *,
                 p: RaysParams) -> np.ndarray:
    """Hits at one end of a laser's run beyond the board's side edge: a holder or clamp beside
    it, flush with the board's plane within the range noise, whose hits extend that one
    laser's run. Returned to be left out of the labels: a rectangle turned to take them in is
    what a fit finds, degrees off.

    The side edges are straight, parallel lines, and every laser that reaches one ends within
    an azimuth step inside it. Their ends at both sides give the two lines (`side_lines`,
    robust: an end beyond them is a holder's, one well inside them a ring leaving through the
    top or bottom edge near a corner). Of a laser whose end lies beyond its side's line by
    more than half a step and `p.overhang_slack`, the hits beyond the line are returned (the
    line lies within a step inside the edge, so at most the laser's last hit on the board goes
    with them). Where too few lasers reach the sides for the lines, the board's known width
    still tells: the hits of one laser between both side edges span at most its width (each
    hit's allowance ``ext`` outside an edge granted), and of a laser that spans more, the end
    farther off the line of the other lasers' ends at that side overhangs. Both tests hold at
    any pose near the board's to first order, a fit's roll error included. ``sides``:
    `Sides.of` these, if the caller has it."""
    out = np.zeros(len(lab), dtype=bool)
    if sides is None:
        sides = Sides.of(x, z, lab, laser, ext, board, p=p)
    if sides is None:
        return out
    ids, ends, hit, x_l, x_r = sides.ids, sides.ends, sides.hit, sides.x_l, sides.x_r
    long = ends[:, 2] - ends[:, 0] > board.width + p.span_slack
    if sides.lines is not None:
        a_l, a_r, b = sides.lines
        off_l = a_l + b * ends[:, 1] - ends[:, 0]  # > 0: beyond the line
        off_r = ends[:, 2] - a_r - b * ends[:, 3]
        for i in np.flatnonzero(long | (np.maximum(off_l, off_r) > sides.tol)):
            m = hit & (laser == ids[i])
            if off_r[i] >= off_l[i]:
                out |= m & (x_r > a_r + b * z)
            else:
                out |= m & (x_l < a_l + b * z)
        return out
    w2 = board.width / 2
    ref_l = ~long & (ends[:, 0] < -w2 + p.edge_reach)
    ref_r = ~long & (ends[:, 2] > w2 - p.edge_reach)
    for i in np.flatnonzero(long):
        off_l = _line_at(ends[ref_l, 1], ends[ref_l, 0], ends[i, 1]) - ends[i, 0]
        off_r = ends[i, 2] - _line_at(ends[ref_r, 3], ends[ref_r, 2], ends[i, 3])
        if np.isnan(off_l) and np.isnan(off_r):
            continue  # no other laser reaches either edge: nothing to tell the ends apart
        m = hit & (laser == ids[i])
        if np.isnan(off_l) or off_r >= off_l:
            out |= m & (x_r > ends[i, 2] - off_r)
        else:
            out |= m & (x_l < ends[i, 0] + off_l)
    return out


@dataclass
class Sides:
    """The lasers' ends at the board's side edges at a pose, and the edges they show.

    ``ids``: the lasers with hits on the board (or just beyond its top or bottom edge: a fit a
    few cm off across the rings); ``ends`` (K, 4): per laser, its left end's x and z and its
    right end's (m), each hit as far in as its side-face allowance lets it lie (``x_l``,
    ``x_r``: every ray's); ``hit``: the hits taken; ``tol``: how far off the lines a board's
    own end may lie (m: within a step inside its edge, within half a step of the lines
    through them all, and `p.overhang_slack`); ``lines``: (a_l, a_r, b), the side edges as
    x = a + b z (`side_lines`), or None when too few lasers reach them."""

    ids: np.ndarray
    ends: np.ndarray
    hit: np.ndarray
    x_l: np.ndarray
    x_r: np.ndarray
    tol: float
    lines: tuple[float, float, float] | None

    @classmethod
    def of(cls, x: np.ndarray, z: np.ndarray, lab: np.ndarray, laser: np.ndarray,
           ext: np.ndarray, board: BoardSpec, *, p: RaysParams) -> Sides | None:
        """From the rays' board coordinates ``x``, ``z``, labels, lasers and side-face
        allowances ``ext`` (`side_widening`); None with fewer than 3 lasers on the board."""
        w2, h2, margin = board.width / 2, board.height / 2, p.outlier_margin
        # the hits, per laser its leftmost hit (the first of equal ones, as argmin) and its
        # rightmost, and the azimuth step on the board (the median spacing of a laser's
        # consecutive hits), in one pass and a sort per laser (`laser_ends`)
        hit, x_l, x_r, il, _, ends, step = laser_ends(x, z, lab, laser, ext, HIT, w2 + margin,
                                                      h2 + margin)
        if len(il) < 3:
            return None
        ids = laser[il]
        tol = 0.5 * step + p.overhang_slack
        return cls(ids, ends, hit, x_l, x_r, tol, side_lines(ends, w2, tol, step + tol, p=p))

    def reaches(self, xs: np.ndarray, zs: np.ndarray) -> bool:
        """Whether the points (``xs``, ``zs``, m) reach a side edge: lie within twice `tol` inside
        a side line or beyond it."""
        a_l, a_r, b = self.lines
        return bool(np.any(xs < a_l + b * zs + 2 * self.tol) or
                    np.any(xs > a_r + b * zs - 2 * self.tol))


def side_lines(ends: np.ndarray, w2: float, tol: float, inward: float, *, p: RaysParams
                ) -> tuple[float, float, float] | None:
    """The board's side edges as seen by the lasers' ends, x = a_l + b z and x = a_r + b z (one
    slope: the edges are parallel), or None when too few lasers reach them. ``ends`` (K, 4):
    per laser the left end's x and z and the right end's, m. The ends within `p.edge_reach` of a
    side take part; the one farthest out of its band is dropped while some lie more than
    ``tol`` beyond the lines (a holder's) or ``inward`` inside them (m: a ring leaving through
    the top or bottom edge near a corner, a laser's last return missing) and enough are left.
    The band is wider inwards: an end kept there pulls the lines in, so that more of the
    board's own ends count as beyond them, which costs their last hit; a holder's end kept
    pulls them out, which hides it."""
    # the ends near each side (left ones first), x = line + residual, and the design of
    # (a_l, a_r, b): compiled (`side_ends`), as the worst end each round (`line_excess`);
    # the normal equations (3 x 3) solved by numpy
    xs, out_sign, a, n_r = side_ends(ends, w2, p.edge_reach)
    keep = np.ones(len(xs), dtype=bool)
    n_kept = len(xs)
    side = a[:, 1]
    while True:
        if n_r < p.side_ends or n_kept - n_r < p.side_ends or n_kept < p.line_ends:
            return None
        ak = a[keep]
        coef = np.linalg.solve(ak.T @ ak, ak.T @ xs[keep])  # three unknowns: normal equations
        worst, excess = line_excess(xs, a, coef, out_sign, keep, tol, inward)
        if excess <= 0.0:
            return float(coef[0]), float(coef[1]), float(coef[2])
        keep[worst] = False
        n_kept -= 1
        n_r -= int(side[worst] == 1)


def _line_at(z: np.ndarray, x: np.ndarray, z0: float) -> float:
    """The line x(z) through the points (z, x) (least squares; their mean for one) at ``z0``,
    or NaN for none."""
    if len(z) == 0:
        return math.nan
    if len(z) == 1 or np.ptp(z) < 1e-6:
        return float(np.mean(x))
    b, a = np.polyfit(z, x, 1)
    return float(a + b * z0)
