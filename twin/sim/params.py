"""Bench parameters a user sets without editing XML, applied to the compiled model.

The MJCF in ``models/`` holds the nominal bench (paper, section IV-A). A `BenchParams` describes
the physical bench you actually have: how the LiDAR sits on its mount (roll, tilt, yaw and the
lever arm from the rotation axis to the optical centre), the board's size and pose, and the
reflectivity of the board and of everything else. `build_model` loads ``models/scene.xml`` into a
`mujoco.MjSpec`, edits the named elements and compiles. SI units (m, rad); reflectivity is the
diffuse (Lambertian) reflectance 0..1.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import mujoco
import numpy as np
from scipy.spatial.transform import Rotation

from models import SCENES

#: Names of the model elements this module edits (kept in one place so the MJCF and code agree).
BOARD_BODY = "target_board"
BOARD_GEOM = "board"
BOARD_STAND_BODY = "target_stand"
SENSOR_BODY = "vlp16"
SENSOR_MODULE_BODY = "sensor_module"
#: Name prefix of a patterned board's squares (geoms of the board body): ``board_square_R_C``.
PATTERN_GEOM_PREFIX = "board_square_"


def _quat_wxyz(roll: float, tilt: float, yaw: float) -> np.ndarray:
    """MuJoCo quaternion (w, x, y, z) of R = Rz(yaw) Rx(tilt) Ry(roll) (DESIGN.md convention)."""
    x, y, z, w = Rotation.from_euler("ZXY", [yaw, tilt, roll]).as_quat()
    return np.array([w, x, y, z])


@dataclass(frozen=True)
class BoardPattern:
    """A chessboard printed on the board's face: ``rows`` x ``cols`` squares of side ``square``.

    The squares alternate between two diffuse reflectances, the top-left one (seen from the
    LiDAR: -X_O, +Z_O) ``dark``; the pattern is centred on the board's face at ``offset`` (X_O,
    Z_O), m. Each square is a box geom ``print_thickness`` thick in front of the face (paper on
    the plate: a print stands proud of it, and a coplanar pair of faces would leave the ray cast
    to pick either), so the patterned face lies that much nearer the LiDAR than the bare plate.
    A dark reflectance of 0 returns nothing (the squares drop out, as black squares do on some
    sensors). SI units.
    """

    rows: int
    cols: int
    square: float
    dark_reflectivity: float = 0.03
    light_reflectivity: float = 0.8
    offset: tuple[float, float] = (0.0, 0.0)
    print_thickness: float = 1e-4

    def __post_init__(self) -> None:
        if self.rows < 1 or self.cols < 1 or not self.square > 0:
            raise ValueError("a board pattern needs rows, cols >= 1 and a positive square (m)")
        if not self.print_thickness > 0:
            raise ValueError("print_thickness must be positive (m): MuJoCo boxes need it")
        for name in ("dark_reflectivity", "light_reflectivity"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} is a diffuse reflectance in [0, 1]")

    @property
    def size(self) -> tuple[float, float]:
        """Width (along X_O) and height (along Z_O) of the pattern, m."""
        return self.cols * self.square, self.rows * self.square

    def squares(self) -> list[tuple[str, float, float, bool]]:
        """(geom name, X_O, Z_O of the square's centre, dark) for every square."""
        w, h = self.size
        out = []
        for r in range(self.rows):
            for c in range(self.cols):
                x = self.offset[0] - w / 2 + (c + 0.5) * self.square
                z = self.offset[1] + h / 2 - (r + 0.5) * self.square
                out.append((f"{PATTERN_GEOM_PREFIX}{r}_{c}", x, z, (r + c) % 2 == 0))
        return out


@dataclass(frozen=True)
class BenchParams:
    """The physical bench. Defaults: the paper's bench with a perfectly mounted LiDAR.

    Attributes (SI):
        mount_roll, mount_tilt, mount_yaw: LiDAR mounting misalignment, rad, relative to the
            turntable, in the convention of `twin.core.pose.Pose` (R = Rz(yaw) Rx(tilt) Ry(roll)).
        lever_arm: optical centre relative to the rotation axis on the turntable's top face, in
            the turntable frame (x right, y forward at stage yaw 0, z up), m. Default 60 mm up:
            the optical centre 0.5 m above the floor, level with the board centre.
        board_width, board_height: board size, m (paper: 0.90 x 0.54).
        board_thickness: plate thickness, m (3 mm aluminium, assumed: models/target_board.xml);
            the front face stays on the board frame's Y_O = 0, the plate grows behind it.
        board_position: centre of the board's front face in the world frame {W} (origin on the
            floor below the nominal board centre), m.
        board_roll, board_tilt, board_yaw: board orientation in {W}, rad (same convention:
            board_roll turns the board about its own normal, its in-plane rotation).
        sensor_module_position: the sensor module stand's floor point in {W}, m (paper: 2.5 m in
            front of the board, 0.7 m to its side; models/bench_frame.xml explains the sign).
        board_reflectivity: diffuse reflectance of the board face (bare aluminium, assumed 0.55).
        background_reflectivity: diffuse reflectance of floor, wall, beams and stands (0.3).
        board_pattern: a chessboard printed on the board's face (`BoardPattern`), or None.
    """

    mount_roll: float = 0.0
    mount_tilt: float = 0.0
    mount_yaw: float = 0.0
    lever_arm: tuple[float, float, float] = (0.0, 0.0, 0.06)
    board_width: float = 0.90
    board_height: float = 0.54
    board_thickness: float = 0.003
    board_position: tuple[float, float, float] = (0.0, 0.0, 0.5)
    board_roll: float = 0.0
    board_tilt: float = 0.0
    board_yaw: float = 0.0
    sensor_module_position: tuple[float, float, float] = (0.7, -2.5, 0.0)
    board_reflectivity: float = 0.55
    background_reflectivity: float = 0.30
    #: Per-geom reflectivity overrides by geom name (e.g. {"wall": 0.8}).
    reflectivity_overrides: dict[str, float] = field(default_factory=dict)
    board_pattern: BoardPattern | None = None
    #: The scene the bench stands in, by name (`models.SCENES`): "bench" (the paper's: floor,
    #: wall, beams) or "lab" (the same bench in a cluttered lab, models/scene_lab.xml).
    scene: str = "bench"

    def __post_init__(self) -> None:
        if self.scene not in SCENES:
            raise ValueError(f"scene {self.scene!r} is not one of {', '.join(SCENES)}")
        if self.board_width <= 0 or self.board_height <= 0:
            raise ValueError("board_width and board_height must be positive (m)")
        if self.board_thickness <= 0:
            # MuJoCo boxes need a positive half size; a sheet is a thin plate, not none.
            raise ValueError("board_thickness must be positive (m)")
        pat = self.board_pattern
        if pat is not None:
            w, h = pat.size
            if (abs(pat.offset[0]) + w / 2 > self.board_width / 2 + 1e-9
                    or abs(pat.offset[1]) + h / 2 > self.board_height / 2 + 1e-9):
                raise ValueError(f"the board pattern ({w:.3f} x {h:.3f} m at {pat.offset}) does "
                                 f"not fit on the {self.board_width} x {self.board_height} m board")
        for name in ("board_reflectivity", "background_reflectivity"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} is a diffuse reflectance in [0, 1]")

    @classmethod
    def from_edge(cls, *, roll_deg: float = 0.0, tilt_deg: float = 0.0, yaw_deg: float = 0.0,
                  lever_arm_mm: tuple[float, float, float] | None = None, **kwargs) -> BenchParams:
        """Mount misalignment in degrees and the lever arm in mm (CLI edge); other fields SI."""
        if lever_arm_mm is not None:
            kwargs["lever_arm"] = tuple(1e-3 * float(v) for v in lever_arm_mm)
        return cls(mount_roll=float(np.deg2rad(roll_deg)), mount_tilt=float(np.deg2rad(tilt_deg)),
                   mount_yaw=float(np.deg2rad(yaw_deg)), **kwargs)

    def mount_quat(self) -> np.ndarray:
        """Orientation of the LiDAR frame in the turntable frame, MuJoCo (w, x, y, z)."""
        return _quat_wxyz(self.mount_roll, self.mount_tilt, self.mount_yaw)

    def board_quat(self) -> np.ndarray:
        """Orientation of the board frame {O} in {W}, MuJoCo (w, x, y, z)."""
        return _quat_wxyz(self.board_roll, self.board_tilt, self.board_yaw)

    def apply(self, spec: mujoco.MjSpec) -> mujoco.MjSpec:
        """Edit a spec of ``models/scene.xml`` in place to this bench; returns it."""
        board = spec.body(BOARD_BODY)
        board.pos = np.asarray(self.board_position, dtype=float)
        board.quat = self.board_quat()
        geom = spec.geom(BOARD_GEOM)
        geom.size = [self.board_width / 2, self.board_thickness / 2, self.board_height / 2]
        geom.pos = [0.0, self.board_thickness / 2, 0.0]
        for corner, (sx, sz) in {"tl": (-1, 1), "tr": (1, 1), "bl": (-1, -1),
                                 "br": (1, -1)}.items():
            spec.site(f"board_corner_{corner}").pos = [
                sx * self.board_width / 2, 0.0, sz * self.board_height / 2]
        # The stand stays on the floor behind the board, wherever the board goes and however it
        # is turned: a board moved back would otherwise stand behind its own post.
        stand = spec.body(BOARD_STAND_BODY)
        off = np.asarray(stand.pos, dtype=float)  # behind the nominal board centre (x = y = 0)
        c, s = np.cos(self.board_yaw), np.sin(self.board_yaw)
        stand.pos = [self.board_position[0] + c * off[0] - s * off[1],
                     self.board_position[1] + s * off[0] + c * off[1], off[2]]
        stand.quat = [np.cos(self.board_yaw / 2), 0.0, 0.0, np.sin(self.board_yaw / 2)]
        # The vlp16 body frame is {L} with its origin at the optical centre, a child of the
        # turntable whose origin lies 10 mm below the rotation-axis site on its top face.
        rot_axis = np.asarray(spec.site("rotation_axis").pos, dtype=float)
        sensor = spec.body(SENSOR_BODY)
        sensor.pos = rot_axis + np.asarray(self.lever_arm, dtype=float)
        sensor.quat = self.mount_quat()
        spec.body(SENSOR_MODULE_BODY).pos = np.asarray(self.sensor_module_position, dtype=float)
        if self.board_pattern is not None:
            self._add_pattern(spec)
        return spec

    def _add_pattern(self, spec: mujoco.MjSpec) -> None:
        """The pattern's squares as box geoms of the board body, just in front of its face."""
        pat = self.board_pattern
        board, cls = spec.body(BOARD_BODY), spec.find_default("board")
        t = pat.print_thickness
        for name, x, z, _ in pat.squares():
            g = board.add_geom(cls)
            g.name = name
            g.size = [pat.square / 2, t / 2, pat.square / 2]
            g.pos = [x, -t / 2, z]

    def build_model(self, scene: Path | str | None = None) -> mujoco.MjModel:
        """Compile ``scene`` (default: this bench's `scene`) with these parameters applied."""
        spec = mujoco.MjSpec.from_file(str(SCENES[self.scene] if scene is None else scene))
        return self.apply(spec).compile()

    def geom_reflectivity(self, model: mujoco.MjModel) -> np.ndarray:
        """Diffuse reflectance of every geom of ``model``, shape (ngeom,)."""
        refl = np.full(model.ngeom, self.background_reflectivity)
        refl[model.geom(BOARD_GEOM).id] = self.board_reflectivity
        if self.board_pattern is not None:
            pat = self.board_pattern
            for name, _, _, dark in pat.squares():
                refl[model.geom(name).id] = (pat.dark_reflectivity if dark
                                             else pat.light_reflectivity)
        for name, value in self.reflectivity_overrides.items():
            refl[model.geom(name).id] = value
        return refl
