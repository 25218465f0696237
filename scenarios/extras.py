"""The optional parts of aimbench and the pip extra that installs each (pyproject.toml).

`make demo` installs the main job's libraries only (issue 38: its .venv under 1 GB); a command
that needs a library of an extra checks for it with `require` before it starts, and a user
without it reads one line naming the extra to install, not a traceback from deep inside.
"""

from __future__ import annotations

import importlib.util

from twin.core.errors import AimbenchError

#: module -> (distribution, extra): what each optional library is installed by.
OPTIONAL = {
    "open3d": ("open3d", "open3d"),
    "rerun": ("rerun-sdk", "rerun"),
    "statsmodels": ("statsmodels", "grr"),
    "nicegui": ("nicegui", "station"),
    "asyncua": ("asyncua", "station"),
    "ouster.sdk": ("ouster-sdk", "ouster"),
}
#: extra -> what to run instead of pip: ouster-sdk pins old rosbags, flask, click and psutil,
#: so the extra lists what it needs and tools/setup.sh installs it without them (pyproject.toml).
SETUP_ONLY = {"ouster": "run tools/setup.sh ouster (it installs ouster-sdk without the old "
                        "rosbags, flask, click and psutil it pins)"}


class MissingExtraError(AimbenchError):
    """A command needs a library of an extra that is not installed."""


def installed(module: str) -> bool:
    """Whether ``module`` can be imported (without importing it: open3d takes seconds)."""
    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):  # a parent package missing, or sys.modules[name] = None
        return False


def require(module: str, what: str) -> None:
    """Raise `MissingExtraError` naming the extra when ``module`` is not installed; ``what``:
    what needs it (the start of the message: "--method icp", "aimbench grr")."""
    if installed(module):
        return
    dist, extra = OPTIONAL[module]
    how = SETUP_ONLY.get(extra, f"pip install 'aimbench[{extra}]'")
    raise MissingExtraError(f"{what} needs {dist}, which is not installed: {how}")
