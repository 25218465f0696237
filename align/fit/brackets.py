"""Hit/miss brackets: along each laser, where a hit and a miss meet an edge of the board lies
between them."""

from __future__ import annotations

import numpy as np

from align.fit.bracket_kernels import between_hits, column_brackets, laser_brackets
from align.fit.rays import DROPOUT, HIT, Rays
from align.params import RaysParams


def rays_between_hits(rays: Rays, lab: np.ndarray, order: np.ndarray | None = None
                  ) -> np.ndarray:
    """Rays that lie between two hits of the same laser in the same scan (by azimuth).
    ``order``: the rays by scan, laser and azimuth, if the caller has it. Compiled
    (`between_hits`)."""
    if order is None:
        order = np.lexsort((rays.azimuth, rays.laser, rays.scan))
    return between_hits(order, rays.scan, rays.laser, lab == HIT)


def hit_miss_brackets(rays: Rays, lab: np.ndarray, *, p: RaysParams) -> tuple[np.ndarray,
                                                                              np.ndarray]:
    """Hit/miss brackets along each laser: pairs (hit-side ray, miss-side ray) of indices.

    Only where a laser enters and leaves the board: the board is convex, so a transition
    between its first and last hit is not its edge but a dropout or a stray inside it (a black
    square that ranged wrong). Dropouts are skipped: a bracket spans them (the edge lies
    anywhere between the hit and the miss).
    """
    # the links and transitions along each laser, its span on the board (`board_spans`) and
    # the walk over the zones, compiled (`laser_brackets`, `edge_brackets`)
    return laser_brackets(np.lexsort((rays.azimuth, rays.laser)), rays.laser, rays.azimuth,
                          lab, DROPOUT, HIT, p.max_gap, p.zone_azimuth)


def vertical_brackets(rays: Rays, lab: np.ndarray, off: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Ring-to-ring brackets of the edges above and below the board's centre, as the LiDAR sees
    them (the top and bottom edges of a level board).

    ``off``: each ray's distance from the board's central column, the line through its centre
    along the LiDAR's up direction. For each ring, the ray nearest that column; going up from
    the lowest ring that hits, the first ring that misses brackets the edge above with the ring
    below it (and likewise down). One bracket per edge for all scans: the rings sit at the same
    heights in every scan.
    """
    return column_brackets(rays.ring, lab, off)  # one pass over the rays, not one per ring
