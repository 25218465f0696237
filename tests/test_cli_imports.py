"""Issue 38: every command's parser (``aimbench CMD --help``) within 0.5 s. A parser that imports
numpy, pydantic, MuJoCo or the estimator cannot keep that on a loaded machine, so each command
module keeps at its top only what its parser needs; what its work needs is imported where it runs
(benchmarks/bench_cli.py measures the times themselves)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from scenarios.cli import command_names

REPO = Path(__file__).resolve().parents[1]

#: Modules no command's parser may import, and what each costs a start (CPU, a quiet machine).
HEAVY = (
    "numpy",  # 0.15 s
    "pydantic",  # the station model: 0.35-0.5 s with it
    "mujoco",  # the twin, 0.3 s
    "scipy",
    "numba",
    "tqdm",  # scenarios.progress' bars
    "align.api",  # the estimator (numba kernels, scipy)
    "align.result",  # align.Hints: numpy
    "ouster.sdk",  # OSF files (twin.lidar.ouster_sdk): its C++ bindings, 0.5 s with numpy
)
#: A command whose parser truly needs one of HEAVY, and why (none does today).
ALLOWED: dict[str, tuple[str, ...]] = {}


def _loaded_by_parser(load: str | None) -> list[str]:
    """The HEAVY modules a fresh process holds after building the parser with ``load``."""
    code = ("import json, sys\n"
            "from scenarios.cli import build_parser\n"
            f"build_parser(load={load!r})\n"
            f"print(json.dumps([m for m in {HEAVY!r} if m in sys.modules]))")
    res = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True,
                         timeout=120)
    assert res.returncode == 0, res.stderr
    return json.loads(res.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("name", command_names())
def test_a_commands_parser_imports_none_of_the_heavy_modules(name: str):
    loaded = set(_loaded_by_parser(name)) - set(ALLOWED.get(name, ()))
    assert not loaded, (f"building `aimbench {name}`'s parser imports {sorted(loaded)}: move "
                        "that import into the function that runs (or the constant the parser "
                        "needs into a light module)")


def test_the_top_level_parser_imports_none_of_the_heavy_modules():
    assert _loaded_by_parser(None) == []


def test_the_light_name_lists_are_the_models_names():
    """The parsers' choices (twin.core.sensor_names, twin.lidar.format_names) are the names the
    models, conventions and renderer are built under, in the same order."""
    from twin.core import sensor_names
    from twin.core.sensors import MODELS
    from twin.lidar.conventions import CONVENTIONS
    from twin.lidar.format_names import CLOUD_CONVENTIONS
    from twin.lidar.hesai import HESAI_MODELS

    assert tuple(MODELS) == sensor_names.VELODYNE_NAMES
    assert tuple(HESAI_MODELS) == sensor_names.HESAI_NAMES
    assert tuple(CONVENTIONS) == CLOUD_CONVENTIONS
