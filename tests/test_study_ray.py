"""The study on Ray, for real: a local Ray started by the test with two CPUs runs the same small
study as the local engine and stores the very same results; a Ray worker SIGKILLed mid-study has
its task retried by Ray, nothing lost or doubled; the project reaches a cluster's workers through
Ray's runtime environment; a missing Ray is one clear line.

Ray is in the ``test`` extra (pyproject.toml), so CI runs these."""

from __future__ import annotations

import os
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path

import psutil
import pytest
import ray
from test_study import COLUMNS

from scenarios.study import run as study_run
from scenarios.study.engines import LocalEngine, RayEngine, runtime_env
from scenarios.study.spec import from_dict

REPO = Path(__file__).resolve().parents[1]
SPEC = {"name": "ray", "seed": 21, "protocol": {"poses": 4, "scans": 2, "scans_fused": [1, 2],
                                                "poses_per_task": 1},
        "grid": {"board.height_mm": [450.0, 600.0]}}
TASKS = 2 * 4


@pytest.fixture(scope="module")
def local_ray():
    """A Ray on this machine with two CPUs, ended with the module (its own processes only;
    the SIGTERM handler ray.init sets in this worker put back, as `RayEngine.close` does)."""
    sigterm = signal.getsignal(signal.SIGTERM)
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False,
             runtime_env=runtime_env("none"))
    try:
        yield ray
    finally:
        ray.shutdown()
        signal.signal(signal.SIGTERM, sigterm)


def _rows(folder: Path) -> list[tuple]:
    with sqlite3.connect(folder / "study.sqlite") as c:
        return c.execute(f"SELECT {COLUMNS} FROM estimate ORDER BY point, pose, fused, grp"
                         ).fetchall()


def _tasks(folder: Path) -> list[tuple]:
    if not (folder / "study.sqlite").exists():
        return []
    with sqlite3.connect(folder / "study.sqlite", timeout=30) as c:
        return c.execute("SELECT point, block, engine FROM task ORDER BY point, block").fetchall()


def _run(folder: Path, engine) -> str:
    store = study_run.create(from_dict(SPEC), folder.parent, folder, {"engine": engine.name})
    try:
        return study_run.execute(store, engine, progress=False)
    finally:
        store.close()


@pytest.mark.slow
def test_ray_and_local_engines_store_the_same_study(tmp_path: Path, local_ray):
    assert _run(tmp_path / "local", LocalEngine(2)) == "completed"
    engine = RayEngine()  # the Ray this test started
    assert engine.cpus == 2 and "2 CPUs" in engine.describe()
    assert _run(tmp_path / "ray", engine) == "completed"
    local, on_ray = _rows(tmp_path / "local"), _rows(tmp_path / "ray")
    assert len(local) == 2 * 4 * 3 and local == on_ray
    assert [t[:2] for t in _tasks(tmp_path / "ray")] == [t[:2] for t in _tasks(tmp_path / "local")]
    assert {t[2] for t in _tasks(tmp_path / "ray")} == {"ray"}

    # A Ray worker killed mid-study: Ray runs its task again; the study is the same study.
    folder = tmp_path / "lost"
    result: dict = {}
    thread = threading.Thread(target=lambda: result.update(status=_run(folder, RayEngine())))
    thread.start()
    killed = None
    end = time.monotonic() + 600
    while killed is None and thread.is_alive() and time.monotonic() < end:
        workers = [p for p in psutil.Process(os.getpid()).children(recursive=True)
                   if "ray::_run_ray" in " ".join(_cmdline(p))]
        if workers and len(_tasks(folder)) >= 1:
            killed = workers[0].pid
            os.kill(killed, signal.SIGKILL)
        time.sleep(0.05)
    thread.join(timeout=900)
    assert killed is not None, "no Ray worker was seen running a task"
    assert result.get("status") == "completed"
    assert _rows(folder) == local and len(_tasks(folder)) == TASKS


def _cmdline(p: psutil.Process) -> list[str]:
    try:
        return p.cmdline()
    except psutil.Error:
        return []


#: A driver with its own Ray whose job ships the project as `--ray-env modules` does; its task
#: says where it imported the project from and draws a pose of the protocol.
DRIVER = """
import json, ray
from scenarios.study.engines import runtime_env
ray.init(num_cpus=1, include_dashboard=False, log_to_driver=False,
         runtime_env=runtime_env("modules"))

@ray.remote(num_cpus=1)
def draw():
    import numpy as np
    import scenarios.study.protocol as protocol
    params, x, yaw = protocol.random_pose(np.random.default_rng(3))
    return protocol.__file__, params.mount_roll, x, yaw

try:
    print(json.dumps(ray.get(draw.remote(), timeout=600)))
finally:
    ray.shutdown()
"""


@pytest.mark.slow
def test_the_project_reaches_the_workers_through_rays_runtime_environment(tmp_path: Path):
    """``--ray-env modules`` uploads the project's packages with the job (Ray's py_modules): a
    worker imports them from Ray's copy, not from this checkout, and draws the protocol's poses
    as this process does."""
    import json

    import numpy as np

    from scenarios.study.protocol import random_pose

    res = subprocess.run([sys.executable, "-c", DRIVER], cwd=tmp_path, capture_output=True,
                         text=True, timeout=900, env={**os.environ, "PYTHONPATH": str(REPO)})
    assert res.returncode == 0, res.stderr[-2000:]
    where, roll, x, yaw = json.loads(res.stdout.strip().splitlines()[-1])
    assert not Path(where).resolve().is_relative_to(REPO), where
    assert "runtime_resources" in where
    params, x0, yaw0 = random_pose(np.random.default_rng(3))
    assert (roll, x, yaw) == (params.mount_roll, x0, yaw0)


def test_without_ray_the_study_says_how_to_install_it(tmp_path: Path):
    (tmp_path / "s.toml").write_text('[grid]\n"board.width_mm" = [900.0]\n')
    code = ("import sys; sys.modules['ray'] = None; from scenarios.cli import main; "
            "sys.exit(main(['study', 's.toml', '--out', 'out', '--engine', 'ray']))")
    res = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True,
                         text=True, timeout=120, env={**os.environ, "PYTHONPATH": str(REPO)})
    assert res.returncode == 2
    assert res.stderr.strip() == ("aimbench study: error: --engine ray needs Ray, which is not "
                                  "installed: pip install 'aimbench[ray]' (or use --engine "
                                  "local)")
    assert not (tmp_path / "out").exists()
