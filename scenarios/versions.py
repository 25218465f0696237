"""The software a result depends on (stored with every run and calibration, printed by `aimbench
version`): aimbench and the git commit it was run from, Python, and the libraries on the data
path, in the estimator, the twin, the stores and the reports.

Here, below the command line, so that the stores and the calibration can record it without
importing a command (`scenarios.commands.version` prints it)."""

from __future__ import annotations

import platform
import subprocess
from functools import cache
from pathlib import Path

#: Distributions whose versions matter to a result: the simulator and the sensor emulation
#: (mujoco, numba), the estimator (numpy, scipy, open3d), the data path (python-pcapng,
#: pyserial), the stores and the reports (pyarrow, matplotlib), the views (rerun-sdk, gymnasium).
TRACKED = ("aimbench", "numpy", "scipy", "mujoco", "numba", "open3d", "pyserial",
           "python-pcapng", "pyarrow", "matplotlib", "rerun-sdk", "gymnasium")
#: The source tree: a git checkout when aimbench is installed for development (`make setup`).
SOURCE = Path(__file__).resolve().parents[1]


@cache
def git_commit(source: Path = SOURCE) -> str:
    """The commit the code runs from, ``+modified`` when the work tree differs from it, or
    ``unknown`` when it is not a git checkout (an installed wheel) or git is missing."""
    def git(*args: str) -> str:
        return subprocess.run(["git", "-C", str(source), *args], capture_output=True, text=True,
                              timeout=10, check=True).stdout.strip()

    try:
        commit = git("rev-parse", "HEAD")
        # Only tracked files count: a run folder or a venv beside the code changes nothing.
        modified = bool(git("status", "--porcelain", "--untracked-files=no"))
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return commit + ("+modified" if modified else "")


def versions() -> dict[str, str]:
    """Installed versions of aimbench (and its commit), Python and the tracked libraries."""
    from importlib import metadata  # here: its import costs --help 30 ms (issue 38)

    out = {"python": platform.python_version()}
    for dist in TRACKED:
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[dist] = "not installed"
    out["aimbench-commit"] = git_commit()
    return out


def short() -> str:
    """One line for ``aimbench --version``: the version and the commit (aimbench's own version
    alone: looking up every tracked library costs more than the 0.3 s the answer may take)."""
    from importlib import metadata

    try:
        own = metadata.version("aimbench")
    except metadata.PackageNotFoundError:
        own = "not installed"
    commit = git_commit()
    return f"aimbench {own} (commit {commit[:12] + commit[40:]})"
