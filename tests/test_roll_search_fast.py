"""The roll search's sweep (`align.search.roll_kernels.window_sweep_projected`: tails sorted alone,
each roll projected into a row) against the numpy reference it replaced (the (n, K) product
points @ axes.T, every column sorted afresh and slid), on the search's own inputs from real
scans: the twin's and the recorded VLP-16's."""

from __future__ import annotations

import numpy as np
import pytest

import align
from align.board import BoardSpec
from align.fit import starts
from align.floats import plane_rows
from align.search import roll as roll_search
from align.search.roll_kernels import window_sweep_projected
from tests import naive
from tests.conftest import DATA_DIR
from tests.test_rays_kernels import ACFR_BOARD
from twin.lidar.pcd import read_pcd_scans
from twin.sim.bench import BenchSim


@pytest.fixture(scope="module")
def searches(request) -> list[tuple[tuple, dict]]:
    """The arguments of every `roll_search.search` call of estimates of real scans."""
    calls: list[tuple[tuple, dict]] = []
    real = starts.search  # the fit's starts call it

    def recorded(*args, **kwargs):
        calls.append((args, kwargs))
        return real(*args, **kwargs)

    mp = pytest.MonkeyPatch()
    mp.setattr(starts, "search", recorded)
    try:
        for seed in range(4):
            align.estimate(BenchSim(seed=seed).scan(), board=BoardSpec(), hints=align.Hints())
        for p in sorted((DATA_DIR / "acfr-vlp16").glob("pose*_full.pcd"))[:2]:
            align.estimate(read_pcd_scans(p)[0], board=ACFR_BOARD,
                           hints=align.Hints(expected_distance=1.8))
    finally:
        mp.undo()
    assert len(calls) >= 4
    return calls


def test_projected_sweep_is_the_sorted_slide_bit_for_bit(searches):
    tails = 0
    for args, _ in searches:
        points, n, board = args[0], args[1], args[2]
        for k, step in ((roll_search.COARSE_POINTS, roll_search.COARSE_STEP),
                        (roll_search.FINE_POINTS, roll_search.FINE_STEP)):
            p = np.ascontiguousarray(roll_search.subsample(points, k))
            rolls = np.arange(-np.pi / 2, np.pi / 2, step)
            for axes, length in zip(plane_rows(rolls, n), (board.width + 0.02, board.height + 0.02),
                                    strict=True):
                got = window_sweep_projected(p, np.ascontiguousarray(axes), length)
                want = naive.window_fit(p @ axes.T, length)
                np.testing.assert_array_equal(got[0], want[0])
                np.testing.assert_array_equal(got[1], want[1])
                tails += int(np.sum((got[0] < len(p)) & (got[0] > 0.75 * len(p))))
    assert tails > 0  # columns the tails decided, not only whole ones


def test_search_starts_are_those_of_the_numpy_reference(searches, monkeypatch):
    got = [roll_search.search(*a, **k) for a, k in searches]
    monkeypatch.setattr(roll_search, "left_out", naive.left_out)
    want = [roll_search.search(*a, **k) for a, k in searches]
    assert got == want
    assert all(len(s) > 0 for s in got)


def test_left_out_is_exact_within_one_of_the_fewest(searches):
    """`left_out` (`window_sweep_pair`: the second axis swept only where a roll can leave
    out within one of the fewest) against every roll swept along both axes: the same count
    and shifts at every roll within one of the fewest, a count above the fewest plus one at
    every other, either axis first; and rolls were left out of the second sweep."""
    skipped = 0
    for args, _ in searches:
        points, n, board = args[0], args[1], args[2]
        for k, step, grow in ((roll_search.COARSE_POINTS, roll_search.COARSE_STEP, 0.0146),
                              (roll_search.FINE_POINTS, roll_search.FINE_STEP, 0.01)):
            p = np.ascontiguousarray(roll_search.subsample(points, k))
            rolls = np.arange(-np.pi / 2 - 0.2, np.pi / 2 + 0.2, step)
            want, w_tx, w_tz = naive.left_out(p, n, board, rolls, grow)
            near = want <= want.min() + 1
            for z_first in (False, True):
                got, tx, tz = roll_search.left_out(p, n, board, rolls, grow, z_first)
                np.testing.assert_array_equal(got[near], want[near])
                np.testing.assert_array_equal(tx[near], w_tx[near])
                np.testing.assert_array_equal(tz[near], w_tz[near])
                assert np.all(got[~near] > want.min() + 1)
                assert np.all(got[~near] <= want[~near])
                skipped += int(np.sum(got != want))
    assert skipped > 0
