"""Scenario plans: the list of bench references a sweep visits and how many scans it takes at each.

A `Plan` is pure data: a name, the references (stage yaw and x, plus for the simulated bench an
optional mount misalignment), and the number of scans per reference. The built-in plans follow the
reference paper (../shared/reference/alignment-paper.tex, sections IV and V):

========================  =====================================================================
``yaw_sweep``             stage yaw -10 .. +10 deg in 1 deg steps, x = 0, 100 scans each (Fig. 8-9)
``x_sweep``               stage x -30 .. +30 mm in 5 mm steps, yaw = 0, 100 scans each (Fig. 10-11)
``grid``                  every (yaw, x) of the two sweeps above (Table II's combined tests)
``monte_carlo``           random mount misalignments: roll, tilt, yaw within +-3 deg and x within
                          +-30 mm, 50 scans per pose, seeded (Table I, the simulation protocol)
``repeatability``         the same pose visited again and again, approached alternately from
                          either side, so stage backlash and scan noise both show
========================  =====================================================================

and `from_toml` reads a user's own sweep (see docs/scenarios.md for the format).

Units: SI inside (m, rad). The ``*_deg`` / ``*_mm`` arguments of the builders and the TOML keys are
the edge units, converted here once.
"""

from __future__ import annotations

import itertools
import math
import tomllib
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from scenarios import station
from twin.core.errors import AimbenchError, few
from twin.core.pose import StagePose

#: Paper defaults (section V): the real bench's sweeps.
PAPER_YAW_DEG = (-10.0, 10.0, 1.0)
PAPER_X_MM = (-30.0, 30.0, 5.0)
PAPER_SCANS = 100
#: Paper defaults (section IV): the simulation's Monte Carlo protocol.
PAPER_MC_ANGLE_DEG = 3.0
PAPER_MC_X_MM = 30.0
PAPER_MC_SCANS = 50
#: Issue 4's protocol for the same study: 200 random poses.
PAPER_MC_POSES = 200

#: Names of the mount misalignment keys a reference may carry (edge units).
MOUNT_KEYS = ("roll_deg", "tilt_deg", "yaw_deg", "x_mm")
#: Most references a plan may have: the paper's grid has 273; a million would take a store of
#: gigabytes before its first scan. A sweep step of 1e-9 once tried to allocate 149 GiB.
MAX_REFERENCES = 100_000
#: Most scans per reference (a day of the sensor at 10 scans/s is 864,000).
MAX_SCANS = 1_000_000


class PlanError(AimbenchError):
    """A plan that cannot be built or read (bad TOML, empty sweep, unknown key)."""


@dataclass(frozen=True)
class Reference:
    """One bench reference: where the stages go and, on the simulated bench, how the LiDAR sits.

    yaw_rad, x_m: the rotation stage's yaw (rad) and the linear stage's x (m), in the bench's
        own coordinates (0, 0 = home pose).
    mount: the LiDAR's mounting misalignment for this reference, in edge units keyed by
        `MOUNT_KEYS` (roll_deg, tilt_deg, yaw_deg, x_mm), or None to keep the bench's own. Only
        a simulated bench can change its mount between references.
    via: an optional `StagePose` the stages visit first, so a reference is approached from a
        chosen side (repeatability); stored as [yaw_rad, x_m].
    label: a short human name for tables and plots.
    """

    yaw_rad: float = 0.0
    x_m: float = 0.0
    mount: dict[str, float] | None = None
    via: StagePose | None = None
    label: str = ""

    @property
    def stage(self) -> StagePose:
        """The stage command of this reference."""
        return StagePose(x_m=self.x_m, yaw_rad=self.yaw_rad)

    @property
    def yaw_deg(self) -> float:
        return math.degrees(self.yaw_rad)

    @property
    def x_mm(self) -> float:
        return self.x_m * 1e3

    def describe(self) -> str:
        """``stage yaw -3.00 deg, stage_x +5.0 mm`` plus the mount if any: for messages and
        progress. The stages' positions, named so: the board frame's x of an estimate is
        another quantity (the LiDAR 700 mm to the side), and printed beside it the two read
        as one (issue 37)."""
        text = f"stage yaw {self.yaw_deg:+.2f} deg, stage_x {self.x_mm:+.1f} mm"
        if self.mount:
            text += " (mount " + ", ".join(f"{k} {v:+.2f}" for k, v in self.mount.items()) + ")"
        return text

    def to_dict(self) -> dict:
        d = asdict(self)
        d["via"] = [self.via.yaw_rad, self.via.x_m] if self.via is not None else None
        return d

    @classmethod
    def from_dict(cls, d: dict) -> Reference:
        via = d.get("via")
        return cls(
            yaw_rad=float(d.get("yaw_rad", 0.0)),
            x_m=float(d.get("x_m", 0.0)),
            mount=dict(d["mount"]) if d.get("mount") else None,
            via=StagePose(yaw_rad=float(via[0]), x_m=float(via[1])) if via else None,
            label=str(d.get("label", "")),
        )


@dataclass(frozen=True)
class Plan:
    """What a sweep does: visit `references` in order and take `scans` scans at each.

    kind: the built-in name (``yaw``, ``x``, ``grid``, ``montecarlo``, ``repeatability``) or
        ``toml``; the report uses it to choose which axis goes on a plot's abscissa.
    settings: the arguments the plan was built from (edge units), stored with the run.
    """

    name: str
    kind: str
    references: tuple[Reference, ...]
    scans: int
    settings: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not self.references:
            raise PlanError(f"plan {self.name!r} has no references; give a non-empty sweep")
        if self.scans < 1:
            raise PlanError(f"plan {self.name!r}: scans per reference must be >= 1, "
                            f"got {self.scans}")
        if self.scans > MAX_SCANS:
            raise PlanError(f"plan {self.name!r}: {self.scans} scans per reference is more than "
                            f"the {MAX_SCANS} a plan may take")
        if len(self.references) > MAX_REFERENCES:
            raise PlanError(f"plan {self.name!r}: {len(self.references)} references is more "
                            f"than the {MAX_REFERENCES} a plan may have; use a coarser step")

    def __len__(self) -> int:
        return len(self.references)

    @property
    def total_scans(self) -> int:
        return self.scans * len(self.references)

    def with_scans(self, scans: int) -> Plan:
        """The same references with another number of scans per reference."""
        return Plan(self.name, self.kind, self.references, int(scans),
                    {**self.settings, "scans": int(scans)})

    def to_dict(self) -> dict:
        return {
            "name": self.name, "kind": self.kind, "scans": self.scans,
            "settings": self.settings, "references": [r.to_dict() for r in self.references],
        }

    @classmethod
    def from_dict(cls, d: dict) -> Plan:
        return cls(
            name=d["name"], kind=d["kind"], scans=int(d["scans"]),
            settings=dict(d.get("settings", {})),
            references=tuple(Reference.from_dict(r) for r in d["references"]),
        )


def steps(start: float, stop: float, step: float) -> np.ndarray:
    """start, start+step, ... up to and including stop (inclusive within 1e-9 of a step).

    Built from integer multiples so that -10..10 by 1 gives exactly 21 values with an exact 0.
    """
    if not all(math.isfinite(v) for v in (start, stop, step)):
        raise PlanError(f"start, stop and step must be finite numbers, got {start}, {stop}, "
                        f"{step}")
    if step <= 0:
        raise PlanError(f"step must be positive, got {step}")
    if stop < start:
        raise PlanError(f"stop ({stop}) is below start ({start})")
    # Counted before anything is allocated: a tiny step must not ask for gigabytes.
    n = math.floor((stop - start) / step + 1e-9) + 1
    if n > MAX_REFERENCES:
        raise PlanError(f"{start:g}..{stop:g} by {step:g} is {n} values, more than the "
                        f"{MAX_REFERENCES} references a plan may have; use a coarser step")
    # Rounded to 1e-12 so -10 + 10 * 1 is exactly 0 (and + 0.0 turns -0.0 into 0.0).
    return np.round(start + step * np.arange(n), 12) + 0.0


def yaw_sweep(start_deg: float = PAPER_YAW_DEG[0], stop_deg: float = PAPER_YAW_DEG[1],
              step_deg: float = PAPER_YAW_DEG[2], scans: int = PAPER_SCANS,
              x_mm: float = 0.0) -> Plan:
    """The paper's first test: stage yaw from `start_deg` to `stop_deg` at fixed x."""
    refs = tuple(Reference(yaw_rad=math.radians(y), x_m=x_mm * 1e-3, label=f"yaw {y:+g} deg")
                 for y in steps(start_deg, stop_deg, step_deg))
    return Plan("yaw sweep", "yaw", refs, scans, {
        "start_deg": start_deg, "stop_deg": stop_deg, "step_deg": step_deg, "x_mm": x_mm,
        "scans": scans})


def x_sweep(start_mm: float = PAPER_X_MM[0], stop_mm: float = PAPER_X_MM[1],
            step_mm: float = PAPER_X_MM[2], scans: int = PAPER_SCANS,
            yaw_deg: float = 0.0) -> Plan:
    """The paper's second test: stage x from `start_mm` to `stop_mm` at fixed yaw."""
    refs = tuple(Reference(yaw_rad=math.radians(yaw_deg), x_m=x * 1e-3, label=f"x {x:+g} mm")
                 for x in steps(start_mm, stop_mm, step_mm))
    return Plan("x sweep", "x", refs, scans, {
        "start_mm": start_mm, "stop_mm": stop_mm, "step_mm": step_mm, "yaw_deg": yaw_deg,
        "scans": scans})


def grid(yaw_deg: Sequence[float] | None = None, x_mm: Sequence[float] | None = None,
         scans: int = PAPER_SCANS) -> Plan:
    """Every combination of the yaw and x references (default: the paper's two sweeps).

    Ordered x-major, yaw fastest, in a serpentine so the rotation stage never swings back the
    whole range between rows (shorter moves, and the order a person running the bench would use).
    """
    yaws = list(steps(*PAPER_YAW_DEG) if yaw_deg is None else yaw_deg)
    xs = list(steps(*PAPER_X_MM) if x_mm is None else x_mm)
    refs = []
    for i, x in enumerate(xs):
        row = yaws if i % 2 == 0 else yaws[::-1]
        refs.extend(Reference(yaw_rad=math.radians(y), x_m=x * 1e-3,
                              label=f"yaw {y:+g} deg, x {x:+g} mm") for y in row)
    return Plan("yaw x grid", "grid", tuple(refs), scans, {
        "yaw_deg": [float(y) for y in yaws], "x_mm": [float(x) for x in xs], "scans": scans})


def monte_carlo(poses: int = PAPER_MC_POSES, scans: int = PAPER_MC_SCANS, seed: int = 0,
                angle_deg: float = PAPER_MC_ANGLE_DEG, x_mm: float = PAPER_MC_X_MM) -> Plan:
    """The paper's simulation protocol: random mount misalignments, `scans` scans per pose.

    Each pose draws roll, tilt and yaw uniformly within +-`angle_deg` and x within +-`x_mm`
    (numpy Generator seeded by `seed`, so the same seed gives the same poses). They are mount
    misalignments, not stage commands: only a simulated bench can run this plan. The stages stay
    at home (0, 0); the error reference is the twin's truth.
    """
    if not 1 <= poses <= MAX_REFERENCES:
        raise PlanError(f"Monte Carlo needs 1..{MAX_REFERENCES} poses, got {poses}")
    rng = np.random.default_rng(seed)
    angles = rng.uniform(-angle_deg, angle_deg, size=(poses, 3))
    xs = rng.uniform(-x_mm, x_mm, size=poses)
    refs = tuple(
        Reference(mount={"roll_deg": float(a[0]), "tilt_deg": float(a[1]), "yaw_deg": float(a[2]),
                         "x_mm": float(x)}, label=f"pose {i}")
        for i, (a, x) in enumerate(zip(angles, xs, strict=True))
    )
    return Plan("Monte Carlo", "montecarlo", refs, scans, {
        "poses": poses, "scans": scans, "seed": seed, "angle_deg": angle_deg, "x_mm": x_mm})


def repeatability(yaw_deg: float = 0.0, x_mm: float = 0.0, repeats: int = 10,
                  scans: int = PAPER_SCANS, approach_deg: float = 2.0,
                  approach_mm: float = 5.0) -> Plan:
    """One pose visited `repeats` times, each time approached from alternate sides.

    Between visits the stages go `approach_deg` / `approach_mm` beyond the pose, alternately on
    the positive and negative side, so the spread of the per-visit means shows the stages'
    repeatability (backlash included) on top of the estimator's scan-to-scan precision.
    """
    if not 1 <= repeats <= MAX_REFERENCES:
        raise PlanError(f"repeatability needs 1..{MAX_REFERENCES} visits, got {repeats}")
    refs = []
    for i in range(repeats):
        sign = 1.0 if i % 2 == 0 else -1.0
        via = StagePose(yaw_rad=math.radians(yaw_deg + sign * approach_deg),
                        x_m=(x_mm + sign * approach_mm) * 1e-3)
        refs.append(Reference(yaw_rad=math.radians(yaw_deg), x_m=x_mm * 1e-3, via=via,
                              label=f"visit {i + 1} from {'+' if sign > 0 else '-'}"))
    return Plan("repeatability", "repeatability", tuple(refs), scans, {
        "yaw_deg": yaw_deg, "x_mm": x_mm, "repeats": repeats, "scans": scans,
        "approach_deg": approach_deg, "approach_mm": approach_mm})


#: The built-in plans by their command-line name.
BUILTIN = {
    "yaw": yaw_sweep,
    "x": x_sweep,
    "grid": grid,
    "montecarlo": monte_carlo,
    "repeatability": repeatability,
}


def _axis(spec: object, key: str, where: str) -> list[float]:
    """A TOML axis: a number, a list of numbers, or a table {start, stop, step}."""
    if isinstance(spec, bool):
        raise PlanError(f"{where}: {key} must be a number, a list or {{start, stop, step}}")
    if isinstance(spec, int | float):
        return [_finite(spec, key, where)]
    if isinstance(spec, list):
        if not spec or not all(isinstance(v, int | float) and not isinstance(v, bool)
                                for v in spec):
            raise PlanError(f"{where}: {key} must be a non-empty list of numbers, got {spec!r}")
        if len(spec) > MAX_REFERENCES:
            raise PlanError(f"{where}: {key} has {len(spec)} values, more than the "
                            f"{MAX_REFERENCES} references a plan may have")
        return [_finite(v, key, where) for v in spec]
    if isinstance(spec, dict):
        missing = {"start", "stop", "step"} - set(spec)
        extra = set(spec) - {"start", "stop", "step"}
        if missing or extra:
            raise PlanError(f"{where}: {key} as a table needs exactly start, stop and step "
                            f"(missing {sorted(missing)}, unknown {sorted(extra)})")
        bounds = [spec[k] for k in ("start", "stop", "step")]
        if not all(isinstance(v, int | float) and not isinstance(v, bool) for v in bounds):
            raise PlanError(f"{where}: {key}: start, stop and step must be numbers, got "
                            f"{bounds!r}")
        try:
            return [float(v) for v in steps(*(_finite(v, key, where) for v in bounds))]
        except PlanError as exc:
            raise PlanError(f"{where}: {key}: {exc}") from None
    raise PlanError(f"{where}: {key} must be a number, a list or {{start, stop, step}}, "
                    f"got {spec!r}")


def _finite(value: object, key: str, where: str) -> float:
    """A TOML number as a float, refusing NaN and inf (TOML has both; neither is a place)."""
    f = float(value)  # type: ignore[arg-type]
    if not math.isfinite(f):
        raise PlanError(f"{where}: {key} must be a finite number, got {value!r}")
    return f


_TOP_KEYS = {"name", "scans", "yaw_deg", "x_mm", "mount", "reference", "method", "seed",
             "board_mm"}
_REF_KEYS = {"yaw_deg", "x_mm", "mount", "label"}


def from_toml(path: str | Path) -> Plan:
    """A user's sweep from a small TOML file.

    Either axes (the grid of every combination)::

        name = "fine yaw"
        scans = 20
        yaw_deg = { start = -2, stop = 2, step = 0.5 }   # or a list, or one number
        x_mm = 0

    or explicit references (``[[reference]]`` tables with yaw_deg, x_mm, an optional label and,
    for the simulated bench, an optional mount table of roll_deg, tilt_deg, yaw_deg, x_mm).
    A top-level ``[mount]`` applies to every reference that has none. ``method``, ``seed`` and
    ``board_mm`` (the board's size, ``"900x540"`` or ``[900, 540]``, in place of the station
    file's) are defaults the command line may override; they are returned in ``settings``
    (``board_mm`` as [width, height]).
    """
    path = Path(path)
    where = str(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise PlanError(f"no such plan file {where}; give a .toml sweep or one of "
                        f"{', '.join(BUILTIN)}") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise PlanError(f"{where} is not valid TOML: {exc}") from None
    except RecursionError:  # tomllib recurses once per level of nested arrays or tables
        raise PlanError(f"{where}: arrays or tables nested too deep to be a plan file; give "
                        "a TOML sweep (docs/scenarios.md)") from None
    unknown = set(data) - _TOP_KEYS
    if unknown:
        raise PlanError(f"{where}: unknown keys {few(unknown)}; allowed: {sorted(_TOP_KEYS)}")
    scans = data.get("scans", PAPER_SCANS)
    if not isinstance(scans, int) or isinstance(scans, bool) or not 1 <= scans <= MAX_SCANS:
        raise PlanError(f"{where}: scans must be a whole number 1..{MAX_SCANS}, got {scans!r}")
    _check_settings(data, where)
    default_mount = _mount(data.get("mount"), where)
    refs: list[Reference] = []
    if "reference" in data:
        if "yaw_deg" in data or "x_mm" in data:
            raise PlanError(f"{where}: give either yaw_deg/x_mm axes or [[reference]] tables, "
                            "not both")
        if not isinstance(data["reference"], list):
            raise PlanError(f"{where}: reference must be an array of tables ([[reference]])")
        if len(data["reference"]) > MAX_REFERENCES:
            raise PlanError(f"{where}: {len(data['reference'])} references, more than the "
                            f"{MAX_REFERENCES} a plan may have")
        for i, r in enumerate(data["reference"]):
            if not isinstance(r, dict):
                raise PlanError(f"{where}: reference {i + 1} must be a table ([[reference]])")
            unknown = set(r) - _REF_KEYS
            if unknown:
                raise PlanError(f"{where}: reference {i + 1}: unknown keys {few(unknown)}")
            yaw, x = (_axis(r.get(k, 0.0), k, f"{where} reference {i + 1}")
                      for k in ("yaw_deg", "x_mm"))
            if len(yaw) != 1 or len(x) != 1:
                raise PlanError(f"{where}: reference {i + 1}: yaw_deg and x_mm must be numbers")
            mount = _mount(r.get("mount"), f"{where} reference {i + 1}") or default_mount
            label = str(r.get("label", f"yaw {yaw[0]:+g} deg, x {x[0]:+g} mm"))
            refs.append(Reference(math.radians(yaw[0]), x[0] * 1e-3, mount, label=label))
        kind = "toml"
    else:
        yaws = _axis(data.get("yaw_deg", 0.0), "yaw_deg", where)
        xs = _axis(data.get("x_mm", 0.0), "x_mm", where)
        if len(xs) * len(yaws) > MAX_REFERENCES:
            raise PlanError(f"{where}: {len(xs)} x values by {len(yaws)} yaw values is "
                            f"{len(xs) * len(yaws)} references, more than the "
                            f"{MAX_REFERENCES} a plan may have")
        for x, y in itertools.product(xs, yaws):
            refs.append(Reference(math.radians(y), x * 1e-3, default_mount,
                                  label=f"yaw {y:+g} deg, x {x:+g} mm"))
        # Report axis: the one that varies (yaw if both or neither do).
        kind = "x" if len(xs) > 1 and len(yaws) == 1 else "yaw" if len(xs) == 1 else "grid"
    settings = {"file": str(path.resolve()), "scans": scans}
    for key in ("method", "seed"):
        if key in data:
            settings[key] = data[key]
    if "board_mm" in data:
        try:
            size = station.board_mm(data["board_mm"], where)
        except station.StationError as exc:
            raise PlanError(str(exc)) from None
        settings["board_mm"] = [size["width_mm"], size["height_mm"]]
    return Plan(str(data.get("name", path.stem)), kind, tuple(refs), scans, settings)


def _check_settings(data: dict, where: str) -> None:
    """The top-level name, method and seed of a TOML plan, if given, are of the right kind."""
    for key in ("name", "method"):
        if key in data and not (isinstance(data[key], str) and data[key].strip()):
            raise PlanError(f"{where}: {key} must be a non-empty string, got {data[key]!r}")
    seed = data.get("seed", 0)
    if not isinstance(seed, int) or isinstance(seed, bool) or not 0 <= seed < 2**63:
        raise PlanError(f"{where}: seed must be a whole number 0..2**63-1, got {seed!r}")


def _mount(spec: object, where: str) -> dict[str, float] | None:
    if spec is None:
        return None
    if not isinstance(spec, dict):
        raise PlanError(f"{where}: mount must be a table of {', '.join(MOUNT_KEYS)}")
    unknown = set(spec) - set(MOUNT_KEYS)
    if unknown:
        raise PlanError(f"{where}: mount: unknown keys {few(unknown)}; allowed: "
                        f"{', '.join(MOUNT_KEYS)}")
    values = {k: spec.get(k, 0.0) for k in MOUNT_KEYS}
    bad = {k: v for k, v in values.items()
           if isinstance(v, bool) or not isinstance(v, int | float)}
    if bad:
        raise PlanError(f"{where}: mount values must be numbers, got {bad}")
    return {k: _finite(v, f"mount {k}", where) for k, v in values.items()}


def build(name: str, *, scans: int | None = None, seed: int = 0,
          poses: int | None = None) -> Plan:
    """A built-in plan by name (`BUILTIN`) or a plan from a ``.toml`` file path.

    scans: override the scans per reference (else the paper's default for that plan).
    seed: the Monte Carlo poses' seed. poses: Monte Carlo pose count (default 200).
    """
    if name in BUILTIN:
        kwargs: dict = {}
        if name == "montecarlo":
            kwargs["seed"] = seed
            if poses is not None:
                kwargs["poses"] = poses
        plan = BUILTIN[name](**kwargs)
    elif name.endswith(".toml") or Path(name).is_file():
        plan = from_toml(name)
    else:
        raise PlanError(f"unknown scenario {name!r}; use one of {', '.join(BUILTIN)} or a "
                        ".toml file")
    return plan.with_scans(scans) if scans is not None else plan


def references_beyond(plan: Plan, yaw_limits_rad: tuple[float, float],
                      x_limits_m: tuple[float, float]) -> Iterable[tuple[int, Reference]]:
    """The references (index, reference) whose stage command or `via` lies beyond the travel."""
    for i, r in enumerate(plan.references):
        points = [r.stage] + ([r.via] if r.via is not None else [])
        for p in points:
            if not (yaw_limits_rad[0] - 1e-12 <= p.yaw_rad <= yaw_limits_rad[1] + 1e-12
                    and x_limits_m[0] - 1e-12 <= p.x_m <= x_limits_m[1] + 1e-12):
                yield i, r
                break
