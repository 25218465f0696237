"""The pose fit's compiled kernels (`align.fit_kernels`) against the numpy versions they
replaced: the same numbers bit for bit (they only compare, count and copy numpy's floats)."""

from __future__ import annotations

import numpy as np

from align import roll_search
from align.board import BoardSpec
from align.feasible import _rows
from align.fit_kernels import window_sweep


def window_fit_reference(coords: np.ndarray, length: float) -> tuple[np.ndarray, np.ndarray]:
    """`roll_search._window_fit` before the kernel: every column sorted afresh, then slid."""
    rows = np.ascontiguousarray(coords.T)
    rows.sort(axis=1)
    return roll_search._slide(rows, length)


def _board_points(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Returns on a 0.6 x 0.45 m board 2.6 m ahead, on a few rings, with a few strays."""
    normal = np.array([0.1, 0.99, -0.05])
    normal /= np.linalg.norm(normal)
    e1 = np.cross(normal, [0.0, 0.0, 1.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    u = rng.uniform(-0.3, 0.3, n)
    v = rng.choice(np.linspace(-0.2, 0.2, 6), n) + rng.normal(0, 1e-3, n)
    pts = 2.6 * normal + u[:, None] * e1 + v[:, None] * e2
    pts[:3] += 0.2  # strays
    return pts, normal


def test_window_sweep_matches_sorting_every_roll():
    rng = np.random.default_rng(3)
    board = BoardSpec()
    for n, step in ((150, np.deg2rad(1.0)), (1000, np.deg2rad(0.1)), (7, np.deg2rad(5.0))):
        pts, normal = _board_points(rng, n)
        rolls = np.arange(-np.pi / 2, np.pi / 2, step)
        r0, r2 = _rows(rolls, normal)
        for coords, length in ((pts @ r0.T, board.width + 0.02),
                               (pts @ r2.T, board.height + 0.02)):
            got, want = window_sweep(coords, length), window_fit_reference(coords, length)
            np.testing.assert_array_equal(got[0], want[0])
            np.testing.assert_array_equal(got[1], want[1])
    # ties, a single point, none
    coords = np.repeat(np.array([[0.0, 1.0, 1.0, 2.0]]).T, 3, axis=1)
    for c in (coords, coords[:1], coords[:0]):
        got, want = window_sweep(c, 1.0), window_fit_reference(c, 1.0)
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_array_equal(got[1], want[1])
