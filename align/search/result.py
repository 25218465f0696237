"""What the board search found in one scan: `Segmentation`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from align.result import Status


@dataclass
class Segmentation:
    """The board's cluster in one scan, or why there is none."""

    status: Status
    board: np.ndarray  # indices into the scan of the board cluster's returns
    n_clusters: int = 0
    distance: float = float("nan")  # mean range of the chosen cluster, m
    rings: int = 0
    reason: str = ""
    #: the next most board-like candidates' returns, best first: what an estimator that finds
    #: the choice is not the board (the known rectangle does not explain its rays) tries next
    alternatives: tuple[np.ndarray, ...] = ()
    #: the search's likeness (`align.search.board.board_score`) of the choice and of each
    #: alternative (nan: not scored, e.g. a candidate of the retry)
    score: float = float("nan")
    alternative_scores: tuple[float, ...] = ()
    #: the returns were chosen by their distance to a plane (`plane_candidates`): their own
    #: plane leans towards that one (the noise beyond the band is left out)
    by_plane: bool = False
