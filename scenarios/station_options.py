"""The station on the command line, without its model: ``--station`` (and ``--board-mm``), the
station file a ``--station`` value names, the shipped stations, and the figures a command's help
states. `scenarios.station` (the pydantic model, about 0.4 s to import) uses them; a command's
parser imports only this (issue 38: a command's parser within 0.5 s).
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import Any

#: Where the shipped example stations live (package data of `scenarios`).
STATIONS_PACKAGE = "scenarios.stations"
#: The default station: the reference paper's bench.
DEFAULT_STATION = "paper"
#: How far a unit's roll on the board may be from the station's nominal, 1 sigma, deg: wide
#: enough for a badly bolted unit and a stage turned by its travel, narrow enough that the
#: board's symmetric rotations (90 deg apart) are told apart (`scenarios.station.Station`'s
#: roll prior; ``aimbench estimate --roll-hint-deg`` states it).
ROLL_PRIOR_SD_DEG = 10.0


def add_arguments(p: Any, board: bool = True) -> None:
    """``--station`` (and ``--board-mm``) on a command's parser."""
    p.add_argument("--station", metavar="FILE|NAME",
                   help="the bench's station file (TOML, docs/station.md) or a shipped one's name "
                        f"({', '.join(shipped())}); default: the paper's bench")
    if board:
        p.add_argument("--board-mm", metavar="WxH",
                       help="board WIDTHxHEIGHT, mm, instead of the station's (e.g. 900x540)")


def resolve(spec: str | Path | None) -> Path:
    """The file a ``--station`` value names: a path, or a shipped station's name."""
    if spec is None:
        spec = DEFAULT_STATION
    text = str(spec)
    if text in shipped():
        return shipped_path(text)
    path = Path(text).expanduser()
    # ``--station my-bench`` for my-bench.toml, as a shipped station is named without it.
    if not path.suffix and not path.exists() and path.with_name(path.name + ".toml").is_file():
        return path.with_name(path.name + ".toml")
    return path


def shipped() -> tuple[str, ...]:
    """The names of the example stations installed with aimbench."""
    folder = resources.files(STATIONS_PACKAGE)
    return tuple(sorted(p.name.removesuffix(".toml") for p in folder.iterdir()
                        if p.name.endswith(".toml")))


def shipped_path(name: str) -> Path:
    return Path(str(resources.files(STATIONS_PACKAGE).joinpath(f"{name}.toml")))
