"""The firmware builds with Debian's AVR toolchain and fits; the host-side unit tests (g++) of its
parser, planner and settings pass; the simavr harness builds."""

from __future__ import annotations

import re
import subprocess

from bench_fw import FIRMWARE_DIR
from twin.stage.hil import build_lock


def make(*targets: str) -> subprocess.CompletedProcess[str]:
    # under the harness's lock: another test worker may be building bench_fw for simavr
    with build_lock():
        return subprocess.run(["make", "-C", str(FIRMWARE_DIR), *targets], capture_output=True,
                              text=True, timeout=600)


def test_firmware_builds_and_fits() -> None:
    out = make("all")
    assert out.returncode == 0, out.stdout + out.stderr
    # The size report: flash and RAM of the ATmega2560.
    size = make("size")
    m = re.search(r"flash (\d+) of 253952 bytes .* RAM (\d+) of 8192 bytes", size.stdout)
    assert m, size.stdout
    flash, ram = int(m.group(1)), int(m.group(2))
    assert flash < 64 * 1024, "the firmware should stay small"
    assert ram < 4096, "leave half the RAM for the stack"
    assert (FIRMWARE_DIR / "build" / "bench_fw.hex").exists()


def test_firmware_compiles_without_warnings() -> None:
    out = make("warnings")  # -Wall -Wextra -Werror on every module
    assert out.returncode == 0, out.stdout + out.stderr


def test_host_unit_tests_pass() -> None:
    out = make("test")
    assert out.returncode == 0, out.stdout + out.stderr
    m = re.search(r"unit_tests: (\d+) tests, (\d+) checks, (\d+) failed", out.stdout)
    assert m, out.stdout
    assert int(m.group(1)) >= 19 and int(m.group(3)) == 0


def test_harness_builds() -> None:
    out = make("harness")
    assert out.returncode == 0, out.stdout + out.stderr
    assert (FIRMWARE_DIR / "build" / "harness" / "bench_hil").exists()
