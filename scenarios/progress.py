"""Progress of a long command: a tqdm bar on a terminal, plain lines in a log.

Every command that runs long (sweep and demo through `scenarios.runner.Progress`, replay,
calibrate, decode and info on big captures) reports through `Bar`, so they all look and behave
the same: on a terminal a bar that redraws in place (tqdm: rate, ETA, and a status text after
it); elsewhere (a pipe, a file, CI) one whole line per milestone, each ending in a newline, so
lines never run together and logs stay short. Why tqdm: it is small, pure Python, already what
the RL and data tools next to aimbench use, and it handles terminal width, redraw rate and
messages printed above the bar (`Bar.write`).
"""

from __future__ import annotations

import math
import os
import sys
from typing import Any, TextIO

from tqdm import tqdm


def is_terminal(stream: TextIO) -> bool:
    """Whether ``stream`` is a terminal a bar can redraw on (one that says it is 0 columns wide,
    as a pseudo-terminal without a size does, cannot show one: it gets lines)."""
    isatty = getattr(stream, "isatty", None)
    try:
        if not (isatty and isatty()):
            return False
        return os.get_terminal_size(stream.fileno()).columns > 0
    except (ValueError, OSError, AttributeError):  # closed, or no file behind it
        return False


class Bar:
    """One job of ``total`` ``unit``s (None: unknown), titled ``desc``.

    On a terminal: a tqdm bar on ``stream`` (default stderr). Elsewhere: a line
    ``desc: done/total unit`` (with the status, if any) every ``every`` units and at the end, or
    with ``every=None`` only the lines the caller writes (`write`). ``enabled=False``: nothing
    at all. ``tty`` overrides the terminal test (for tests). ``estimated``: the total is a guess
    (e.g. from a file's size), set to what was done when the bar closes.
    """

    def __init__(self, total: int | None, desc: str, unit: str = "scans", *,
                 stream: TextIO | None = None, enabled: bool = True, every: int | None = 0,
                 initial: int = 0, tty: bool | None = None, estimated: bool = False) -> None:
        self.stream = stream if stream is not None else sys.stderr
        self.total, self.desc, self.unit = total, desc, unit
        self.enabled = enabled
        self.estimated = estimated
        self.tty = enabled and (is_terminal(self.stream) if tty is None else tty)
        self.done = int(initial)
        self.status = ""
        # every=0: about ten lines per job (every 100 units when the total is unknown).
        self.every = every if every != 0 else max(1, -(-(total or 1000) // 10))
        self._printed = self.done
        self._bar = (tqdm(total=total, desc=desc, unit=f" {unit}", file=self.stream,
                          initial=self.done, dynamic_ncols=True, mininterval=0.1, leave=True)
                     if self.tty else None)

    def update(self, n: int = 1, status: str | None = None) -> None:
        """``n`` more units done; ``status``: the text shown after the bar (and in the lines)."""
        before, self.done = self.done, self.done + n
        if status is not None:
            self.status = status
        if self._bar is not None:
            if status is not None:
                self._bar.set_postfix_str(status, refresh=False)
            self._bar.update(n)
        elif self.enabled and self.every and (self.done // self.every > before // self.every
                                              or self.done == self.total):
            self._line()

    def set_status(self, status: str) -> None:
        """Change the status text without counting anything."""
        self.status = status
        if self._bar is not None:
            self._bar.set_postfix_str(status)

    def write(self, text: str) -> None:
        """A whole line: above the bar on a terminal, as it is elsewhere."""
        if not self.enabled:
            return
        if self._bar is not None:
            self._bar.write(text, file=self.stream)
        else:
            self.stream.write(text + "\n")
            self.stream.flush()

    def _line(self) -> None:
        of = f"/{self.total}" if self.total is not None and not self.estimated else ""
        self.write(f"{self.desc}: {self.done}{of} {self.unit}"
                   + (f" | {self.status}" if self.status else ""))
        self._printed = self.done

    def close(self) -> None:
        """End the bar (a last line elsewhere, unless the last one said it all); idempotent."""
        if self._bar is not None:
            if self.estimated:
                self._bar.total = self.done
            self._bar.close()
            self._bar = None
        elif self.enabled and self.every and self._printed != self.done:
            self._line()
        self.enabled = False

    def __enter__(self) -> Bar:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class StageMotion:
    """The stages' position while they home or move (a callable for
    `twin.stage.controller.StageController`'s ``on_status``): on a terminal a bar whose text
    follows the stages, elsewhere a line every ten status reports (about one a second)."""

    def __init__(self, desc: str, enabled: bool = True, stream: TextIO | None = None) -> None:
        self.bar = Bar(None, desc, unit="reports", every=10, enabled=enabled, stream=stream)

    def __call__(self, st: Any) -> None:
        """``st``: a `twin.stage.controller.StageStatus` (relative to the bench reference)."""
        self.bar.update(1, status=f"{st.state}  x {st.x_m * 1000.0:+8.3f} mm  "
                                  f"yaw {math.degrees(st.yaw_rad):+8.4f} deg")

    def close(self) -> None:
        self.bar.close()

    def __enter__(self) -> StageMotion:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
