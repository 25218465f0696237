"""The `aimbench` command line: subcommands are discovered from `scenarios.commands`.

Each command module defines ``register(subparsers) -> argparse.ArgumentParser`` and sets
``func`` on its parser with ``set_defaults(func=...)``; ``func(args) -> int`` is the exit code.
Errors a user can fix (a missing file, a bad capture, an unreachable port) are raised as
`twin.core.errors.AimbenchError` (or a subclass) and printed as one line, never as a traceback.

Only the command that runs is imported (issue 38: ``aimbench --help`` within 0.3 s, every command
at work within 0.5 s). The others appear in ``--help`` by the one-line help their ``register``
passes to ``add_parser``, read from their source without importing them (`command_help`).
"""

from __future__ import annotations

import argparse
import ast
import difflib
import importlib
import io
import pkgutil
import sys
import tokenize
from pathlib import Path

from scenarios import commands, versions
from twin.core.errors import AimbenchError

#: build_parser's default: register every command in full (the tests and the docs use it).
ALL = "*"


class _Version(argparse.Action):
    """``--version``: asks git for the commit only when given (not on every command)."""

    def __call__(self, parser: argparse.ArgumentParser, *args: object) -> None:
        print(versions.short())
        parser.exit(0)


def command_names() -> list[str]:
    """The subcommands: one module each in `scenarios.commands`, found without importing them."""
    return sorted(m.name for m in pkgutil.iter_modules(commands.__path__))


def command_help(name: str) -> str:
    """The ``help=`` a command's module gives ``add_parser("NAME", ...)``, read from its source
    (a literal string, as every command writes it); empty when there is none. Only that call is
    parsed: parsing every command's whole module would cost --help a quarter of a second."""
    source = Path(commands.__path__[0], f"{name}.py").read_text(encoding="utf-8")
    start = source.find(f'add_parser("{name}"')
    if start < 0:
        return ""
    call = source[start + len("add_parser"):]
    depth = 0
    for tok in tokenize.generate_tokens(io.StringIO(call).readline):
        if tok.type == tokenize.OP and tok.string in "([{":
            depth += 1
        elif tok.type == tokenize.OP and tok.string in ")]}":
            depth -= 1
            if depth == 0:
                lines = call.splitlines(keepends=True)[: tok.end[0]]
                lines[-1] = lines[-1][: tok.end[1]]
                node = ast.parse("f" + "".join(lines), mode="eval").body
                break
    else:
        return ""
    for kw in getattr(node, "keywords", ()):
        if kw.arg == "help" and isinstance(kw.value, ast.Constant):
            return str(kw.value.value)
    return ""


def build_parser(load: str | None = ALL) -> argparse.ArgumentParser:
    """The parser. ``load``: the command whose module is imported and registered in full (`ALL`:
    every command; None: none, enough for ``--help`` and ``--version``). The other commands are
    listed by name and help line only."""
    parser = argparse.ArgumentParser(
        prog="aimbench",
        description="LiDAR alignment inspection bench and its digital twin.",
    )
    parser.add_argument("--version", action=_Version, nargs=0,
                        help="print aimbench's version and commit, and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in command_names():
        if load in (ALL, name):
            importlib.import_module(f"{commands.__name__}.{name}").register(sub)
        else:
            sub.add_parser(name, help=command_help(name))
    return parser


def _command_in(argv: list[str]) -> str | None:
    """The subcommand argv names: its first word that is not an option (the top-level parser
    has no option taking a value)."""
    return next((word for word in argv if not word.startswith("-")), None)


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
    argv = sys.argv[1:] if argv is None else list(argv)
    # Line by line even into a pipe: a table on stdout and a warning on stderr then reach the
    # terminal in the order they were written, not the warning glued onto the table's end.
    if hasattr(sys.stdout, "reconfigure"):
        sys.stdout.reconfigure(line_buffering=True)
    parser = build_parser(load=_command_in(argv))
    _did_you_mean(parser, argv)
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
