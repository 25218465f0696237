"""The `aimbench` command line: subcommands are discovered from `scenarios.commands`.

Each command module defines ``register(subparsers) -> argparse.ArgumentParser`` and sets
``func`` on its parser with ``set_defaults(func=...)``; ``func(args) -> int`` is the exit code.
Errors a user can fix (a missing file, a bad capture, an unreachable port) are raised as
`twin.core.errors.AimbenchError` (or a subclass) and printed as one line, never as a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

from scenarios import commands, versions
from twin.core.errors import AimbenchError


class _Version(argparse.Action):
    """``--version``: asks git for the commit only when given (not on every command)."""

    def __call__(self, parser: argparse.ArgumentParser, *args: object) -> None:
        print(versions.short())
        parser.exit(0)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="aimbench",
        description="LiDAR alignment inspection bench and its digital twin.",
    )
    parser.add_argument("--version", action=_Version, nargs=0,
                        help="print aimbench's version and commit, and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        module = importlib.import_module(f"{commands.__name__}.{info.name}")
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except AimbenchError as exc:
        print(f"aimbench {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"aimbench {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
