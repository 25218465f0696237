"""Compiled kernels of the pose fit (numba, ``cache=True``; `scenarios.warmup` compiles them
ahead): the roll search's sliding windows and the joint fit's bookkeeping.

Each replaces a numpy version whose cost was python overhead or sorting, not arithmetic. They
take the floats numpy computed (board coordinates, range residuals) and do on them only
comparisons, counts and the same elementwise operations in the same order (numba neither
contracts nor reorders floating-point arithmetic without ``fastmath``), so they give bit for
bit what the numpy versions gave. tests/test_fit_kernels.py checks each against its numpy
reference.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def _insertion_sort(xs: np.ndarray, order: np.ndarray) -> None:
    """Sort ``xs`` ascending in place, permuting ``order`` with it: linear in the length plus
    the pairs out of order, which are few in a row already nearly sorted."""
    for i in range(1, xs.shape[0]):
        v, o = xs[i], order[i]
        j = i - 1
        while j >= 0 and xs[j] > v:
            xs[j + 1] = xs[j]
            order[j + 1] = order[j]
            j -= 1
        xs[j + 1] = v
        order[j + 1] = o


@njit(cache=True)
def window_sweep(coords: np.ndarray, length: float) -> tuple[np.ndarray, np.ndarray]:
    """`align.roll_search._window_fit`: for each column of ``coords`` (n, K), the most points a
    window of ``length`` holds and the shift that centres it on them (minus the middle of the
    first such window's points).

    The columns are the points' coordinates along a rectangle's axis at consecutive rolls:
    each is sorted starting from the previous column's order, which a small turn hardly changes
    (an insertion sort then costs little more than a copy; sorting every column afresh and
    sliding after cost twice as much). The sorted values are the same whatever sorted them,
    so the counts and shifts are those of sorting each column anew."""
    n, k = coords.shape
    count = np.zeros(k, dtype=np.int64)
    shift = np.zeros(k)
    if n == 0 or k == 0:
        shift[:] = -0.0  # -(0 + 0) / 2: an empty window's middle, as the numpy version's
        return count, shift
    rows = np.ascontiguousarray(coords.T)  # each roll's coordinates together: gathered fast
    order = np.argsort(rows[0])
    xs = np.empty(n)
    for c in range(k):
        row = rows[c]
        for i in range(n):
            xs[i] = row[order[i]]
        _insertion_sort(xs, order)
        j = 0
        best, lo, hi = 0, 0.0, 0.0
        for i in range(n):
            if j < i:
                j = i
            while j + 1 < n and xs[j + 1] <= xs[i] + length:
                j += 1
            if j - i + 1 > best:
                best, lo, hi = j - i + 1, xs[i], xs[j]
        count[c] = best
        shift[c] = -0.5 * (lo + hi)
    return count, shift
