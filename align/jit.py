"""The estimator's numba kernels: how they are compiled, cached and when a cache is stale.

Every compiled kernel in `align` is declared with `kernel` (numba's ``njit`` with its on-disk
cache). numba keys a kernel's cache on its own source file only: a kernel that calls a kernel of
another file keeps running the old machine code after that file changed. The rule here (kept by
tests/test_kernel_calls.py): a kernel calls kernels of its own module and of `align.floats` only,
the one leaf of float helpers every stage shares; and this module makes a kernel's cache stale
when either its own file or `align.floats` changes, so no kernel ever needs a hand copy of a
helper to stay correct.

`scenarios.warmup` compiles them all ahead, once per install.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

from numba import njit
from numba.core import caching

#: The package whose kernels this module caches, and its leaf of shared float helpers.
PACKAGE = Path(__file__).resolve().parent
LEAF = PACKAGE / "floats.py"


def _stamp(path: Path) -> tuple[float, int]:
    st = os.stat(path)
    return st.st_mtime, st.st_size


class _LeafStamped:
    """A numba cache locator mixin: a kernel of `align` is stale when its own file or the leaf
    changes (numba's own locators look at the kernel's file alone)."""

    @classmethod
    def from_function(cls, py_func, py_file):
        if not Path(py_file).resolve().is_relative_to(PACKAGE):
            return None  # not ours: numba's own locators take it
        return super().from_function(py_func, py_file)

    def get_source_stamp(self):
        return (super().get_source_stamp(), _stamp(LEAF))


def _leaf_stamped(base: type) -> type:
    return type(f"LeafStamped{base.__name__}", (_LeafStamped, base), {})


# numba's order of locators (a user's NUMBA_CACHE_DIR first, then __pycache__ beside the
# source, then the user's cache directory), each with the leaf in its stamp, ahead of numba's.
_OURS = [_leaf_stamped(c) for c in (caching.UserProvidedCacheLocator,
                                    caching.InTreeCacheLocator,
                                    caching.UserWideCacheLocator)]
if not any(c.__name__.startswith("LeafStamped") for c in caching.CacheImpl._locator_classes):
    caching.CacheImpl._locator_classes[:0] = _OURS


def kernel(func: Callable | None = None, **options) -> Callable:
    """``@kernel`` or ``@kernel(error_model="numpy")``: numba's ``njit`` with the on-disk
    cache this module keeps fresh."""
    if func is not None:
        return njit(cache=True, **options)(func)
    return njit(cache=True, **options)
