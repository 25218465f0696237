"""The `Bench`: one interface over the simulated bench (MuJoCo, in process) and the real one.

A scenario only ever does this with a bench: home it, move the stages to a reference (a
`StagePose`: x and yaw, keyword-only everywhere),
wait until they are really there, take N scans, and close it. `SimBench` runs the twin in process
(`twin.sim.bench.BenchSim`); `HardwareBench` drives the stage controller over serial
(`twin.stage.controller.StageController`) and reads scans from the VLP-16 over UDP or from a pcap
capture (a replay). `HardwareBench` runs unchanged against the real bench and against the
wire-level twin of ``aimbench serve``.

Units: SI (rad, m, s). Every bench reports its travel so that a plan is checked before any move.
"""

from __future__ import annotations

import abc
import json
import math
import select
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from scenarios.config import RunConfig
from scenarios.station import Station
from scenarios.station import default as default_station
from twin.core.errors import AimbenchError
from twin.core.pose import StagePose
from twin.core.scan import Scan
from twin.core.sensors import MODELS
from twin.core.vlp16 import DATA_PORT

#: The paper's bench travel, used when a bench cannot tell its own: yaw +-10 deg sweeps need at
#: least that, x +-30 mm likewise. Real limits come from the controller's settings or the model.
DEFAULT_YAW_LIMITS_RAD = (math.radians(-180.0), math.radians(180.0))
DEFAULT_X_LIMITS_M = (-0.1, 0.1)
#: Where a hardware bench listens for the LiDAR unless told: every interface, the data port.
DEFAULT_LIDAR = f"udp://0.0.0.0:{DATA_PORT}"

Travel = tuple[tuple[float, float], tuple[float, float]]


def within(travel: Travel, station: Station | None) -> Travel:
    """`travel` limited to what the station file allows (its ``[stages]`` travel)."""
    if station is None:
        return travel
    return tuple((max(a[0], b[0]), min(a[1], b[1]))  # type: ignore[return-value]
                 for a, b in zip(travel, station.travel(), strict=True))


class BenchError(AimbenchError):
    """The bench could not do what a scenario asked (move, scan, connect)."""


class TravelError(BenchError):
    """A reference beyond the stages' travel."""


class NoScanError(BenchError):
    """No scan arrived: the LiDAR is silent, unplugged, or the capture has run out."""


class Bench(abc.ABC):
    """What a scenario needs from a bench. Use as a context manager; `close` is idempotent."""

    #: ``sim`` or ``hw``: stored with every run.
    kind: str = "bench"
    #: Whether `set_mount` can change the LiDAR's mount (the simulated bench only).
    can_set_mount: bool = False

    @abc.abstractmethod
    def info(self) -> dict[str, Any]:
        """What the bench says about itself (stored with the run): kind, model, travel,
        calibration, firmware, sensor. JSON-able. ``lever_arm_m`` if known: the optical centre's
        offset from the rotation axis at stage yaw 0, in the board frame (m)."""

    @abc.abstractmethod
    def travel(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """((yaw_min_rad, yaw_max_rad), (x_min_m, x_max_m)) the stages can reach."""

    #: Show the stages' position while they home (a hardware bench; the sweep's --no-progress
    #: turns it off).
    progress = True

    @abc.abstractmethod
    def home(self) -> None:
        """Find the stages' home (limit switches on hardware); afterwards yaw = x = 0."""

    @abc.abstractmethod
    def move_to(self, *, x_m: float, yaw_rad: float) -> None:
        """Command the stages to x (m) and yaw (rad); returns once the command is accepted."""

    @abc.abstractmethod
    def wait_until_there(self, timeout_s: float = 120.0) -> StagePose:
        """Block until the stages have stopped at the commanded pose; return where the stages
        report they are. Raises `BenchError` on a timeout or an alarm."""

    @abc.abstractmethod
    def position(self) -> StagePose:
        """Where the stages are now."""

    @abc.abstractmethod
    def scans(self, n: int) -> Iterator[Scan]:
        """Take `n` scans at the current pose, yielding each as soon as it is whole.

        The caller may stop iterating early (Ctrl-C between scans); the bench must then be left
        usable. Raises `NoScanError` when the sensor is silent.
        """

    def set_mount(self, mount: dict[str, float] | None) -> None:
        """Set the LiDAR's mounting misalignment (edge units, `scenarios.plans.MOUNT_KEYS`).

        Only a simulated bench can: on hardware, the mount is what it is.
        """
        if mount:
            raise BenchError(f"the {self.kind} bench cannot change the LiDAR's mount; plans with "
                             "mount misalignments (Monte Carlo) run on --bench sim only")

    def prepare(self, reference: int, first_scan: int) -> None:  # noqa: B027 - optional hook
        """Called before the scans of `reference` numbered from `first_scan` (a simulated bench
        seeds each scan from them, so resumed runs are reproducible)."""

    def close(self) -> None:  # noqa: B027 - optional hook, nothing to release by default
        """Release the stages, the sensor and any process the bench started."""

    def check_reachable(self, target: StagePose, what: str | None = None) -> None:
        """Raise `TravelError` if `target` lies beyond `travel`; `what` names it."""
        (y0, y1), (x0, x1) = self.travel()
        if not (y0 - 1e-9 <= target.yaw_rad <= y1 + 1e-9
                and x0 - 1e-12 <= target.x_m <= x1 + 1e-12):
            what = what or target.describe()
            raise TravelError(
                f"{what} is beyond the stages' travel (yaw {math.degrees(y0):+.1f}.."
                f"{math.degrees(y1):+.1f} deg, x {x0 * 1e3:+.1f}..{x1 * 1e3:+.1f} mm); change "
                "the plan or the travel settings")

    def __enter__(self) -> Bench:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# -- the hardware bench -------------------------------------------------------------------------

class HardwareBench(Bench):
    """The real bench: the stage controller over serial and the VLP-16 over UDP (or a capture).

    port: the controller's serial port or pyserial URL (``/dev/ttyACM0``, a pty of the simavr
        harness); None (``--port none``) for a bench without stages: a LiDAR on a fixed fixture,
        or the replay of a capture, taken to be at the plan's references.
    lidar: any source name of `twin.lidar.sources` (``udp://HOST:PORT``, a capture, a bag, a
        PCD file), read through a `twin.lidar.sources.ScanFeed` (None: the station's sensor
        network).
    settle_s: wait after arrival before scanning, so the bench stops ringing (s).
    station: the station file's bench (`scenarios.station.Station`): the stages' axis letters
        and travel, the LiDAR's address, the lever arm the report uses; None: the paper's
        defaults, with the travel the controller reports.
    axis_letters: the controller's (linear, rotation) axis letters, if not the station's.
    decode: how the LiDAR's packets are decoded (`twin.lidar.sources.open_scans`'s ``model``
        and ``lasers``: a named station's sensor, `scenarios.config.RunConfig.lidar_decoding`);
        None: as their product id says.
    """

    kind = "hw"

    def __init__(self, port: str | None, lidar: str | None = None,
                 settle_s: float = 0.2, silence_timeout_s: float = 2.0,
                 controller: Any = None, station: Station | None = None,
                 axis_letters: tuple[str, str] | None = None,
                 decode: dict[str, Any] | None = None) -> None:
        if lidar is None:
            lidar = station.lidar_url() if station is not None else DEFAULT_LIDAR
        self.port = port
        self.lidar = lidar
        self.station = station
        self.settle_s = settle_s
        self._target = StagePose()
        self._closed = False
        self.source = _scan_feed(lidar, silence_timeout_s, decode or {})
        self.controller = controller
        if port is not None and port.lower() == "none":
            self.port = port = None
        if self.controller is None and port is not None:
            from twin.stage.controller import StageController

            try:
                letters = axis_letters or (station.axis_letters if station is not None
                                           else ("X", "A"))
                self.controller = StageController(port, letters)
                self.controller.connect()
            except AimbenchError as exc:
                self.source.close()
                raise BenchError(f"stage controller on {port}: {exc}") from None
            except OSError as exc:
                self.source.close()
                raise BenchError(f"cannot open the stage controller port {port}: {exc}; check "
                                 "the cable and the port name (ls /dev/ttyACM*)") from None

    def info(self) -> dict[str, Any]:
        out: dict[str, Any] = {"kind": "hw", "port": self.port, **self.source.info()}
        c = self.controller
        if c is not None:
            out["banner"] = getattr(c, "banner", None)
            out["axis_letters"] = list(getattr(c, "axis_letters", ()))
            settings = _controller_settings(c)
            out["settings"] = {f"${k}": v for k, v in sorted(settings.items())}
        (y0, y1), (x0, x1) = self.travel()
        out["travel"] = {"yaw_deg": [math.degrees(y0), math.degrees(y1)],
                         "x_mm": [x0 * 1e3, x1 * 1e3]}
        if self.station is not None:
            out["station"] = self.station.name
            # The turntable's frame at stage yaw 0 is taken square to the board, as on the twin.
            out["lever_arm_m"] = [v / 1000.0 for v in self.station.mount.lever_arm_mm]
        return out

    def travel(self) -> Travel:
        """From the controller's settings as its firmware applies them ($13x max travel, $23
        homing direction: home at 0 with travel positive, or at 0 with travel negative),
        relative to the bench reference, within the station's travel; without a controller
        that tells, the station's travel (or the paper's defaults)."""
        return within(self._controller_travel(), self.station)

    def _controller_travel(self) -> Travel:
        c = self.controller
        settings = _controller_settings(c) if c is not None else {}
        if c is None or not settings:
            return DEFAULT_YAW_LIMITS_RAD, DEFAULT_X_LIMITS_M
        try:
            ix, ia = c.slot(0), c.slot(1)  # MPos/settings index of each axis (A and Y alike)
            mask = int(settings.get(23, 0))

            def span(axis: int) -> tuple[float, float]:
                t = float(settings[130 + axis])
                return (0.0, t) if mask & (1 << axis) else (-t, 0.0)

            (xl, xh), (al, ah) = span(ix), span(ia)
        except (KeyError, ValueError, AttributeError):
            return DEFAULT_YAW_LIMITS_RAD, DEFAULT_X_LIMITS_M
        return ((math.radians(al - c.yaw_ref_deg), math.radians(ah - c.yaw_ref_deg)),
                ((xl - c.x_ref_mm) * 1e-3, (xh - c.x_ref_mm) * 1e-3))

    def home(self) -> None:
        if self.controller is not None:
            from scenarios.progress import StageMotion

            # a homing cycle takes seconds (15 on the wire-level twin): the position as it goes
            with StageMotion("homing", enabled=self.progress) as shown:
                self.controller.home(on_status=shown)
        self._target = StagePose()

    def move_to(self, *, x_m: float, yaw_rad: float) -> None:
        target = StagePose(x_m=x_m, yaw_rad=yaw_rad)
        self.check_reachable(target)
        self._target = target
        if self.controller is not None:
            self.controller.move_to(x_m=x_m, yaw_rad=yaw_rad, wait=False)

    def wait_until_there(self, timeout_s: float = 120.0) -> StagePose:
        if self.controller is None:
            return self._target
        st = self.controller.wait_idle(timeout=timeout_s)
        # Idle means the step generator has stopped; let the mechanics settle before scanning.
        time.sleep(self.settle_s)
        return StagePose(x_m=float(st.x_m), yaw_rad=float(st.yaw_rad))

    def position(self) -> StagePose:
        if self.controller is None:
            return self._target
        return self.controller.position()

    def scans(self, n: int) -> Iterator[Scan]:
        from twin.lidar.sources import SourceExhaustedError
        from twin.lidar.udp import SensorSilentError

        got = 0
        try:
            for scan in self.source.take(n):
                got += 1
                yield scan
        except SensorSilentError as exc:
            raise NoScanError(f"LiDAR silent after {got} of {n} scans: {exc}") from None
        except SourceExhaustedError as exc:
            raise NoScanError(str(exc)) from None

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self.source.close()
        if self.controller is not None:
            self.controller.close()


def _scan_feed(lidar: str, timeout_s: float, decode: dict[str, Any]) -> Any:
    """The `twin.lidar.sources.ScanFeed` of a LiDAR source name; its errors as `NoScanError`."""
    from twin.lidar.sources import ScanFeed

    try:
        return ScanFeed(lidar, timeout_s, **decode)
    except AimbenchError as exc:
        raise NoScanError(f"{exc}") from None


def _controller_settings(controller: Any) -> dict[int, float]:
    """The controller's settings as read at connect ($$), without asking it again."""
    cached = getattr(controller, "cached_settings", None)  # a property of StageController
    if callable(cached):
        cached = cached()
    if isinstance(cached, dict):
        return dict(cached)
    return dict(getattr(controller, "_settings", None) or {})


class ServedBench(HardwareBench):
    """`HardwareBench` against an ``aimbench serve`` it starts itself (the wire-level twin).

    The twin runs in its own process (the firmware in simavr plus the VLP-16 emulation streaming
    UDP in real time), so the sweep's estimation does not steal its time; this bench talks to it
    exactly as to the real bench: Grbl over the pty, packets over UDP on loopback.
    """

    kind = "serve"

    def __init__(self, port: str, lidar: str, process: subprocess.Popen, log: Path,
                 station_json: Path | None = None, **kwargs: Any) -> None:
        self.process = process
        self.log = log
        self.station_json = station_json
        try:
            super().__init__(port, lidar, **kwargs)
        except BaseException:
            self._stop_process()
            raise

    @classmethod
    def launch(cls, seed: int = 0, ideal: bool = False, start_timeout_s: float = 300.0,
               station: Station | None = None, **kwargs: Any) -> ServedBench:
        """Start ``aimbench serve`` on a free loopback UDP port and connect to it; its twin is
        built from `station` (handed over as the JSON the run stores). The served firmware is
        the bench's own (axes X and A), whatever letters the station gives a real controller."""
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.bind(("127.0.0.1", 0))
            udp_port = s.getsockname()[1]
        log = Path(tempfile.mkstemp(prefix="aimbench-serve-", suffix=".log")[1])
        cmd = [sys.executable, "-m", "scenarios.cli", "serve", "--udp",
               f"127.0.0.1:{udp_port}", "--seed", str(seed)] + (["--ideal"] if ideal else [])
        if station is not None:
            fd, name = tempfile.mkstemp(prefix="aimbench-station-", suffix=".json")
            with open(fd, "w", encoding="utf-8") as f:
                json.dump(station.to_dict(), f)
            cmd += ["--station", name]
            kwargs["station_json"] = Path(name)
        with log.open("w") as err:
            # Its own session: a Ctrl-C at the terminal must stop the sweep between scans, not
            # the twin under the scan in flight; close() ends it.
            proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=err, text=True,
                                    start_new_session=True)
        # The first line is the pty (the firmware may be built first: allow for it).
        ready, _, _ = select.select([proc.stdout], [], [], start_timeout_s)
        pty = proc.stdout.readline().strip() if ready else ""
        if not pty.startswith("/dev/"):
            proc.terminate()
            proc.wait(timeout=10)
            tail = log.read_text(errors="replace").strip().splitlines()[-3:]
            if kwargs.get("station_json") is not None:
                kwargs["station_json"].unlink(missing_ok=True)
            raise BenchError(f"aimbench serve did not start (no pty within "
                             f"{start_timeout_s:.0f} s): {' / '.join(tail) or 'no output'}")
        return cls(pty, f"udp://127.0.0.1:{udp_port}", proc, log, station=station,
                   axis_letters=("X", "A"), **kwargs)

    def info(self) -> dict[str, Any]:
        return {**super().info(), "kind": "serve", "serve_pid": self.process.pid}

    def _stop_process(self) -> None:
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        if self.process.stdout is not None:
            self.process.stdout.close()

    def close(self) -> None:
        try:
            super().close()
        finally:
            self._stop_process()
            self.log.unlink(missing_ok=True)
            if self.station_json is not None:
                self.station_json.unlink(missing_ok=True)


# -- the simulated bench ------------------------------------------------------------------------

class SimBench(Bench):
    """The twin in process: `twin.sim.bench.BenchSim` (MuJoCo stages, VLP-16 emulation, truth).

    seed: the twin's seed. It draws the sensor once (its per-laser range offsets: one physical
        VLP-16 for the whole run); then every scan is drawn by itself: scan k of reference i
        (`prepare` names them) takes its noise, its rpm and its rotation phase from a generator
        seeded by (seed, i, k) and begins at a sensor time fixed by k (`scan_start_s`), so it
        depends on nothing scanned or moved before. A resumed run, a run on any number of
        worker processes and a replay of one scan all give the very same scans.
    ideal: every error source of the emulation off.
    station: the bench (`scenarios.station.Station`; default: the paper's, a perfect mount): the
        twin is built from it (`Station.bench_params`; it emulates the station's sensor.model
        unless ``noise`` says otherwise) and plans keep within its travel.
    params: a `twin.sim.params.BenchParams` instead of the station's (studies of the twin).
    A reference's mount misalignment (Monte Carlo) rebuilds the twin with it added to the
    station's nominal mount, keeping the same sensor; its ``x_mm`` shifts the LiDAR sideways on
    the turntable (the lever arm's x).
    Moves run in simulated time (the stages' trapezoidal profiles), so they cost no wall time.
    """

    kind = "sim"
    can_set_mount = True

    def __init__(self, seed: int = 0, ideal: bool = False, params: Any = None,
                 noise: Any = None, station: Station | None = None) -> None:
        from twin.sim.bench import BenchSim
        from twin.sim.emulation import EmulationConfig

        self.seed = int(seed)
        self.ideal = bool(ideal)
        self.station = station
        if params is None:
            params = (station if station is not None else default_station()).bench_params()
        self.base_params = params
        #: An Ouster's or a Hesai's model: its own twin (`twin.sim.sensor_twins`) makes the
        #: scans, on this bench's MuJoCo scene; None: `BenchSim`'s Velodyne emulation does.
        self.own_model: str | None = None
        if noise is None:
            # The station's sensor model (its nominal lasers: the twin is no particular unit).
            model = (station if station is not None else default_station()).sensor.model
            if model not in MODELS:
                from twin.sim.sensor_twins import is_own_twin

                if not is_own_twin(model):
                    raise AimbenchError(
                        f"the twin bench emulates {', '.join(MODELS)}, the Ouster models, the "
                        f"PandarXT32 and the PandarQT128; the station's sensor.model is {model}")
                # BenchSim still builds the scene and moves the stages; its own emulator
                # (a Velodyne's) is never asked for a scan.
                self.own_model, model = model, next(iter(MODELS))
            noise = (EmulationConfig.ideal(model=model) if ideal
                     else EmulationConfig(model=model))
        self._mount: dict[str, float] | None = None
        self._reference, self._next_scan = 0, 0
        self._sim = BenchSim(self.base_params, seed=self.seed, noise=noise)
        # Freeze the sensor drawn from the seed so a rebuilt twin (new mount) has the same one.
        offsets = getattr(self._sim.emulator, "laser_offsets", None)
        self.noise = (noise.with_(laser_offsets=tuple(float(v) for v in offsets))
                      if offsets is not None else noise)

    def _params(self) -> Any:
        p = self.base_params
        m = self._mount
        if not m:
            return p
        lever = tuple(p.lever_arm)
        return replace(p, mount_roll=p.mount_roll + math.radians(m.get("roll_deg", 0.0)),
                       mount_tilt=p.mount_tilt + math.radians(m.get("tilt_deg", 0.0)),
                       mount_yaw=p.mount_yaw + math.radians(m.get("yaw_deg", 0.0)),
                       lever_arm=(lever[0] + m.get("x_mm", 0.0) * 1e-3, lever[1], lever[2]))

    @property
    def sim(self) -> Any:
        """The `twin.sim.bench.BenchSim` in use (for studies that need more than a `Bench`)."""
        return self._sim

    def info(self) -> dict[str, Any]:
        p = self.base_params
        (y0, y1), (x0, x1) = self.travel()
        return {
            "kind": "sim", "seed": self.seed, "ideal": self.ideal, "seeding": SEEDING,
            **({"own_twin": self.own_model} if self.own_model is not None else {}),
            **({"station": self.station.name} if self.station is not None else {}),
            "params": {k: (list(v) if isinstance(v, tuple) else v)
                       for k, v in vars(p).items() if not k.startswith("_")},
            "noise": {k: (list(v) if isinstance(v, tuple) else v)
                      for k, v in vars(self.noise).items() if not k.startswith("_")},
            "travel": {"yaw_deg": [math.degrees(y0), math.degrees(y1)],
                       "x_mm": [x0 * 1e3, x1 * 1e3]},
            # The turntable's frame is square to the board at stage yaw 0 (the paper's bench),
            # so the lever arm in that frame is the offset the relative report swings.
            "lever_arm_m": list(p.lever_arm),
        }

    def travel(self) -> Travel:
        """The twin's stage travel (twin/stage/motion.py), within the station's."""
        from twin.stage.motion import X_AXIS, YAW_AXIS

        return within(((YAW_AXIS.travel_min, YAW_AXIS.travel_max),
                       (X_AXIS.travel_min, X_AXIS.travel_max)), self.station)

    def set_mount(self, mount: dict[str, float] | None) -> None:
        from twin.sim.bench import BenchSim

        if (mount or None) != self._mount:
            self._mount = dict(mount) if mount else None
            self._sim = BenchSim(self._params(), seed=self.seed, noise=self.noise)

    def prepare(self, reference: int, first_scan: int) -> None:
        """The scans that follow are scans `first_scan`, `first_scan` + 1, ... of `reference`."""
        if int(reference) < 0 or int(first_scan) < 0:
            raise ValueError(f"prepare({reference}, {first_scan}): indices must be >= 0")
        self._reference, self._next_scan = int(reference), int(first_scan)

    def home(self) -> None:
        self._sim.move_to(x_m=0.0, yaw_rad=0.0)

    def move_to(self, *, x_m: float, yaw_rad: float) -> None:
        self.check_reachable(StagePose(x_m=x_m, yaw_rad=yaw_rad))
        try:
            self._sim.move_to(x_m=x_m, yaw_rad=yaw_rad)  # blocks in simulated time until there
        except AimbenchError as exc:
            raise TravelError(str(exc)) from None

    def wait_until_there(self, timeout_s: float = 120.0) -> StagePose:
        return self.position()

    def position(self) -> StagePose:
        return StagePose(x_m=float(self._sim.stage_x()), yaw_rad=float(self._sim.stage_yaw()))

    def scans(self, n: int) -> Iterator[Scan]:
        # One at a time, so a Ctrl-C between scans wastes nothing.
        for _ in range(n):
            i, k = self._reference, self._next_scan
            self._next_scan += 1
            # The twin's generator (noise, rpm wander, dropouts, the rotation's phase) and its
            # clock, both from (seed, reference, scan) alone.
            rng = np.random.default_rng((self.seed, i, k))
            if self.own_model is not None:
                from twin.sim.sensor_twins import own_twin_packets

                # the own twins are at rest and phase-locked: one scan from its own generator
                sigma = 0.0 if self.ideal else OWN_TWIN_RANGE_SIGMA
                yield own_twin_packets(self._sim, self.own_model, 1, rng=rng,
                                       range_sigma=sigma).scans[0]
                continue
            self._sim.restart_sensor(rng, scan_start_s(k))
            yield self._sim.scan()


#: The range noise of an Ouster's or a Hesai's twin on `SimBench`, 1-sigma, m (the twins'
#: default: `twin.sim.sensor_twins.own_twin_packets`).
OWN_TWIN_RANGE_SIGMA = 0.01
#: How `SimBench` seeds its scans (stored in a run's bench info, so that a replay knows a run
#: made before scans were seeded one by one).
SEEDING = "per scan: (seed, reference, scan)"
#: Sensor time between the starts of consecutive scans of a reference on `SimBench` (longer than
#: a rotation at 300 rpm plus its phase), and how many fit before the clock's hour wraps.
SCAN_SLOT_S = 0.4
SCAN_SLOTS = 9000


def scan_start_s(k: int) -> float:
    """The sensor time (s past the hour) at which `SimBench` begins scan `k` of a reference:
    fixed by k alone, increasing with k within the hour (the clock's own wrap)."""
    return SCAN_SLOT_S * (int(k) % SCAN_SLOTS)


def open_bench(config: RunConfig) -> Bench:
    """The bench a run's configuration names: sim (its seed, ideal), hw (its port and LiDAR) or
    serve (its seed, ideal), each the bench of the run's station."""
    try:
        config.check()
    except AimbenchError as exc:
        raise BenchError(str(exc)) from None
    if config.bench == "sim":
        return SimBench(seed=config.seed, ideal=config.ideal, station=config.station)
    if config.bench == "hw":
        return HardwareBench(config.port, config.lidar, station=config.station,
                             decode=config.lidar_decoding())
    return ServedBench.launch(seed=config.seed, ideal=config.ideal, station=config.station)
