"""Argument types of the command line that refuse a bad value where it is typed.

argparse calls each with the option's text; a bad value raises `argparse.ArgumentTypeError`,
which argparse prints as one line (``aimbench sweep: error: argument --jobs: ...``, exit code 2)
before anything runs: no run folder is made for a sweep that cannot work. Each says what it
wants. Kept apart from the commands so that every command uses the same rule for the same kind
of number.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from pathlib import Path

#: Largest seed: numpy's generators take any non-negative integer, the store keeps 64 bits.
MAX_SEED = 2**63 - 1


def _int(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None


def _float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
    return value


def int_at_least(low: int) -> Callable[[str], int]:
    """A whole number >= `low`."""
    def parse(text: str) -> int:
        value = _int(text)
        if value < low:
            raise argparse.ArgumentTypeError(f"must be a whole number >= {low}, got {value}")
        return value

    parse.__name__ = f"int >= {low}"
    return parse


#: A count of things that must happen at least once (scans, jobs, poses, failures in a row).
positive_int = int_at_least(1)


def seed(text: str) -> int:
    """A seed: a whole number 0 .. 2**63 - 1 (numpy's generators take no negative seed)."""
    value = _int(text)
    if not 0 <= value <= MAX_SEED:
        raise argparse.ArgumentTypeError(f"a seed is a whole number 0..{MAX_SEED}, got {value}")
    return value


def finite_float(text: str) -> float:
    """Any finite number (NaN and inf refused: they would pass every comparison silently)."""
    return _float(text)


def float_above(low: float) -> Callable[[str], float]:
    """A finite number > `low`."""
    def parse(text: str) -> float:
        value = _float(text)
        if not value > low:
            raise argparse.ArgumentTypeError(f"must be > {low:g}, got {value:g}")
        return value

    parse.__name__ = f"float > {low:g}"
    return parse


def float_within(low: float, high: float) -> Callable[[str], float]:
    """A finite number in [`low`, `high`]."""
    def parse(text: str) -> float:
        value = _float(text)
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"must be within {low:g}..{high:g}, got {value:g}")
        return value

    parse.__name__ = f"float in {low:g}..{high:g}"
    return parse


def probability(text: str) -> float:
    """A level strictly between 0 and 1 (a confidence: 0.95; 1.5 or 95 is a mistake)."""
    value = _float(text)
    if not 0.0 < value < 1.0:
        hint = f" (did you mean {value / 100:g}?)" if 50.0 <= value < 100.0 else ""
        raise argparse.ArgumentTypeError(f"must be between 0 and 1, e.g. 0.95, got {value:g}"
                                         + hint)
    return value


#: A limit or a size that can be 0 but not negative (tolerances, thicknesses).
non_negative_float = float_within(0.0, math.inf)
#: A distance or a length that must be more than nothing.
positive_float = float_above(0.0)


#: Longest unit id (a VIN is 17 characters, serial numbers are shorter).
MAX_ID_CHARS = 64


def unit_id(text: str) -> str:
    """A unit's id (a VIN, a serial): printable, no control characters (a newline split the
    record list), no blank ends, at most `MAX_ID_CHARS` characters."""
    if not text or not text.isprintable() or text != text.strip():
        raise argparse.ArgumentTypeError(f"{text!r} is not a unit id: give printable "
                                         "characters, no newline, tab or blank at the ends "
                                         "(e.g. VIN123)")
    if len(text) > MAX_ID_CHARS:
        raise argparse.ArgumentTypeError(f"a unit id has at most {MAX_ID_CHARS} characters, "
                                         f"got {len(text)}")
    return text


def output_file(text: str) -> Path:
    """A file to write: not a folder, in a folder that exists (it is not created silently)."""
    path = Path(text)
    if path.is_dir():
        raise argparse.ArgumentTypeError(f"{text} is a folder; give a file name in it, e.g. "
                                         f"{path / 'out'}")
    if not path.parent.is_dir():
        raise argparse.ArgumentTypeError(f"the folder {path.parent} does not exist; create it "
                                         "first or write elsewhere")
    return path


def input_file(text: str) -> Path:
    """A file to read: it exists and is a file."""
    path = Path(text)
    if path.is_dir():
        raise argparse.ArgumentTypeError(f"{text} is a folder, not a file")
    if not path.is_file():
        raise argparse.ArgumentTypeError(f"no such file {text}")
    return path


def estimation_method(text: str) -> str:
    """align's method name (its ``choices`` are checked after); ``icp`` only with Open3D, which
    comes with the ``open3d`` extra: without it the user reads what to install before anything
    runs, rather than every scan failing."""
    if text == "icp":
        from scenarios.extras import MissingExtraError, require

        try:
            require("open3d", "--method icp")
        except MissingExtraError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None
    return text

