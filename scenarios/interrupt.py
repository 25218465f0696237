"""Ctrl-C and SIGTERM as a request to stop between units of work (scans, study tasks).

A run or a study checks `StopFlag.stop` between its scans or tasks and ends cleanly with what it
committed; a second Ctrl-C or SIGTERM raises `KeyboardInterrupt` at once (still safe: a store's
transaction is atomic). The sweep's runner and the study's dealer share it.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Callable
from typing import Any


class StopFlag:
    """SIGINT/SIGTERM set a flag the loop checks between scans; a second one interrupts (a
    scan that never ends, as one of a station with NaN in it did, must not make SIGTERM
    ignored).

    on_first: called at the first signal (e.g. to say that the run is stopping).
    """

    def __init__(self, on_first: Callable[[], None]) -> None:
        self.stop = False
        #: The signal's name (``SIGINT``...), None until one came.
        self.signal: str | None = None
        self._on_first = on_first
        self._saved: dict[int, Any] = {}

    def _handler(self, signum: int, frame: object) -> None:
        if self.stop:
            raise KeyboardInterrupt
        self.stop = True
        self.signal = signal.Signals(signum).name
        self._on_first()

    def __enter__(self) -> StopFlag:
        # Signal handlers can only be set from the main thread; elsewhere (a test calling the
        # runner from a worker) the loop still honours `stop` set directly.
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._saved[sig] = signal.signal(sig, self._handler)
        return self

    def __exit__(self, *exc: object) -> None:
        for sig, handler in self._saved.items():
            signal.signal(sig, handler)
