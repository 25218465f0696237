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


def test_cli_version_names_every_library_and_the_commit(tmp_path):
    from scenarios.versions import git_commit

    v = json.loads(subprocess.run([sys.executable, "-m", "scenarios.cli", "version", "--json"],
                                  cwd=tmp_path, capture_output=True, text=True,
                                  check=True).stdout)
    for dist in ("numba", "pyarrow", "matplotlib", "python-pcapng", "numpy", "mujoco"):
        assert v[dist] not in ("", "not installed"), dist
    head = subprocess.run(["git", "-C", str(REPO_DIR), "rev-parse", "HEAD"], capture_output=True,
                          text=True, check=True).stdout.strip()
    assert v["aimbench-commit"].split("+")[0] == head
    assert git_commit(tmp_path) == "unknown"  # not a checkout (an installed wheel)


def test_cli_dash_dash_version_exits_0(tmp_path):
    out = subprocess.run([sys.executable, "-m", "scenarios.cli", "--version"], cwd=tmp_path,
                         capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    version = json.loads(subprocess.run(
        [sys.executable, "-m", "scenarios.cli", "version", "--json"], cwd=tmp_path,
        capture_output=True, text=True, check=True).stdout)
    assert out.stdout.startswith(f"aimbench {version['aimbench']} (commit ")
    assert version["aimbench-commit"][:12] in out.stdout


def test_method_options_list_their_choices(tmp_path):
    for command in ("sweep", "demo", "replay"):
        out = subprocess.run([sys.executable, "-m", "scenarios.cli", command, "--help"],
                             cwd=tmp_path, capture_output=True, text=True, check=True)
        assert "--method {rays,paper,icp}" in out.stdout, command
    bad = subprocess.run([sys.executable, "-m", "scenarios.cli", "sweep", "yaw", "--method",
                          "nope", "--out", "r"], cwd=tmp_path, capture_output=True, text=True)
    assert bad.returncode == 2 and "choose from 'rays', 'paper', 'icp'" in bad.stderr
    assert not (tmp_path / "r").exists()


def test_every_python_package_is_installed():
    """Every folder with an ``__init__.py`` under the project's packages is in pyproject's
    package list (a wheel, or Ray's pip runtime environment, would lack an unlisted one: the
    align.* subpackages were), and every listed package exists."""
    import tomllib

    listed = set(tomllib.loads((REPO_DIR / "pyproject.toml").read_text())["tool"]["setuptools"]
                 ["packages"])
    found = {".".join(p.parent.relative_to(REPO_DIR).parts)
             for top in ("aimbench", "align", "models", "scenarios", "twin")
             for p in (REPO_DIR / top).rglob("__init__.py")}
    assert found - listed == set(), sorted(found - listed)
    assert all((REPO_DIR / name.replace(".", "/")).is_dir() for name in listed)
