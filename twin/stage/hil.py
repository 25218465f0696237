"""Hardware in the loop without hardware: the real stage firmware running in simavr.

`SimavrHarness` builds bench_fw (firmware .elf and the C harness, ``make -C bench_fw all
harness``) if needed, starts ``bench_fw/build/harness/bench_hil`` and gives

- ``pty_path``: a pseudo-terminal that `twin.stage.controller.StageController` (or any Grbl
  sender) opens like ``/dev/ttyACM0``; opening it resets the simulated MCU, as on a real Mega;
- ``positions()``: the live step counts of both stages as observed on the firmware's STEP/DIR
  pins, and the same in SI relative to the bench reference, so the twin can move its MuJoCo joints
  from the firmware's real step pulses.

Channel from the harness to Python: a 192-byte shared-memory file (``mmap``), written by the
harness at every step pulse under a seqlock; the layout is documented at the top of
bench_fw/harness/bench_hil.c and in bench_fw/PROTOCOL.md. Reading it costs no syscalls and is
never stale. The host writes one field, a mark request: the harness then restarts the window
over which it records each axis' lowest and highest position (``mark()``, ``positions().extremes``),
so a test sees where the stages really went between two status polls.

Physical model: step 0 is the homed machine zero; the min switch reads hit below
-pulloff, the max switch above travel + pulloff (so after ``$H`` the observed steps equal the
firmware's MPos in steps exactly).
"""

from __future__ import annotations

import fcntl
import math
import mmap
import select
import shutil
import struct
import subprocess
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any

from bench_fw import FIRMWARE_DIR
from twin.core.errors import AimbenchError

BUILD_DIR = FIRMWARE_DIR / "build"
ELF_PATH = BUILD_DIR / "bench_fw.elf"
HARNESS_PATH = BUILD_DIR / "harness" / "bench_hil"

_SHM_SIZE = 192
_SHM_FORMAT = "<8sII2qQ2Q2QII2q2qQQQ2q2qII"
_MARK_REQUEST_OFFSET = 176
_MAGIC = b"AIMBHIL1"


class HilError(AimbenchError):
    """The simavr harness cannot be built or started."""


@dataclass(frozen=True)
class BenchAxes:
    """The bench's axis geometry (the firmware's EEPROM defaults, PROTOCOL.md).

    steps_per_mm, steps_per_deg: $100, $101. x_travel_mm, a_travel_deg: $130, $131.
    pulloff: $27 in mm / deg. x_ref_mm, yaw_ref_deg: machine position of the bench reference.
    """

    steps_per_mm: float = 400.0
    steps_per_deg: float = 800.0
    x_travel_mm: float = 100.0
    a_travel_deg: float = 60.0
    pulloff: float = 1.0
    x_ref_mm: float = 50.0
    yaw_ref_deg: float = 30.0

    def trips(self) -> tuple[tuple[int, int], tuple[int, int]]:
        """(min, max) switch trip points in steps for X and A."""
        x = (-round(self.pulloff * self.steps_per_mm),
             round((self.x_travel_mm + self.pulloff) * self.steps_per_mm))
        a = (-round(self.pulloff * self.steps_per_deg),
             round((self.a_travel_deg + self.pulloff) * self.steps_per_deg))
        return x, a


@dataclass(frozen=True)
class HilPositions:
    """A snapshot of the simulated stages.

    x_steps, a_steps: physical positions in steps from the homed machine zero.
    x_m, yaw_rad: the same relative to the bench reference (m, rad; yaw counter-clockwise).
    sim_time_s: simulated time since the harness started (s).
    last_step_s: simulated time of each axis' latest step pulse (s).
    last_rx_s: simulated time at which the host's latest byte entered the UART (s); with
    last_step_s, how long the firmware took from a command to the end of its motion.
    rx_bytes: bytes from the host fed to the UART so far.
    pulses: step pulses seen per axis, either direction.
    limits: (X switch hit, A switch hit). resets: MCU resets so far (port opens, crashes).
    idle_s: simulated time the MCU spent asleep with nothing to do (s); the CPU load over a
    stretch is 1 - d(idle_s) / d(sim_time_s).
    extremes: ((x_min, x_max), (a_min, a_max)) in steps since the last ``mark()``.
    marked: whether the harness has taken the latest ``mark()`` (extremes start from it).
    """

    x_steps: int
    a_steps: int
    x_m: float
    yaw_rad: float
    sim_time_s: float
    last_step_s: tuple[float, float]
    last_rx_s: float
    rx_bytes: int
    pulses: tuple[int, int]
    limits: tuple[bool, bool]
    resets: int
    idle_s: float
    extremes: tuple[tuple[int, int], tuple[int, int]]
    marked: bool


@contextmanager
def build_lock() -> Iterator[None]:
    """One `make` in bench_fw at a time across processes: two makes writing the same objects at
    once (two test workers, two `aimbench hil` started together on a fresh tree) corrupt them."""
    BUILD_DIR.mkdir(exist_ok=True)
    with open(BUILD_DIR / ".make.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
        yield


def build(quiet: bool = True) -> None:
    """Build the firmware and the harness (make is a no-op when they are up to date)."""
    cmd = ["make", "-s", "-C", str(FIRMWARE_DIR), "all", "harness"]
    try:
        with build_lock():
            out = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    except FileNotFoundError as exc:
        raise HilError("`make` is not installed: run tools/setup.sh (make setup)") from exc
    if out.returncode != 0:
        tail = "\n".join((out.stdout + out.stderr).strip().splitlines()[-15:])
        raise HilError(
            f"building bench_fw failed ({' '.join(cmd)}); are gcc-avr, arduino-core-avr and "
            f"libsimavr-dev installed (tools/setup.sh)?\n{tail}"
        )
    if not quiet and out.stdout.strip():
        print(out.stdout.strip())


class SimavrHarness:
    """The firmware in simavr on a pty; a context manager (starts on enter, stops on exit).

    start_x_mm, start_a_deg: where the stages physically stand at power-up (machine units from
    the homed zero; the firmware does not know it until it homes). pace: run in real time
    (False: as fast as simavr goes, about 4x; host timeouts then mislead). axes: the geometry
    the limit switches are placed from. build_first: run make before starting. reset_on_open:
    reset the MCU when a host opens the pty, as a Mega's DTR auto-reset does (False: a board
    without it, which keeps running and sends no banner on open).
    """

    def __init__(
        self,
        start_x_mm: float = 20.0,
        start_a_deg: float = 10.0,
        *,
        pace: bool = True,
        axes: BenchAxes | None = None,
        build_first: bool = True,
        start_timeout_s: float = 20.0,
        reset_on_open: bool = True,
    ) -> None:
        self.axes = axes or BenchAxes()
        self.start_x_mm = start_x_mm
        self.start_a_deg = start_a_deg
        self.pace = pace
        self.build_first = build_first
        self.start_timeout_s = start_timeout_s
        self.reset_on_open = reset_on_open
        self.pty_path: str | None = None
        self.shm_path: Path | None = None
        self.log_path: Path | None = None
        self._proc: subprocess.Popen[str] | None = None
        self._tmp: str | None = None
        self._map: mmap.mmap | None = None
        self._log = None

    @property
    def url(self) -> str:
        """The port to give StageController (the pty path)."""
        if self.pty_path is None:
            raise HilError("the simavr harness is not running: call start() first")
        return self.pty_path

    def start(self) -> SimavrHarness:
        """Build if needed, start the harness, read the pty path from its first line."""
        if self.build_first:
            build()
        if not HARNESS_PATH.exists() or not ELF_PATH.exists():
            raise HilError(
                f"{HARNESS_PATH} or {ELF_PATH} missing: run make -C bench_fw all harness"
            )
        self._tmp = tempfile.mkdtemp(prefix="aimbench-hil-")
        self.shm_path = Path(self._tmp) / "positions.shm"
        self.log_path = Path(self._tmp) / "bench_hil.log"
        (xmin, xmax), (amin, amax) = self.axes.trips()
        cmd = [
            str(HARNESS_PATH),
            "--shm", str(self.shm_path),
            "--x-start", str(round(self.start_x_mm * self.axes.steps_per_mm)),
            "--a-start", str(round(self.start_a_deg * self.axes.steps_per_deg)),
            "--x-trip", f"{xmin},{xmax}",
            "--a-trip", f"{amin},{amax}",
        ]
        if not self.pace:
            cmd.append("--no-pace")
        if not self.reset_on_open:
            cmd.append("--no-reset-on-open")
        cmd.append(str(ELF_PATH))
        self._log = open(self.log_path, "w")  # noqa: SIM115 - lives as long as the process
        self._proc = subprocess.Popen(
            cmd, stdout=subprocess.PIPE, stderr=self._log, text=True, bufsize=1
        )
        assert self._proc.stdout is not None
        ready, _, _ = select.select([self._proc.stdout], [], [], self.start_timeout_s)
        line = self._proc.stdout.readline().strip() if ready else ""
        if not line.startswith("/dev/"):
            self.stop()
            raise HilError(
                f"the simavr harness did not print its pty within {self.start_timeout_s:.0f} s "
                f"(got {line!r}); see {self.log_path}"
            )
        self.pty_path = line
        with open(self.shm_path, "r+b") as f:
            self._map = mmap.mmap(f.fileno(), _SHM_SIZE, access=mmap.ACCESS_WRITE)
        self._mark = 0
        return self

    def running(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    def raw(self) -> tuple[Any, ...]:
        """The shared-memory record as a tuple (consistent: seqlock retried)."""
        if self._map is None:
            raise HilError("the simavr harness is not running: call start() first")
        # The harness may be descheduled in the middle of an update on a loaded host: retry for
        # up to a second, yielding the CPU after the first spins.
        deadline = time.monotonic() + 1.0
        spins = 0
        while True:
            s1 = struct.unpack_from("<I", self._map, 8)[0]
            if not s1 & 1:
                rec = struct.unpack_from(_SHM_FORMAT, self._map, 0)
                if rec[1] == s1 and rec[0] == _MAGIC:
                    return rec
            spins += 1
            if spins > 200:
                if time.monotonic() > deadline:
                    break
                time.sleep(0.0002)
        raise HilError("could not read a consistent position record from the harness")

    def positions(self) -> HilPositions:
        """The live positions of both stages as observed on the STEP/DIR pins."""
        rec = self.raw()
        (_, _, resets, xs, as_, cycle, lx, la, px, pa, limits, freq, _, _, _, _, rx_cycle,
         rx_bytes, idle, xmin, amin, xmax, amax, ack, _) = rec
        ax = self.axes
        return HilPositions(
            x_steps=xs,
            a_steps=as_,
            x_m=(xs / ax.steps_per_mm - ax.x_ref_mm) / 1000.0,
            yaw_rad=math.radians(as_ / ax.steps_per_deg - ax.yaw_ref_deg),
            sim_time_s=cycle / freq,
            last_step_s=(lx / freq, la / freq),
            last_rx_s=rx_cycle / freq,
            rx_bytes=rx_bytes,
            pulses=(px, pa),
            limits=(bool(limits & 1), bool(limits & 2)),
            resets=resets,
            idle_s=idle / freq,
            extremes=((xmin, xmax), (amin, amax)),
            marked=ack == self._mark,
        )

    def mark(self, timeout_s: float = 2.0) -> None:
        """Restart the window of `HilPositions.extremes` at the present position; returns once
        the harness has taken it (it looks every 0.2 ms of simulated time)."""
        if self._map is None:
            raise HilError("the simavr harness is not running: call start() first")
        self._mark = (self._mark + 1) & 0xFFFFFFFF
        struct.pack_into("<I", self._map, _MARK_REQUEST_OFFSET, self._mark)
        if not wait_until(lambda: self.positions().marked, timeout_s, poll_s=0.001):
            raise HilError("the simavr harness did not take the mark request")

    def stop(self) -> None:
        """Stop the harness and remove its temporary files."""
        if self._map is not None:
            self._map.close()
            self._map = None
        if self._proc is not None:
            if self._proc.poll() is None:
                self._proc.terminate()
                try:
                    self._proc.wait(timeout=5)
                except subprocess.TimeoutExpired:
                    self._proc.kill()
                    self._proc.wait()
            if self._proc.stdout is not None:
                self._proc.stdout.close()
            self._proc = None
        if self._log is not None:
            self._log.close()
            self._log = None
        if self._tmp is not None:
            shutil.rmtree(self._tmp, ignore_errors=True)
            self._tmp = None
        self.pty_path = None

    def __enter__(self) -> SimavrHarness:
        if self._proc is None:
            self.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()

    def __del__(self) -> None:
        if getattr(self, "_proc", None) is not None and self._proc.poll() is None:
            self._proc.terminate()


def wait_until(predicate: Callable[[], bool], timeout_s: float, poll_s: float = 0.01) -> bool:
    """Poll `predicate()` until true or `timeout_s` passes; returns its last value."""
    deadline = time.monotonic() + timeout_s
    while True:
        if predicate():
            return True
        if time.monotonic() >= deadline:
            return False
        time.sleep(poll_s)


__all__ = ["BenchAxes", "HilError", "HilPositions", "SimavrHarness", "build", "build_lock",
           "wait_until"]
