"""The estimator: the LiDAR's pose in the board frame from scans. Pure: arrays in, results out.

>>> from align import estimate, BoardSpec
>>> result = estimate(scan, BoardSpec(0.90, 0.54))          # doctest: +SKIP
>>> result.status, result.pose, result.std                   # doctest: +SKIP
"""

from align.api import DEFAULT_METHOD, METHODS, estimate
from align.board import BoardSpec
from align.result import Hints, PoseEstimate, Status

__all__ = ["DEFAULT_METHOD", "METHODS", "BoardSpec", "Hints", "PoseEstimate", "Status", "estimate"]
