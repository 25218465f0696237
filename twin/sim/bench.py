"""`BenchSim`: the simulated bench. Bench parameters and a seed in; stage moves, scans with ground
truth, and the lidar's packets out (VLP-16 by default; Puck Hi-Res, VLP-32C, HDL-32E by
``EmulationConfig.model``).

Time: one simulation clock (s, MuJoCo's ``data.time``) drives the physics, the stage moves and
the sensor. The sensor fires on its fixed grid (`twin.core.sensors.SensorModel`: for a VLP-16 a
firing sequence every 55.296 us from t = 0, lasers 2.304 us apart; the VLP-32C's lasers in pairs,
the HDL-32E's 1.152 us apart in 46.08 us), spins at the configured rpm with a fresh
scan-to-scan wander each rotation, and reports its clock as seconds past the hour (``Scan.time``,
packet timestamps). A rotation runs
from one pass of the cut azimuth to the next (default pi, behind the sensor, like
`twin.lidar.scans.ScanAssembler`), so the twin's scans and the scans decoded from its packets
coincide.

Ground truth: every `Scan` carries ``meta["truth"]`` (the true LiDAR pose in the board frame at
the scan's first firing, edge units: mm and deg, `Pose.to_edge`), ``meta["truth_pose"]`` (the same
as a `twin.core.pose.Pose`) and ``meta["truth_end_pose"]`` (at the last firing: differs only when
the stages moved during the scan). Each firing is cast from the pose of its own instant.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from twin.core import vlp16
from twin.core.pose import Pose
from twin.core.scan import Scan, points_from_polar
from twin.core.sensors import VLP16, model_named
from twin.sim import raykernel
from twin.sim.emulation import EmulationConfig, LidarEmulator, RayCaster, Returns
from twin.sim.params import BenchParams
from twin.sim.physics import BenchPhysics
from twin.stage.motion import X_AXIS, YAW_AXIS, StageMove

TWO_PI = 2.0 * math.pi
SECONDS_PER_HOUR = 3600.0
#: A move is over when the servo error is below these (then the stepper's position is exact).
SETTLE_X = 1e-6  # m
SETTLE_YAW = 1e-6  # rad
SETTLE_TIMEOUT = 1.0  # s after the profile ends
#: Rotations emulated per window by `BenchSim.scans` (memory: about 30 MB per rotation).
ROTATIONS_PER_WINDOW = 4
#: Firing sequences per window of `BenchSim.packets` (about 4 rotations at 600 rpm).
CHUNK_SEQUENCES = 7200


def _past_the_hour(t: np.ndarray) -> np.ndarray:
    """Simulation time (s) as the sensor's clock: seconds past the hour."""
    if len(t) and t[0] >= 0.0 and t[-1] < SECONDS_PER_HOUR:
        # The times themselves (a view): a scan of a longer window copies its arrays anyway
        # (`BenchSim._to_scans`), and a scan of its own window is all that holds them.
        return t
    return np.mod(t, SECONDS_PER_HOUR)


@dataclass
class Firings:
    """Firings of a time window, in firing order (sequence-major, laser-minor)."""

    laser_id: np.ndarray  # (N,) uint8
    time: np.ndarray  # (N,) s, simulation clock
    azimuth: np.ndarray  # (N,) rad in [0, 2 pi)
    first_rotation: int  # the first rotation `rotation_start` holds
    #: (K,) int64: the index of rotation ``first_rotation + k``'s first firing in this window (0
    #: for one that began before it, N for one that begins after it); rotation j's firings
    #: are one slice (`of_rotation`)
    rotation_start: np.ndarray
    returns: Returns

    def of_rotation(self, j: int) -> slice:
        """Rotation ``j``'s firings (one slice: the firings are in time order)."""
        k = j - self.first_rotation
        return slice(int(self.rotation_start[k]), int(self.rotation_start[k + 1]))


class BenchSim:
    """The simulated bench (MuJoCo physics + VLP-16 emulation).

    ``params``: the physical bench (`BenchParams`, default the paper's). ``seed``: an int, a
    `numpy.random.Generator` or None; every random draw (noise, rpm wander, laser offsets,
    dropouts) comes from it. ``noise``: the `EmulationConfig` (default: every effect on).
    ``cut_azimuth``: where one rotation ends and the next begins, rad. ``model``: the sensor
    (a name of `twin.core.sensors.MODELS`) when ``noise`` is not given (else ``noise.model``).
    """

    def __init__(self, params: BenchParams | None = None,
                 seed: int | np.random.Generator | None = None,
                 noise: EmulationConfig | None = None, cut_azimuth: float = math.pi,
                 model: str | None = None) -> None:
        self.params = params or BenchParams()
        self.config = noise or EmulationConfig(model=model or VLP16.name)
        if model is not None and model_named(model).name != self.config.model:
            raise ValueError(f"model {model!r} differs from the emulation's {self.config.model!r}")
        self.sensor = self.config.sensor
        self.rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
        self.physics = BenchPhysics(self.params)
        self.caster = RayCaster(self.physics.model, self.physics.data,
                                self.physics.sensor_body_id, cutoff=self.config.range_max + 1.0)
        self.emulator = LidarEmulator(self.caster,
                                      self.params.geom_reflectivity(self.physics.model),
                                      self.config, self.rng)
        self.cut_azimuth = float(cut_azimuth) % TWO_PI
        self._move: StageMove | None = None
        self._move_t0 = 0.0
        # Spin schedule: rotation i passes the cut at _rot_start[i], spinning at _rot_omega[i].
        self._rot_start: list[float] = []
        self._rot_omega: list[float] = []
        self._next_rotation = 0  # the next rotation scan() returns
        # Sensor time when the last scan's window was emulated: if nothing has moved the clock
        # since, the next scan continues back to back, although the physics stepped a little
        # past the next rotation's start to finish the window.
        self._fired_until = -1.0
        self._packets_until = 0  # index of the first packet packets() has not emitted
        # Pose history of the current window (for firings slightly before "now").
        self._last_pose = self.physics.lidar_pose_world()
        self._window_record: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._pose_history: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._truth_cache: tuple[tuple, Pose] | None = None
        self._edge_cache: tuple[Pose, dict[str, float]] | None = None  # `_edge_of`
        self.scan_count = 0
        # When the spin schedule begins (the first cut pass lies within a rotation after it).
        self._spin_epoch = 0.0

    # ---------------------------------------------------------------------------------------
    # Stages
    # ---------------------------------------------------------------------------------------
    def stage_x(self) -> float:
        """Linear stage position relative to the reference, m."""
        return self.physics.carriage_x()

    def stage_yaw(self) -> float:
        """Rotation stage angle relative to the reference, rad."""
        return self.physics.stage_yaw()

    def lidar_pose_in_board(self) -> Pose:
        """The true LiDAR pose in the board frame now."""
        return self.physics.lidar_pose_in_board()

    @property
    def time(self) -> float:
        """Simulation time, s."""
        return self.physics.time

    @property
    def moving(self) -> bool:
        """True while a commanded move has not settled."""
        return self._move is not None

    def start_move(self, *, x_m: float, yaw_rad: float) -> StageMove:
        """Begin a coordinated trapezoidal move to (x, yaw); scans taken meanwhile see it."""
        self._finish_if_settled()
        start = (self.stage_x(), self.stage_yaw())
        move = StageMove.plan(start, (float(x_m), float(yaw_rad)), (X_AXIS, YAW_AXIS))
        self._move = move
        self._move_t0 = self.time
        return move

    def move_to(self, *, x_m: float, yaw_rad: float) -> float:
        """Drive both stages to (x m, yaw rad) and return once they have arrived (both arrive
        together, as the firmware's coordinated move does); returns the move's duration, s."""
        self.start_move(x_m=x_m, yaw_rad=yaw_rad)
        t0 = self._move_t0
        while self._move is not None:
            self._advance(self.time + 0.05)
        return self.time - t0

    def set_stage_positions(self, *, x_m: float, yaw_rad: float) -> None:
        """Put the stages at (x, yaw) now, at rest: for an external step source (the firmware's
        step counts in the simavr harness) that drives the joints itself."""
        self._move = None
        self.physics.set_stage_positions(x_m=float(x_m), yaw_rad=float(yaw_rad))
        self._last_pose = self.physics.lidar_pose_world()

    def restart_sensor(self, rng: np.random.Generator, at: float) -> None:
        """Start the sensor afresh at time ``at`` (s) with generator ``rng``: a new spin
        schedule (its phase and rpm drawn from ``rng``), no window history, the clock set to
        ``at``. With the stages at rest the next scan then depends on nothing but ``rng``,
        ``at`` and the stage pose, whatever was scanned or moved before: what makes a scan
        reproducible by itself (`scenarios.bench.SimBench` seeds every scan this way). The
        stages must be at rest (nothing in the scene moves, so the clock may be set)."""
        if self._move is not None:
            raise RuntimeError("restart_sensor while the stages move")
        self.rng = rng
        self.emulator.rng = rng
        self.physics.data.time = float(at)
        self._spin_epoch = float(at)
        self._rot_start, self._rot_omega = [], []
        self._next_rotation = 0
        self._fired_until = -1.0
        self._packets_until = 0
        self._window_record = None
        self._pose_history = None

    def wait(self, seconds: float) -> None:
        """Let simulated time pass (stages keep moving if a move is under way)."""
        self._advance(self.time + seconds)

    def _static(self) -> bool:
        return self._move is None

    def _setpoint(self, t: float) -> np.ndarray:
        assert self._move is not None
        return self._move.at(t - self._move_t0)

    def _finish_if_settled(self) -> None:
        """End the move once the profile is done and the servo error is below the settle
        tolerance; the stepper then sits exactly on its commanded position."""
        if self._move is None:
            return
        if self.time - self._move_t0 < self._move.duration:
            return
        x_t, yaw_t = self._move.end
        err_x = abs(self.stage_x() - x_t)
        err_yaw = abs(self.stage_yaw() - yaw_t)
        overdue = self.time - self._move_t0 > self._move.duration + SETTLE_TIMEOUT
        if (err_x < SETTLE_X and err_yaw < SETTLE_YAW) or overdue:
            self._move = None
            self.physics.set_stage_positions(x_m=x_t, yaw_rad=yaw_t)
            self._last_pose = self.physics.lidar_pose_world()

    def _advance(self, t_end: float, record: bool = False
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """Step the physics to ``t_end`` (s), following the move's setpoints.

        With ``record``, returns the LiDAR pose in the world at every step (times (K,),
        positions (K, 3), rotations (K, 3, 3)), or None when the stages were at rest throughout
        (the pose is then `_last_pose`)."""
        ph = self.physics
        dt = ph.timestep
        times, pos, rot = [], [], []
        moved = False
        while self.time < t_end - 1e-12:
            if self._move is None:
                # Stages at rest: nothing in the scene moves, so time just passes.
                n = max(1, math.ceil((t_end - self.time) / dt - 1e-9))
                ph.data.time += n * dt
                break
            moved = True
            if record and not times:
                p, r = ph.lidar_pose_world()
                times.append(self.time)
                pos.append(p)
                rot.append(r)
            x_t, yaw_t = self._setpoint(self.time + dt)
            ph.set_stage_targets(x_m=x_t, yaw_rad=yaw_t)
            ph.step()
            if record:
                p, r = ph.lidar_pose_world()
                times.append(self.time)
                pos.append(p)
                rot.append(r)
            self._finish_if_settled()
        self._last_pose = ph.lidar_pose_world()
        if not record or not moved:
            return None
        return np.array(times), np.array(pos), np.array(rot)

    # ---------------------------------------------------------------------------------------
    # Spin schedule
    # ---------------------------------------------------------------------------------------
    def _draw_omega(self) -> float:
        rpm = self.config.rpm
        if self.config.rpm_wander_sigma > 0:
            rpm = rpm + self.rng.normal(0.0, self.config.rpm_wander_sigma)
        # (min/max, not np.clip: the same value without numpy's scalar overhead, per rotation)
        rpm = min(max(float(rpm), self.sensor.rpm_min), self.sensor.rpm_max)
        return rpm * TWO_PI / 60.0

    def _ensure_rotations(self, upto: int) -> None:
        """Extend the spin schedule to rotation index ``upto`` (inclusive)."""
        if not self._rot_start:
            omega = self._draw_omega()
            # The sensor was already spinning: the first cut pass lies within one rotation.
            self._rot_start.append(self._spin_epoch
                                   + float(self.rng.uniform(0.0, TWO_PI / omega)))
            self._rot_omega.append(omega)
        while len(self._rot_start) <= upto + 1:
            i = len(self._rot_start) - 1
            self._rot_start.append(self._rot_start[i] + TWO_PI / self._rot_omega[i])
            self._rot_omega.append(self._draw_omega())

    # ---------------------------------------------------------------------------------------
    # Firings
    # ---------------------------------------------------------------------------------------
    def _sequences_of_rotation(self, i: int) -> tuple[int, int]:
        """Sequence index range [lo, hi) covering rotation i's firings."""
        self._ensure_rotations(i + 1)
        t0, t1 = self._rot_start[i], self._rot_start[i + 1]
        period = self.sensor.sequence_period
        lo = max(0, math.floor(t0 / period) - 1)
        hi = math.ceil(t1 / period) + 1
        return lo, hi

    def _to_scans(self, f: Firings, rotations: list[int]) -> list[Scan]:
        """Cut firings into the given rotations' scans (firing-level cut at `cut_azimuth`)."""
        cfg = self.config
        scans = []
        for i in rotations:
            m = f.of_rotation(i)
            lo, hi = m.start, m.stop
            # Truth from the world poses at the first and last firing of the rotation.
            t_first = float(f.time[lo]) if hi > lo else self._rot_start[i]
            t_last = float(f.time[hi - 1]) if hi > lo else self._rot_start[i]
            truth = self._truth_at(t_first)
            # At rest (no pose record) the truth is one pose: computed and converted once.
            at_rest = self._window_record is None
            truth_end = truth if at_rest else self._truth_at(t_last)
            edge = self._edge_of(truth)
            edge_end = dict(edge) if at_rest else truth_end.to_edge()
            parts = []
            beam_az = self._beam_azimuth(f.azimuth[m], f.laser_id[m])
            for s in range(cfg.n_returns):
                d = f.returns.distance[s, m]
                if f.returns.x is not None:  # the emulator's own (as `points_from_polar`)
                    x, y, z = f.returns.x[s, m], f.returns.y[s, m], f.returns.z[s, m]
                else:  # trigonometry for the returns only
                    x, y, z = (np.zeros(len(d)) for _ in range(3))
                    v = np.flatnonzero(d > 0)
                    x[v], y[v], z[v] = points_from_polar(d[v], beam_az[v], f.laser_id[m][v],
                                                         cfg.vertical_offsets, self.sensor.lasers)
                parts.append(dict(distance=d, azimuth=beam_az, laser_id=f.laser_id[m],
                                  intensity=f.returns.intensity[s, m],
                                  time=_past_the_hour(f.time[m]),
                                  return_type=f.returns.return_type[s, m], x=x, y=y, z=z))
            if cfg.n_returns == 1:
                arrays = parts[0]
                if len(rotations) > 1:  # a slice of a longer window: do not keep it alive
                    arrays = {k: np.array(v) for k, v in arrays.items()}
            else:
                # Dual: the two returns of each firing side by side (last, then the other).
                arrays = {k: np.column_stack([p[k] for p in parts]).reshape(-1)
                          for k in parts[0]}
            rpm = self._rot_omega[i] * 60.0 / TWO_PI
            scans.append(Scan(
                **arrays, index=self.scan_count, complete=True, packets=0, missing_packets=0,
                return_mode=cfg.return_mode_byte, product_id=self.sensor.product_id,
                vertical_offsets_applied=cfg.vertical_offsets, lasers=self.sensor.lasers,
                meta={"truth": edge, "truth_pose": truth,
                      "truth_end": edge_end, "truth_end_pose": truth_end,
                      "source": "twin", "rpm": rpm, "rotation": i, "model": self.sensor.name,
                      "stage_x_m": self.stage_x(), "stage_yaw_rad": self.stage_yaw()}))
            self.scan_count += 1
        return scans

    def _beam_azimuth(self, azimuth: np.ndarray, laser_id: np.ndarray) -> np.ndarray:
        """The beams' azimuths of firings at encoder azimuths ``azimuth``: plus each laser's
        azimuth offset (VLP-32C manual 9.5), in [0, 2 pi). The VLP-16's offsets are 0."""
        offset = self.sensor.lasers.azimuth_offset
        if not offset.any():
            return azimuth
        a = azimuth + offset[laser_id]
        return np.where(a >= TWO_PI, a - TWO_PI, np.where(a < 0.0, a + TWO_PI, a))

    def _edge_of(self, pose: Pose) -> dict[str, float]:
        """``pose.to_edge()``, a new dict each call; the conversion is kept for the last pose
        (at rest every scan's truth is the same `Pose` object, `_truth_at`'s cache)."""
        if self._edge_cache is None or self._edge_cache[0] is not pose:
            self._edge_cache = (pose, pose.to_edge())
        return dict(self._edge_cache[1])

    def _truth_at(self, t: float) -> Pose:
        """True pose of {L} in {O} at time t within the last window (interpolated)."""
        rec = self._window_record
        p_o, r_o = self.physics.board_pose_world()
        if rec is None:
            p, r = self._last_pose
            key = (p.tobytes(), r.tobytes(), p_o.tobytes(), r_o.tobytes())
            if self._truth_cache is None or self._truth_cache[0] != key:
                self._truth_cache = (key, Pose.from_matrix(r_o.T @ r, r_o.T @ (p - p_o)))
            return self._truth_cache[1]
        else:
            times, ps, rs = rec
            tc = float(np.clip(t, times[0], times[-1]))
            p = np.array([np.interp(tc, times, ps[:, j]) for j in range(3)])
            r = Slerp(times, Rotation.from_matrix(rs))([tc]).as_matrix()[0]
        return Pose.from_matrix(r_o.T @ r, r_o.T @ (p - p_o))

    # ---------------------------------------------------------------------------------------
    # Scans
    # ---------------------------------------------------------------------------------------
    def _next_rotation_index(self) -> int:
        """The first rotation after the last one returned that has not begun before now (a
        scan is whole: it starts at a pass of the cut azimuth)."""
        i = self._next_rotation
        self._ensure_rotations(i + 1)
        if self.time == self._fired_until:
            return i
        while self._rot_start[i] < self.time - 2 * self.sensor.sequence_period:
            i += 1
            self._ensure_rotations(i + 1)
        return i

    def scans(self, n: int) -> list[Scan]:
        """The next ``n`` whole rotations, back to back."""
        out: list[Scan] = []
        while len(out) < n:
            first = self._next_rotation_index()
            block = list(range(first, first + min(ROTATIONS_PER_WINDOW, n - len(out))))
            lo, _ = self._sequences_of_rotation(block[0])
            _, hi = self._sequences_of_rotation(block[-1])
            f = self._fire_window(lo, hi)
            self._next_rotation = block[-1] + 1
            self._fired_until = self.time
            out += self._to_scans(f, block)
        return out

    def scan(self) -> Scan:
        """One rotation (the next whole one from now)."""
        return self.scans(1)[0]

    def _fire_window(self, lo: int, hi: int) -> Firings:
        """Emulate every firing of sequences [lo, hi) on the sensor's grid. The physics first
        advances to the window's end, recording the pose at every step if the stages move; each
        firing gets its own instant's pose. Firings a little before "now" (windows overlap by a
        sequence or two at rotation boundaries) take theirs from the previous window's record.
        The record is kept in `_window_record` for the scans' truth."""
        sensor = self.sensor
        t_end = (hi - 1) * sensor.sequence_period + float(sensor.firing_offset[-1])
        i = len(self._rot_start) - 1
        while self._rot_start[-1] <= t_end:
            i += 1
            self._ensure_rotations(i)
        # The rotations this window touches: from the last to begin by its first firing to the
        # first to begin after its end (the schedule grows by one every rotation; passing it
        # whole made each scan cost more than the one before)
        j0 = max(0, bisect.bisect_right(self._rot_start, lo * sensor.sequence_period) - 1)
        j1 = bisect.bisect_right(self._rot_start, t_end) + 1
        laser, t, azimuth, rotation_start = raykernel.firing_schedule(
            lo, hi, sensor.sequence_period, sensor.firing_offset,
            np.array(self._rot_start[j0:j1]), np.array(self._rot_omega[j0:j1]),
            self.cut_azimuth)
        t_end = float(t[-1])
        record = self._advance(t_end, record=True) if t_end > self.time else None
        if record is None:
            # Stages at rest throughout: one pose, the emulator's grid fast path.
            self._window_record = None
            self._pose_history = None
            pos, rot = self._last_pose
            returns = self.emulator.fire_grid(
                self._beam_azimuth(self._cast_azimuth(azimuth), laser).reshape(
                    -1, sensor.n_lasers), pos, rot)
            return Firings(laser, t, azimuth, j0, rotation_start, self._decoded(returns))
        times, ps, rs = record
        hist = self._pose_history
        if hist is not None:
            # The new record may start at the very instant the history ends: keep each once.
            before = hist[0] < times[0]
            times = np.concatenate((hist[0][before], times))
            ps = np.concatenate((hist[1][before], ps))
            rs = np.concatenate((hist[2][before], rs))
        record = (times, ps, rs)
        self._window_record = record
        self._pose_history = (times[-20:], ps[-20:], rs[-20:])  # the last 20 ms
        tc = np.clip(t, times[0], times[-1])
        pos = np.column_stack([np.interp(tc, times, ps[:, j]) for j in range(3)])
        rot = Slerp(times, Rotation.from_matrix(rs))(tc).as_matrix()
        returns = self.emulator.fire(self._beam_azimuth(self._cast_azimuth(azimuth), laser),
                                     laser, pos, rot)
        return Firings(laser, t, azimuth, j0, rotation_start, self._decoded(returns))

    def _cast_azimuth(self, azimuth: np.ndarray) -> np.ndarray:
        """The encoder azimuths the firings are cast at: their own, or without the firing
        delays (`EmulationConfig.firing_delays` False) each sequence's first firing's for every
        laser of it (firings in whole sequences, lasers in order)."""
        if self.config.firing_delays:
            return azimuth
        n_l = self.sensor.n_lasers
        a = azimuth.reshape(-1, n_l)
        return np.ascontiguousarray(np.broadcast_to(a[:, :1], a.shape)).reshape(-1)

    def _decoded(self, returns):
        """Without the firing delays the emulator's points are at the cast azimuths: dropped,
        so that the scans' points come from the azimuths a decoder reports."""
        if not self.config.firing_delays:
            returns.x = returns.y = returns.z = None
        return returns

    def _fire_range(self, lo: int, hi: int) -> Firings:
        """`_fire_window` over [lo, hi) in contiguous chunks of about `CHUNK_SEQUENCES` (memory
        stays bounded for long captures), joined; the pose records are joined too."""
        parts: list[Firings] = []
        records: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        for a in range(lo, hi, CHUNK_SEQUENCES):
            parts.append(self._fire_window(a, min(a + CHUNK_SEQUENCES, hi)))
            if self._window_record is not None:
                records.append(self._window_record)
        if len(parts) == 1:
            return parts[0]
        if records:
            times = np.concatenate([r[0] for r in records])
            # Each chunk's record starts with the previous one's history: keep every instant once.
            keep = np.concatenate(([True], times[1:] > np.maximum.accumulate(times)[:-1]))
            self._window_record = tuple(np.concatenate([r[j] for r in records])[keep]
                                        for j in range(3))
        ret = Returns(*(np.concatenate([getattr(p.returns, k) for p in parts], axis=1)
                        for k in ("distance", "intensity", "return_type")))
        if all(p.returns.x is not None for p in parts):
            ret.x, ret.y, ret.z = (np.concatenate([getattr(p.returns, k) for p in parts], axis=1)
                                   for k in "xyz")
        # A rotation's first firing in the whole range: the firings before it in every part
        # (none of a part that it began before; all of a part that ends before it begins).
        first = min(p.first_rotation for p in parts)
        end = max(p.first_rotation + len(p.rotation_start) for p in parts)
        rotation_start = sum(np.pad(p.rotation_start, (p.first_rotation - first,
                                                       end - p.first_rotation
                                                       - len(p.rotation_start)),
                                    constant_values=(0, len(p.time))) for p in parts)
        return Firings(*(np.concatenate([getattr(p, k) for p in parts])
                         for k in ("laser_id", "time", "azimuth")), first_rotation=first,
                       rotation_start=rotation_start, returns=ret)

    # ---------------------------------------------------------------------------------------
    # Packets
    # ---------------------------------------------------------------------------------------
    def packets(self, n_scans: int) -> tuple[np.ndarray, np.ndarray, list[Scan]]:
        """Byte-exact data packets of the sensor covering the next ``n_scans`` rotations.

        Returns (payloads (n_packets, 1206) uint8, arrival times (n_packets,) s on the
        simulation clock, the scans). Packets sit on the sensor's own grid (12 blocks of 32
        channels: 24 firing sequences of a 16-laser model, 12 of a 32-laser one; half in dual
        mode), so the first and the last packet also carry firings of the
        neighbouring rotations, emulated like the rest.
        """
        from twin.lidar.packets import encode_data_packets  # the data-path encoder

        cfg = self.config
        first = self._next_rotation_index()
        rotations = list(range(first, first + n_scans))
        lo, _ = self._sequences_of_rotation(rotations[0])
        _, hi = self._sequences_of_rotation(rotations[-1])
        sensor = self.sensor
        n_l = sensor.n_lasers
        seq_per_packet = sensor.sequences_per_packet // cfg.n_returns
        # Whole packets: sequences [p_lo * spp, p_hi * spp).
        p_lo = max(0, lo // seq_per_packet)
        if self.time == self._fired_until:  # continuing: never emit a packet twice
            p_lo = max(p_lo, self._packets_until)
        p_hi = -(-hi // seq_per_packet)
        self._packets_until = p_hi
        f = self._fire_range(p_lo * seq_per_packet, p_hi * seq_per_packet)
        self._next_rotation = rotations[-1] + 1
        self._fired_until = self.time
        scans = self._to_scans(f, rotations)
        n_pk = p_hi - p_lo
        n_seq = n_pk * seq_per_packet
        ch = 32  # channels per block (every model's packet)
        raw = np.rint(f.returns.distance / sensor.distance_unit).astype(np.uint16)
        raw = raw.reshape(cfg.n_returns, n_seq * n_l // ch, ch)
        refl = f.returns.intensity.reshape(cfg.n_returns, n_seq * n_l // ch, ch)
        # Block azimuth = encoder azimuth of the block's first firing, 0.01 deg counts.
        az_first = f.azimuth[::ch]
        az_cdeg = (np.rint(np.rad2deg(az_first) / vlp16.AZIMUTH_UNIT_DEG).astype(np.int64)
                   % 36000).astype(np.uint16)
        if cfg.n_returns == 1:
            block_raw, block_refl, block_az = raw[0], refl[0], az_cdeg
        else:
            # Dual: block pairs (last return, then strongest / second strongest), same azimuth.
            block_raw = np.stack((raw[0], raw[1]), axis=1).reshape(-1, ch)
            block_refl = np.stack((refl[0], refl[1]), axis=1).reshape(-1, ch)
            block_az = np.repeat(az_cdeg, 2)
        t_packet = f.time[::seq_per_packet * n_l]
        ts_us = (np.rint(np.mod(t_packet, SECONDS_PER_HOUR) * 1e6).astype(np.int64)
                 % int(SECONDS_PER_HOUR * 1e6)).astype(np.uint32)
        payloads = encode_data_packets(block_az, block_raw, block_refl, ts_us,
                                       return_mode=cfg.return_mode_byte,
                                       product_id=sensor.product_id)
        # A packet leaves the sensor once its last firing is done.
        arrival = t_packet + seq_per_packet * sensor.sequence_period
        return payloads, arrival, scans

    def write_pcap(self, path: str | Path, n_scans: int) -> list[Scan]:
        """Write ``n_scans`` rotations as a pcap capture any Velodyne tool reads; returns the scans
        (each with its ground truth)."""
        from twin.lidar.pcap import PcapWriter

        payloads, arrival, scans = self.packets(n_scans)
        with PcapWriter(path) as w:
            for payload, ts in zip(payloads, arrival, strict=True):
                w.write_udp(bytes(payload), float(ts), dst_port=vlp16.DATA_PORT)
        return scans

    def send_udp(self, n_scans: int, host: str = "127.0.0.1", port: int = vlp16.DATA_PORT,
                 realtime: bool = True) -> list[Scan]:
        """Send ``n_scans`` rotations as UDP datagrams to (host, port) at the sensor's real
        packet rate (about 754 packets/s, twice that in dual mode; ``realtime=False``: as fast
        as possible), through `twin.lidar.udp.send_packets`. Returns the scans (with truth)."""
        from twin.lidar.udp import send_packets

        payloads, _, scans = self.packets(n_scans)
        rate = self.sensor.packet_rate(self.config.return_mode_byte) if realtime else None
        send_packets(payloads, dst=(host, port), rate_hz=rate)
        return scans
