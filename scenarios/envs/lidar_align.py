"""`LidarAlignEnv`: active alignment of the LiDAR on the bench, as a Gymnasium environment.

Importing this module registers ``aimbench/LidarAlign-v0`` (actions in SI units) and
``aimbench/LidarAlignNormalized-v0`` (the same task with the float32 [-1, 1] actions RL libraries
expect), both with a `TimeLimit` of `MAX_EPISODE_STEPS` steps. Gymnasium 1.x has no plugin
entry points any more, so either import it first or let `gymnasium.make` import it::

    import gymnasium as gym
    env = gym.make("scenarios.envs.lidar_align:aimbench/LidarAlign-v0")  # imports the module
    env = gym.make("aimbench/LidarAlign-v0", bench="hw",  # after `import aimbench`
                   bench_kwargs={"port": "/dev/ttyACM0", "lidar": "udp://0.0.0.0:2368"})

The environment runs over any `scenarios.bench.Bench`: the MuJoCo twin (`SimBench`, default), the
real bench (`HardwareBench`), or whatever `scenarios.bench.open_bench` opens by name. Each step
commands the two stages, takes a few scans where they stopped, and runs the estimator (`align`)
on them; the agent sees only what a real alignment station sees, the estimate and its
uncertainty. See `LidarAlignEnv` for the task, the spaces and the reward. SI units throughout
(m, rad, s); degrees and millimetres only in the ``*_deg`` / ``*_mm`` names of `info`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

import align
from scenarios.bench import Bench, SimBench, open_bench
from scenarios.config import RunConfig
from scenarios.envs.view import BenchView, Frame, check_display
from scenarios.plans import MOUNT_KEYS, PAPER_MC_ANGLE_DEG, PAPER_MC_X_MM
from scenarios.truth import scan_truth
from twin.core.pose import Pose
from twin.core.scan import Scan
from twin.stage.motion import X_AXIS, YAW_AXIS, StageMove

#: The registered ids (SI actions; normalised actions), and the `TimeLimit` they carry (steps).
ENV_ID = "aimbench/LidarAlign-v0"
ENV_ID_NORMALIZED = "aimbench/LidarAlignNormalized-v0"
MAX_EPISODE_STEPS = 20

#: "Aligned": the LiDAR's true yaw and x in the board frame within these of the target.
DEFAULT_YAW_TOLERANCE_RAD = math.radians(0.2)
DEFAULT_X_TOLERANCE_M = 0.004
#: The paper's bench when a bench cannot tell its nominal pose: the LiDAR 0.7 m to the board's
#: side (DESIGN.md), square to it.
PAPER_NOMINAL_X_M = 0.7
#: VLP-16 at the default 600 rpm: one scan per 0.1 s (the time a real scan costs).
SCAN_PERIOD_S = 0.1
#: Scans fused per estimate. One scan's estimate scatters by about 5 mm / 0.12 deg (1-sigma),
#: as wide as the tolerance, so a controller acting on it chases noise (seeded episodes of
#: `scripted_policy`: 2.4 steps on average, up to 8); two scans bring that to 1.2, at most 3.
DEFAULT_SCANS_PER_STEP = 2

#: Observation bounds. The estimator works up to 6 m (align.Hints.max_distance); anything it
#: reports beyond these is clipped (and would be a failed estimate anyway).
POSITION_LIMIT_M = 10.0
STD_LIMIT = 10.0  # m or rad: also the "unknown" value of a failed estimate's std


@dataclass(frozen=True)
class MountRange:
    """Half-widths of the uniform mount misalignment drawn at every reset (edge units, like
    `scenarios.plans.MOUNT_KEYS`). Default: the paper's Monte Carlo protocol (+-3 deg, +-30 mm).

    ``x_mm`` shifts the optical centre sideways on the turntable (the lever arm's x).
    """

    roll_deg: float = PAPER_MC_ANGLE_DEG
    tilt_deg: float = PAPER_MC_ANGLE_DEG
    yaw_deg: float = PAPER_MC_ANGLE_DEG
    x_mm: float = PAPER_MC_X_MM

    def draw(self, rng: np.random.Generator) -> dict[str, float]:
        """One misalignment, uniform within +- each half-width (keys: `MOUNT_KEYS`)."""
        half = np.array([getattr(self, k) for k in MOUNT_KEYS], dtype=float)
        return {k: float(v) for k, v in zip(MOUNT_KEYS, rng.uniform(-half, half), strict=True)}


@dataclass(frozen=True)
class RewardWeights:
    """Weights of the reward terms (see `LidarAlignEnv`)."""

    #: per unit of (|yaw error| / yaw tolerance + |x error| / x tolerance)
    align: float = 0.1
    #: per second of bench time (stage move + scans)
    time: float = 1.0
    #: per full travel span moved (|d yaw| / yaw span + |d x| / x span)
    travel: float = 1.0
    #: when the estimator could not produce a pose (the board left the view)
    no_estimate: float = 1.0
    #: once, on the step that ends aligned
    success: float = 10.0


BenchSpec = str | Bench | Callable[[], Bench]


def _usable(est: align.PoseEstimate) -> bool:
    """A successful estimate with a finite pose (the only kind the env reports)."""
    return est.success and bool(np.all(np.isfinite(est.pose.as_array())))


def _wrap(angle: float) -> float:
    """Angle wrapped to [-pi, pi), rad."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


class LidarAlignEnv(gym.Env[dict[str, np.ndarray], np.ndarray]):
    """Bring a misaligned LiDAR square to the board with the bench's two stages.

    **Task.** The VLP-16 sits on the rotation stage (yaw) on the linear stage (x) with a mounting
    misalignment (drawn at every reset on the twin: roll, tilt, yaw and a sideways offset, see
    `MountRange`). The agent moves the stages until the LiDAR's *true* yaw and x in the board
    frame {O} are at the target: yaw = ``target_yaw_rad`` (default 0: Y_L points straight at the
    board) and x = ``target_x_m`` (default: where a perfectly mounted LiDAR sits with the stages
    at home; 0.7 m on the paper's bench). The stages must thus cancel the mount's yaw and
    sideways offset; roll and tilt are observed but no stage can correct them. On a bench
    without ground truth (hardware) "true" falls back to the estimate.

    **Action** ``Box(2,)`` float64, absolute stage targets (not increments), SI units; actions
    beyond the travel are clipped to it:

    ===  ===========  ====  ==========================================================
    idx  name         unit  range
    ===  ===========  ====  ==========================================================
    0    stage yaw    rad   the rotation stage's travel (twin: +-0.5236, i.e. +-30 deg)
    1    stage x      m     the linear stage's travel (twin: +-0.050)
    ===  ===========  ====  ==========================================================

    With ``normalized_actions=True`` (registered as ``aimbench/LidarAlignNormalized-v0``) the
    action is ``Box(-1, 1, (2,))`` float32, the same two targets scaled linearly over the travel
    (-1: one end, 0: mid-travel, +1: the other end), as PPO, SAC and friends expect; values
    beyond +-1 are clipped. ``info["stage_command"]`` is always in SI units, and
    `LidarAlignEnv.action_for` turns SI targets into this env's actions.

    **Observation** ``Dict``; the estimator's result from the scans taken after the move:

    ======================  ===============  =====================================================
    key                     space            meaning
    ======================  ===============  =====================================================
    ``pose``                Box(6,) float64  estimated x, y, z (m), roll, tilt, yaw (rad) of the
                                             LiDAR in {O} (`twin.core.pose.POSE_FIELDS` order);
                                             zeros when ``estimate_ok`` is 0
    ``pose_std``            Box(6,) float64  its 1-sigma, same order and units; `STD_LIMIT`
                                             (10) when ``estimate_ok`` is 0
    ``estimate_ok``         Discrete(2)      1 if the estimator found the board and solved
    ``stage``               Box(2,) float64  stage yaw (rad) and x (m) as the bench reports them
    ``board_points``        Box(N, 3)        only with ``n_board_points=N > 0``: up to N of the
                                             board returns the estimate used, in {L} (m), evenly
                                             subsampled, zero-padded
    ``board_points_count``  Discrete(N + 1)  only with ``n_board_points``: how many are real
    ======================  ===============  =====================================================

    **Reward** per step, the sum of these terms (weights: `RewardWeights`; values:
    ``info["reward_terms"]``):

    * ``align``: -w * (|e_yaw| / yaw_tolerance + |e_x| / x_tolerance), e = true pose - target;
    * ``time``: -w * bench time of the step in s (the stages' coordinated trapezoidal move,
      modelled with the firmware's speeds and accelerations, plus the scans at 10 Hz);
    * ``travel``: -w * (|d yaw| / yaw travel span + |d x| / x travel span);
    * ``no_estimate``: -w when the estimator failed (e.g. the board left the field of view);
    * ``success``: +w on the step that ends aligned.

    **Episode end.** ``terminated`` once |e_yaw| <= yaw_tolerance_rad (default 0.2 deg) and
    |e_x| <= x_tolerance_m (default 4 mm); ``truncated`` by the registration's `TimeLimit`.

    **Info**: ``true_pose`` (6-array, SI; None on hardware), ``true_error_yaw_rad``,
    ``true_error_x_m`` (and ``*_deg`` / ``*_mm``; None on hardware); ``error_yaw_rad``,
    ``error_x_m``, the error the reward and the termination used, and ``error_source``
    ("truth", "estimate", or "last": the last known, when neither is available);
    ``estimate_error_yaw_rad``, ``estimate_error_x_m`` (the estimate's view; None when it
    failed), ``estimate_status``; ``aligned`` and ``is_success``; ``reward_terms``; ``mount``
    (the episode's misalignment, edge units; None when the bench keeps its own);
    ``stage_command`` (the clipped action); ``step_time_s`` and ``episode_time_s`` (modelled
    bench time, s); ``scans`` (how many were taken for the estimate).

    **Rendering** (``render_mode``): ``"rgb_array"``: `render` returns a picture of the bench
    (``render_height`` x ``render_width`` x 3 uint8, MuJoCo's offscreen renderer, no display
    needed) from the scene's overview camera, with the board, the stages where they are, the
    estimate (a red disc at the estimated optical centre, a red arrow along its forward axis,
    the board returns it used as yellow dots), the target direction (green arrow) and a caption
    (`scenarios.envs.view`). ``"human"``: MuJoCo's viewer window, refreshed after every reset
    and step (needs a display).

    **Seeding.** All randomness of an episode comes from ``reset(seed=...)`` through
    ``self.np_random``: the mount, and a key that seeds every scan's noise on the twin
    (`SimBench.prepare`). The twin's sensor itself (its per-laser range offsets) is fixed by the
    bench's own seed: one physical VLP-16. Same seed and actions give identical observations.

    Parameters: ``bench`` a `Bench`, a factory returning one, or a name for
    `scenarios.bench.open_bench` ("sim", "hw", "serve") with ``bench_kwargs``; the env closes
    a bench it opened, never one handed in. ``scans_per_step`` scans per estimate (fused by the
    estimator; default `DEFAULT_SCANS_PER_STEP`). ``method``, ``board`` and ``hints`` go to
    `align.estimate`. ``mount_range`` a `MountRange`, or None to keep the bench's mount
    (default: a `MountRange` on a simulated bench, None otherwise).
    ``reset(options={"mount": {...}})`` sets one episode's mount (edge units, `MOUNT_KEYS`).
    The first reset homes the stages (``rehome=True``: every reset); every reset then moves
    them to the bench reference (0, 0).
    ``render_mode`` ("rgb_array", "human" or None) with ``render_width`` x ``render_height``
    pixels; ``normalized_actions`` the [-1, 1] float32 action space.
    """

    # A step costs about a second of bench time; 4 frames/s plays an episode a little faster.
    metadata: dict[str, Any] = {"render_modes": ["human", "rgb_array"],  # noqa: RUF012
                                "render_fps": 4}

    def __init__(
        self,
        bench: BenchSpec = "sim",
        *,
        bench_kwargs: Mapping[str, Any] | None = None,
        scans_per_step: int = DEFAULT_SCANS_PER_STEP,
        method: str = align.DEFAULT_METHOD,
        board: align.BoardSpec | None = None,
        hints: align.Hints | None = None,
        target_yaw_rad: float = 0.0,
        target_x_m: float | None = None,
        yaw_tolerance_rad: float = DEFAULT_YAW_TOLERANCE_RAD,
        x_tolerance_m: float = DEFAULT_X_TOLERANCE_M,
        mount_range: MountRange | str | None = "auto",
        n_board_points: int = 0,
        reward_weights: RewardWeights | None = None,
        rehome: bool = False,
        render_mode: str | None = None,
        render_width: int = 640,
        render_height: int = 480,
        normalized_actions: bool = False,
    ) -> None:
        super().__init__()
        if scans_per_step < 1:
            raise ValueError(f"scans_per_step must be at least 1, got {scans_per_step}")
        if n_board_points < 0:
            raise ValueError(f"n_board_points must be >= 0, got {n_board_points}")
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode {render_mode!r}: use one of "
                             f"{self.metadata['render_modes']} or None")
        if render_mode == "human":
            check_display()  # before a bench is opened: nothing to clean up
        if isinstance(mount_range, str) and mount_range != "auto":
            raise ValueError(f"mount_range {mount_range!r}: a MountRange, None or 'auto'")
        self.render_mode = render_mode
        self._view = BenchView(render_width, render_height) if render_mode else None
        self.normalized_actions = bool(normalized_actions)
        self.scans_per_step = int(scans_per_step)
        self.method = method
        self.board = board or align.BoardSpec()
        self.hints = hints
        self.yaw_tolerance_rad = float(yaw_tolerance_rad)
        self.x_tolerance_m = float(x_tolerance_m)
        self.weights = reward_weights or RewardWeights()
        self.n_board_points = int(n_board_points)
        self.rehome = bool(rehome)
        self.target_yaw_rad = float(target_yaw_rad)
        self.bench, self._owns_bench = self._open(bench, bench_kwargs)
        try:
            # Bench-dependent set-up: a bench this env opened (a served twin is a process) must
            # not outlive a failure here.
            if isinstance(mount_range, str):
                mount_range = MountRange() if isinstance(self.bench, SimBench) else None
            self.mount_range: MountRange | None = mount_range
            self.target_x_m = (float(target_x_m) if target_x_m is not None
                               else self._nominal_x())
            (y0, y1), (x0, x1) = self.bench.travel()
        except BaseException:
            if self._owns_bench:
                self.bench.close()
            raise
        self._travel = np.array([[y0, x0], [y1, x1]], dtype=np.float64)
        if self.normalized_actions:
            self.action_space = spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)
        else:
            self.action_space = spaces.Box(self._travel[0], self._travel[1], dtype=np.float64)
        big = np.array([POSITION_LIMIT_M] * 3 + [math.pi] * 3)
        obs: dict[str, spaces.Space] = {
            "pose": spaces.Box(-big, big, dtype=np.float64),
            "pose_std": spaces.Box(0.0, STD_LIMIT, shape=(6,), dtype=np.float64),
            "estimate_ok": spaces.Discrete(2),
            "stage": spaces.Box(self._travel[0], self._travel[1], dtype=np.float64),
        }
        if self.n_board_points:
            obs["board_points"] = spaces.Box(-POSITION_LIMIT_M, POSITION_LIMIT_M,
                                             shape=(self.n_board_points, 3), dtype=np.float64)
            obs["board_points_count"] = spaces.Discrete(self.n_board_points + 1)
        self.observation_space = spaces.Dict(obs)

        self._homed = False
        self._episode_key = 0
        self._step_index = 0
        self._episode_time_s = 0.0
        self._stage = np.zeros(2)
        self._mount: dict[str, float] | None = None
        self._last_set_mount: object = _UNSET
        self._last_error: tuple[float, float] | None = None
        self.last_estimate: align.PoseEstimate | None = None
        self.last_scans: list[Scan] = []

    # -- set-up --------------------------------------------------------------------------------
    @staticmethod
    def _open(bench: BenchSpec, kwargs: Mapping[str, Any] | None) -> tuple[Bench, bool]:
        """(the bench, whether this env opened it and so must close it)."""
        if isinstance(bench, Bench):
            if kwargs:
                raise ValueError("bench_kwargs only apply when the env opens the bench itself")
            return bench, False
        if isinstance(bench, str):
            return open_bench(RunConfig(bench=bench, **(kwargs or {}))), True
        if callable(bench):
            made = bench(**(kwargs or {}))
            if not isinstance(made, Bench):
                raise TypeError(f"the bench factory returned {type(made).__name__}, not a Bench")
            return made, True
        raise TypeError(f"bench must be a Bench, a factory or a name, not {type(bench).__name__}")

    def _nominal_x(self) -> float:
        """x of a perfectly mounted LiDAR at stage home, m: from the twin's model when the bench
        is the twin (its own geometry, whatever its `BenchParams`), else the paper's bench."""
        if isinstance(self.bench, SimBench):
            from twin.sim.physics import BenchPhysics

            p = replace(self.bench.base_params, mount_roll=0.0, mount_tilt=0.0, mount_yaw=0.0)
            return float(BenchPhysics(p).lidar_pose_in_board().x)
        return PAPER_NOMINAL_X_M

    # -- gymnasium API -------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None
              ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        super().reset(seed=seed)
        options = options or {}
        rng = self.np_random
        if "mount" in options:
            mount = options["mount"]
            unknown = set(mount or {}) - set(MOUNT_KEYS)
            if unknown:
                raise ValueError(f"reset option mount: unknown keys {sorted(unknown)}; "
                                 f"use {MOUNT_KEYS} (deg, mm)")
            mount = {k: float(v) for k, v in mount.items()} if mount else None
        elif self.mount_range is not None:
            mount = self.mount_range.draw(rng)
        else:
            mount = None
        # Drawn after the mount, so a fixed mount option leaves the noise stream as it was.
        self._episode_key = int(rng.integers(0, 2**31 - 1))
        self._set_mount(mount)
        # The twin is rebuilt at every reset (`_set_mount`), so it homes every time: the same
        # sequence each reset keeps its clock, hence its scans, a function of the seed alone.
        if self.rehome or not self._homed or isinstance(self.bench, SimBench):
            self.bench.home()
            self.bench.wait_until_there()
            self._homed = True
        # Homing leaves a real controller at its switches, not at the bench reference: every
        # episode starts from the reference (0, 0), where the mount misalignment shows whole.
        self.bench.move_to(x_m=0.0, yaw_rad=0.0)
        self.bench.wait_until_there()
        self._step_index = 0
        self._episode_time_s = 0.0
        self._last_error = None
        self._stage = self._read_stage()
        obs, est = self._observe()
        info = self._info(est, step_time_s=0.0, command=None)
        if self.render_mode == "human":
            self.render()
        return obs, info

    def step(self, action: np.ndarray) -> tuple[dict[str, np.ndarray], float, bool, bool,
                                                 dict[str, Any]]:
        a = np.asarray(action, dtype=np.float64).reshape(-1)
        if a.shape != (2,) or not np.all(np.isfinite(a)):
            units = "in [-1, 1]" if self.normalized_actions else "(yaw rad, x m)"
            raise ValueError(f"action must be 2 finite numbers {units}, got {action!r}")
        # Policies with unbounded outputs overshoot; the stages stop at their travel.
        command = np.clip(self._to_si(a), self._travel[0], self._travel[1])
        before = self._stage.copy()
        move_s = _move_duration(before, command)
        self.bench.move_to(x_m=float(command[1]), yaw_rad=float(command[0]))
        self.bench.wait_until_there()
        self._stage = self._read_stage()
        self._step_index += 1
        step_time_s = move_s + self.scans_per_step * SCAN_PERIOD_S
        self._episode_time_s += step_time_s
        obs, est = self._observe()
        info = self._info(est, step_time_s=step_time_s, command=command)

        span = self._travel[1] - self._travel[0]
        w = self.weights
        e_yaw, e_x = info["error_yaw_rad"], info["error_x_m"]
        terms = {
            "align": -w.align * (abs(e_yaw) / self.yaw_tolerance_rad
                                 + abs(e_x) / self.x_tolerance_m),
            "time": -w.time * step_time_s,
            "travel": -w.travel * float(np.sum(np.abs(command - before) / span)),
            "no_estimate": -w.no_estimate * (0.0 if _usable(est) else 1.0),
            "success": w.success if info["aligned"] else 0.0,
        }
        info["reward_terms"] = terms
        reward = float(sum(terms.values()))
        if self.render_mode == "human":
            self.render()
        return obs, reward, bool(info["aligned"]), False, info

    def render(self) -> np.ndarray | None:
        """``rgb_array``: the picture of the bench (see the class docstring); ``human``: refresh
        the viewer window (returns None); no render mode: None."""
        if self._view is None:
            return None
        frame = Frame(self.bench, self._stage.copy(), self.last_estimate, self.last_scans,
                      self.target_yaw_rad, self._caption())
        if self.render_mode == "human":
            self._view.show(frame)
            return None
        return self._view.rgb(frame)

    def action_for(self, stage_target: np.ndarray) -> np.ndarray:
        """The action that commands the stage targets (yaw rad, x m) in this env's action space
        (the targets themselves, or scaled to [-1, 1] with ``normalized_actions``)."""
        target = np.asarray(stage_target, dtype=np.float64).reshape(2)
        if not self.normalized_actions:
            return target
        low, high = self._travel
        return np.clip(2.0 * (target - low) / (high - low) - 1.0, -1.0, 1.0).astype(np.float32)

    def close(self) -> None:
        """Close the bench if this env opened it, and the renderer (idempotent)."""
        if self._view is not None:
            self._view.close()
        if self._owns_bench and self.bench is not None:
            self.bench.close()
        super().close()

    # -- internals -----------------------------------------------------------------------------
    def _to_si(self, action: np.ndarray) -> np.ndarray:
        """Stage targets (yaw rad, x m) of an action of this env's action space."""
        if not self.normalized_actions:
            return action
        low, high = self._travel
        return low + (np.clip(action, -1.0, 1.0) + 1.0) * 0.5 * (high - low)

    def _caption(self) -> list[str]:
        """The picture's caption: the step, the estimate and the error (deg, mm)."""
        est, head = self.last_estimate, f"step {self._step_index}"
        if est is None or not _usable(est):
            return [f"{head}  no estimate ({est.status if est is not None else 'not yet'})"]
        e = est.pose.to_edge()
        lines = [f"{head}  estimate: yaw {e['yaw_deg']:+.3f} deg, x {e['x_mm']:.1f} mm",
                 f"tilt {e['tilt_deg']:+.3f} deg, roll {e['roll_deg']:+.3f} deg"]
        if self._last_error is not None:
            e_yaw, e_x = self._last_error
            lines.append(f"error: yaw {math.degrees(e_yaw):+.3f} deg, x {e_x * 1e3:+.1f} mm")
        return lines

    def _set_mount(self, mount: dict[str, float] | None) -> None:
        """Give the twin this episode's mount, always as a freshly built twin: `SimBench` only
        rebuilds on a changed mount, and a reused twin carries its clock and spin phase from the
        last episode, which would make ``reset(seed=s)`` depend on the past."""
        if isinstance(self.bench, SimBench):
            if mount == self._last_set_mount or self._last_set_mount is _UNSET:
                self.bench.set_mount({"yaw_deg": 0.0} if mount is None else None)
            self.bench.set_mount(mount)
        elif mount is not None:
            self.bench.set_mount(mount)  # raises: only a simulated bench can change its mount
        self._last_set_mount = mount
        self._mount = mount

    def _read_stage(self) -> np.ndarray:
        p = self.bench.position()
        return np.array([p.yaw_rad, p.x_m], dtype=np.float64)

    def _scans(self) -> list[Scan]:
        # On the twin each step's scans draw their noise from (bench seed, episode key, step):
        # seeded by reset(seed) alone, whatever happened before. A no-op on hardware.
        self.bench.prepare(self._episode_key, self._step_index * self.scans_per_step)
        return list(self.bench.scans(self.scans_per_step))

    def _observe(self) -> tuple[dict[str, np.ndarray], align.PoseEstimate]:
        scans = self._scans()
        est = align.estimate(scans, board=self.board, method=self.method, hints=self.hints)
        self.last_scans, self.last_estimate = scans, est
        big = self.observation_space["pose"].high
        ok = _usable(est)
        if ok:
            p = est.pose.as_array()
            p[3:] = [_wrap(v) for v in p[3:]]
            pose = np.clip(p, -big, big)
            std = est.std if est.std is not None else np.full(6, STD_LIMIT)
            std = np.clip(np.nan_to_num(std, nan=STD_LIMIT), 0.0, STD_LIMIT)
        else:
            pose, std = np.zeros(6), np.full(6, STD_LIMIT)
        obs: dict[str, Any] = {
            "pose": pose.astype(np.float64),
            "pose_std": std.astype(np.float64),
            "estimate_ok": int(ok),
            "stage": np.clip(self._stage, self._travel[0], self._travel[1]),
        }
        if self.n_board_points:
            pts, count = self._board_points(scans, est)
            obs["board_points"] = pts
            obs["board_points_count"] = count
        return obs, est

    def _board_points(self, scans: list[Scan], est: align.PoseEstimate
                      ) -> tuple[np.ndarray, int]:
        """Up to N board returns in {L}, evenly subsampled (deterministic), zero-padded."""
        n = self.n_board_points
        out = np.zeros((n, 3))
        idx = np.asarray(est.used.get("board", []) if _usable(est) else [], dtype=np.int64)
        if idx.size == 0:
            return out, 0
        xyz = Scan.concatenate(scans).xyz[idx]
        if len(xyz) > n:
            xyz = xyz[np.linspace(0, len(xyz) - 1, n).round().astype(np.int64)]
        out[: len(xyz)] = np.clip(xyz, -POSITION_LIMIT_M, POSITION_LIMIT_M)
        return out, len(xyz)

    def _info(self, est: align.PoseEstimate, step_time_s: float,
              command: np.ndarray | None) -> dict[str, Any]:
        truth = scan_truth(self.last_scans[0]) if self.last_scans else None
        error: tuple[float, float] | None
        if truth is not None:
            source = "truth"
            error = self._error(truth)
        elif _usable(est):
            source = "estimate"
            error = self._error(est.pose)
        else:
            # Nothing tells where the LiDAR is: keep the last known error (0 before any).
            source = "last"
            error = self._last_error
        self._last_error = error
        e_yaw, e_x = error if error is not None else (0.0, 0.0)
        known = error is not None
        aligned = bool(known and abs(e_yaw) <= self.yaw_tolerance_rad
                       and abs(e_x) <= self.x_tolerance_m)
        est_err = self._error(est.pose) if _usable(est) else None
        return {
            "aligned": aligned,
            "is_success": aligned,
            "error_source": source,
            "error_yaw_rad": float(e_yaw),
            "error_x_m": float(e_x),
            "true_pose": truth.as_array() if truth is not None else None,
            "true_error_yaw_rad": float(e_yaw) if truth is not None else None,
            "true_error_x_m": float(e_x) if truth is not None else None,
            "true_error_yaw_deg": math.degrees(e_yaw) if truth is not None else None,
            "true_error_x_mm": e_x * 1e3 if truth is not None else None,
            "estimate_status": str(est.status),
            "estimate_error_yaw_rad": est_err[0] if est_err else None,
            "estimate_error_x_m": est_err[1] if est_err else None,
            "mount": dict(self._mount) if self._mount else None,
            "stage_command": command.copy() if command is not None else None,
            "step_time_s": float(step_time_s),
            "episode_time_s": float(self._episode_time_s),
            "scans": len(self.last_scans),
        }

    def _error(self, pose: Pose) -> tuple[float, float]:
        """(yaw error rad, x error m) of `pose` from the target."""
        return _wrap(pose.yaw - self.target_yaw_rad), float(pose.x - self.target_x_m)


class _Unset:
    def __repr__(self) -> str:
        return "<unset>"


_UNSET = _Unset()


def _move_duration(start: np.ndarray, end: np.ndarray) -> float:
    """Duration of the coordinated (Grbl G1) stage move from ``start`` to ``end`` (yaw rad, x m),
    s, with the firmware's speeds and accelerations (`twin.stage.motion`). The travel check is the
    bench's business, so the axes here have none."""
    axes = (replace(X_AXIS, travel_min=-math.inf, travel_max=math.inf),
            replace(YAW_AXIS, travel_min=-math.inf, travel_max=math.inf))
    move = StageMove.plan((float(start[1]), float(start[0])), (float(end[1]), float(end[0])), axes)
    return float(move.duration)


def scripted_policy(env: gym.Env, obs: Mapping[str, Any]) -> np.ndarray:
    """The obvious controller: read the estimate, command the correction.

    New stage target = where the stages are - (estimated pose - target), in yaw and x. The yaw
    error is the stage's to cancel exactly (the LiDAR's yaw in {O} is the stage yaw plus the
    mount's); x likewise along the linear stage. Without an estimate, stay put. Returned in the
    env's action space (`LidarAlignEnv.action_for`), so it drives either registered id.
    """
    target_yaw, target_x = env.unwrapped.target_yaw_rad, env.unwrapped.target_x_m
    stage = np.asarray(obs["stage"], dtype=np.float64)
    if not obs["estimate_ok"]:
        return env.unwrapped.action_for(stage)
    pose = np.asarray(obs["pose"], dtype=np.float64)
    correction = np.array([_wrap(pose[5] - target_yaw), pose[0] - target_x])
    return env.unwrapped.action_for(stage - correction)


def register() -> None:
    """Register `ENV_ID` and `ENV_ID_NORMALIZED` with gymnasium (idempotent: a re-import does
    not re-register)."""
    for env_id, kwargs in ((ENV_ID, {}), (ENV_ID_NORMALIZED, {"normalized_actions": True})):
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point=f"{__name__}:LidarAlignEnv",
                         max_episode_steps=MAX_EPISODE_STEPS, kwargs=kwargs)


register()

__all__ = ["ENV_ID", "ENV_ID_NORMALIZED", "MAX_EPISODE_STEPS", "LidarAlignEnv", "MountRange",
           "RewardWeights", "register", "scripted_policy"]
