"""`aimbench version`: the software a result depends on (also stored with every run): aimbench and
the git commit it was run from, Python, and the libraries on the data path, in the estimator, the
twin, the stores and the reports."""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
from functools import cache
from importlib import metadata
from pathlib import Path

#: Distributions whose versions matter to a result: the simulator and the sensor emulation
#: (mujoco, numba), the estimator (numpy, scipy, open3d), the data path (python-pcapng,
#: pyserial), the stores and the reports (pyarrow, matplotlib), the views (rerun-sdk, gymnasium).
TRACKED = ("aimbench", "numpy", "scipy", "mujoco", "numba", "open3d", "pyserial",
           "python-pcapng", "pyarrow", "matplotlib", "rerun-sdk", "gymnasium")
#: The source tree: a git checkout when aimbench is installed for development (`make setup`).
SOURCE = Path(__file__).resolve().parents[2]


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
    try:
        own = metadata.version("aimbench")
    except metadata.PackageNotFoundError:
        own = "not installed"
    commit = git_commit()
    return f"aimbench {own} (commit {commit[:12] + commit[40:]})"


def run(args: argparse.Namespace) -> int:
    v = versions()
    if args.json:
        print(json.dumps(v))
    else:
        width = max(len(name) for name in v)
        for name, version in v.items():
            print(f"{name:{width}s} {version}")
    return 0


def register(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser("version", help="print the versions of aimbench, its commit and its "
                                       "libraries")
    p.add_argument("--json", action="store_true", help="one JSON object")
    p.set_defaults(func=run)
    return p
