"""The study file: which station, which parameters to vary, and the Monte Carlo protocol.

A study is a TOML file (docs/studies.md has every key)::

    name = "board-distance"
    station = "paper"            # a station file (relative to this file) or a shipped name
    seed = 2026
    method = "rays"

    [protocol]                   # the paper's Monte Carlo protocol, at every design point
    poses = 20
    scans = 10
    scans_fused = [1, 10]

    [noise]                      # the twin's measurement model (the paper's by default)
    range_sigma_mm = 14.0

    [grid]                       # every combination of these values
    "board.width_mm" = [600.0, 900.0, 1200.0]
    distance_mm = [2000.0, 2500.0, 3000.0]

    [draws]                      # and/or draws within ranges: random or Latin hypercube
    kind = "lhs"
    n = 8
    [draws.ranges]
    "board.in_plane_deg" = [0.0, 45.0]

A parameter is a key of the station file (``board.width_mm``, ``board.in_plane_deg``,
``sensor.model``, ``stages.base_position_mm[1]``: an element of a list by its index), or one of
the study's own: ``distance_mm`` (the LiDAR stand's distance in front of the board's face, sets
``stages.base_position_mm[1]``), ``noise.range_sigma_mm``, ``noise.range_offset_mm``,
``noise.divergence``, ``method``, and ``scans_fused`` (grid only: every value is estimated on the
same scans of each pose). A design point is the station with its parameters set, validated as a
station file is: a bad value is refused before anything runs, naming the key.

Why pydantic (v2), as for the station file: nested, typed, user-written; every bad key located,
unknown keys refused.
"""

from __future__ import annotations

import itertools
import math
import re
import tomllib
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    StrictBool,
    StrictFloat,
    StrictInt,
    StrictStr,
    ValidationError,
    model_validator,
)

from scenarios import station as stations
from twin.core.errors import AimbenchError, one_line, short_repr

#: Most design points one study may hold (a study of more is several studies).
MAX_POINTS = 5000
#: The study's own parameters (not station keys) and what each is.
OWN_PARAMETERS = {
    "distance_mm": "the LiDAR stand's distance in front of the board's face, mm",
    "noise.range_sigma_mm": "1-sigma range noise, mm",
    "noise.range_offset_mm": "a range offset common to every laser, mm (the estimator is not told)",
    "noise.divergence": "beam divergence and mixed edge returns on the twin (true/false)",
    "method": "the estimation method (align.METHODS)",
    "scans_fused": "scans fused per estimate (grid only)",
}
_INDEXED = re.compile(r"^(?P<key>[a-z_.]+)\[(?P<index>\d+)\]$")

Positive = Annotated[StrictFloat, Field(gt=0)]
Count = Annotated[StrictInt, Field(ge=1)]


class StudyError(AimbenchError):
    """A study file that cannot be read or is not valid (the message names the key)."""


class _Section(BaseModel):
    # allow_inf_nan=False: a NaN or inf value (a grid's, a range's) made a store that could
    # be neither resumed nor reported (issue 37).
    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True,
                              allow_inf_nan=False)


class Protocol(_Section):
    """The Monte Carlo at each design point (the paper's, section IV-B; `benchmarks/
    bench_align.py`): `poses` random poses, mount angles within +-`angle_deg`, x within
    +-`x_mm`, the stage's yaw within +-`stage_yaw_deg`; `scans` scans at each; every value of
    `scans_fused` estimated on groups of that many of them. `poses_per_task`: poses one task
    evaluates (the unit of work an engine deals and a resume redoes at most)."""

    poses: Count = 20
    scans: Count = 10
    scans_fused: tuple[Count, ...] = (1,)
    angle_deg: Annotated[StrictFloat, Field(ge=0)] = 3.0
    x_mm: Annotated[StrictFloat, Field(ge=0)] = 30.0
    stage_yaw_deg: Annotated[StrictFloat, Field(ge=0)] = 0.0
    poses_per_task: Count = 5

    @model_validator(mode="after")
    def _fused_fit(self) -> Protocol:
        if not self.scans_fused:
            raise ValueError("scans_fused needs at least one value")
        if max(self.scans_fused) > self.scans:
            raise ValueError(f"scans_fused {max(self.scans_fused)} is more than the {self.scans} "
                             "scans per pose; raise protocol.scans")
        return self


class Noise(_Section):
    """The twin's measurement model at every design point (the paper's: 14 mm range noise, 2 mm
    quantisation, rpm wander; per-laser offsets off: they are what `align.calibration`
    removes)."""

    range_sigma_mm: Annotated[StrictFloat, Field(ge=0)] = 14.0
    range_offset_mm: StrictFloat = 0.0
    divergence: StrictBool = False


Value = StrictFloat | StrictInt | StrictStr | StrictBool


class Draws(_Section):
    """`n` points drawn within `ranges` (``[low, high]`` per parameter): ``random`` (uniform,
    independent) or ``lhs`` (a Latin hypercube, scipy.stats.qmc: every range cut into n strata,
    each stratum drawn once); seeded by the study's seed."""

    kind: Literal["random", "lhs"] = "lhs"
    n: Count
    ranges: dict[StrictStr, tuple[StrictFloat, StrictFloat]]


class StudySpec(_Section):
    """A study, as the study file describes it (module docstring; docs/studies.md)."""

    name: StrictStr = "study"
    description: StrictStr = ""
    station: StrictStr = stations.DEFAULT_STATION
    seed: Annotated[StrictInt, Field(ge=0)] = 0
    method: StrictStr = "rays"
    protocol: Protocol = Protocol()
    noise: Noise = Noise()
    grid: dict[StrictStr, list[Value]] = {}
    draws: Draws | None = None

    def parameters(self) -> list[str]:
        """The varied parameters, grid first (``scans_fused`` is not one: it is a mode)."""
        names = [k for k in self.grid if k != "scans_fused"]
        return names + ([k for k in self.draws.ranges if k not in names] if self.draws else [])

    def fused(self) -> tuple[int, ...]:
        """The scans fused per estimate: the grid's ``scans_fused``, else the protocol's."""
        if "scans_fused" in self.grid:
            return tuple(int(v) for v in self.grid["scans_fused"])
        return self.protocol.scans_fused


# -- reading -----------------------------------------------------------------------------------

def load(path: str | Path) -> tuple[StudySpec, Path]:
    """The study of a TOML file and the folder its relative paths are read from."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise StudyError(f"no such study file {path}; give a TOML study file "
                         "(docs/studies.md)") from None
    except (IsADirectoryError, UnicodeDecodeError) as exc:
        raise StudyError(f"{path} is not a study file ({exc}); give a TOML file") from None
    except tomllib.TOMLDecodeError as exc:
        raise StudyError(f"{path} is not valid TOML: {exc}") from None
    except RecursionError:  # tomllib recurses once per level of nested arrays or tables
        raise StudyError(f"{path}: arrays or tables nested too deep to be a study file; give "
                         "a TOML study file (docs/studies.md)") from None
    return from_dict(data, str(path)), path.parent


def from_dict(data: dict[str, Any], where: str = "study") -> StudySpec:
    try:
        spec = StudySpec.model_validate(data)
    except ValidationError as exc:
        raise StudyError(f"{where}: {_describe(exc)}; see docs/studies.md") from None
    _check_parameters(spec, where)
    return spec


#: The members of `Value` as pydantic names them in an error's location.
_VALUE_TAGS = {"float", "int", "str", "bool"}


def _describe(exc: ValidationError) -> str:
    """pydantic's errors as ``key: problem`` (one per key, the key spelt as in the file)."""
    parts: dict[str, str] = {}
    for err in exc.errors(include_url=False):
        loc = [str(p) for p in err["loc"]]
        # A grid value is a number, a string or true/false (`Value`): pydantic says why each
        # of the four does not fit; one sentence says it better.
        union = bool(loc) and loc[-1] in _VALUE_TAGS
        loc = [p for p in loc if p not in _VALUE_TAGS]
        ranges = loc[:2] == ["draws", "ranges"] and len(loc) >= 3
        key = ".".join(loc[:3] if ranges else [p for p in loc if not p.isdigit()]) or "study"
        msg = err["msg"].removeprefix("Value error, ")
        if err["type"] == "extra_forbidden":
            msg = "unknown key"
        elif union:
            msg = "each value must be a number, a string or true/false"
        elif ranges:
            msg = "give [low, high], two numbers"
        elif loc[:1] == ["grid"] and err["type"] == "list_type":
            msg = "give a list of values, e.g. [900.0]"
        if err["type"] not in ("missing", "extra_forbidden") and not isinstance(
                err.get("input"), dict) and not (ranges and err["type"] == "missing"):
            msg += f" (got {short_repr(err.get('input'))})"
        parts.setdefault(key, f"{key}: {msg}")
    return one_line(list(parts.values()))


def _check_parameters(spec: StudySpec, where: str) -> None:
    for key, values in spec.grid.items():
        check_name(key, f"{where}: grid")
        if not values:
            raise StudyError(f"{where}: grid.{key}: give at least one value")
    if spec.draws is not None:
        for key, (lo, hi) in spec.draws.ranges.items():
            check_name(key, f"{where}: draws.ranges")
            if key in spec.grid:
                raise StudyError(f"{where}: draws.ranges.{key}: also in [grid]; vary it one way")
            if key in ("scans_fused", "method", "noise.divergence", "sensor.model"):
                raise StudyError(f"{where}: draws.ranges.{key}: not a number to draw; list its "
                                 "values in [grid]")
            if not lo <= hi:
                raise StudyError(f"{where}: draws.ranges.{key}: [{lo:g}, {hi:g}] needs low <= "
                                 "high")
    varied = set(spec.parameters())
    if "distance_mm" in varied and "stages.base_position_mm[1]" in varied:
        raise StudyError(f"{where}: distance_mm and stages.base_position_mm[1] both set where the "
                         "LiDAR stand is; vary one of them")
    if "scans_fused" in spec.grid:
        bad = [v for v in spec.grid["scans_fused"] if not isinstance(v, int) or isinstance(
            v, bool) or not 1 <= v <= spec.protocol.scans]
        if bad:
            raise StudyError(f"{where}: grid.scans_fused: {bad[0]!r} is not a whole number "
                             f"1..{spec.protocol.scans} (protocol.scans)")
    n = math.prod(len(v) for k, v in spec.grid.items() if k != "scans_fused") * (
        spec.draws.n if spec.draws else 1)
    if n > MAX_POINTS:
        raise StudyError(f"{where}: {n} design points is more than the {MAX_POINTS} one study "
                         "may hold; use coarser steps or several studies")
    # Every point must be a valid station: one bad value fails now, naming it.
    base = stations.Station()
    for values in _corners(spec):
        apply(base, spec, values, where)


def check_name(key: str, where: str) -> None:
    """Refuse a parameter that is neither a station key nor one of the study's own."""
    if key in OWN_PARAMETERS:
        return
    m = _INDEXED.match(key)
    name = m["key"] if m else key
    parts = name.split(".")
    model: Any = stations.Station
    for i, part in enumerate(parts):
        field = model.model_fields.get(part) if isinstance(model, type) else None
        if field is None:
            allowed = ", ".join(list(model.model_fields) if isinstance(model, type) else [])
            raise StudyError(f"{where}: {key}: not a station key ({'.'.join(parts[:i + 1])} "
                             f"unknown; allowed there: {allowed}) nor one of the study's own "
                             f"({', '.join(OWN_PARAMETERS)}); see docs/studies.md")
        model = stations.section_type(field.annotation) or field.annotation
    if isinstance(model, type) and issubclass(model, BaseModel):
        raise StudyError(f"{where}: {key}: a table of the station file, not a value; name one of "
                         f"its keys ({', '.join(model.model_fields)})")


def _corners(spec: StudySpec) -> list[dict[str, Any]]:
    """Every grid value and the ends of every range, at least once each (for the checks)."""
    keys = [k for k in spec.grid if k != "scans_fused"]
    rows: list[dict[str, Any]] = []
    for k in keys:
        rows += [{k: v} for v in spec.grid[k]]
    if spec.draws is not None:
        for k, (lo, hi) in spec.draws.ranges.items():
            rows += [{k: lo}, {k: hi}]
    return rows or [{}]


# -- the design ----------------------------------------------------------------------------

def design(spec: StudySpec) -> list[dict[str, Any]]:
    """The design points, in order: every grid combination (the first key slowest) times the
    draws (Latin hypercube or uniform, seeded by the study's seed), as parameter -> value."""
    keys = [k for k in spec.grid if k != "scans_fused"]
    grid = [dict(zip(keys, combo, strict=True))
            for combo in itertools.product(*(spec.grid[k] for k in keys))]
    if spec.draws is None:
        return grid
    names = list(spec.draws.ranges)
    lo = np.array([spec.draws.ranges[k][0] for k in names])
    hi = np.array([spec.draws.ranges[k][1] for k in names])
    if spec.draws.kind == "lhs":
        from scipy.stats import qmc

        unit = qmc.LatinHypercube(d=len(names), seed=np.random.default_rng(spec.seed)).random(
            spec.draws.n)
    else:
        unit = np.random.default_rng(spec.seed).random((spec.draws.n, len(names)))
    drawn = [dict(zip(names, (float(v) for v in lo + u * (hi - lo)), strict=True))
             for u in unit]
    return [{**g, **d} for g in grid for d in drawn]


def apply(base: stations.Station, spec: StudySpec, values: dict[str, Any],
          where: str = "study") -> tuple[stations.Station, dict[str, Any]]:
    """The station of a design point and its own settings (method, noise): `base` with the
    point's station keys set, validated again; a `StudyError` naming the key otherwise."""
    data = base.model_dump()
    own: dict[str, Any] = {"method": spec.method, **{f"noise.{k}": v for k, v in
                                                     spec.noise.model_dump().items()}}
    for key, value in values.items():
        if key == "distance_mm":
            if not isinstance(value, int | float) or isinstance(value, bool) or value <= 0:
                raise StudyError(f"{where}: distance_mm: {value!r} must be a positive number")
            base_pos = list(data["stages"]["base_position_mm"])
            base_pos[1] = float(data["board"]["position_mm"][1]) - float(value)
            data["stages"]["base_position_mm"] = tuple(base_pos)
        elif key in OWN_PARAMETERS:
            own[key] = value
        else:
            _set(data, key, value, where)
    try:
        point = stations.from_dict(data, f"{where}: design point {values}")
    except stations.StationError as exc:
        raise StudyError(str(exc).replace("see docs/station.md", "see docs/station.md and "
                                          "docs/studies.md")) from None
    try:
        Noise.model_validate({k.removeprefix("noise."): v for k, v in own.items()
                              if k.startswith("noise.")})
    except ValidationError as exc:
        raise StudyError(f"{where}: design point {values}: noise: {_describe(exc)}; see "
                         "docs/studies.md") from None
    import align

    if own["method"] not in align.METHODS:
        raise StudyError(f"{where}: method: unknown estimation method {own['method']!r}; use "
                         f"one of {', '.join(align.METHODS)}")
    return point, own


def _set(data: dict[str, Any], key: str, value: Any, where: str) -> None:
    m = _INDEXED.match(key)
    name, index = (m["key"], int(m["index"])) if m else (key, None)
    *path, last = name.split(".")
    node = data
    for part in path:
        if node.get(part) is None:
            node[part] = {}
        node = node[part]
    if index is None:
        node[last] = _like(node.get(last), value)
        return
    seq = list(node.get(last) or ())
    if index >= len(seq):
        raise StudyError(f"{where}: {key}: {last} has {len(seq)} values; index {index} is "
                         "beyond them")
    seq[index] = _like(seq[index], value)
    node[last] = tuple(seq)


def _like(current: Any, value: Any) -> Any:
    """TOML's 900 is the station's 900.0 where the key holds a float (and 7 stays 7 where it
    holds a whole number)."""
    if isinstance(current, float) and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    return value
