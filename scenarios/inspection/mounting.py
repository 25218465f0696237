"""The mounting error: where the LiDAR sits in the station frame, relative to its nominal pose.

The estimator gives the LiDAR's pose in the board frame {O} with a 6 x 6 covariance. The station
file says where the board stands in the bench frame and how the station (vehicle) frame {S}
relates to it (`scenarios.station.Station.lidar_in_station`), and where the LiDAR should be in
{S} (``mount.nominal``). The mounting error of a pose P_S = (R, p) against the nominal N = (R_N,
p_N) is

    position: p - p_N, along the station's axes (m)
    angles:   roll, tilt, yaw of R_N^T R, the rotation from the nominal LiDAR frame to the
              actual one, in the project's convention R = Rz(yaw) Rx(tilt) Ry(roll) (rad)

so a twin unit mounted with a misalignment (roll, tilt, yaw) on a square turntable has exactly
that error. Its covariance is J C J^T with J the derivative of the error with respect to the
board-frame pose (central differences: the map is smooth and cheap).

Without ``mount.nominal`` the nominal is where the station's bench puts a perfectly mounted
LiDAR with the stages at home, as the twin models the bench (the paper's: x 700, y -2500,
z 500 mm, angles 0).
"""

from __future__ import annotations

import functools

import numpy as np

from scenarios.station import Station
from twin.core.pose import Pose

#: Central-difference steps per pose parameter (m, m, m, rad, rad, rad): far below the
#: estimator's precision, far above rounding.
_STEPS = np.array([1e-6, 1e-6, 1e-6, 1e-7, 1e-7, 1e-7])


def nominal_pose(station: Station) -> tuple[Pose, str]:
    """The LiDAR's nominal pose in the station frame, and where it came from (``station`` or
    ``twin``: the bench's perfectly mounted LiDAR at stage home, module docstring)."""
    if station.mount.nominal is not None:
        return station.mount.nominal.to_pose(), "station"
    return _twin_nominal(station.model_dump_json()), "twin"


@functools.cache
def _twin_nominal(station_json: str) -> Pose:
    from scenarios.station import Station as _Station
    from twin.sim.bench import BenchSim

    station = _Station.model_validate_json(station_json)
    sim = BenchSim(station.bench_params(), seed=0)
    return station.lidar_in_station(sim.lidar_pose_in_board())


def error_of(pose_in_station: Pose, nominal: Pose) -> np.ndarray:
    """The mounting error (x, y, z, roll, tilt, yaw), m and rad (module docstring)."""
    r_rel = nominal.rotation().T @ pose_in_station.rotation()
    rel = Pose.from_matrix(r_rel, pose_in_station.translation - nominal.translation)
    return rel.as_array()


def mounting_error(pose_in_board: Pose, covariance: np.ndarray | None, station: Station,
                   nominal: Pose) -> tuple[np.ndarray, np.ndarray | None, Pose]:
    """(error (6,), its covariance (6, 6) or None, the pose in the station frame)."""
    in_station = station.lidar_in_station(pose_in_board)
    err = error_of(in_station, nominal)
    if covariance is None:
        return err, None, in_station
    base = pose_in_board.as_array()
    jac = np.empty((6, 6))
    for j, h in enumerate(_STEPS):
        d = np.zeros(6)
        d[j] = h
        hi = error_of(station.lidar_in_station(Pose.from_array(base + d)), nominal)
        lo = error_of(station.lidar_in_station(Pose.from_array(base - d)), nominal)
        jac[:, j] = (hi - lo) / (2 * h)
    cov = jac @ np.asarray(covariance, float) @ jac.T
    return err, 0.5 * (cov + cov.T), in_station


def true_error(scan_meta: dict, station: Station, nominal: Pose) -> np.ndarray | None:
    """The twin's true mounting error of a scan (from its ``truth_pose``), or None."""
    truth = scan_meta.get("truth_pose")
    if truth is None:
        return None
    return error_of(station.lidar_in_station(truth), nominal)
