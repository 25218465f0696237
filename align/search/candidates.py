"""The board search's other candidates, in the order they are worth trying when its first
choice is not the board's rectangle."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace

import numpy as np

from align.board import BoardSpec
from align.result import Hints, Status
from align.search.board import find_board
from align.search.plane_first import plane_candidates
from align.search.result import Segmentation
from align.search.static import regrown
from twin.core.scan import Scan

#: Board searches redone, each without the returns of every candidate tried before, when none
#: of a search's candidates is the board's rectangle.
RESEARCHES = 2
#: Then at most this many candidates of the plane-first search (`plane_candidates`).
PLANE_CANDIDATES = 4


def candidate_segmentation(scan: Scan, returns: np.ndarray, n_clusters: int,
                           by_plane: bool = False) -> Segmentation:
    """The returns ``returns`` of ``scan`` taken as the board's cluster."""
    rings = scan.lasers.ring_of_laser[scan.laser_id[returns]]
    return Segmentation(Status.OK, returns, n_clusters, float(np.mean(scan.distance[returns])),
                        len(np.unique(rings)), by_plane=by_plane)


def other_candidates(scan: Scan, ref: Segmentation | None, board: BoardSpec, hints: Hints
                     ) -> Iterator[Segmentation]:
    """The search's other candidates on ``scan``, best first; each is taken as tried once
    yielded. The search's runners-up come first (the first choice regrown onto the rings
    beside it, then its alternatives); then the search is redone without the returns of every
    candidate tried, up to `RESEARCHES` times: the board's cluster can score below a box's
    face behind it (its main plane taking in returns of its stand or of a box beside it: a
    fifth of its returns off the rectangle) and then not be among the runners-up at all. Last,
    the board is searched plane first (`plane_candidates`): the clustering cut the board apart
    (its rings running on onto things just behind it) or buried it in a plane that holds more.
    ``ref``: the search's first choice; None when the search found none (then only the
    plane-first search is made)."""
    tried = [] if ref is None else [ref.board]
    n_clusters = 0 if ref is None else ref.n_clusters

    def candidate(returns: np.ndarray, by_plane: bool = False) -> Segmentation:
        tried.append(returns)
        return candidate_segmentation(scan, returns, n_clusters, by_plane)

    grown = None if ref is None else regrown(scan, ref.board, hints)
    queue = ([] if grown is None else [grown]) + ([] if ref is None else list(ref.alternatives))
    for search in range(0 if ref is None else RESEARCHES + 1):
        while queue:
            yield candidate(queue.pop(0))
        if search == RESEARCHES:
            break
        # the same scan with the tried candidates' returns taken as none, for the search only
        # (the estimate labels every ray of the scan itself)
        distance = scan.distance.copy()
        distance[np.concatenate(tried)] = 0.0
        g = find_board(replace(scan, distance=distance), board, hints)
        if g.status != Status.OK:
            break
        queue = [g.board, *g.alternatives]
    for returns in plane_candidates(scan, board, hints, tried)[:PLANE_CANDIDATES]:
        yield candidate(returns, by_plane=True)
