"""The `aimbench` command line: subcommands are discovered from `scenarios.commands`.

Each command module defines ``register(subparsers) -> argparse.ArgumentParser`` and sets
``func`` on its parser with ``set_defaults(func=...)``; ``func(args) -> int`` is the exit code.
Errors a user can fix (a missing file, a bad capture, an unreachable port) are raised as
`twin.core.errors.AimbenchError` (or a subclass) and printed as one line, never as a traceback.
"""

from __future__ import annotations

import argparse
import difflib
import importlib
import pkgutil
import sys

from scenarios import commands
from scenarios.commands import version
from twin.core.errors import AimbenchError


class _Version(argparse.Action):
    """``--version``: asks git for the commit only when given (not on every command)."""

    def __call__(self, parser: argparse.ArgumentParser, *args: object) -> None:
        print(version.short())
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


def _did_you_mean(parser: argparse.ArgumentParser, argv: list[str]) -> None:
    """A mistyped command refused with the nearest one (argparse lists them all, no hint)."""
    first = next((a for a in argv if not a.startswith("-")), None)
    sub = next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)), None)
    if first is None or sub is None or first in sub.choices:
        return
    near = difflib.get_close_matches(first, list(sub.choices), n=1, cutoff=0.6)
    hint = f"; did you mean '{near[0]}'?" if near else ""
    parser.exit(2, f"aimbench: error: unknown command '{first}'{hint} (aimbench --help lists "
                   "them)\n")


def main(argv: list[str] | None = None) -> int:
    # Line by line even into a pipe: a table on stdout and a warning on stderr then reach the
    # terminal in the order they were written, not the warning glued onto the table's end.
    if hasattr(sys.stdout, "reconfigure"):
        sys.stdout.reconfigure(line_buffering=True)
    parser = build_parser()
    _did_you_mean(parser, sys.argv[1:] if argv is None else argv)
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except AimbenchError as exc:
        sys.stdout.flush()
        print(f"aimbench {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"aimbench {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
