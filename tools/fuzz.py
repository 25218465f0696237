"""The long fuzz run: every property of the fuzz suites with a large, seeded budget.

    .venv/bin/python tools/fuzz.py [--examples N] [--seed S] [--only PATTERN]

runs tests/test_decode_fuzz.py and tests/test_fuzz.py under pytest with N examples per property
(default 2000) drawn from seed S (default 0; the same seed draws the same inputs), then prints
per target the inputs tried, the slowest input and the hangs (inputs over tests/fuzzing.py's
HANG_S), and the crashes: every property that failed (hypothesis shrinks each to its smallest
input and prints it, with the blob to reproduce it). Exit code: pytest's. CI runs the same
properties with a small derandomized budget (tests/fuzzing.py).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SUITES = ("tests/test_decode_fuzz.py", "tests/test_fuzz.py")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--examples", type=int, default=2000, help="examples per property")
    ap.add_argument("--seed", type=int, default=0, help="hypothesis seed")
    ap.add_argument("--only", help="pytest -k expression: some properties only")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        report = Path(tmp) / "tally.json"
        junit = Path(tmp) / "junit.xml"
        env = {**os.environ, "AIMBENCH_FUZZ_EXAMPLES": str(args.examples),
               "AIMBENCH_FUZZ_REPORT": str(report)}
        cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
               f"--hypothesis-seed={args.seed}", f"--junitxml={junit}", "-o", "timeout=0",
               *SUITES]
        if args.only:
            cmd += ["-k", args.only]
        t0 = time.monotonic()
        rc = subprocess.call(cmd, cwd=REPO, env=env)
        wall = time.monotonic() - t0
        tally = json.loads(report.read_text()) if report.exists() else {}
        failed = _failures(junit)
    print(f"\nfuzz run: {args.examples} examples per property, seed {args.seed}, "
          f"{wall:.0f} s")
    print(f"{'target':40} {'inputs':>8} {'slowest s':>10} {'hangs':>6}")
    for name, t in sorted(tally.items()):
        print(f"{name:40} {t['inputs']:8d} {t['slowest_s']:10.2f} {t['hangs']:6d}")
    total = sum(t["inputs"] for t in tally.values())
    hangs = sum(t["hangs"] for t in tally.values())
    print(f"{'total':40} {total:8d} {'':10} {hangs:6d}")
    print(f"crashes (failed properties): {len(failed)}" + "".join(f"\n  {f}" for f in failed))
    return rc


def _failures(junit: Path) -> list[str]:
    """The properties that failed (not the expected failures), from pytest's JUnit report."""
    import xml.etree.ElementTree as ET

    if not junit.exists():
        return ["pytest wrote no report"]
    out = []
    for case in ET.parse(junit).iter("testcase"):
        if case.find("failure") is not None or case.find("error") is not None:
            out.append(f"{case.get('classname')}.{case.get('name')}")
    return out


if __name__ == "__main__":
    sys.exit(main())
