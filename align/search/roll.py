"""The board's in-plane rotation found without a hint: the roll at which its returns fit the
known rectangle.

For a fixed plane every return's point on it is fixed; a roll only turns the rectangle about
the plane's normal. At the true roll every return lies inside the W x H rectangle; turned by
delta, the returns' extent along the rectangle's axes grows (about W |sin delta| + H (1 - cos
delta) across the height), so returns fall outside whatever the position. For each roll of a
grid over the whole symmetry range (a rectangle: 180 deg) we count the returns a W x H box
cannot hold, its best position found along each axis by a sliding window over the sorted
coordinates. The rolls with the fewest left out form one or a few intervals; their middles are
the start rolls for the fit. A prior on the roll (`Hints.roll_prior`) narrows the grid.

Only the returns are used here: they are many and sit inside the board by construction, so a
few strays (a hand, a stand) do not move the minimum. The misses, which bound the rectangle from
outside, are left to the fit and the hit/miss posterior that follow
(`align.posterior.hit_miss.label_posterior`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from align.board import BoardSpec
from align.floats import plane_rows
from align.search.roll_kernels import window_sweep, window_sweep_pair

#: Roll grid steps, rad: a coarse pass over the whole range, then a fine one about the coarse
#: pass's best rolls. The interval of rolls that fit is a degree or more wide for a board seen
#: by a few rings; its middle is refined by the fit.
COARSE_STEP = np.deg2rad(1.0)
FINE_STEP = np.deg2rad(0.1)
#: The fine pass covers this much either side of each coarse interval, rad.
FINE_REACH = np.deg2rad(1.5)
#: Starts across a wide interval of rolls are at most this far apart, rad (the fit's own reach:
#: it restarts 1 and 2 deg away, and a single scan's posterior searches 4 deg either side).
SPREAD = np.deg2rad(6.0)
#: How far a return may lie outside the rectangle and still fit, m (mixed returns at the edge;
#: the plane's error moves the points by less).
TOLERANCE = 0.01
#: Returns used by the coarse and the fine pass (evenly subsampled): the count of returns left
#: out only has to resist a few strays.
COARSE_POINTS = 150
FINE_POINTS = 1000


@dataclass(frozen=True)
class RollStart:
    """A start for the fit: roll (rad), position of the rectangle (t_x, t_z, m, for
    `align.geometry.pose_from_plane` at that roll) and how many returns it leaves out."""

    roll: float
    t_x: float
    t_z: float
    left_out: int


def _window_fit(coords: np.ndarray, length: float) -> tuple[np.ndarray, np.ndarray]:
    """For each column of ``coords`` (n, K): the most points a window of ``length`` holds, and
    the shift that centres the window on them (minus the middle of their extent). The columns
    are consecutive rolls: `window_sweep` sorts each from the last's order (the same counts
    and shifts as `align.search.roll_kernels._slide` on each column sorted anew)."""
    return window_sweep(np.ascontiguousarray(coords, dtype=np.float64), float(length))


def subsample(points: np.ndarray, k: int) -> np.ndarray:
    return points if len(points) <= k else points[np.linspace(0, len(points) - 1, k).astype(
        np.int64)]


def left_out(points: np.ndarray, n: np.ndarray, board: BoardSpec, rolls: np.ndarray,
              tol: float, z_first: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per roll: how many returns a W x H box (grown by ``tol``) leaves out, and its shift.

    Exact at every roll within one of the fewest left out (all that `search` reads: its
    intervals, and the starts' counts and shifts); a roll that leaves out more gets a bound
    below its count and above the fewest plus one (what the window along one axis leaves
    out, the other axis then not swept there: `window_sweep_pair`) and a shift of 0 along
    the other axis. ``z_first``: sweep across the rings first (cheaper where most rolls
    leave out many along z and few along x: the coarse pass), else along them."""
    r0, r2 = plane_rows(rolls, n)
    # `_window_fit` of points @ r0.T and points @ r2.T, the products computed roll by roll
    # inside the sweep (the same floats), not gathered column by column out of (n, K) arrays
    p = np.ascontiguousarray(points, dtype=np.float64)
    ax, az = np.ascontiguousarray(r0), np.ascontiguousarray(r2)
    lx, lz = float(board.width + 2 * tol), float(board.height + 2 * tol)
    if z_first:
        cz, tz, cx, tx, counted = window_sweep_pair(p, az, ax, lz, lx)
        first = cz
    else:
        cx, tx, cz, tz, counted = window_sweep_pair(p, ax, az, lx, lz)
        first = cx
    m = len(points)
    return np.where(counted, 2 * m - cx - cz, m - first), tx, tz


def _runs(good: np.ndarray) -> list[tuple[int, int]]:
    """(first, last) index of each run of True."""
    edges = np.flatnonzero(np.diff(np.concatenate(([0], good.astype(np.int8), [0]))))
    return list(zip(edges[::2], edges[1::2] - 1, strict=True))


def search(points: np.ndarray, n: np.ndarray, board: BoardSpec, lo: float, hi: float,
           period: float = np.pi, max_starts: int = 12) -> list[RollStart]:
    """Start rolls in [lo, hi] (rad) for the plane with unit normal ``n``, best first.

    ``points`` (M, 3): the board's returns projected along their rays onto the plane, {L}.
    The starts are the middles of the intervals of rolls that leave out the fewest returns
    (within one of the least), several across a wide one, at most ``max_starts`` of them. A
    coarse pass (its box grown by what half a coarse step turns the board's corners by) finds
    where to look; a fine pass there gives the intervals. A grid over the whole symmetry
    ``period`` runs a little past both ends, so that an interval at the seam is seen whole (its
    twin one period away is dropped).
    """
    whole = hi - lo >= period - 1e-9
    pad = np.deg2rad(10.0) if whole else 0.0
    rolls = np.arange(lo - pad, hi + pad + 0.5 * COARSE_STEP, COARSE_STEP)
    coarse = subsample(points, COARSE_POINTS)
    grow = TOLERANCE + 0.5 * board.diagonal * np.sin(0.5 * COARSE_STEP)
    left, _, _ = left_out(coarse, n, board, rolls, grow, z_first=True)
    fine = subsample(points, FINE_POINTS)
    starts: list[RollStart] = []
    for a, b in _runs(left <= left.min() + 1):
        grid = np.arange(rolls[a] - FINE_REACH, rolls[b] + FINE_REACH + 0.5 * FINE_STEP,
                         FINE_STEP)
        out, tx, tz = left_out(fine, n, board, grid, TOLERANCE)
        for c, e in _runs(out <= out.min() + 1):
            # a wide interval (few rings on the board: its returns fit the rectangle at many
            # rolls) gets starts across it, `SPREAD` apart: the misses decide in the fit
            k_n = int(np.ceil((grid[e] - grid[c]) / SPREAD)) if e > c else 1
            for k in np.unique(np.linspace(c, e, k_n + 2)[1:-1].round().astype(int)):
                r = float(grid[k])
                if any(abs(((r - s.roll) + period / 2) % period - period / 2) < FINE_REACH
                       for s in starts):
                    continue  # the same interval seen again (one period away, or twice)
                starts.append(RollStart(r, float(tx[k]), float(tz[k]), int(out[k])))
    starts.sort(key=lambda s: s.left_out)
    return starts[:max_starts]
