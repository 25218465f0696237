"""What an estimate returns: a status (never an exception), the pose, its covariance, and why."""

from __future__ import annotations

import enum
from dataclasses import dataclass, field

import numpy as np

from align.hint_defaults import EDGE_TOLERANCE
from twin.core.pose import POSE_FIELDS_EDGE, Pose


class Status(enum.StrEnum):
    """Outcome of an estimate. Only ``OK`` carries a pose a report may use."""

    OK = "ok"
    EMPTY_SCAN = "empty_scan"  # no return at all
    NO_BOARD = "no_board"  # returns, but no cluster looks like the board
    PARTIAL_BOARD = "partial_board"  # a board-like plane, but not the whole rectangle is seen
    TOO_FEW_RINGS = "too_few_rings"  # fewer rings on the board than the method needs
    BOARD_TOO_FAR = "board_too_far"  # a board-like cluster beyond the usable distance
    NOT_CONVERGED = "not_converged"  # the solver did not settle
    #: two board-like objects explain the rays about as well (`align.choice`): no pose
    AMBIGUOUS_BOARD = "ambiguous_board"
    #: the only board-like objects found lie outside the station's board region
    BOARD_OUTSIDE_REGION = "board_outside_region"
    UNKNOWN_METHOD = "unknown_method"
    #: Never returned by `align.estimate`: what a caller that catches an exception the
    #: estimator raised records instead of its answer (the runner: one bad scan must not lose
    #: a sweep), with the message as ``diagnostics["error"]``.
    ESTIMATOR_ERROR = "estimator_error"


@dataclass(frozen=True)
class Hints:
    """Optional prior knowledge; every field has a default that suits the paper's bench.

    Distances in m, angles in rad.
    """

    #: Expected distance from the LiDAR to the board's centre, m (None: search 0.5-6 m).
    expected_distance: float | None = None
    #: Azimuth window (centre, half width), rad, in the LiDAR's azimuth convention (None: all).
    azimuth_window: tuple[float, float] | None = None
    #: Farthest usable board distance, m: beyond it fewer than ~3 rings cross a 0.54 m board.
    max_distance: float = 6.0
    #: Nearest return considered, m.
    min_distance: float = 0.5
    #: Range noise 1-sigma, m, if known (None: estimated from the plane residuals).
    range_sigma: float | None = None
    #: 1-sigma of the random part of an edge's hit/miss transition, m (mixed returns, jitter).
    edge_blur: float = 0.2e-3
    #: How far a hit may lie outside the board's edge, and a miss inside it, as angles seen
    #: from the LiDAR across the side edges and across the top and bottom edges, rad: a beam
    #: that straddles an edge returns from whichever side reflects more of it. The twin's
    #: VLP-16 (3 x 1.5 mrad beam, a wall 1.5 m behind the board): hits seen up to 0.03 mrad
    #: outside a side edge and 0.3 mrad outside the top or bottom one, where a ring runs along
    #: the edge; 0.5 mrad is the most its beam allows there (a third of the divergence). (0, 0)
    #: for a sharp beam (a twin without beam divergence).
    edge_tolerance: tuple[float, float] = EDGE_TOLERANCE
    #: How far outside an edge a hit may lie whose intensity is below half the board's (only
    #: part of the beam met the board), rad, across the side edges and across the top and
    #: bottom edges: the beam's half-divergence (the VLP-16's 3 x 1.5 mrad beam). Before a dark
    #: or far background a beam straddling the edge returns the board's part of its spot, at
    #: the board's range and along the beam's centre: the twin's, up to its side sub-ray's
    #: 1 mrad outside a side edge (a constant tolerance that wide would loosen every label).
    #: A spot's board part outweighs a background returning less per beam than the board, its
    #: centre just beyond the edge: a real (Gaussian) beam's bleeds about 0.7 mrad there even
    #: before the bench's wall; the twin's five-point beam, only before a background below 0.18
    #: of the board's energy. Not applied where `edge_tolerance` is 0 (a sharp beam has no
    #: partial returns).
    partial_edge_tolerance: tuple[float, float] = (1.5e-3, 0.75e-3)
    #: Prior on the LiDAR's roll in the board frame, (mean, 1-sigma), rad, or None: the board's
    #: in-plane rotation is then found over the whole range (-90, 90] deg. A board hung turned
    #: by a about its normal (clockwise as the LiDAR sees it) puts a level LiDAR's roll at -a.
    #: The search and the posterior use it.
    roll_prior: tuple[float, float] | None = None
    #: Prior on a common range offset the sensor adds to every range, (mean, 1-sigma), m, or
    #: None: ranges taken as unbiased (a calibrated unit). Given, the offset is a nuisance
    #: parameter of `rays`: the board's known width and height against its angular extent
    #: hold the distance, the ranges the plane's orientation; it is estimated (shared by every
    #: fused scan) and reported (``diagnostics["range_offset_m"]``, ``..._std_m``). A unit's
    #: known offset: (its value, its standard error); a new unit: (0, the datasheet's spread);
    #: 1-sigma ``math.inf``: free.
    range_offset_prior: tuple[float, float] | None = None
    #: 1-sigma of per-laser range offsets left uncalibrated, m (0: none). Each laser's rings
    #: then share an unknown offset: a random effect in the plane's fit, whose tilt it would
    #: otherwise bias (about 0.35 deg for +-5 mm) with a sigma that does not cover it.
    laser_offset_sigma: float = 0.0
    #: Where the station's board is: its centre in the LiDAR's frame {L}, m, and the radius
    #: it may be off by, m; or None (anywhere). A candidate beyond the radius is never the
    #: board; within, the prior weighs it (`align.choice`).
    board_region: tuple[tuple[float, float, float], float] | None = None
    #: Seed for the randomised parts (RANSAC; the hit/miss posterior's fallbacks).
    seed: int = 0


@dataclass
class PoseEstimate:
    """The LiDAR's pose in the board frame {O}, with its uncertainty and diagnostics.

    ``covariance`` is 6 x 6 in the order x, y, z, roll, tilt, yaw (m, rad). ``used`` holds the
    indices of the firings the estimate used (``used["board"]``: the board's returns;
    ``used["features"]``: the feature firings, e.g. the paper's four corner points or the hit/miss
    firings bracketing an edge; ``used["candidates"]``: every board-like object weighed, and
    ``used["cluster"]``: for `BOARD_TOO_FAR`, the returns of the board-like cluster found too
    far); indices refer to the scan, or to the concatenation of the scans for a fused
    estimate. ``timings`` are wall-clock seconds per stage.
    """

    status: Status
    method: str
    pose: Pose | None = None
    covariance: np.ndarray | None = None
    diagnostics: dict = field(default_factory=dict)
    used: dict = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)

    @property
    def success(self) -> bool:
        return self.status == Status.OK and self.pose is not None

    @property
    def std(self) -> np.ndarray | None:
        """1-sigma of x, y, z, roll, tilt, yaw (m, rad), or None."""
        if self.covariance is None:
            return None
        return np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))

    def to_edge_dict(self) -> dict:
        """JSON-ready: status, method, pose in mm/deg, the same ``*_std`` and a few diagnostics."""
        out: dict = {"status": str(self.status), "method": self.method}
        names = POSE_FIELDS_EDGE
        if self.pose is not None:
            out.update({k: float(v) for k, v in self.pose.to_edge().items()})
            # the CLI's SI columns beside the edge units
            out.update({"x_m": self.pose.x, "y_m": self.pose.y, "z_m": self.pose.z})
        else:
            out.update(dict.fromkeys(names))
        std = self.std
        scale = np.array([1e3, 1e3, 1e3, *([np.rad2deg(1.0)] * 3)])
        for i, k in enumerate(names):
            out[f"{k}_std"] = None if std is None else float(std[i] * scale[i])
        if std is not None:
            out.update({f"{k}_m_std": float(std[i]) for i, k in enumerate("xyz")})
        for k, v in self.diagnostics.items():
            if isinstance(v, bool | int | float | str) or v is None:
                out[k] = v
        out["time_ms"] = 1e3 * float(self.timings.get("total", np.nan))
        return out

    @classmethod
    def failed(cls, status: Status, method: str, **diagnostics) -> PoseEstimate:
        return cls(status=status, method=method, diagnostics=diagnostics)
