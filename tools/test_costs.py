"""Refresh tests/costs.json, each test file's seconds as a run measured them, from a pytest log
with ``--durations=0`` (or ``--durations=N``: the files it leaves out count as cheap).

    .venv/bin/python -m pytest -n 2 --dist loadfile --no-loadscope-reorder --durations=0 \\
        | tee /tmp/pytest.log
    .venv/bin/python tools/test_costs.py /tmp/pytest.log

tests/conftest.py hands the files to the two workers dearest first (`pytest_collection_
modifyitems`): xdist's default order, most tests first, started the study on Ray (3 tests,
4 min) last, and one worker ran it alone for minutes while the other had finished. The table
need not be exact, only keep the few long files ahead of the many short ones.
"""

from __future__ import annotations

import argparse
import json
import re
from collections import defaultdict
from pathlib import Path

COSTS = Path(__file__).resolve().parents[1] / "tests" / "costs.json"
#: A duration line: "12.34s call     tests/test_x.py::test_y[param]".
LINE = re.compile(r"^\s*([0-9.]+)s\s+(setup|call|teardown)\s+(tests/[^:]+\.py)::")
#: Files below this many seconds are left out of the table (their order does not matter).
MIN_S = 5.0


def costs(log: str) -> dict[str, float]:
    """Seconds per test file (setup, call and teardown summed), dearest first."""
    total: dict[str, float] = defaultdict(float)
    for line in log.splitlines():
        m = LINE.match(line)
        if m:
            total[m.group(3)] += float(m.group(1))
    return {f: round(s, 1) for f, s in sorted(total.items(), key=lambda kv: -kv[1])
            if s >= MIN_S}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("log", type=Path, help="a pytest log with --durations")
    args = p.parse_args()
    table = costs(args.log.read_text(encoding="utf-8", errors="replace"))
    COSTS.write_text(json.dumps(table, indent=1) + "\n", encoding="utf-8")
    print(f"{COSTS}: {len(table)} files, {sum(table.values()):.0f} s")


if __name__ == "__main__":
    main()
