"""The fuzz suites' budget and tally (tests/test_fuzz.py, tests/test_decode_fuzz.py).

In CI (no environment variable) every property runs a bounded number of examples, derandomized
(hypothesis draws them from the test's name: the same inputs on every run, so a failure is
reproducible and the suite's time is bounded). The long run (tools/fuzz.py) sets
``AIMBENCH_FUZZ_EXAMPLES`` (examples per property) and pytest's ``--hypothesis-seed``, and
``AIMBENCH_FUZZ_REPORT``: a JSON file this module writes at exit with, per target, the inputs
tried, the slowest input (s) and the inputs slower than `HANG_S` (hangs).
"""

from __future__ import annotations

import atexit
import contextlib
import json
import os
import time
from collections.abc import Iterator
from pathlib import Path

from hypothesis import HealthCheck, settings

#: Examples per property and run when no budget is set (CI).
BUDGET = int(os.environ.get("AIMBENCH_FUZZ_EXAMPLES", "0") or 0)
#: An input that takes longer than this is counted as a hang (s).
HANG_S = 10.0

_TALLY: dict[str, dict[str, float]] = {}


def fuzz(ci_examples: int) -> settings:
    """Hypothesis settings: `ci_examples` derandomized examples, or the long run's budget."""
    return settings(max_examples=BUDGET or ci_examples, deadline=None, derandomize=not BUDGET,
                    database=None, print_blob=True,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                           HealthCheck.filter_too_much])


@contextlib.contextmanager
def fuzz_input(target: str) -> Iterator[None]:
    """Count one input of `target` and how long it took."""
    t0 = time.monotonic()
    try:
        yield
    finally:
        dt = time.monotonic() - t0
        t = _TALLY.setdefault(target, {"inputs": 0, "slowest_s": 0.0, "hangs": 0})
        t["inputs"] += 1
        t["slowest_s"] = max(t["slowest_s"], dt)
        t["hangs"] += int(dt > HANG_S)


def _write_report() -> None:
    path = os.environ.get("AIMBENCH_FUZZ_REPORT")
    if path and _TALLY:
        Path(path).write_text(json.dumps(_TALLY, indent=1, sort_keys=True), encoding="utf-8")


atexit.register(_write_report)
