"""The station file: one TOML file that describes a real bench, and from which the twin is built.

A `Station` says what a bench is (docs/station.md has every key): the target board (size,
thickness, pose in the bench frame, in-plane rotation, reflectivity, an optional printed
pattern), the sensor (model, factory calibration, network, the per-laser range calibration of
``aimbench calibrate``), the mount (lever arm from the rotation axis, the LiDAR's nominal
orientation on it and, for an inspection, its nominal pose in the station frame), the stages
(serial port, axis letters, travel, where they stand), the inspection's tolerances and decision
rule, and the station/vehicle frame the inspection reports in.

The same file configures the real bench (`aimbench sweep --bench hw`: the stage driver's axis
letters and travel, the LiDAR's address), the estimator (the board as align's `BoardSpec`) and
the twin (`bench_params`: the `twin.sim.params.BenchParams` the MuJoCo scene is compiled with),
so that ``--bench sim`` and ``--bench hw`` describe the same bench. The model's defaults are the
paper's bench, which ships as ``scenarios/stations/paper.toml``.

Units: the file is for people, so degrees and millimetres with the unit in every key name; the
accessors (`board_spec`, `bench_params`, `travel`...) return SI. Why pydantic (v2): a station
file is nested, typed and user-written; pydantic validates it with the location of every bad
key, refuses unknown keys (a typo must not be silently ignored) and dumps it back to JSON for
the run store, which hand-written dataclass checks would repeat for every field.
"""

from __future__ import annotations

import functools
import json
import math
import sys
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
    ValidationInfo,
    field_validator,
    model_validator,
)

# The command line's part (--station, the shipped stations, the default, the roll prior's SD)
# lives in station_options, which a command's parser imports without pydantic; these names stay
# reachable here, where the model and its users have always read them.
from scenarios.station_options import (
    DEFAULT_STATION,
    ROLL_PRIOR_SD_DEG,
    resolve,
    shipped,
)
from scenarios.station_options import STATIONS_PACKAGE as STATIONS_PACKAGE
from scenarios.station_options import add_arguments as add_arguments
from scenarios.station_options import shipped_path as shipped_path
from twin.core.errors import AimbenchError, one_line, short_repr
from twin.core.pose import Pose
from twin.core.sensors import MODELS, model_named

#: The sensor models aimbench can decode and emulate (twin/core/sensors.py).
SENSOR_MODELS = tuple(MODELS)
#: The decision rules an inspection may use (docs/station.md says what each does).
DECISION_RULES = ("iso14253-1", "vda5", "simple")

#: A pattern's smallest square, mm, and most squares: the twin builds each square as a geom,
#: and an absurdly fine chessboard (1e-3 mm squares) took minutes and gigabytes (issue 37);
#: a VLP-16's beam is ~10 mm wide at 2.5 m, so finer squares are not seen anyway.
MIN_SQUARE_MM = 5.0
MAX_SQUARES = 2500

#: A board whose both sides are below this, mm, is a size in metres given as millimetres.
MIN_BOARD_MM = 20.0

Mm = StrictFloat
Deg = StrictFloat
Positive = Annotated[StrictFloat, Field(gt=0)]
NonNegative = Annotated[StrictFloat, Field(ge=0)]
Reflectance = Annotated[StrictFloat, Field(ge=0, le=1)]
Vec3 = tuple[StrictFloat, StrictFloat, StrictFloat]


#: A sensor model's range accuracy where `twin.core.sensors` has none, m (the VLP-16's +-30 mm).
DEFAULT_RANGE_ACCURACY = 0.03
#: The 1-sigma a known, non-zero common offset (``range_offset_std_mm = 0``) is given, m: far
#: below any estimate's, so that the estimate applies it rather than estimating it.
KNOWN_OFFSET_STD = 1e-5


class StationError(AimbenchError):
    """A station file that cannot be read or is not valid (the message names the key)."""


class _Section(BaseModel):
    """A table of the station file: typed, frozen, no unknown keys, defaults validated too."""

    # allow_inf_nan=False: every float of a station is finite. A NaN mount angle made the twin
    # loop forever on MuJoCo warnings and an inspection store a record with x NaN (issue 37).
    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True,
                              allow_inf_nan=False)


class PoseMmDeg(_Section):
    """A pose in edge units: position in mm, roll/tilt/yaw in deg (R = Rz(yaw) Rx(tilt) Ry(roll),
    docs/DESIGN.md)."""

    x_mm: Mm = 0.0
    y_mm: Mm = 0.0
    z_mm: Mm = 0.0
    roll_deg: Deg = 0.0
    tilt_deg: Deg = 0.0
    yaw_deg: Deg = 0.0

    def to_pose(self) -> Pose:
        return Pose.from_edge(**self.model_dump())


class Pattern(_Section):
    """A pattern printed on the board's face: a chessboard of ``squares`` (columns x rows) of
    ``square_mm``, centred on the board (offset by ``offset_mm`` in the board plane, x right and
    z up), its squares alternately ``dark_reflectivity`` (the top-left one, seen from the LiDAR)
    and ``light_reflectivity``; defaults as the twin's `BoardPattern` (a black print, white
    paper). A dark reflectivity of 0 returns nothing, as black squares do on some sensors."""

    kind: Literal["chessboard"] = "chessboard"
    squares: tuple[Annotated[StrictInt, Field(ge=1)], Annotated[StrictInt, Field(ge=1)]]
    square_mm: Annotated[StrictFloat, Field(ge=MIN_SQUARE_MM)]
    dark_reflectivity: Reflectance = 0.03
    light_reflectivity: Reflectance = 0.8
    offset_mm: tuple[StrictFloat, StrictFloat] = (0.0, 0.0)

    @model_validator(mode="after")
    def _few_enough(self) -> Pattern:
        n = self.squares[0] * self.squares[1]
        if n > MAX_SQUARES:
            raise ValueError(f"{self.squares[0]} x {self.squares[1]} = {n} squares; the twin "
                             f"draws each as a body, at most {MAX_SQUARES} (larger squares: "
                             "a LiDAR's beam is about 10 mm wide at the board anyway)")
        return self


class Board(_Section):
    """The target board. Its frame {O} (docs/DESIGN.md) has its origin at the centre of the front
    face; the pose is that of {O} in the bench frame."""

    width_mm: Positive = 900.0
    height_mm: Positive = 540.0
    thickness_mm: NonNegative = 3.0  # 0: a printed sheet
    #: Centre of the front face in the bench frame, mm (paper: 0.5 m above the floor).
    position_mm: Vec3 = (0.0, 0.0, 500.0)
    #: Turned about the vertical (positive: the face turns to the left seen from above), deg.
    yaw_deg: Deg = 0.0
    #: Tipped about its horizontal edge (positive: the face looks up), deg.
    tilt_deg: Deg = 0.0
    #: Rotated in its own plane, about its normal, clockwise as seen from the LiDAR, deg
    #: (45: a diamond).
    in_plane_deg: Deg = 0.0
    #: Diffuse (Lambertian) reflectance of the face, 0..1 (bare aluminium, assumed 0.55).
    reflectivity: Reflectance = 0.55
    pattern: Pattern | None = None
    #: How far the board's centre may be from where this station puts it, as the LiDAR at
    #: its nominal pose sees it, mm: the board's own placement and the unit's mounting
    #: tolerance together. Given, the estimate never takes an object beyond it for the board
    #: (`align.Hints.board_region`; status board_outside_region) and weighs the candidates
    #: within it. None: the board may be anywhere the search looks.
    position_tolerance_mm: Positive | None = None

    @model_validator(mode="after")
    def _pattern_fits(self) -> Board:
        p = self.pattern
        if p is not None:
            w, h = p.squares[0] * p.square_mm, p.squares[1] * p.square_mm
            if (w / 2 + abs(p.offset_mm[0]) > self.width_mm / 2 + 1e-9
                    or h / 2 + abs(p.offset_mm[1]) > self.height_mm / 2 + 1e-9):
                raise ValueError(f"the pattern's {w:g} x {h:g} mm (pattern.squares x square_mm, "
                                 f"plus offset_mm) do not fit on the {self.width_mm:g} x "
                                 f"{self.height_mm:g} mm board")
        return self


class Network(_Section):
    """Where the LiDAR's data packets arrive: the address to listen on and the data port."""

    host: StrictStr = "0.0.0.0"
    port: Annotated[StrictInt, Field(ge=1, le=65535)] = 2368


def _existing_file(value: str | None, info: ValidationInfo, what: str) -> str | None:
    """A path of the file resolved against the station file's folder; when read from a file
    (context ``base``), it must exist."""
    if value is None:
        return None
    ctx = info.context or {}
    base = ctx.get("base")
    path = Path(value).expanduser()
    if base is not None and not path.is_absolute():
        path = Path(base) / path
    if ctx.get("check_files") and not path.is_file():
        raise ValueError(f"no such file {path}; {what}")
    return str(path)


class Sensor(_Section):
    """The LiDAR: its model, the unit's factory calibration, its network and the per-laser
    range calibration (`aimbench calibrate`) every scan gets before estimating. A station file
    given to a command decodes the sensor's packets as its model with the factory calibration's
    laser table (`Station.decoding`), as ``--model`` and ``--sensor-calibration`` do."""

    #: One of `SENSOR_MODELS` (as users write it: ``VLP-32C``, ``vlp32c``... kept by its name).
    model: StrictStr = "VLP-16"
    #: The unit's factory calibration (Velodyne's db.xml or the ROS driver's YAML), if any.
    calibration_file: StrictStr | None = None
    #: The per-laser range calibration written by `aimbench calibrate`, if any.
    range_calibration: StrictStr | None = None
    #: The unit's common range offset (what it adds to every range), mm, and its 1-sigma: the
    #: estimate's prior on it (`align.Hints.range_offset_prior`), so that the offset is
    #: estimated with the pose. A unit measured before: its value and standard error. Not
    #: given (a new unit, the default): 0 and the datasheet's spread, its range accuracy
    #: taken as a uniform's half width (the VLP-16's +-30 mm: 17.3 mm; `datasheet_offset_std`).
    #: 0: the offset is known to be ``range_offset_mm`` and not estimated. A per-laser range
    #: calibration applied to the scans (`aimbench calibrate`) measured the offset: then it is
    #: not estimated either.
    range_offset_mm: StrictFloat = 0.0
    range_offset_std_mm: NonNegative | None = None
    #: 1-sigma of the unit's per-laser range offsets, mm (the paper: up to 5 mm): carried in
    #: the covariance (`align.Hints.laser_offset_sigma`) of an estimate from ranges that no
    #: range calibration corrected; one that is applied removes them (`range_offset_hints`).
    #: Default the paper's: a Velodyne unit's are there unless a calibration removed them.
    laser_offset_std_mm: NonNegative = 2.5
    network: Network = Network()

    @field_validator("model")
    @classmethod
    def _known_model(cls, value: str) -> str:
        try:
            return model_named(value).name
        except KeyError:
            pass
        from twin.lidar.ouster import OUSTER_MODELS, ouster_model_name

        ouster = ouster_model_name(value)
        if ouster is not None:  # an Ouster: read with its metadata JSON (--metadata)
            return ouster
        from twin.lidar.hesai import HESAI_MODELS, hesai_model

        hesai = hesai_model(value)
        if hesai is not None:  # a Hesai: read with its angle-correction file (--angles)
            return hesai.name
        raise ValueError(f"unknown sensor model {value!r}; aimbench knows "
                         f"{', '.join((*SENSOR_MODELS, *OUSTER_MODELS, *HESAI_MODELS))}")

    @field_validator("calibration_file")
    @classmethod
    def _factory_file(cls, value: str | None, info: ValidationInfo) -> str | None:
        return _existing_file(value, info, "give the unit's factory calibration file or remove "
                                           "the key")

    @field_validator("range_calibration")
    @classmethod
    def _range_file(cls, value: str | None, info: ValidationInfo) -> str | None:
        return _existing_file(value, info, "make one with `aimbench calibrate` or remove the key")


class Mount(_Section):
    """How the LiDAR sits. ``lever_arm_mm``: the optical centre relative to the rotation axis on
    the rotation stage's top face, in the turntable's frame (x right, y forward at stage yaw 0,
    z up), mm. ``roll_deg``, ``tilt_deg``, ``yaw_deg``: the LiDAR's orientation on the turntable
    when perfectly mounted (the twin mounts it so; a Monte Carlo misalignment adds to it).
    ``nominal``: the LiDAR's intended pose in the station frame, what an inspection measures
    the mounting error from (None: not stated)."""

    lever_arm_mm: Vec3 = (0.0, 0.0, 60.0)
    roll_deg: Deg = 0.0
    tilt_deg: Deg = 0.0
    yaw_deg: Deg = 0.0
    nominal: PoseMmDeg | None = None


AxisLetter = Literal["X", "Y", "Z", "A", "B", "C"]


class Stages(_Section):
    """The stage controller (Grbl subset, bench_fw/PROTOCOL.md) and where its stages stand.

    port: serial port or pyserial URL (None: give ``--port``; ``none``: a bench without stages).
    x_axis, yaw_axis: the Grbl axis letters of the linear and the rotation stage.
    x_travel_mm, yaw_travel_deg: the travel a plan may use, relative to the bench reference
    (mid-travel; the controller's own settings limit it further).
    base_position_mm: the floor point of the sensor module's stand in the bench frame (paper:
    0.7 m to the board's side, 2.5 m in front of it; models/bench_frame.xml explains the sign).
    """

    port: StrictStr | None = None
    x_axis: AxisLetter = "X"
    yaw_axis: AxisLetter = "A"
    x_travel_mm: tuple[StrictFloat, StrictFloat] = (-50.0, 50.0)
    yaw_travel_deg: tuple[StrictFloat, StrictFloat] = (-30.0, 30.0)
    base_position_mm: Vec3 = (700.0, -2500.0, 0.0)

    @field_validator("x_travel_mm", "yaw_travel_deg")
    @classmethod
    def _holds_reference(cls, value: tuple[float, float]) -> tuple[float, float]:
        lo, hi = value
        if not lo <= 0.0 <= hi:
            raise ValueError(f"[{lo:g}, {hi:g}] must hold the bench reference 0 (give "
                             "[min, max] with min <= 0 <= max)")
        return value

    @model_validator(mode="after")
    def _two_axes(self) -> Stages:
        if self.x_axis == self.yaw_axis:
            raise ValueError(f"x_axis and yaw_axis are both {self.x_axis!r}; give two different "
                             "Grbl axis letters (X and A on the paper's bench)")
        return self


Limit = Annotated[StrictFloat, Field(gt=0)] | None


class SystemSigma(_Section):
    """The measurement system's own 1-sigma per axis beyond the estimator's covariance (0: none
    stated): what the estimator does not know of, such as a new unit's uncalibrated per-laser
    range offsets or the fixture's placement, measured by the inspection's bias study (`aimbench
    grr --bias`, docs/inspection.md). Added in quadrature to every unit's estimator sigma."""

    x_mm: NonNegative = 0.0
    y_mm: NonNegative = 0.0
    z_mm: NonNegative = 0.0
    roll_deg: NonNegative = 0.0
    tilt_deg: NonNegative = 0.0
    yaw_deg: NonNegative = 0.0


class Tolerances(_Section):
    """An inspection's specification: the largest allowed mounting error per axis (None: the
    axis is not judged) and the decision rule. ``iso14253-1``: PASS only when the error plus its
    expanded uncertainty (``coverage_k`` sigma) is inside the limit, FAIL when the error minus
    it is outside, otherwise inconclusive; ``vda5``: VDA 5's acceptance, PASS only inside the
    tolerance narrowed by that expanded uncertainty, otherwise FAIL; ``simple``: the error
    alone against the limit.
    Example limits: the paper states none; its method's accuracy (0.2 deg, 4 mm) fits well
    inside these. y and z are not judged (the paper inspects orientation and horizontal
    position only)."""

    roll_deg: Limit = 1.0
    tilt_deg: Limit = 1.0
    yaw_deg: Limit = 1.0
    x_mm: Limit = 10.0
    y_mm: Limit = None
    z_mm: Limit = None
    rule: Literal["iso14253-1", "vda5", "simple"] = "iso14253-1"
    coverage_k: Positive = 2.0
    system_sigma: SystemSigma = SystemSigma()


class StationFrame(_Section):
    """The station (or vehicle) frame {S} an inspection reports the mounting pose in, as its pose
    in the bench frame (axes as the bench's: X right, Y towards the board, Z up). Identity: {S}
    is the bench frame (origin on the floor below the board's nominal centre)."""

    name: StrictStr = "bench"
    pose: PoseMmDeg = PoseMmDeg()


class Twin(_Section):
    """What only the twin uses: the scene the simulated bench stands in (`models.SCENES`:
    "bench", the paper's floor, wall and beams; "lab", the same bench in a cluttered lab)."""

    scene: Literal["bench", "lab"] = "bench"


class LineUser(_Section):
    """Someone who may log in to the line station (`aimbench station`): the web pages and, for
    the PLC's account, OPC UA. ``password_scrypt``: the password's scrypt hash as `aimbench
    station --hash-password` prints it (never the password itself)."""

    name: Annotated[StrictStr, Field(min_length=1)]
    role: Literal["operator", "engineer", "plc"]
    password_scrypt: Annotated[StrictStr, Field(pattern=r"^scrypt\$")]


class OpcUa(_Section):
    """The station's OPC UA server for the line's PLC. ``anonymous``: anyone who reaches the
    port may trigger inspections, no security policy (a closed cell network only); otherwise
    users with the role ``plc`` log in by name and password over Basic256Sha256
    SignAndEncrypt with the station's certificate (generated, self-signed, when the files
    named here do not exist), from a client whose own certificate is in ``trust_list``: a
    folder of the trusted client certificates, or of the CAs that issued them (DER or PEM),
    created empty on first start, read again at every new session (a PLC added needs no
    restart). Relative paths are beside the store."""

    port: Annotated[StrictInt, Field(ge=1, le=65535)] = 4840
    anonymous: StrictBool = True
    certificate: StrictStr = "station-cert.der"
    private_key: StrictStr = "station-key.pem"
    trust_list: Annotated[StrictStr, Field(min_length=1)] = "opcua-trusted"


class Line(_Section):
    """The line station (`aimbench station`, docs/station-line.md): the address its web pages,
    HTTP/JSON endpoint and OPC UA server listen on (the machine itself unless named), the
    web port, who may log in and as what, and the OPC UA server's security."""

    address: StrictStr = "127.0.0.1"
    port: Annotated[StrictInt, Field(ge=1, le=65535)] = 8080
    users: tuple[LineUser, ...] = ()
    opcua: OpcUa = OpcUa()

    @model_validator(mode="after")
    def _unique_users(self) -> Line:
        names = [u.name for u in self.users]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"users named twice: {dup}")
        return self


class Station(_Section):
    """A bench, as the station file describes it (module docstring; docs/station.md)."""

    name: StrictStr = "paper"
    description: StrictStr = ""
    board: Board = Board()
    sensor: Sensor = Sensor()
    mount: Mount = Mount()
    stages: Stages = Stages()
    tolerances: Tolerances = Tolerances()
    frame: StationFrame = StationFrame()
    twin: Twin = Twin()
    line: Line = Line()

    # -- what the rest of aimbench takes (SI) -------------------------------------------------
    def board_spec(self) -> Any:
        """align's `BoardSpec`: the board's size and thickness, m."""
        from align.board import BoardSpec

        b = self.board
        return BoardSpec(*_m((b.width_mm, b.height_mm, b.thickness_mm)))

    def roll_prior(self) -> tuple[float, float] | None:
        """The estimator's prior on the LiDAR's roll in the board frame (`align.Hints.roll_prior`,
        rad): where a nominally mounted LiDAR sees a board hung turned in its plane, within
        `ROLL_PRIOR_SD_DEG`. None for a board hung level (in_plane_deg 0): the search then
        covers every rotation, as it always did on such benches."""
        if self.board.in_plane_deg == 0.0:
            return None
        m = self.mount
        r_wl = Pose(0.0, 0.0, 0.0, math.radians(m.roll_deg), math.radians(m.tilt_deg),
                    math.radians(m.yaw_deg)).rotation()
        r_ol = self.board_in_bench()[:3, :3].T @ r_wl
        roll = Pose.from_matrix(r_ol, np.zeros(3)).roll
        return roll, math.radians(ROLL_PRIOR_SD_DEG)

    def board_region(self, lidar_in_station: Pose | None) -> tuple[tuple[float, float, float],
                                                                   float] | None:
        """The board's region as the LiDAR at ``lidar_in_station`` (its nominal pose) sees it:
        (the board's centre in {L}, m; the radius, m), as `align.Hints.board_region`; None
        without ``board.position_tolerance_mm`` or a nominal pose."""
        tol = self.board.position_tolerance_mm
        if tol is None or lidar_in_station is None:
            return None
        centre_l = self._board_centre_seen(lidar_in_station)
        return (float(centre_l[0]), float(centre_l[1]), float(centre_l[2])), tol * 1e-3

    def board_distance(self, lidar_in_station: Pose | None) -> float | None:
        """How far the board's centre is from the LiDAR at ``lidar_in_station`` (its nominal
        pose), m, as `align.Hints.expected_distance`: what a line states of every unit (a
        board-sized panel hiding the board, 1 m nearer, is then refused); None without a
        nominal pose."""
        if lidar_in_station is None:
            return None
        return float(np.linalg.norm(self._board_centre_seen(lidar_in_station)))

    def _board_centre_seen(self, lidar_in_station: Pose) -> np.ndarray:
        """The board's centre in the frame {L} of the LiDAR at ``lidar_in_station``, m."""
        w_from_s = self.frame.pose.to_pose().matrix()
        w_from_l = w_from_s @ lidar_in_station.matrix()
        centre_w = self.board_in_bench()[:3, 3]
        return np.linalg.solve(w_from_l, np.append(centre_w, 1.0))[:3]

    def datasheet_offset_std(self) -> float:
        """A new unit's common range offset's 1-sigma, m: the sensor model's datasheet range
        accuracy (+-a, "typical") taken as a uniform's half width, a / sqrt(3). A model without
        one in `twin.core.sensors` (an Ouster, a Hesai): +-30 mm, the VLP-16's."""
        try:
            accuracy = model_named(self.sensor.model).range_accuracy
        except KeyError:
            accuracy = DEFAULT_RANGE_ACCURACY
        return accuracy / math.sqrt(3.0)

    def range_offset_hints(self, calibrated: bool = False) -> dict[str, Any]:
        """The sensor's range-offset priors as `align.Hints` fields, m (`Sensor.range_offset_mm`
        says when the common offset is estimated). ``calibrated``: a per-laser range
        calibration is applied to the scans, so the common and per-laser offsets it measured
        are gone (what is left of them is its standard errors: far below the estimate's
        noise), not estimated and not put into the covariance."""
        s = self.sensor
        mean = s.range_offset_mm * 1e-3
        if calibrated:
            prior = None
        elif s.range_offset_std_mm is None:
            prior = (mean, self.datasheet_offset_std())
        elif s.range_offset_std_mm == 0.0:  # known: applied, not estimated
            prior = None if mean == 0.0 else (mean, KNOWN_OFFSET_STD)
        else:
            prior = (mean, s.range_offset_std_mm * 1e-3)
        laser = 0.0 if calibrated else s.laser_offset_std_mm * 1e-3
        return {"range_offset_prior": prior, "laser_offset_sigma": laser}

    def estimate_hints(self, calibrated: bool = False) -> Any:
        """align's `Hints` for this station's scans at any stage pose: the roll prior and the
        range offsets (`range_offset_hints`). The board's region is not among them: it holds at
        the nominal pose only (`board_region`)."""
        import align

        return align.Hints(roll_prior=self.roll_prior(),
                           **self.range_offset_hints(calibrated=calibrated))

    def bench_params(self, **changes: Any) -> Any:
        """The twin's `twin.sim.params.BenchParams` for this station (``changes``: fields to set
        besides, e.g. a reflectivity override). Imported lazily: MuJoCo only when a twin is
        built."""
        from twin.sim.params import BenchParams, BoardPattern

        b, m = self.board, self.mount
        p = b.pattern
        pattern = None if p is None else BoardPattern(
            rows=p.squares[1], cols=p.squares[0], square=float(p.square_mm) / 1000.0,
            dark_reflectivity=p.dark_reflectivity, light_reflectivity=p.light_reflectivity,
            offset=_m(p.offset_mm))
        values: dict[str, Any] = {
            **dict(zip(("board_width", "board_height", "board_thickness"),
                       _m((b.width_mm, b.height_mm, b.thickness_mm)), strict=True)),
            "board_position": _m(b.position_mm),
            # R = Rz(yaw) Rx(tilt) Ry(roll): roll about the board's normal Y_O is the in-plane
            # rotation.
            "board_roll": math.radians(b.in_plane_deg), "board_tilt": math.radians(b.tilt_deg),
            "board_yaw": math.radians(b.yaw_deg), "board_reflectivity": b.reflectivity,
            "board_pattern": pattern,
            "lever_arm": _m(m.lever_arm_mm),
            "mount_roll": math.radians(m.roll_deg), "mount_tilt": math.radians(m.tilt_deg),
            "mount_yaw": math.radians(m.yaw_deg),
            "sensor_module_position": _m(self.stages.base_position_mm),
            "scene": self.twin.scene,
        }
        values.update(changes)
        return BenchParams(**values)

    def travel(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """((yaw_min_rad, yaw_max_rad), (x_min_m, x_max_m)) the station allows, as
        `scenarios.bench.Bench.travel`."""
        s = self.stages
        return ((math.radians(s.yaw_travel_deg[0]), math.radians(s.yaw_travel_deg[1])),
                _m(s.x_travel_mm))

    @property
    def axis_letters(self) -> tuple[str, str]:
        """(linear, rotation) Grbl axis letters, as `StageController` takes them."""
        return (self.stages.x_axis, self.stages.yaw_axis)

    def factory_lasers(self) -> Any:
        """The laser table (`twin.core.lasers.LaserTable`) of the sensor's factory calibration
        file, None without one; a `StationError` naming the key if the file cannot be read or
        is another model's (another number of lasers)."""
        path = self.sensor.calibration_file
        if path is None:
            return None
        from twin.lidar.calibration_file import read_calibration_file

        try:
            table, _ = read_calibration_file(path)
        except AimbenchError as exc:
            raise StationError(f"sensor.calibration_file: {exc}; see docs/station.md") from None
        if self.sensor.model not in SENSOR_MODELS:
            raise StationError(f"sensor.calibration_file {path}: a Velodyne calibration file, but "
                               f"sensor.model is {self.sensor.model} (an Ouster reads its "
                               "metadata JSON, --metadata; a Hesai its angle file, "
                               "--angles); see docs/station.md")
        model = model_named(self.sensor.model)
        if table.n_lasers != model.n_lasers:
            raise StationError(f"sensor.calibration_file {path}: {table.n_lasers} lasers, but a "
                               f"{model.name} (sensor.model) has {model.n_lasers}; give that "
                               "unit's file or its model; see docs/station.md")
        return table

    def decoding(self) -> dict[str, Any]:
        """How this station's sensor is decoded, as `twin.lidar.sources.open_scans` takes it:
        ``model`` (sensor.model, whatever the packets' product id says, as ``--model``) and
        ``lasers`` (sensor.calibration_file's table, as ``--sensor-calibration``; None: the
        model's nominal one)."""
        return {"model": self.sensor.model, "lasers": self.factory_lasers()}

    def lidar_url(self) -> str:
        """The LiDAR source of the sensor's network: ``udp://HOST:PORT``."""
        n = self.sensor.network
        return f"udp://{n.host}:{n.port}"

    def board_in_bench(self) -> np.ndarray:
        """4 x 4 transform of the board frame {O} into the bench frame {W}."""
        b = self.board
        return Pose(*_m(b.position_mm), math.radians(b.in_plane_deg), math.radians(b.tilt_deg),
                    math.radians(b.yaw_deg)).matrix()

    def lidar_in_station(self, pose_in_board: Pose) -> Pose:
        """The LiDAR's pose in the station frame {S} from its pose in the board frame (what the
        estimator returns): {S} <- {W} <- {O} <- {L}."""
        w_from_s = self.frame.pose.to_pose().matrix()
        s_from_l = np.linalg.solve(w_from_s, self.board_in_bench() @ pose_in_board.matrix())
        return Pose.from_matrix(s_from_l[:3, :3], s_from_l[:3, 3])

    def with_board(self, where: str = "the command line", **board_mm: float | None) -> Station:
        """The same station with board keys changed (``--board-mm``: width_mm and height_mm;
        ``--board-thickness-mm``), validated again; `where` names the override in errors."""
        changes = {k: float(v) for k, v in board_mm.items() if v is not None}
        if not changes:
            return self
        data = self.model_dump()
        data["board"].update(changes)
        return from_dict(data, where=where)

    def notes(self, twin: bool = False) -> list[str]:
        """What of this station a command does not apply (said, never silently dropped): on
        the twin, the factory calibration file (the twin emulates the model's nominal lasers;
        decoding applies the file)."""
        out = []
        if twin and self.sensor.calibration_file:
            out.append(f"sensor.calibration_file {self.sensor.calibration_file} decodes the real "
                       f"sensor's packets; the twin emulates the {self.sensor.model}'s nominal "
                       "laser table")
        return out

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready, the form a run's configuration keeps (file paths resolved). Without the
        line station's users: their password hashes belong in the station file only, not in
        every record, the station's hash or the engineer's page."""
        return self.model_dump(mode="json", exclude={"line": {"users"}})


def _m(mm: tuple[float, ...]) -> tuple[float, ...]:
    # Divided, not multiplied by 1e-3: 700 mm is then exactly the paper's 0.7 m.
    return tuple(float(v) / 1000.0 for v in mm)


# -- reading -----------------------------------------------------------------------------------

def from_dict(data: dict[str, Any], where: str = "station", *, base: Path | None = None,
              check_files: bool = False) -> Station:
    """A `Station` from the file's tables; a `StationError` naming each bad key otherwise.

    base: the folder relative file paths are resolved against; check_files: refuse a named
    file that does not exist (when read from a file; a stored run's station is taken as is).
    """
    try:
        return Station.model_validate(data, context={"base": base, "check_files": check_files})
    except ValidationError as exc:
        raise StationError(f"{where}: {_describe(exc)}; see docs/station.md") from None


def load(spec: str | Path | None = None) -> Station:
    """The station of a file path, of a shipped example's name (``paper``), or the default."""
    path = resolve(spec)
    try:
        text = path.read_text(encoding="utf-8")
        if path.suffix == ".json":
            # A station as a run stores it (`Station.to_dict`): `aimbench serve` gets it so.
            return from_dict(json.loads(text), str(path))
    except FileNotFoundError:
        raise StationError(f"no such station file {path}; give a TOML station file "
                           f"(docs/station.md) or one of: {', '.join(shipped())}") from None
    except (IsADirectoryError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise StationError(f"{path} is not a station file ({exc}); give a TOML file") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise StationError(f"{path} is not valid TOML: {exc}") from None
    except RecursionError:  # tomllib recurses once per level of nested arrays or tables
        raise StationError(f"{path}: arrays or tables nested too deep to be a station file; "
                           "give a TOML station file (docs/station.md)") from None
    return from_dict(data, str(path), base=path.parent, check_files=True)


def board_mm(text: str | list | tuple, where: str) -> dict[str, float]:
    """``"900x540"`` (the CLI's form) or ``[900, 540]`` (a TOML list) to width_mm, height_mm."""
    values: list = []
    if isinstance(text, str):
        try:
            values = [float(v) for v in text.lower().split("x")]
        except ValueError:
            values = []
    elif isinstance(text, list | tuple) and all(
            isinstance(v, int | float) and not isinstance(v, bool) for v in text):
        values = [float(v) for v in text]
    if len(values) != 2 or not min(values) > 0 or not math.isfinite(max(values)):
        raise StationError(f"{where}: board_mm {text!r}: give WIDTHxHEIGHT in mm, e.g. "
                           "\"900x540\" (or [900, 540] in a TOML file)")
    if max(values) < MIN_BOARD_MM:
        # 0.9x0.54: metres given for millimetres; every scan then said "no cluster looks like
        # the board" (issue 37).
        raise StationError(f"{where}: board_mm {text!r} is {values[0]:g} x {values[1]:g} mm, "
                           f"smaller than any target board; did you mean "
                           f"{values[0] * 1000:g}x{values[1] * 1000:g} (the size in mm)?")
    return {"width_mm": values[0], "height_mm": values[1]}


def from_args(args: Any, twin: bool = False) -> tuple[Station, str | None]:
    """The station a command's ``--station`` names, with ``--board-mm`` (and
    ``--board-thickness-mm`` where a command has it) applied; and the file it came from. Its
    `Station.notes` go to stderr (``twin``: the command builds the twin)."""
    spec = getattr(args, "station", None)
    station = load(spec)
    changes: dict[str, float | None] = {}
    if getattr(args, "board_mm", None) is not None:
        changes.update(board_mm(args.board_mm, "--board-mm"))
    changes["thickness_mm"] = getattr(args, "board_thickness_mm", None)
    station = station.with_board("--board-mm / --board-thickness-mm", **changes)
    for note in station.notes(twin):
        print(f"aimbench: note: {note}", file=sys.stderr)
    return station, (str(resolve(spec).resolve()) if spec is not None else None)


@functools.cache
def default() -> Station:
    """The default station: the shipped paper's bench (read once; a `Station` is frozen)."""
    return load(DEFAULT_STATION)


def _describe(exc: ValidationError) -> str:
    """The validation errors as one line: ``key.path: problem (got value)`` joined by ``; ``."""
    parts = []
    for err in exc.errors(include_url=False):
        loc = [str(p) for p in err["loc"]]
        # A tuple's element index: name the key and say how many values it takes.
        while loc and loc[-1].isdigit():
            loc.pop()
        key = ".".join(loc) or "station"
        kind = err["type"]
        if kind == "extra_forbidden":
            parts.append(f"{key}: unknown key; allowed here: {', '.join(_allowed(loc[:-1]))}")
            continue
        msg = err["msg"].removeprefix("Value error, ")
        if kind in ("missing", "too_short", "too_long", "tuple_type") and _arity(loc):
            msg = f"expects a list of {_arity(loc)} numbers"
        elif kind == "missing":
            msg = "required key missing"
        elif kind in ("model_type", "dict_type"):
            msg = f"must be a table ([{key}] or {key} = {{...}})"
        got = err.get("input")
        # A value error's own message already says what it got.
        if kind not in ("missing", "value_error") and not isinstance(got, dict):
            msg += f" (got {short_repr(got)})"
        parts.append(f"{key}: {msg}")
    # One message per key (a tuple's elements would repeat it).
    return one_line(list(dict.fromkeys(parts)))


def _model_at(loc: list[str]) -> type[BaseModel] | None:
    model: type[BaseModel] | None = Station
    for name in loc:
        field = model.model_fields.get(name) if model is not None else None
        if field is None:
            return None
        model = section_type(field.annotation)
    return model


def section_type(annotation: Any) -> type[BaseModel] | None:
    """The station section (a pydantic model) a field's annotation holds, e.g. through
    ``Section | None``; None for a plain value."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in getattr(annotation, "__args__", ()):
        found = section_type(arg)
        if found is not None:
            return found
    return None


def _allowed(loc: list[str]) -> list[str]:
    model = _model_at(loc)
    return list(model.model_fields) if model is not None else []


def _arity(loc: list[str]) -> int | None:
    """How many values a tuple key takes (None: not a tuple key)."""
    if not loc:
        return None
    model = _model_at(loc[:-1])
    field = model.model_fields.get(loc[-1]) if model is not None else None
    if field is None or getattr(field.annotation, "__origin__", None) is not tuple:
        return None
    return len(field.annotation.__args__)
