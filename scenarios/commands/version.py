"""`aimbench version`: the software a result depends on (`scenarios.versions`, also stored with
every run): aimbench and the git commit it was run from, Python, and the tracked libraries."""

from __future__ import annotations

import argparse
import json

from scenarios.versions import versions


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
