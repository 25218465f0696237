"""The estimator: the LiDAR's pose in the board frame from scans. Pure: arrays in, results out.

>>> from align import estimate, BoardSpec
>>> result = estimate(scan, BoardSpec(0.90, 0.54))          # doctest: +SKIP
>>> result.status, result.pose, result.std                   # doctest: +SKIP

The package's names load on first use (PEP 562): ``import align`` alone, or a submodule such as
``align.methods``, does not import the estimator's kernels, so a command line that only names
the methods starts at once.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from align.api import estimate
    from align.board import BoardSpec
    from align.methods import DEFAULT_METHOD, METHODS
    from align.result import Hints, PoseEstimate, Status

#: Each public name and the module that holds it.
_HOMES = {"estimate": "align.api", "BoardSpec": "align.board", "Hints": "align.result",
          "PoseEstimate": "align.result", "Status": "align.result",
          "DEFAULT_METHOD": "align.methods", "METHODS": "align.methods"}

__all__ = ["DEFAULT_METHOD", "METHODS", "BoardSpec", "Hints", "PoseEstimate", "Status", "estimate"]


def __getattr__(name: str) -> Any:
    home = _HOMES.get(name)
    if home is None:
        raise AttributeError(f"module 'align' has no attribute {name!r}")
    value = getattr(importlib.import_module(home), name)
    globals()[name] = value  # later lookups (and a wrapper set on it) skip this function
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_HOMES])
