"""One design point evaluated two ways: the Monte Carlo on the twin, and the precision bound.

`evaluate_task` is what an engine runs (on a local worker process or a Ray worker): a block of
the protocol's poses at one design point. Pose k of every design point is drawn from a generator
seeded by (study seed, k) alone (`random_pose`: the mount misalignment, the stage's x and yaw,
the twin's seed): every design point sees the same poses and the same noise draws (common random
numbers: a study's differences are the design's, not the draws'), and a block's result depends
on nothing but its point and its poses, whichever worker, engine or session computes it.

Per pose: the twin of the point's station (`Station.bench_params`, the mount misalignment added)
takes `protocol.scans` scans; every value of ``scans_fused`` is estimated on consecutive groups
of that many; each estimate's error against the twin's truth and its reported sigma are kept per
axis, in the station's frame (`Station.lidar_in_station`: the bench frame of docs/station.md,
so that a diamond's roll and height are those of a level board's). The bound (`align.design.bound`,
when this aimbench has it) is evaluated at the pose's truth for each ``scans_fused``.
"""

from __future__ import annotations

import math
import time
import warnings
from typing import Any

import numpy as np

from scenarios import station as stations
from scenarios.study import engines
from scenarios.study.protocol import pose_errors, random_pose, wrap
from scenarios.study.spec import StudySpec, apply
from twin.core import vlp16
from twin.core.pose import Pose

#: What a block returns when the caller stopped it (nothing of it is kept).
STOPPED = "stopped"
#: Finite-difference steps of the station-frame Jacobian: m for positions, rad for angles.
FD_STEP = 1e-6


def bound_available() -> bool:
    """Whether this aimbench has the precision bound (`align.design.bound`)."""
    try:
        import align.design.bound  # noqa: F401
    except ImportError:
        return False
    return True


#: Why a study has no bound, when it has none.
NO_BOUND = ("the precision bound (align.design.bound) is not in this aimbench yet: the study has "
            "the Monte Carlo only; the bound columns are empty")


def evaluate_task(spec_dict: dict, station_dict: dict, values: dict[str, Any], first_pose: int,
                  n_poses: int) -> dict[str, Any] | str:
    """Poses `first_pose` .. `first_pose` + `n_poses` - 1 of the design point `values` of the
    study; rows of estimates and of bounds (SI), or `STOPPED` if the caller stopped it."""
    warnings.simplefilter("ignore", RuntimeWarning)  # the twin's NaN masks
    spec = StudySpec.model_validate(spec_dict)
    base = stations.from_dict(station_dict, "the study's station")
    station, own = apply(base, spec, values)
    point = Point(spec, station, own)
    estimates: list[tuple] = []
    bounds: list[tuple] = []
    c0 = time.process_time()
    for pose in range(first_pose, first_pose + n_poses):
        if engines.stopping():
            return STOPPED
        e, b = point.pose(pose)
        estimates += e
        bounds += b
    return {"estimates": estimates, "bounds": bounds, "cpu_s": time.process_time() - c0}


class Point:
    """A design point ready to evaluate: its station, estimator, twin noise and bound inputs."""

    def __init__(self, spec: StudySpec, station: stations.Station, own: dict[str, Any]) -> None:
        import align
        from twin.sim.emulation import EmulationConfig

        self.spec, self.station = spec, station
        self.protocol = spec.protocol
        self.fused = spec.fused()
        self.method = own["method"]
        sigma = float(own["noise.range_sigma_mm"]) * 1e-3
        offset = float(own["noise.range_offset_mm"]) * 1e-3
        self.divergence = bool(own["noise.divergence"])
        noise = {"range_noise_sigma": sigma, "range_bias": offset, "laser_offset_sigma": 0.0,
                 "divergence": self.divergence}
        # A Velodyne model reaches the twin as EmulationConfig.model (twin.core.sensors); an
        # Ouster or a Hesai has a twin of its own (twin.sim.sensor_twins: Gaussian range noise
        # of the study's sigma, a sharp beam; no range offset or divergence to set there).
        from twin.sim.sensor_twins import is_own_twin

        self.own_twin = is_own_twin(station.sensor.model)
        if self.own_twin and (offset or self.divergence):
            raise ValueError(f"{station.sensor.model}'s twin has no range offset or beam "
                             "divergence to set: leave noise.range_offset_mm and "
                             "noise.divergence at their defaults for it")
        self.sigma = sigma
        if not self.own_twin:
            noise["model"] = station.sensor.model
        self.config = EmulationConfig(**noise)
        self.board = station.board_spec()
        # The estimator told the beam the twin has, as a user tells it the sensor's (the
        # protocol of benchmarks/bench_align.py).
        self.hints = align.Hints() if self.divergence else align.Hints(edge_tolerance=(0.0, 0.0))
        self.in_plane = math.radians(station.board.in_plane_deg)
        self.range_sigma = math.hypot(sigma, vlp16.DISTANCE_UNIT / math.sqrt(12))
        self.range_offset = abs(offset)
        self._identity = _is_translation(station)

    def pose(self, k: int) -> tuple[list[tuple], list[tuple]]:
        """Pose k: its estimates' rows (pose, fused, group, status, success, error[6],
        sigma[6], cpu s) and its bounds' rows (pose, fused, std[6], cpu s)."""
        import align
        from twin.sim.bench import BenchSim

        p = self.protocol
        rng = np.random.default_rng([self.spec.seed, k])
        params, x, yaw = random_pose(rng, p.angle_deg, p.x_mm, p.stage_yaw_deg,
                                     base=self.station.bench_params())
        seed = int(rng.integers(2**31))
        if self.own_twin:  # an Ouster's or a Hesai's twin, through its packets
            from twin.sim.sensor_twins import own_twin_scans

            scans, truth = own_twin_scans(params, self.station.sensor.model, x=x,
                                          yaw=math.radians(yaw), n=p.scans, seed=seed,
                                          range_sigma=self.sigma)
        else:
            sim = BenchSim(params, seed=seed, noise=self.config)
            sim.move_to(x_m=x, yaw_rad=math.radians(yaw))
            scans = [sim.scan() for _ in range(p.scans)]
            truth = scans[0].meta["truth_pose"]
        truth_s = self.station.lidar_in_station(truth)
        rows = []
        for n in self.fused:
            for g, i in enumerate(range(0, p.scans - n + 1, n)):
                c0 = time.process_time()
                est = align.estimate(scans[i:i + n] if n > 1 else scans[i], board=self.board,
                                     method=self.method, hints=self.hints)
                cpu = time.process_time() - c0
                status = str(est.status)
                if not est.success:
                    rows.append((k, n, g, status, False, [math.nan] * 6, [math.nan] * 6, cpu))
                    continue
                err, sig = self._in_station(est, truth, truth_s)
                rows.append((k, n, g, status, True, list(err), list(sig), cpu))
        return rows, self._bounds(k, truth, scans[0].lasers)

    def _in_station(self, est: Any, truth: Pose, truth_s: Pose
                    ) -> tuple[np.ndarray, np.ndarray]:
        """The estimate's error and sigma in the station frame."""
        if self._identity:
            return pose_errors(est, truth)
        e = self.station.lidar_in_station(est.pose).as_array() - truth_s.as_array()
        e[3:] = wrap(e[3:])
        if est.covariance is None:
            return e, np.full(6, np.nan)
        jac = self.jacobian(est.pose)
        cov = jac @ np.asarray(est.covariance, float) @ jac.T
        return e, np.sqrt(np.clip(np.diag(cov), 0.0, None))

    def jacobian(self, pose: Pose) -> np.ndarray:
        """d (pose in the station frame) / d (pose in the board's frame), by central
        differences (identity for a board square to the bench)."""
        if self._identity:
            return np.eye(6)
        theta = pose.as_array()
        cols = []
        for j in range(6):
            d = np.zeros(6)
            d[j] = FD_STEP
            a = self.station.lidar_in_station(Pose.from_array(theta + d)).as_array()
            b = self.station.lidar_in_station(Pose.from_array(theta - d)).as_array()
            diff = a - b
            diff[3:] = wrap(diff[3:])
            cols.append(diff / (2 * FD_STEP))
        return np.stack(cols, axis=1)

    def _bounds(self, k: int, truth: Pose, lasers: Any) -> list[tuple]:
        """The bound at the pose's truth, per scans fused, in the station frame (NaN rows when
        this aimbench has no bound)."""
        if not bound_available():
            return [(k, n, [math.nan] * 6, 0.0) for n in self.fused]
        from align.design.bound import Firing, RangeNoise, board_to_station, precision_bound
        from twin.sim.sensor_twins import firing_of

        level = board_to_station(truth, self.in_plane)
        own = firing_of(self.station.sensor.model)
        if own is not None:
            firing = Firing(rpm=own.rpm, period=own.period, laser_times=own.laser_times,
                            phase_locked=own.phase_locked)
        elif self.station.sensor.model == "VLP-16":
            firing = Firing(rpm=self.config.rpm, period=vlp16.SEQUENCE_PERIOD)
        else:  # another Velodyne: its own firing sequence (a VLP-32C's took the VLP-16's: no bound)
            from twin.core.sensors import model_named

            m = model_named(self.station.sensor.model)
            firing = Firing(rpm=self.config.rpm, period=m.sequence_period,
                            laser_times=tuple(float(v) for v in m.firing_offset))
        noise = RangeNoise(sigma=self.range_sigma, offset_sigma=self.range_offset)
        jac = self.jacobian(truth)
        rows = []
        for n in self.fused:
            c0 = time.process_time()
            try:
                b = precision_bound(level, lasers=lasers, board=self.board, firing=firing,
                                    noise=noise, n_scans=n, board_rotation=self.in_plane,
                                    seed=k)
                cov = jac @ np.asarray(b.covariance_board, float) @ jac.T
                std = list(np.sqrt(np.clip(np.diag(cov), 0.0, None)))
            except ValueError:  # a geometry the bound cannot take (the LiDAR behind the board)
                std = [math.nan] * 6
            rows.append((k, n, std, time.process_time() - c0))
        return rows


def _is_translation(station: stations.Station) -> bool:
    """Whether the station frame differs from the board's by a translation only."""
    m = np.linalg.solve(station.frame.pose.to_pose().matrix(), station.board_in_bench())
    return bool(np.allclose(m[:3, :3], np.eye(3), atol=1e-12))
