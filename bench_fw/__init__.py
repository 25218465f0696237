"""The stage controller's Arduino Mega firmware and its simavr harness (data: C/C++ sources)."""

from pathlib import Path

FIRMWARE_DIR = Path(__file__).resolve().parent
