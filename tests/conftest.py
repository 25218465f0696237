"""Shared fixtures. Tests find data relative to this file, never the working directory."""

from __future__ import annotations

from pathlib import Path

import pytest

TESTS_DIR = Path(__file__).resolve().parent
REPO_DIR = TESTS_DIR.parent
DATA_DIR = TESTS_DIR / "data"


@pytest.fixture(scope="session")
def sample_pcap() -> Path:
    """The real VLP-16 capture (see tests/data/SOURCE.md)."""
    return DATA_DIR / "vlp16-strongest-10hz.pcap"


def pytest_addoption(parser: pytest.Parser) -> None:
    """--port: run the stage-controller protocol suite (tests/test_stage_*.py) against a real
    board on that serial port instead of the firmware in simavr."""
    parser.addoption(
        "--port",
        default=None,
        help="serial port of a real stage controller (e.g. /dev/ttyACM0) for the stage protocol "
        "tests; default: the firmware in simavr",
    )
