"""Shared fixtures. Tests find data relative to this file, never the working directory."""

from __future__ import annotations

import json
import socket
from pathlib import Path

import pytest

TESTS_DIR = Path(__file__).resolve().parent
REPO_DIR = TESTS_DIR.parent
DATA_DIR = TESTS_DIR / "data"
#: Each long test file's seconds as a run measured them (`tools/test_costs.py` refreshes it).
COSTS = TESTS_DIR / "costs.json"


def free_udp_port() -> int:
    """A UDP port on 127.0.0.1 that nothing holds now (the OS picks it), for a test's sender."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


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


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """The test files dearest first (tests/costs.json; the others after, in their own order).

    `make test` hands whole files to two workers in the collection's order (--dist loadfile
    --no-loadscope-reorder): a long file started last runs alone while the other worker is
    idle. xdist's own order, most tests first, started the study on Ray (3 tests, 4 min) near
    the end. Deterministic, as xdist requires: every worker collects the same order."""
    cost = json.loads(COSTS.read_text(encoding="utf-8")) if COSTS.exists() else {}
    items.sort(key=lambda item: -cost.get(item.location[0], 0.0))
