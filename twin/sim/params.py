"""Bench parameters a user sets without editing XML, applied to the compiled model.

The MJCF in ``models/`` holds the nominal bench (paper, section IV-A). A `BenchParams` describes
the physical bench you actually have: how the LiDAR sits on its mount (roll, tilt, yaw and the
lever arm from the rotation axis to the optical centre), the board's size and pose, and the
reflectivity of the board and of everything else. `build_model` loads ``models/scene.xml`` into a
`mujoco.MjSpec`, edits the named elements and compiles. SI units (m, rad); reflectivity is the
diffuse (Lambertian) reflectance 0..1.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
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
#: The lab wall behind the board (models/bench_frame.xml) and the stand's parts it moves.
WALL_GEOM = "wall"
#: Name prefixes of the geoms `BenchParams` adds: holders on the board, clutter in the room.
HOLDER_GEOM_PREFIX = "board_holder_"
CLUTTER_GEOM_PREFIX = "clutter_"


#: The plate the twin builds for a board of thickness 0 (a printed sheet), m.
SHEET = 1e-4


@dataclass(frozen=True)
class SceneBox:
    """A box the scene holds besides the nominal bench: a holder on the board (``pos`` in the
    board frame {O}: a clamp or bracket at an edge, just beyond it, near the board's plane) or
    a piece of clutter in the room (``pos`` in {W}: a cabinet, a tripod, a box on the floor).
    ``size``: half sizes along the frame's axes, m; ``yaw``: turned about the vertical, rad;
    ``reflectivity``: its diffuse reflectance (None: the background's); ``roll``: then turned
    about its own Y axis, rad (R = Rz(yaw) Ry(roll), `BenchParams`' convention): a panel thin
    along Y hung turned about its normal, as a diamond board is (`twin.sim.distractors`: a
    second panel hung as the board is). 0 builds the box exactly as before the field was."""

    pos: tuple[float, float, float]
    size: tuple[float, float, float]
    yaw: float = 0.0
    reflectivity: float | None = None
    roll: float = 0.0

    def __post_init__(self) -> None:
        if min(self.size) <= 0:
            raise ValueError("a scene box needs positive half sizes (m)")
        if self.reflectivity is not None and not 0.0 <= self.reflectivity <= 1.0:
            raise ValueError("reflectivity is a diffuse reflectance in [0, 1]")

    def quat(self) -> np.ndarray:
        """The box's orientation in its parent's frame, MuJoCo (w, x, y, z). Without a roll the
        quaternion of the yaw alone, written as it always was (the same floats: a scene without
        rolled boxes compiles to the same model)."""
        if self.roll == 0.0:
            return np.array([np.cos(self.yaw / 2), 0.0, 0.0, np.sin(self.yaw / 2)])
        return quat_wxyz(self.roll, 0.0, self.yaw)


def quat_wxyz(roll: float, tilt: float, yaw: float) -> np.ndarray:
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
        wall_distance: the lab wall's distance behind the board's nominal face, m (None: the
            model's 1.5 m).
        stand_offset: the board stand's distance behind the board's face, m (None: the
            model's 0.15 m; its base then sits that far behind, its post hidden by the board).
        holders: boxes fixed to the board (`SceneBox`, board frame): clamps, brackets.
        clutter: boxes standing in the room (`SceneBox`, world frame).
        `random_scene` draws all four (and the reflectivities) for a twin of a bench not known
        in detail: an estimator must not depend on one scene's particulars.
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
    wall_distance: float | None = None
    stand_offset: float | None = None
    holders: tuple[SceneBox, ...] = ()
    clutter: tuple[SceneBox, ...] = ()

    def __post_init__(self) -> None:
        if self.scene not in SCENES:
            raise ValueError(f"scene {self.scene!r} is not one of {', '.join(SCENES)}")
        if self.board_width <= 0 or self.board_height <= 0:
            raise ValueError("board_width and board_height must be positive (m)")
        if self.board_thickness < 0:
            raise ValueError("board_thickness must not be negative (m)")
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
        if self.wall_distance is not None and not self.wall_distance > self.board_thickness:
            raise ValueError("wall_distance must put the wall behind the board (m)")
        if self.stand_offset is not None and not self.stand_offset > 0:
            raise ValueError("stand_offset must put the stand behind the board's face (m)")

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
        return quat_wxyz(self.mount_roll, self.mount_tilt, self.mount_yaw)

    def board_quat(self) -> np.ndarray:
        """Orientation of the board frame {O} in {W}, MuJoCo (w, x, y, z)."""
        return quat_wxyz(self.board_roll, self.board_tilt, self.board_yaw)

    def apply(self, spec: mujoco.MjSpec) -> mujoco.MjSpec:
        """Edit a spec of ``models/scene.xml`` in place to this bench; returns it."""
        board = spec.body(BOARD_BODY)
        board.pos = np.asarray(self.board_position, dtype=float)
        board.quat = self.board_quat()
        geom = spec.geom(BOARD_GEOM)
        # a printed sheet (thickness 0) is a plate of SHEET thick: MuJoCo's boxes need a positive
        # half size, and no ray meets a 0.1 mm edge face at the bench's incidences
        depth = max(self.board_thickness, SHEET)
        geom.size = [self.board_width / 2, depth / 2, self.board_height / 2]
        geom.pos = [0.0, depth / 2, 0.0]
        for corner, (sx, sz) in {"tl": (-1, 1), "tr": (1, 1), "bl": (-1, -1),
                                 "br": (1, -1)}.items():
            spec.site(f"board_corner_{corner}").pos = [
                sx * self.board_width / 2, 0.0, sz * self.board_height / 2]
        # The stand stays on the floor behind the board, wherever the board goes and however it
        # is turned: a board moved back would otherwise stand behind its own post.
        stand = spec.body(BOARD_STAND_BODY)
        off = np.asarray(stand.pos, dtype=float)  # behind the nominal board centre (x = y = 0)
        if self.stand_offset is not None:
            off[1] = self.stand_offset
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
        if self.wall_distance is not None:
            wall = spec.geom(WALL_GEOM)
            wall.pos = [wall.pos[0], float(self.wall_distance), wall.pos[2]]
        self._add_boxes(spec)
        return spec

    def _add_boxes(self, spec: mujoco.MjSpec) -> None:
        """The holders (geoms of the board body) and the clutter (of a body of the world), each
        of the environment class, named by its index."""
        cls = spec.find_default("environment")
        board = spec.body(BOARD_BODY)
        for i, box in enumerate(self.holders):
            g = board.add_geom(cls)
            g.name, g.type = f"{HOLDER_GEOM_PREFIX}{i}", mujoco.mjtGeom.mjGEOM_BOX
            g.size, g.pos = list(box.size), list(box.pos)
            g.quat = box.quat()
        if self.clutter:
            room = spec.worldbody.add_body(name="clutter", childclass="aimbench")
            for i, box in enumerate(self.clutter):
                g = room.add_geom(cls)
                g.name, g.type = f"{CLUTTER_GEOM_PREFIX}{i}", mujoco.mjtGeom.mjGEOM_BOX
                g.size, g.pos = list(box.size), list(box.pos)
                g.quat = box.quat()

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
        for prefix, boxes in ((HOLDER_GEOM_PREFIX, self.holders),
                              (CLUTTER_GEOM_PREFIX, self.clutter)):
            for i, box in enumerate(boxes):
                if box.reflectivity is not None:
                    refl[model.geom(f"{prefix}{i}").id] = box.reflectivity
        for name, value in self.reflectivity_overrides.items():
            refl[model.geom(name).id] = value
        return refl


def random_scene(rng: np.random.Generator, base: BenchParams | None = None,
                 max_holders: int = 4) -> BenchParams:
    """``base`` (default the paper's bench) in a scene drawn at random: the wall 0.5-3 m behind
    the board, the stand 0.05-0.35 m behind it, up to four holders at the board's edges (a clamp
    or bracket reaching 0-40 mm beyond an edge, its face from just behind the plate to
    60 mm behind it), up to six pieces of clutter wholly behind the board's plane (behind and
    beside it, up to the wall), and
    every reflectivity (wall, floor, stand, holders, clutter) between dark and bright.
    ``max_holders``: at most this many of the holders drawn are kept (0: a board on its stand
    alone).

    Nothing is put between the LiDAR and the board's face: an occluder is another test. What
    is drawn is what differs between labs and between the twin and a real bench (the twin's
    own scene once hid an estimator's reliance on a far, grey wall behind a bare board)."""
    base = base or BenchParams()
    w2, h2 = base.board_width / 2, base.board_height / 2
    holders = []
    # drawn whatever max_holders is, so that a seed gives the same wall and clutter with and
    # without them
    n_holders = int(rng.integers(0, 5))
    for k in range(n_holders):
        edge = int(rng.integers(4))  # left, right, bottom, top
        reach = rng.uniform(0.0, 0.04)  # beyond the edge, m
        depth = rng.uniform(0.01, 0.04)  # half size across the edge, m
        along = rng.uniform(0.01, 0.05)  # half size along it
        # its front face behind the board's (from just behind the plate: a bracket on its
        # back), m; a clamp's jaw in front of the face would be an occluder
        face = rng.uniform(base.board_thickness, 0.06)
        thick = rng.uniform(0.005, 0.03)  # half size along Y_O
        y = face + thick
        if edge < 2:
            sx = -1 if edge == 0 else 1
            pos = (sx * (w2 + reach - depth), y, rng.uniform(-h2 + along, h2 - along))
            size = (depth, thick, along)
        else:
            sz = -1 if edge == 2 else 1
            pos = (rng.uniform(-w2 + along, w2 - along), y, sz * (h2 + reach - depth))
            size = (along, thick, depth)
        refl_h = float(rng.uniform(0.05, 0.9))
        if k < max_holders:
            holders.append(SceneBox(tuple(float(v) for v in pos),
                                    tuple(float(v) for v in size), reflectivity=refl_h))
    wall = float(rng.uniform(0.5, 3.0))
    clutter = []
    bx, by, _ = base.board_position
    for _ in range(int(rng.integers(0, 7))):
        size = rng.uniform(0.05, 0.4, 3)
        yaw = float(rng.uniform(-np.pi, np.pi))
        # how far the turned box reaches along Y_W from its centre: its half size along Y
        # alone would let a turned box's corner stand up to 0.15 m in front of the board's
        # face, between the LiDAR and the board (an occluder: another test)
        reach = abs(size[0] * np.sin(yaw)) + abs(size[1] * np.cos(yaw))
        # behind the board's plane (between it and the wall) or beside it, on the floor
        y = by + reach + rng.uniform(0.02, max(wall - 2 * reach, 0.05))
        x = bx + rng.uniform(-2.0, 2.0)
        clutter.append(SceneBox((float(x), float(y), float(size[2])), tuple(float(v) for v in size),
                                yaw=yaw, reflectivity=float(rng.uniform(0.05, 0.9))))
    refl = dict(base.reflectivity_overrides)
    refl.update({"wall": float(rng.uniform(0.05, 0.9)), "floor": float(rng.uniform(0.05, 0.6)),
                 "stand_base": float(rng.uniform(0.05, 0.9)),
                 "stand_post": float(rng.uniform(0.05, 0.9))})
    return replace(base, wall_distance=wall, stand_offset=float(rng.uniform(0.05, 0.35)),
                   holders=tuple(holders), clutter=tuple(clutter), reflectivity_overrides=refl)
