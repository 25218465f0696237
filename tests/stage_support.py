"""Shared pieces of the stage-controller tests (tests/test_stage_*.py).

The stage tests run against the real firmware in simavr (`twin.stage.hil.SimavrHarness`) by default,
or against a real board with ``pytest --port /dev/ttyACM0``. `RawLink` is a line-level Grbl client
with no interpretation, so protocol tests can state exact command/response tables.
"""

from __future__ import annotations

import re
import termios
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import pytest
import serial

from twin.stage import grbl
from twin.stage.hil import SimavrHarness

#: Where the simulated stages stand at power-up (mm, deg from home): close, so homing is quick.
START_X_MM = 2.0
START_A_DEG = 2.0
STEPS_PER_MM = 400
STEPS_PER_DEG = 800
FINAL = re.compile(r"^(ok|error:\d+)$")


class RawLink:
    """A Grbl line client over pyserial: send a line, get every line up to its ok/error."""

    def __init__(self, url: str) -> None:
        self.url = url
        self.ser = serial.serial_for_url(url, baudrate=115200, timeout=0.01)
        self.buf = bytearray()
        self.pushed: list[str] = []  # lines that were not the awaited reply

    def close(self) -> None:
        self.ser.close()

    def reopen(self) -> list[str]:
        """Close and open the port again, as a host does; returns the boot lines.

        The pause lets the harness see the port closed (it polls every 0.2 ms of simulated
        time), like the real DTR line needs to drop to reset a Mega.
        """
        attrs = termios.tcgetattr(self.ser.fileno())
        attrs[2] |= termios.HUPCL  # drop DTR on close, so the open raises it: a reset
        termios.tcsetattr(self.ser.fileno(), termios.TCSANOW, attrs)
        self.ser.close()
        time.sleep(0.1)
        self.ser = serial.serial_for_url(self.url, baudrate=115200, timeout=0.01)
        self.buf = bytearray()
        return self.wait_banner(timeout=10.0)

    def boot_lines(self, timeout: float = 5.0) -> list[str]:
        """The banner after opening; a board that did not reset on open is soft-reset."""
        try:
            return self.wait_banner(timeout=timeout)
        except AssertionError:
            return self.reset()

    def readline(self, timeout: float) -> str | None:
        deadline = time.monotonic() + timeout
        while True:
            i = self.buf.find(b"\n")
            if i >= 0:
                line = self.buf[:i].decode("ascii", "replace").strip()
                del self.buf[: i + 1]
                if line:
                    return line
                continue
            if time.monotonic() > deadline:
                return None
            self.buf.extend(self.ser.read(max(1, self.ser.in_waiting)))

    def drain(self, quiet: float = 0.2, limit: float = 10.0) -> list[str]:
        """All lines until none arrives for `quiet` s (at most `limit` s)."""
        out: list[str] = []
        end = time.monotonic() + limit
        while time.monotonic() < end:
            line = self.readline(quiet)
            if line is None:
                break
            out.append(line)
        return out

    def write(self, data: bytes) -> None:
        self.ser.write(data)
        self.ser.flush()

    def send(self, line: str | bytes, timeout: float = 3.0) -> list[str]:
        """Send one line; return every line received up to and including its ok/error:N."""
        data = line.encode("latin-1") if isinstance(line, str) else line
        self.write(data + b"\n")
        out: list[str] = []
        while True:
            reply = self.readline(timeout)
            if reply is None:
                raise AssertionError(f"no ok/error for {line!r} within {timeout} s; got {out}")
            if reply.startswith("<"):
                continue
            out.append(reply)
            if FINAL.match(reply):
                return out

    def status(self, timeout: float = 2.0) -> grbl.GrblStatus:
        self.write(b"?")
        while True:
            line = self.readline(timeout)
            if line is None:
                raise AssertionError("no status report")
            if line.startswith("<"):
                return grbl.parse_status(line)
            self.pushed.append(line)

    def status_line(self, timeout: float = 2.0) -> str:
        self.write(b"?")
        while True:
            line = self.readline(timeout)
            if line is None:
                raise AssertionError("no status report")
            if line.startswith("<"):
                return line
            self.pushed.append(line)

    def wait_state(self, state: str, timeout: float = 10.0) -> grbl.GrblStatus:
        deadline = time.monotonic() + timeout
        while True:
            st = self.status()
            if st.state == state:
                return st
            if time.monotonic() > deadline:
                raise AssertionError(f"state {st.state}, not {state}, after {timeout} s")
            time.sleep(0.02)

    def wait_banner(self, timeout: float = 5.0) -> list[str]:
        """Lines up to the banner and those that follow it at once."""
        out: list[str] = []
        deadline = time.monotonic() + timeout
        while True:
            line = self.readline(max(0.0, deadline - time.monotonic()))
            if line is None:
                raise AssertionError(f"no banner within {timeout} s; got {out}")
            out.append(line)
            if grbl.banner_version(line):
                return out + self.drain(quiet=0.15)

    def reset(self) -> list[str]:
        """Ctrl-X; returns the lines up to and after the new banner."""
        self.write(grbl.SOFT_RESET)
        return self.wait_banner()

    def prepare(self, homed: bool) -> None:
        """A known state: soft reset, unlocked (or homed), Idle, parser at power-up defaults."""
        self.drain(quiet=0.05, limit=1.0)
        self.reset()
        if homed:
            assert self.send("$H", timeout=60)[-1] == "ok"
        elif self.status().state == "Alarm":
            assert self.send("$X")[-1] == "ok"
        assert self.status().state == "Idle"


def expect(lines: Sequence[str], patterns: Sequence[str]) -> None:
    """Every line matches its pattern (full match), and there are as many lines as patterns."""
    assert len(lines) == len(patterns), f"{lines} vs {patterns}"
    for line, pat in zip(lines, patterns, strict=True):
        assert re.fullmatch(pat, line), f"{line!r} does not match {pat!r} (all: {lines})"


@dataclass
class Bench:
    """The device under test: the simavr harness (hil) or a real board (hil is None)."""

    url: str
    hil: SimavrHarness | None

    def need_hil(self) -> SimavrHarness:
        if self.hil is None:
            pytest.skip("needs the simavr harness to observe the step pulses (not on a real board)")
        return self.hil

    def pulses(self) -> tuple[int, int] | None:
        return None if self.hil is None else self.hil.positions().pulses


@pytest.fixture(scope="module")
def bench(request: pytest.FixtureRequest) -> Iterator[Bench]:
    port = request.config.getoption("--port")
    if port:
        yield Bench(url=port, hil=None)
        return
    with SimavrHarness(start_x_mm=START_X_MM, start_a_deg=START_A_DEG) as hil:
        yield Bench(url=hil.url, hil=hil)


# ---- a stock grbl-Mega 1.1g at the wire level -------------------------------------------------

#: grbl-Mega 1.1g's defaults (grbl/defaults.h, DEFAULTS_GENERIC) with the bench's axis values on X
#: and Y (the rotary stage wired to Y's pins): $$ lists them in this order, as report.c does.
STOCK_SETTINGS: dict[int, str] = {
    0: "10", 1: "25", 2: "0", 3: "0", 4: "0", 5: "0", 6: "0", 10: "1", 11: "0.010",
    12: "0.002", 13: "0", 20: "0", 21: "0", 22: "1", 23: "3", 24: "25.000", 25: "500.000",
    26: "250", 27: "1.000", 30: "1000", 31: "0", 32: "0",
    100: "400.000", 101: "800.000", 102: "250.000", 110: "600.000", 111: "1200.000",
    112: "500.000", 120: "50.000", 121: "40.000", 122: "10.000", 130: "100.000",
    131: "60.000", 132: "200.000",
}


class StockGrblMega:
    """A stock grbl-Mega 1.1g as a host sees it on the wire, on a real pty: its banner on open,
    its replies (text taken from grbl-Mega's report.c and system.c) and a machine position that
    jumps to each target (no motion model). Why not the real one: its GPLv3 source cannot be
    fetched or vendored here, and bench_fw built with three axes would answer in bench_fw's own
    formats (no WCO, error:15 for soft limits), so it would test the driver against itself."""

    BANNER = "Grbl 1.1g ['$' for help]"

    def __init__(self) -> None:
        import os
        import pty
        import threading

        self._os = os
        self.master, slave = pty.openpty()
        attrs = termios.tcgetattr(slave)
        attrs[3] &= ~(termios.ECHO | termios.ICANON)  # raw: no echo, no line editing
        attrs[1] &= ~termios.OPOST
        termios.tcsetattr(slave, termios.TCSANOW, attrs)
        self.url = os.ttyname(slave)
        os.close(slave)
        self.state = "Alarm"  # $22=1 and HOMING_INIT_LOCK: locked until $H or $X
        self.mpos = [0.0, 0.0, 0.0]
        self.received: list[str] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self._os.close(self.master)

    def _send(self, text: str) -> None:
        self._os.write(self.master, text.replace("\n", "\r\n").encode())

    def _serve(self) -> None:
        import select

        poller = select.poll()
        poller.register(self.master, select.POLLIN)
        opened = False
        buf = b""
        while not self._stop.is_set():
            events = dict(poller.poll(10))
            hung_up = bool(events.get(self.master, 0) & select.POLLHUP)
            if hung_up:  # no host has the port open
                opened = False
                time.sleep(0.01)
                continue
            if not opened:  # a host opened it: a Mega resets (DTR) and greets it, as in main.c
                opened = True
                time.sleep(0.05)
                self._send(f"\n{self.BANNER}\n")
                if self.state == "Alarm":
                    self._send("[MSG:'$H'|'$X' to unlock]\n")
            if not events:
                continue
            try:
                buf += self._os.read(self.master, 1024)
            except OSError:
                continue
            while buf:
                if buf[:1] == b"?":
                    buf = buf[1:]
                    self._send(self._status() + "\n")
                    continue
                if buf[:1] == b"\x18":
                    buf = buf[1:]
                    self._send(f"\n{self.BANNER}\n")
                    if self.state == "Alarm":
                        self._send("[MSG:'$H'|'$X' to unlock]\n")
                    continue
                i = buf.find(b"\n")
                if i < 0:
                    break
                line, buf = buf[:i].decode().strip().upper().replace(" ", ""), buf[i + 1:]
                self.received.append(line)
                for reply in self._line(line):
                    self._send(reply + "\n")

    def _status(self) -> str:
        pos = ",".join(f"{v:.3f}" for v in self.mpos)
        return f"<{self.state}|MPos:{pos}|FS:0,0|WCO:0.000,0.000,0.000>"

    def _line(self, line: str) -> list[str]:
        if line == "$I":
            return ["[VER:1.1g.20180813.Mega:]", "[OPT:VNM+,35,255]", "ok"]
        if line == "$$":
            return [f"${n}={v}" for n, v in STOCK_SETTINGS.items()] + ["ok"]
        if line == "$X":
            was = self.state
            self.state = "Idle"
            return ["[MSG:Caution: Unlocked]", "ok"] if was == "Alarm" else ["ok"]
        if line == "$H":
            # limits.c: homed toward the min end ($23 bit set) the position is -travel + pull-off.
            for k in range(3):
                travel = float(STOCK_SETTINGS[130 + k])
                self.mpos[k] = -travel + 1.0
            self.state = "Idle"
            return ["ok"]
        if line.startswith("$"):
            m = re.fullmatch(r"\$(\d+)=(-?[\d.]+)", line)
            if m and int(m.group(1)) in STOCK_SETTINGS:
                STOCK_SETTINGS[int(m.group(1))] = m.group(2)
                return ["ok"]
            return ["error:3"]
        if self.state == "Alarm":
            return ["error:9"]
        absolute = "G91" not in line
        words = dict(re.findall(r"([A-Z])(-?[\d.]+)", line))
        if any(letter in words for letter in "ABC"):
            return ["error:20"]  # a 3-axis build has no A, B, C: unsupported command
        for k, letter in enumerate("XYZ"):
            if letter in words:
                v = float(words[letter])
                self.mpos[k] = v if absolute else self.mpos[k] + v
        return ["ok"]
