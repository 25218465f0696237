"""`aimbench version`: the software versions a run depends on (also stored with every run)."""

from __future__ import annotations

import argparse
import json
import platform
from importlib import metadata

#: Distributions whose versions matter to a result.
TRACKED = ("aimbench", "numpy", "scipy", "mujoco", "open3d", "pyserial", "rerun-sdk", "gymnasium")


def versions() -> dict[str, str]:
    """Installed versions of aimbench, Python and the libraries a result depends on."""
    out = {"python": platform.python_version()}
    for dist in TRACKED:
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[dist] = "not installed"
    return out


def run(args: argparse.Namespace) -> int:
    v = versions()
    if args.json:
        print(json.dumps(v))
    else:
        for name, version in v.items():
            print(f"{name:10s} {version}")
    return 0


def register(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser("version", help="print the versions of aimbench and its libraries")
    p.add_argument("--json", action="store_true", help="one JSON object")
    p.set_defaults(func=run)
    return p
