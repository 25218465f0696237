"""`RunConfig`: how a run is made (which bench, which estimator, which seed), typed.

The sweep command fills it from its options (and a TOML plan's defaults), the store keeps it as
JSON (`as_dict`) so that ``--resume``, the report and the replay use exactly what the run used,
and `from_dict` reads it back, with the defaults for keys an older store did not write.

The run keeps its station (`scenarios.station.Station`: the board, the mount, the stages, the
sensor) by content, not only by path: a resumed run, its report and its replay use the bench the
run used even if the file has changed or gone since.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
from typing import Any

from align.calibration import LaserCalibration
from scenarios.defaults import MAX_CONSECUTIVE_FAILURES
from scenarios.station import Station, StationError
from scenarios.station import default as default_station
from scenarios.station import from_dict as station_from_dict
from twin.core.errors import AimbenchError

#: Benches a run can use: the twin in process, the real one, the wire-level twin it starts.
BENCHES = ("sim", "hw", "serve")


@dataclass(frozen=True)
class RunConfig:
    """One run's settings (edge units where a unit shows: none do yet).

    scenario: the plan's name or TOML path as given. bench: one of `BENCHES`. port: the stage
    controller's serial port (``none`` for a bench without stages). lidar: the LiDAR source of a
    hardware bench (``udp://HOST:PORT`` or a capture). method: align's method (None: its default,
    resolved by name when the run is created). seed: the twin's noise and the Monte Carlo poses.
    ideal: the twin with every error source off. scans, poses: what the command line asked for.
    argv: the command line. demo: made by ``aimbench demo``. max_consecutive_failures: see
    `MAX_CONSECUTIVE_FAILURES`. jobs: worker processes (simulated bench only). calibration: the
    per-laser calibration applied to every scan (read once, from its file or the store), or
    None.
    station: the bench (`scenarios.station.Station`; default: the paper's), with any command
    line override (``--board-mm``) applied; station_file: the file it was read from, if any.
    sensor_id: the LiDAR's serial number or a user's id for it (None: not given; on the twin
    its seed names it), checked against the calibration's.
    """

    scenario: str | None = None
    bench: str = "sim"
    port: str | None = None
    lidar: str | None = None
    method: str | None = None
    seed: int = 0
    ideal: bool = False
    scans: int | None = None
    poses: int | None = None
    argv: tuple[str, ...] = ()
    demo: bool = False
    max_consecutive_failures: int = MAX_CONSECUTIVE_FAILURES
    jobs: int = 1
    calibration: LaserCalibration | None = field(default=None, hash=False, compare=False)
    station: Station = field(default_factory=default_station, hash=False, compare=False)
    station_file: str | None = None
    sensor_id: str | None = None

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready, the form the store keeps."""
        d = {f.name: getattr(self, f.name) for f in fields(self)}
        d["argv"] = list(self.argv)
        d["station"] = self.station.to_dict()
        d["calibration"] = self.calibration.to_dict() if self.calibration is not None else None
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> RunConfig:
        """From a stored configuration; unknown keys are ignored, missing ones take defaults."""
        d = dict(d or {})
        names = {f.name for f in fields(cls)}
        values = {k: v for k, v in d.items() if k in names and v is not None}
        if "argv" in values:
            values["argv"] = tuple(str(a) for a in values["argv"])
        for key in ("seed", "jobs", "max_consecutive_failures"):
            if key in values:
                values[key] = int(values[key])
        for key in ("ideal", "demo"):
            if key in values:
                values[key] = bool(values[key])
        if "station" in values:
            try:
                values["station"] = station_from_dict(values["station"], "the run's station")
            except StationError as exc:
                raise AimbenchError(f"{exc} (the run was stored by another aimbench version; "
                                    "start a new run)") from None
        if values.pop("calibration", None):  # parsed here once: the run uses the object
            try:
                values["calibration"] = LaserCalibration.from_dict(d["calibration"])
            except (ValueError, KeyError, TypeError, AttributeError) as exc:
                raise AimbenchError(f"the run's stored calibration cannot be read ({exc}; the "
                                    "run was stored by another aimbench version): start a new "
                                    "run") from None
        return cls(**values)

    def with_(self, **changes: Any) -> RunConfig:
        return replace(self, **changes)

    def lidar_decoding(self) -> dict[str, Any]:
        """How the run's LiDAR packets are decoded (`twin.lidar.sources.open_scans`'s ``model``
        and ``lasers``): as its station's sensor when the run named a station file
        (`scenarios.station.Station.decoding`), else as the packets' product id says."""
        return self.station.decoding() if self.station_file is not None else {}

    def check(self) -> None:
        """Refuse settings that cannot work, before a run folder is made."""
        if self.bench not in BENCHES:
            raise AimbenchError(f"unknown bench {self.bench!r}; use {', '.join(BENCHES)}")
        if self.bench == "hw" and not self.port:
            raise AimbenchError("--bench hw needs the stage controller's --port (e.g. "
                                "/dev/ttyACM0), or --port none for a LiDAR without stages or a "
                                "capture replay")
        if self.jobs < 1 or self.max_consecutive_failures < 1:
            raise AimbenchError(f"jobs ({self.jobs}) and max_consecutive_failures "
                                f"({self.max_consecutive_failures}) must be at least 1")
        if self.jobs > 1 and self.bench != "sim":
            raise AimbenchError("--jobs runs several simulated benches; there is one "
                                f"{'real' if self.bench == 'hw' else 'served'} bench: drop --jobs")
