"""Project hygiene: the CLI runs as installed, and the tree is ruff clean."""

import json
import shutil
import subprocess
import sys

from conftest import REPO_DIR


def test_cli_version_json(tmp_path):
    out = subprocess.run(
        [sys.executable, "-m", "scenarios.cli", "version", "--json"],
        cwd=tmp_path, capture_output=True, text=True, check=True,
    )
    v = json.loads(out.stdout)
    assert v["aimbench"] != "not installed"
    assert "mujoco" in v


def test_console_script_installed():
    exe = shutil.which("aimbench", path=str(REPO_DIR / ".venv" / "bin")) or shutil.which("aimbench")
    assert exe, "the aimbench console script is not installed (make setup)"
    out = subprocess.run([exe, "--help"], capture_output=True, text=True, check=True)
    assert "version" in out.stdout


def test_ruff_clean():
    ruff = shutil.which("ruff", path=str(REPO_DIR / ".venv" / "bin")) or shutil.which("ruff")
    assert ruff, "ruff is a test dependency; make setup installs it"
    out = subprocess.run([ruff, "check", str(REPO_DIR)], capture_output=True, text=True)
    assert out.returncode == 0, out.stdout + out.stderr


def test_importing_aimbench_registers_the_gym_env(tmp_path):
    code = ("import gymnasium as gym, aimbench; "
            "assert aimbench.ENV_ID in gym.registry; print(gym.spec(aimbench.ENV_ID).id)")
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True,
                         text=True, check=True)
    assert out.stdout.strip() == "aimbench/LidarAlign-v0"
