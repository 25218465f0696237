"""Host driver of the bench's stage controller (bench_fw/, or a stock grbl-Mega board).

`StageController` talks Grbl 1.1 over ``serial.serial_for_url``, so a USB port
(``/dev/ttyACM0``), the simavr harness's pty (`twin.stage.hil`) or ``loop://`` all work. It copes
with the boot banner of a board that resets when the port opens and with a board that does not
(it asks for a soft reset), waits until the stages have really arrived (Grbl's ``ok`` only means
"accepted"), and turns timeouts, lost replies, errors and alarms into exceptions that carry
Grbl's code and meaning.

Units: the public API is SI and relative to the bench reference (x in m from the bench centre,
yaw in rad, positive counter-clockwise seen from above). On the wire the linear axis is in mm and
the rotary axis in degrees of machine position; the bench reference sits at machine
X = ``x_ref_mm`` (50 mm) and A = ``yaw_ref_deg`` (30 deg). Conversion happens here only.

Axes: at connect the driver finds out which controller it talks to and which axes it has, from
the banner, ``$I`` (``[VER:...]``, ``[AXS:n:letters]``) and the status report's MPos values:
bench_fw reports X, Y, Z slots with the rotary stage A in the Y slot; a stock grbl-Mega reports
X, Y, Z, and the bench wires the rotary stage to its Y pins (bench_fw/PROTOCOL.md). Unless told
otherwise the driver then drives X and A (bench_fw) or X and Y (stock Grbl), and says which in
`axis_note`.
"""

from __future__ import annotations

import math
import termios
import time
from collections.abc import Callable
from dataclasses import dataclass
from types import TracebackType

import serial

from twin.core.errors import AimbenchError
from twin.core.pose import StagePose
from twin.stage import grbl

#: The bench's machine position of the reference pose (PROTOCOL.md, "Bench settings").
X_REF_MM = 50.0
YAW_REF_DEG = 30.0
#: How often a line that waits (``$H``) asks for the position when a display wants it, s: ten
#: reports a second redraw a position smoothly and cost the controller nothing.
STATUS_POLL_S = 0.1


class StageError(AimbenchError):
    """Base of every stage-controller error."""


class StageConnectionError(StageError):
    """The port cannot be opened, or no Grbl controller answers on it."""


class StageTimeout(StageError):
    """A reply or an arrival did not come in time."""


class StageResetError(StageError):
    """The controller reset (banner seen) while a reply was awaited."""


class StageReplyError(StageError, ValueError):
    """A reply that cannot be read (a status report garbled on the line). A ValueError too,
    as `grbl.parse_status` raises, so callers that caught that still do."""


class GrblError(StageError):
    """The controller refused a line with ``error:N``."""

    def __init__(self, code: int, command: str = "") -> None:
        self.code = code
        self.meaning = grbl.error_meaning(code)
        self.command = command
        where = f" to {command!r}" if command else ""
        super().__init__(f"stage controller replied error:{code}{where}: {self.meaning}")


class GrblAlarm(StageError):
    """The controller is in (or raised) ``ALARM:N``; code 0 = alarm state of unknown cause
    (for example power-up with homing enabled)."""

    def __init__(self, code: int, context: str = "") -> None:
        self.code = code
        self.meaning = (
            grbl.alarm_meaning(code)
            if code
            else "the controller is in alarm state: home it ($H) or unlock it ($X)"
        )
        prefix = f"ALARM:{code}" if code else "alarm state"
        tail = f" ({context})" if context else ""
        super().__init__(f"stage controller {prefix}: {self.meaning}{tail}")


@dataclass(frozen=True)
class StageStatus:
    """A status report in both machine and bench units.

    state: Grbl state ("Idle", "Run", "Hold", "Home", "Alarm", ...); substate: e.g. Hold:0.
    x_mm, yaw_deg: machine position (mm, deg). x_m, yaw_rad: relative to the bench reference (m,
    rad). limits: the axis letters whose limit input reads hit.
    """

    state: str
    substate: int | None
    x_mm: float
    yaw_deg: float
    x_m: float
    yaw_rad: float
    limits: str
    raw: grbl.GrblStatus

    @property
    def position_known(self) -> bool:
        """False in Alarm: after power-up, a hard limit or a reset in motion the controller's
        position is not the stages' until they are homed (or unlocked, trusting it)."""
        return self.state != "Alarm"


class StageController:
    """Driver of the two-axis stage controller.

    url: anything ``serial.serial_for_url`` opens (``/dev/ttyACM0``, a pty, ``loop://``).
    axis_letters: the letters of the (linear, rotary) axes on the controller; None (default):
    chosen at connect, ("X", "A") for bench_fw and ("X", "Y") for a stock grbl-Mega (its Y pins
    drive the rotary stage), see `axis_note`. Letters the controller lacks are an error.
    x_ref_mm, yaw_ref_deg: machine position of the bench reference; None (default): 50 mm and
    30 deg on bench_fw (travel [0, $13x]), the middle of the travel on a stock Grbl (travel
    [-$13x, 0]: -$130/2, -$131/2).
    reply_timeout_s: how long a line's ``ok``/``error`` may take (s).
    boot_timeout_s: how long to wait for the banner after opening the port (s); a board that has
    not sent one by then is soft-reset.
    mpos_axes: the controller's axis letter per MPos value; default: detected at connect ("XA"
    for bench_fw, whose rotary A fills the Y slot; "XYZ..." from $I or the number of values
    for anything else).
    hold_dtr: on close, leave DTR up (clear HUPCL), so that the next open does not reset an
    Arduino and its position survives between connections (the first open after plugging the
    board in still resets it).
    """

    def __init__(
        self,
        url: str,
        axis_letters: tuple[str, str] | None = None,
        *,
        baudrate: int = 115200,
        x_ref_mm: float | None = None,
        yaw_ref_deg: float | None = None,
        reply_timeout_s: float = 2.0,
        boot_timeout_s: float = 2.5,
        mpos_axes: str | None = None,
        hold_dtr: bool = True,
    ) -> None:
        self._requested_letters: tuple[str, str] | None = None
        if axis_letters is not None:
            letters = tuple(s.upper() for s in axis_letters)
            if len(letters) != 2 or letters[0] == letters[1] or not all(
                len(s) == 1 and s in "XYZABC" for s in letters
            ):
                raise ValueError(
                    f"axis_letters must be two different Grbl axis letters, got {axis_letters}"
                )
            self._requested_letters = (letters[0], letters[1])
        self.url = url
        self.axis_letters: tuple[str, str] = self._requested_letters or ("X", "A")
        self.baudrate = baudrate
        self._ref_override = (x_ref_mm, yaw_ref_deg)
        self.x_ref_mm = X_REF_MM if x_ref_mm is None else x_ref_mm
        self.yaw_ref_deg = YAW_REF_DEG if yaw_ref_deg is None else yaw_ref_deg
        self.reply_timeout_s = reply_timeout_s
        self.boot_timeout_s = boot_timeout_s
        self._mpos_axes_override = mpos_axes
        self.hold_dtr = hold_dtr
        self.mpos_axes = mpos_axes or "XA"
        self._slots: dict[str, int] = {"X": 0, "A": 1, "Y": 1}
        self.bench_firmware = True  # bench_fw (True) or another Grbl such as stock grbl-Mega
        self.axis_note = ""  # which axes the driver chose, and why
        self.banner: str | None = None
        self.messages: list[str] = []  # [MSG:...] and other push messages, oldest first
        self.last_alarm: int | None = None
        self._ser: serial.SerialBase | None = None
        self._buf = bytearray()
        self._settings: dict[int, float] = {}

    # ---- connection ---------------------------------------------------------------------------

    def connect(self) -> str:
        """Open the port and make sure a Grbl controller answers; returns its banner ("" if it
        answered a status query without one).

        A board that resets on open (Arduino DTR) sends its banner by itself. A board that does
        not (DTR held up, or no auto-reset) is asked for a status report first, so a move in
        progress is not disturbed; only if that gets no answer is it soft-reset (Ctrl-X). Then
        the settings are read (for move timeouts and step rounding).
        """
        try:
            # exclusive: a second client on the port (two aimbench, a serial monitor) would
            # interleave its lines with ours and the errors would blame the hardware (issue 37);
            # the port is locked (flock) and a second open fails below, saying so.
            self._ser = serial.serial_for_url(
                self.url, baudrate=self.baudrate, timeout=0.02, write_timeout=2.0,
                exclusive=True,
            )
        except (serial.SerialException, ValueError, OSError) as exc:
            raise StageConnectionError(
                f"cannot open the stage controller port {self.url!r}: {exc}; check the USB cable "
                "and the port name (ls /dev/ttyACM* /dev/ttyUSB*), and that no other program "
                "has the port open"
            ) from exc
        # DTR only rises (resetting an Arduino) if the last close dropped it (HUPCL set).
        expect_reset = self._hupcl() is not False
        banner = self._wait_banner(self.boot_timeout_s if expect_reset else 0.3)
        first: grbl.GrblStatus | None = None
        if banner is None:
            try:
                first = self._raw_status(timeout_s=min(self.reply_timeout_s, 1.0))
            except (StageTimeout, ValueError):
                first = None
        if banner is None and first is None:
            self._buf.clear()
            self._write(grbl.SOFT_RESET)
            banner = self._wait_banner(self.reply_timeout_s)
            if banner is None:
                self.close()
                raise StageConnectionError(
                    f"no Grbl controller answers on {self.url!r} (no banner, no status report, "
                    f"nothing after a soft reset): is the stage firmware flashed "
                    f"(make -C bench_fw flash) and the baud rate {self.baudrate}?"
                )
        self._detect_axes(banner, first)
        try:
            self._settings = self.settings()
        except StageError:
            self._settings = {}
        self._choose_reference()
        return banner or ""

    def _detect_axes(self, banner: str | None, first: grbl.GrblStatus | None) -> None:
        """Which controller this is, the letter of each MPos value, and the letters to drive."""
        version = axes = None
        try:
            for line in self.command("$I"):
                version = grbl.parse_version(line) or version
                axes = grbl.parse_axes(line) or axes
        except StageError:
            pass  # $I refused (moving) or unknown: the banner and the status report decide
        self.bench_firmware = "aimbench" in (banner or "") or "aimbench" in (version or "")
        if self._mpos_axes_override is not None:
            self.mpos_axes = self._mpos_axes_override
        elif self.bench_firmware:
            self.mpos_axes = "XA"  # MPos X, then A in the Y slot (and Z = 0 on 3-value builds)
        else:
            n = len((first or self._raw_status()).mpos)
            self.mpos_axes = axes if axes and len(axes) == n else "XYZABC"[:n]
        self._slots = {letter: i for i, letter in enumerate(self.mpos_axes)}
        if self.bench_firmware:
            self._slots.setdefault("Y", self._slots.get("A", 1))  # A answers to its slot's Y
        kind = "bench_fw" if self.bench_firmware else "a stock Grbl controller"
        if self._requested_letters is None:
            rotary = "A" if "A" in self._slots else "Y"
            self.axis_letters = ("X", rotary)
            wiring = "" if self.bench_firmware else " (the bench wires the rotary stage to Y)"
            self.axis_note = (
                f"{kind} with axes {self.mpos_axes}: linear stage on X, rotary stage on "
                f"{rotary}{wiring}"
            )
        else:
            self.axis_note = f"{kind} with axes {self.mpos_axes}: axes {''.join(self.axis_letters)}"
        for letter in self.axis_letters:
            if letter not in self._slots:
                self.close()
                raise StageConnectionError(
                    f"axis {letter} is not an axis of the controller on {self.url!r} "
                    f"(it has {self.mpos_axes}); pass axis letters that it has "
                    f"(aimbench stage --axes), or leave them out to let the driver choose"
                )

    def _choose_reference(self) -> None:
        """The bench reference in machine units, unless given: bench_fw's fixed 50 mm / 30 deg;
        on a stock Grbl (travel [-$13x, 0]) the middle of each axis' travel."""
        if self.bench_firmware:
            return
        for which, attr in ((0, "x_ref_mm"), (1, "yaw_ref_deg")):
            travel = self._settings.get(130 + self.slot(which))
            if self._ref_override[which] is None and travel:
                setattr(self, attr, -travel / 2.0)

    def slot(self, which: int) -> int:
        """Index in MPos (and in the $1Nk settings) of axis `which`: 0 linear, 1 rotary."""
        return self._slots[self.axis_letters[which]]

    def _hupcl(self) -> bool | None:
        """Whether the port drops DTR on close (None: not a terminal, e.g. loop://)."""
        try:
            fd = self.port.fileno()
            return bool(termios.tcgetattr(fd)[2] & termios.HUPCL)
        except (AttributeError, OSError, termios.error):
            return None

    def close(self) -> None:
        """Close the port (the controller keeps running). With hold_dtr, DTR stays up so the
        next open does not reset the board."""
        if self._ser is not None:
            try:
                if self.hold_dtr and self._hupcl():
                    fd = self._ser.fileno()
                    attrs = termios.tcgetattr(fd)
                    attrs[2] &= ~termios.HUPCL
                    termios.tcsetattr(fd, termios.TCSANOW, attrs)
            except (OSError, termios.error):
                pass
            try:
                self._ser.close()
            finally:
                self._ser = None

    def __enter__(self) -> StageController:
        if self._ser is None:
            self.connect()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    # ---- low level ----------------------------------------------------------------------------

    @property
    def port(self) -> serial.SerialBase:
        if self._ser is None:
            raise StageConnectionError(
                f"the stage controller on {self.url!r} is not connected: call connect() first"
            )
        return self._ser

    def _write(self, data: bytes) -> None:
        try:
            self.port.write(data)
            self.port.flush()
        except (serial.SerialException, OSError) as exc:
            raise StageConnectionError(
                f"writing to the stage controller on {self.url!r} failed: {exc}; "
                "was it unplugged?"
            ) from exc

    def _readline(self, deadline: float) -> str | None:
        """The next line (without its line end), or None at the deadline (time.monotonic)."""
        while True:
            for sep in (b"\n", b"\r"):
                i = self._buf.find(sep)
                if i >= 0:
                    line = bytes(self._buf[:i])
                    del self._buf[: i + 1]
                    text = line.decode("ascii", "replace").strip()
                    if text:
                        return text
                    break
            else:
                if time.monotonic() >= deadline:
                    return None
                try:
                    chunk = self.port.read(max(1, self.port.in_waiting))
                except (serial.SerialException, OSError) as exc:
                    raise StageConnectionError(
                        f"reading from the stage controller on {self.url!r} failed: {exc}; "
                        "was it unplugged?"
                    ) from exc
                self._buf.extend(chunk)
                continue

    def _note(self, line: str) -> None:
        """Record a push message (alarm, [MSG:...], banner)."""
        code = grbl.alarm_code(line)
        if code is not None:
            self.last_alarm = code
        self.messages.append(line)
        del self.messages[:-50]

    def _wait_banner(self, timeout_s: float) -> str | None:
        """Wait for a start-up banner; then collect the messages that follow it briefly."""
        deadline = time.monotonic() + timeout_s
        banner = None
        while banner is None:
            line = self._readline(deadline)
            if line is None:
                return None
            if grbl.banner_version(line):
                banner = line
            else:
                self._note(line)
        self.banner = banner
        quiet = time.monotonic() + 0.15
        while (line := self._readline(quiet)) is not None:
            self._note(line)
        return banner

    def command(self, line: str, timeout_s: float | None = None,
                on_status: Callable[[StageStatus], None] | None = None) -> list[str]:
        """Send one line and wait for its ``ok``; returns the lines printed before it.

        on_status: while waiting, ask for a status report every `STATUS_POLL_S` and call it with
        each (a line that waits long, such as ``$H``, shows where the stages are).
        Raises GrblError on ``error:N``, GrblAlarm if an alarm was raised meanwhile,
        StageTimeout if no reply came, StageResetError if the controller reset meanwhile.
        """
        timeout = self.reply_timeout_s if timeout_s is None else timeout_s
        self._write(line.encode("ascii") + b"\n")
        deadline = time.monotonic() + timeout
        info: list[str] = []
        alarm: int | None = None
        asked = 0  # status queries sent and not answered yet
        next_poll = time.monotonic() + STATUS_POLL_S if on_status is not None else math.inf
        while True:
            reply = self._readline(min(deadline, next_poll))
            if reply is None and time.monotonic() < deadline:  # time to ask where the stages are
                self._write(grbl.STATUS_QUERY)
                asked += 1
                next_poll = time.monotonic() + STATUS_POLL_S
                continue
            if reply is None:
                if alarm is not None:  # a stock Grbl sends no reply after a critical alarm
                    raise GrblAlarm(alarm, f"while executing {line!r}")
                raise StageTimeout(
                    f"no reply to {line!r} from the stage controller on {self.url!r} within "
                    f"{timeout:.1f} s: the reply was lost or the controller hangs; reset it "
                    "(power or Ctrl-X) and check the cable"
                )
            if reply == "ok":
                if alarm is not None:
                    raise GrblAlarm(alarm, f"while executing {line!r}")
                self._collect_reports(asked)
                return info
            code = grbl.error_code(reply)
            if code is not None:
                if alarm is not None:
                    raise GrblAlarm(alarm, f"{line!r} ended with error:{code}")
                raise GrblError(code, line)
            code = grbl.alarm_code(reply)
            if code is not None:
                self._note(reply)
                alarm = code
                deadline = min(deadline, time.monotonic() + 1.0)
                continue
            if grbl.banner_version(reply):
                self.banner = reply
                raise StageResetError(
                    f"the stage controller on {self.url!r} reset while executing {line!r}; "
                    "re-home it before moving"
                )
            if reply.startswith("<"):  # asked for here, or a stale one
                if asked > 0:
                    asked -= 1
                    self._report(reply, on_status)
                continue
            if reply.startswith("[MSG:"):
                self._note(reply)
            info.append(reply)

    def _report(self, line: str, on_status: Callable[[StageStatus], None] | None) -> None:
        """Hand a status report to ``on_status`` (one that cannot be read is skipped: it only
        feeds a display)."""
        if on_status is None:
            return
        try:
            st = self._to_status(grbl.parse_status(line))
        except ValueError:
            return
        on_status(st)

    def _collect_reports(self, asked: int) -> None:
        """Read the replies to status queries still unanswered when a line's ``ok`` came, so
        that the next `status` reads its own report, not one of these."""
        deadline = time.monotonic() + self.reply_timeout_s
        while asked > 0:
            line = self._readline(deadline)
            if line is None:
                return
            if line.startswith("<"):
                asked -= 1
            else:
                self._note(line)

    # ---- state --------------------------------------------------------------------------------

    def status(self, timeout_s: float | None = None) -> StageStatus:
        """Ask for a realtime status report (does not disturb a line in progress)."""
        return self._to_status(self._raw_status(timeout_s))

    def _raw_status(self, timeout_s: float | None = None) -> grbl.GrblStatus:
        timeout = self.reply_timeout_s if timeout_s is None else timeout_s
        self._write(grbl.STATUS_QUERY)
        deadline = time.monotonic() + timeout
        while True:
            line = self._readline(deadline)
            if line is None:
                raise StageTimeout(
                    f"no status report from the stage controller on {self.url!r} within "
                    f"{timeout:.1f} s; check the cable, or reset it"
                )
            if line.startswith("<"):
                try:
                    return grbl.parse_status(line)
                except ValueError as exc:
                    raise StageReplyError(
                        f"the stage controller on {self.url!r} sent a status report that "
                        f"cannot be read ({exc}); check the cable and the baud rate "
                        f"{self.baudrate}") from None
            self._note(line)

    def _to_status(self, st: grbl.GrblStatus) -> StageStatus:
        x_mm, yaw_deg = st.mpos[self.slot(0)], st.mpos[self.slot(1)]
        return StageStatus(
            state=st.state,
            substate=st.substate,
            x_mm=x_mm,
            yaw_deg=yaw_deg,
            x_m=(x_mm - self.x_ref_mm) / 1000.0,
            yaw_rad=math.radians(yaw_deg - self.yaw_ref_deg),
            limits=st.pins,
            raw=st,
        )

    def position(self) -> StagePose:
        """Where the stages are relative to the bench reference, from a status report."""
        st = self.status()
        return StagePose(x_m=st.x_m, yaw_rad=st.yaw_rad)

    def wait_idle(
        self,
        timeout: float = 60.0,
        poll_s: float = 0.02,
        target: tuple[float, float] | None = None,
        on_status: Callable[[StageStatus], None] | None = None,
    ) -> StageStatus:
        """Poll status until the controller is Idle (arrived); returns the final status.

        target: the commanded machine position (x mm, a deg); then Idle only counts once the
        reported position is there too (a stock Grbl may report Idle for a moment before a
        just-accepted move starts), and resting elsewhere for 0.5 s raises StageError.
        on_status: called with every status polled (a progress display of the position).
        Raises GrblAlarm if it is (or goes) into alarm, StageTimeout after `timeout` s.
        """
        deadline = time.monotonic() + timeout
        elsewhere_since: float | None = None
        while True:
            st = self.status()
            if on_status is not None:
                on_status(st)
            now = time.monotonic()
            if st.state == "Idle":
                if target is None or self._at(st, target):
                    return st
                if elsewhere_since is None:
                    elsewhere_since = now
                elif now - elsewhere_since > 0.5:
                    raise StageError(
                        f"the stages came to rest at x={st.x_mm:.4f} mm, a={st.yaw_deg:.4f} deg "
                        f"instead of the commanded x={target[0]:.4f} mm, a={target[1]:.4f} deg; "
                        "the move was cut short: re-home before trusting the position"
                    )
            else:
                elsewhere_since = None
            if st.state == "Alarm":
                where = f"at x={st.x_mm:.3f} mm, a={st.yaw_deg:.3f} deg"
                raise GrblAlarm(self.last_alarm or 0, where)
            if now >= deadline:
                raise StageTimeout(
                    f"the stages did not come to rest within {timeout:.1f} s (state {st.state}, "
                    f"x={st.x_mm:.3f} mm, a={st.yaw_deg:.3f} deg); is a feed hold (!) active?"
                )
            time.sleep(poll_s)

    def _at(self, st: StageStatus, target: tuple[float, float]) -> bool:
        """The status position equals `target` to a step (plus the report's 3-decimal rounding)."""
        for value, goal, which in ((st.x_mm, target[0], 0), (st.yaw_deg, target[1], 1)):
            spu = self._settings.get(100 + self.slot(which))
            tol = (1.0 / spu + 0.001) if spu else 0.005
            if abs(value - goal) > tol:
                return False
        return True

    # ---- commands -----------------------------------------------------------------------------

    def home(self, timeout: float = 120.0,
             on_status: Callable[[StageStatus], None] | None = None) -> StageStatus:
        """Run the homing cycle ($H) and wait until it is done; machine zero is then known.
        on_status: called with every status polled while it homes and until it is Idle."""
        self.last_alarm = None
        self.command("$H", timeout_s=timeout, on_status=on_status)
        return self.wait_idle(timeout, on_status=on_status)

    def unlock(self) -> None:
        """Leave the alarm state without homing ($X); the position is then trusted as is."""
        self.command("$X")

    def _move(
        self,
        words: str,
        wait: bool,
        timeout: float | None,
        estimate_s: float,
        target: tuple[float, float] | None,
        on_status: Callable[[StageStatus], None] | None = None,
    ) -> None:
        self.last_alarm = None
        self.command(words)
        if wait:
            limit = timeout if timeout is not None else 2.0 * estimate_s + 5.0
            self.wait_idle(limit, target=target, on_status=on_status)

    def move_to(
        self, *, x_m: float, yaw_rad: float, wait: bool = True, timeout: float | None = None,
        on_status: Callable[[StageStatus], None] | None = None,
    ) -> None:
        """Rapid move (G0) to x (m) and yaw (rad) relative to the bench reference.

        With wait, returns once the stages are at rest there (raises on alarm or timeout);
        on_status is called with every status polled meanwhile (`wait_idle`).
        """
        x_mm = self._quantize(self.x_ref_mm + x_m * 1000.0, 0)
        yaw_deg = self._quantize(self.yaw_ref_deg + math.degrees(yaw_rad), 1)
        lx, la = self.axis_letters
        estimate = self._estimate_s(x_mm, yaw_deg, relative=False)
        self._move(
            f"G90G0{lx}{grbl.format_number(x_mm)}{la}{grbl.format_number(yaw_deg)}",
            wait, timeout, estimate, (x_mm, yaw_deg), on_status,
        )

    def move_by(
        self, *, dx_m: float, dyaw_rad: float, wait: bool = True, timeout: float | None = None
    ) -> None:
        """Relative rapid move (G91 G0) by dx (m) and dyaw (rad)."""
        dx_mm = self._quantize(dx_m * 1000.0, 0)
        dyaw_deg = self._quantize(math.degrees(dyaw_rad), 1)
        lx, la = self.axis_letters
        estimate = self._estimate_s(dx_mm, dyaw_deg, relative=True)
        target = None
        if wait:
            here = self.status()
            target = (here.x_mm + dx_mm, here.yaw_deg + dyaw_deg)
        self._move(
            f"G91G0{lx}{grbl.format_number(dx_mm)}{la}{grbl.format_number(dyaw_deg)}",
            wait, timeout, estimate, target,
        )

    def _quantize(self, value: float, which: int) -> float:
        """`value` (machine units) rounded to a whole step of axis `which` (0 linear, 1 rotary),
        half a step up, when the steps per unit are known: the controller then receives a value
        that is a step exactly, so no decimal rounding on the wire can flip a step."""
        spu = self._settings.get(100 + self.slot(which))
        if not spu:
            return value
        return math.floor(value * spu + 0.5) / spu

    def _estimate_s(self, x: float, a: float, relative: bool) -> float:
        """A generous estimate of a move's duration from the settings (s), for the timeout."""
        ix, ia = self.slot(0), self.slot(1)
        s = self._settings
        try:
            travel = (s[130 + ix], s[130 + ia])
            rate = (s[110 + ix] / 60.0, s[110 + ia] / 60.0)
            accel = (s[120 + ix], s[120 + ia])
        except KeyError:
            return 60.0
        dist = (abs(x), abs(a)) if relative else travel
        return max(trapezoid_time(d, v, acc) for d, v, acc in zip(dist, rate, accel, strict=True))

    def stop(self) -> None:
        """Feed hold (!): decelerate to a stop, keeping the rest of the move; `resume` goes on."""
        self._write(grbl.FEED_HOLD)

    def resume(self) -> None:
        """Cycle start (~): continue after a feed hold."""
        self._write(grbl.CYCLE_START)

    def reset(self, timeout: float | None = None) -> str:
        """Soft reset (Ctrl-X): stop at once, drop queued moves; returns the new banner.

        A reset during a move leaves the controller in ALARM:3 (position not guaranteed).
        """
        self._buf.clear()
        self._write(grbl.SOFT_RESET)
        banner = self._wait_banner(self.reply_timeout_s if timeout is None else timeout)
        if banner is None:
            raise StageTimeout(
                f"no banner after a soft reset of the stage controller on {self.url!r}"
            )
        return banner

    @property
    def cached_settings(self) -> dict[int, float]:
        """The settings as last read ($$ at connect, then kept up to date by set_setting),
        without asking the controller; {} if they could not be read."""
        return dict(self._settings)

    def settings(self) -> dict[int, float]:
        """All settings ($$) as {number: value}."""
        out: dict[int, float] = {}
        for line in self.command("$$"):
            item = grbl.parse_setting(line)
            if item is not None:
                out[item[0]] = item[1]
        self._settings = dict(out)
        return out

    def set_setting(self, number: int, value: float) -> None:
        """Write setting $number=value (kept in the controller's EEPROM)."""
        self.command(f"${int(number)}={grbl.format_number(value)}")
        self._settings[int(number)] = float(value)


def trapezoid_time(distance: float, rate: float, accel: float) -> float:
    """Duration (s) of a move over `distance` with a trapezoidal speed profile from rest to rest,
    cruise `rate` and acceleration `accel` (any consistent units, e.g. deg, deg/s, deg/s^2)."""
    if distance <= 0.0:
        return 0.0
    if distance >= rate * rate / accel:
        return distance / rate + rate / accel
    return 2.0 * math.sqrt(distance / accel)
