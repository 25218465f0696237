"""Rerun logging of the bench: scans, the board, estimates, the truth, the stages, errors, events.

Every function takes an explicit `rerun.RecordingStream` (the style of rerun's own examples), so
nothing here touches rerun's global recording and several recordings can coexist (a live stream
and a file, a test's recording). This is an edge module: `align/` and the twin's core never import
it, and nothing imports rerun unless a caller asked for a recording.

The recording's world frame is the board frame {O} of docs/DESIGN.md (X_O right, Y_O into the
board, Z_O up; m). Entity tree:

====================================  ==============================================================
entity                                what
====================================  ==============================================================
``world``                             view coordinates (right-handed, Z up), static
``world/board``                       the target board as a 3-D box (front face on Y_O = 0), static
``world/board/corners``               its four corners (the paper's order), static
``world/bench/<body>``                one MuJoCo body of the bench (stand, stages, mount, VLP-16):
                                      a transform posed from the joint positions, its geoms (boxes,
                                      cylinders) under ``.../geoms`` static in the body's frame
``world/truth``                       the LiDAR's true pose (twin only), transform and axes
``world/estimate``                    the estimated pose, transform and axes (cleared on failure)
``world/sensor``                      where the scan is drawn: the estimate, else the truth
``world/sensor/scan``                 the raw returns in {L}, coloured by intensity or ring
``world/sensor/board_points``         the returns the estimator took for the board
``world/sensor/features``             the feature firings the method used (corner points, edge rays)
``world/sensor/plane``                the least-squares plane through the board points (a patch)
``plots/error/<axis>``                estimate - truth per axis (mm, deg) with the tolerance band
``plots/estimate/<axis>``             the estimate per axis (mm, deg), where there is no truth
``log``                               text annotations: references, failed scans, dropped packets,
                                      alarms, run status
====================================  ==============================================================

Timelines: ``scan`` (the scan's index in the run, a sequence), ``sensor_time`` (the VLP-16's clock
at the scan's first firing, s past the hour), ``stage_time`` (the twin's simulation clock, s) and
``wall_time`` (when the scan was acquired), each where known.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from align.plane.fit import fit_lsq
from twin.core.pose import Pose
from twin.core.scan import Scan
from twin.sim.params import BOARD_BODY

if TYPE_CHECKING:  # rerun is imported by callers that asked for a recording, never at import
    import rerun as rr
    import rerun.blueprint as rrb

    from twin.sim.physics import BenchPhysics

#: Application id of every aimbench recording (the viewer groups recordings and blueprints by it).
APP_ID = "aimbench"

#: Pose axes in the order of `twin.core.pose.POSE_FIELDS`, named with their edge units.
AXES = ("x_mm", "y_mm", "z_mm", "roll_deg", "tilt_deg", "yaw_deg")
#: SI -> edge units, per axis of `AXES`.
_EDGE_SCALE = np.array([1e3, 1e3, 1e3, *([180.0 / math.pi] * 3)])

# Colours (RGB): chosen to stay apart on the viewer's dark background.
BOARD_COLOR = (230, 230, 220)
TRUTH_COLOR = (80, 220, 100)
ESTIMATE_COLOR = (255, 170, 40)
BOARD_POINTS_COLOR = (60, 200, 255)
FEATURE_COLOR = (255, 60, 200)
PLANE_COLOR = (60, 200, 255, 70)
TOLERANCE_COLOR = (200, 60, 60)
STAGE_COLOR = (150, 150, 160)
SENSOR_COLOR = (70, 70, 80)

#: Thickness of the board's box, m (the model's 3 mm plate; only the front face matters).
BOARD_THICKNESS = 0.003


# ---------------------------------------------------------------------------------------------
# Colour maps (numpy only: the points of a scan are coloured with one table look-up)
# ---------------------------------------------------------------------------------------------
#: Turbo (Mikhailov 2019, Apache-2.0) at 33 evenly spaced knots, RGB hex: matplotlib's table
#: sampled once. Linear interpolation between them stays within 4 levels of the full table
#: (tests/test_rerun.py checks), without importing a plotting library (about a second of CPU)
#: into every recording.
_TURBO_KNOTS = (
    "30123b392a734040a24456c7466be34680f64294ff37a8fa28bceb1ccdd818ddc21fe9af32f2984ef97d6d"
    "fe628bff4ba4fc3cb9f635cdec34dfdf37eecf3af8be39fdac34fe962bfb7e21f46617eb500edf3f08d02f"
    "05be2102a91601920b017a0403"
)


@functools.cache
def turbo_lut(n: int = 256) -> np.ndarray:
    """The Turbo colour map as an (n, 3) uint8 table."""
    knots = np.frombuffer(bytes.fromhex(_TURBO_KNOTS), dtype=np.uint8).reshape(-1, 3)
    t = np.linspace(0.0, 1.0, len(knots))
    x = np.linspace(0.0, 1.0, n)
    rgb = np.column_stack([np.interp(x, t, knots[:, j].astype(float)) for j in range(3)])
    return np.rint(rgb).astype(np.uint8)


def ring_colors() -> np.ndarray:
    """One colour per ring (0 = lowest beam), spread over Turbo, (16, 3) uint8."""
    return turbo_lut()[np.linspace(0, 255, 16).astype(int)]


def pack_rgba(rgb: np.ndarray) -> np.ndarray:
    """(N, 3) uint8 colours as rerun's packed 0xRRGGBBAA uint32 (opaque)."""
    rgb = np.asarray(rgb, dtype=np.uint32)
    return (rgb[..., 0] << 24) | (rgb[..., 1] << 16) | (rgb[..., 2] << 8) | np.uint32(0xFF)


@functools.cache
def _packed_tables() -> tuple[np.ndarray, np.ndarray]:
    return pack_rgba(turbo_lut()), pack_rgba(ring_colors())


def scan_colors(scan: Scan, mask: np.ndarray | None = None, by: str = "intensity") -> np.ndarray:
    """Colours of the scan's firings (where ``mask``) as packed 0xRRGGBBAA uint32 (rerun takes
    them as they are; (N, 3) bytes would cost a conversion per scan): by calibrated
    ``intensity`` (through Turbo; the VLP-16 maps diffuse reflectors to 0..100, retro-reflectors
    above, so the table is stretched over 0..100 and saturates beyond) or by elevation ``ring``.
    """
    intensity_lut, ring_lut = _packed_tables()
    if by == "ring":
        ring = scan.ring if mask is None else scan.ring[mask]
        return ring_lut[ring]
    if by != "intensity":
        raise ValueError(f"colour points by 'intensity' or 'ring', not {by!r}")
    inten = scan.intensity if mask is None else scan.intensity[mask]
    idx = np.minimum(inten.astype(np.uint16) * 255 // 100, 255)
    return intensity_lut[idx]


# ---------------------------------------------------------------------------------------------
# Small conversions
# ---------------------------------------------------------------------------------------------
def pose_transform(pose: Pose) -> rr.Transform3D:
    """The rerun transform of a pose of {L} in {O}: child (sensor) to parent (board frame)."""
    import rerun as rr

    return rr.Transform3D(translation=pose.translation, mat3x3=pose.rotation())


def pose_edge(pose: Pose) -> np.ndarray:
    """(x_mm, y_mm, z_mm, roll_deg, tilt_deg, yaw_deg) of a pose."""
    return pose.as_array() * _EDGE_SCALE


def set_scan_time(rec: rr.RecordingStream, scan_index: int, *, sensor_time: float | None = None,
                  stage_time: float | None = None, wall_time: float | None = None) -> None:
    """Put `rec` at a scan on the bench's timelines (only those known are set)."""
    rec.set_time("scan", sequence=int(scan_index))
    if sensor_time is not None and math.isfinite(sensor_time):
        rec.set_time("sensor_time", duration=float(sensor_time))
    if stage_time is not None and math.isfinite(stage_time):
        rec.set_time("stage_time", duration=float(stage_time))
    if wall_time is not None and math.isfinite(wall_time):
        rec.set_time("wall_time", timestamp=float(wall_time))


# ---------------------------------------------------------------------------------------------
# Static scene
# ---------------------------------------------------------------------------------------------
def log_world(rec: rr.RecordingStream) -> None:
    """The world frame: the board frame {O}, right-handed with Z up (static)."""
    import rerun as rr

    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)


def log_board(rec: rr.RecordingStream, width: float = 0.90, height: float = 0.54,
              entity: str = "world/board") -> None:
    """The target board as a 3-D box whose front face is Y_O = 0, and its corners (static).

    Corners in the paper's order (Eq. 3): top-left, top-right, bottom-left, bottom-right.
    """
    import rerun as rr

    rec.log(entity, rr.Boxes3D(centers=[[0.0, BOARD_THICKNESS / 2, 0.0]],
                               half_sizes=[[width / 2, BOARD_THICKNESS / 2, height / 2]],
                               colors=[BOARD_COLOR], fill_mode="solid", labels=["board"]),
            static=True)
    w, h = width / 2, height / 2
    corners = np.array([[-w, 0.0, h], [w, 0.0, h], [-w, 0.0, -h], [w, 0.0, -h]])
    rec.log(f"{entity}/corners", rr.Points3D(corners, radii=0.012, colors=[BOARD_COLOR],
                                             labels=["TL", "TR", "BL", "BR"]), static=True)


# ---------------------------------------------------------------------------------------------
# The stages (MuJoCo geometry posed from the joint positions)
# ---------------------------------------------------------------------------------------------
_MJ_PLANE, _MJ_SPHERE, _MJ_CYLINDER, _MJ_BOX = 0, 2, 5, 6
#: The MJCF body of the board plate (models/target_board.xml).
BOARD_BODY_NAME = BOARD_BODY


@dataclass
class BenchGeometry:
    """The bench's MuJoCo bodies drawn as boxes and cylinders, posed in the board frame.

    Built from a `twin.sim.physics.BenchPhysics` (the live twin's, or one made from the run's bench
    parameters for a replay). The geoms are logged once, static, in their body's frame; afterwards
    only the transforms of the bodies that hang on a joint (the carriage, the turntable and what
    they carry) are logged, each time the stages' joint positions change. The floor and the wall
    (planes) are left out: they would hide the board from most viewpoints.
    """

    physics: BenchPhysics
    entity: str = "world/bench"
    moving: list[int] = field(default_factory=list)  # body ids below a joint
    bodies: list[int] = field(default_factory=list)  # body ids with drawable geoms
    _last: tuple[float, float] | None = None

    @classmethod
    def from_physics(cls, physics: BenchPhysics, entity: str = "world/bench") -> BenchGeometry:
        m = physics.model
        drawable = sorted({int(m.geom_bodyid[g]) for g in range(m.ngeom)
                           if m.geom_type[g] in (_MJ_SPHERE, _MJ_CYLINDER, _MJ_BOX)})
        # The world body holds only planes; the board is drawn from its spec (`log_board`),
        # which on hardware is what the estimator assumes, so the model's plate would only
        # z-fight with it.
        drawable = [b for b in drawable if b != 0 and m.body(b).name != BOARD_BODY_NAME]
        moving = [b for b in drawable if _below_joint(m, b)]
        return cls(physics, entity, moving, drawable)

    def body_entity(self, body: int) -> str:
        return f"{self.entity}/{self.physics.model.body(body).name}"

    def log_static(self, rec: rr.RecordingStream) -> None:
        """Every drawable body's geoms (static, body frame) and the fixed bodies' poses."""
        import rerun as rr

        m = self.physics.model
        for b in self.bodies:
            ids = [g for g in range(m.ngeom) if m.geom_bodyid[g] == b]
            boxes = [g for g in ids if m.geom_type[g] == _MJ_BOX]
            cyls = [g for g in ids if m.geom_type[g] == _MJ_CYLINDER]
            spheres = [g for g in ids if m.geom_type[g] == _MJ_SPHERE]
            name = self.body_entity(b)
            color = SENSOR_COLOR if m.body(b).name == "vlp16" else STAGE_COLOR
            if boxes:
                rec.log(f"{name}/geoms/boxes", rr.Boxes3D(
                    centers=m.geom_pos[boxes], half_sizes=m.geom_size[boxes],
                    quaternions=[_xyzw(m.geom_quat[g]) for g in boxes],
                    colors=[color], fill_mode="solid"), static=True)
            if cyls:
                rec.log(f"{name}/geoms/cylinders", rr.Cylinders3D(
                    lengths=2 * m.geom_size[cyls, 1], radii=m.geom_size[cyls, 0],
                    centers=m.geom_pos[cyls], quaternions=[_xyzw(m.geom_quat[g]) for g in cyls],
                    colors=[color], fill_mode="solid"), static=True)
            if spheres:
                rec.log(f"{name}/geoms/spheres", rr.Points3D(
                    m.geom_pos[spheres], radii=m.geom_size[spheres, 0], colors=[color]),
                    static=True)
            if b not in self.moving:
                rec.log(name, self._body_transform(b), static=True)

    def _body_transform(self, body: int) -> rr.Transform3D:
        import rerun as rr

        d = self.physics.data
        p_o, r_o = self.physics.board_pose_world()
        pos = r_o.T @ (d.xpos[body] - p_o)
        rot = r_o.T @ d.xmat[body].reshape(3, 3)
        return rr.Transform3D(translation=pos, mat3x3=rot)

    def log_joints(self, rec: rr.RecordingStream, x_m: float | None = None,
                   yaw_rad: float | None = None, force: bool = False) -> None:
        """Pose the moving bodies from the stages' joint positions (m, rad) at the current time.

        Without positions the physics' own state is drawn (the live twin). Nothing is logged when
        the joints have not moved since the last call (most scans of a reference), unless
        ``force``.
        """
        ph = self.physics
        if x_m is not None and yaw_rad is not None and (
                abs(ph.carriage_x() - x_m) > 1e-9 or abs(ph.stage_yaw() - yaw_rad) > 1e-9):
            ph.set_stage_positions(x_m=float(x_m), yaw_rad=float(yaw_rad))
        now = (ph.carriage_x(), ph.stage_yaw())
        if not force and self._last is not None and np.allclose(now, self._last, atol=1e-9):
            return
        self._last = now
        for b in self.moving:
            rec.log(self.body_entity(b), self._body_transform(b))


def _below_joint(m: Any, body: int) -> bool:
    """True if a joint moves `body` (it or an ancestor carries one)."""
    while body > 0:
        if m.body_jntnum[body] > 0:
            return True
        body = int(m.body_parentid[body])
    return False


def _xyzw(wxyz: np.ndarray) -> Any:
    """MuJoCo's (w, x, y, z) quaternion as rerun's."""
    import rerun as rr

    return rr.Quaternion(xyzw=[wxyz[1], wxyz[2], wxyz[3], wxyz[0]])


def log_stage_move(rec: rr.RecordingStream, geometry: BenchGeometry,
                   start: tuple[float, float], end: tuple[float, float], t0: float,
                   rate_hz: float = 20.0) -> float:
    """The stages' move from ``start`` to ``end`` ((x m, yaw rad)) on the ``stage_time`` timeline,
    sampled at ``rate_hz`` along the firmware's coordinated trapezoidal profile
    (`twin.stage.motion.StageMove`), from stage time ``t0`` (s). Returns the move's end time (s).

    Used by replays, which know where the stages went but not how; the live twin logs its own
    joint positions instead. Only ``stage_time`` is set for these rows: they belong to no scan.
    """
    from twin.core.errors import AimbenchError
    from twin.stage.motion import X_AXIS, YAW_AXIS, StageMove

    try:
        move = StageMove.plan(tuple(map(float, start)), tuple(map(float, end)),
                              (X_AXIS, YAW_AXIS))
    except AimbenchError:
        # Beyond the twin's travel (a real bench with longer stages): show the arrival only.
        rec.set_time("stage_time", duration=t0)
        geometry.log_joints(rec, float(end[0]), float(end[1]))
        return t0
    n = max(2, math.ceil(move.duration * rate_hz) + 1)
    for t in np.linspace(0.0, move.duration, n):
        x, yaw = move.at(t)
        rec.set_time("stage_time", duration=t0 + float(t))
        geometry.log_joints(rec, float(x), float(yaw))
    return t0 + move.duration


# ---------------------------------------------------------------------------------------------
# Per scan
# ---------------------------------------------------------------------------------------------
def log_pose(rec: rr.RecordingStream, entity: str, pose: Pose | None,
             axis_length: float = 0.2) -> None:
    """A pose of {L} in {O} as a transform with axes; None clears it (a failed estimate must not
    leave the previous scan's pose on screen)."""
    import rerun as rr

    if pose is None:
        rec.log(entity, rr.Clear(recursive=False))
        return
    rec.log(entity, pose_transform(pose), rr.TransformAxes3D(axis_length))


#: How far beyond the board's returns a decimated cloud keeps every return, rad: in azimuth, and
#: in elevation a little more than the VLP-16's 2 deg between lasers, so the board's edges and
#: the misses beside them (what the estimator reads) stay whole, left, right, above and below.
NEIGHBOURHOOD_AZIMUTH_RAD = math.radians(5.0)
NEIGHBOURHOOD_ELEVATION_RAD = math.radians(2.5)


def board_neighbourhood(scan: Scan, used: Mapping[str, Any] | None,
                        azimuth_rad: float = NEIGHBOURHOOD_AZIMUTH_RAD,
                        elevation_rad: float = NEIGHBOURHOOD_ELEVATION_RAD
                        ) -> np.ndarray | None:
    """The firings (a mask over the scan) within the azimuth and elevation span of the board's
    returns (the estimator's ``used["board"]``), widened by ``azimuth_rad`` and
    ``elevation_rad`` each side; None without board returns. The azimuth span is taken about
    their circular mean (the board may straddle azimuth 0)."""
    board = _indices(used, "board", len(scan))
    if not len(board):
        return None
    az = np.asarray(scan.azimuth, dtype=float)
    centre = float(np.angle(np.exp(1j * az[board]).mean()))
    off = np.abs(np.angle(np.exp(1j * (az - centre))))
    elevation = np.asarray(scan.elevation, dtype=float)
    low, high = elevation[board].min() - elevation_rad, elevation[board].max() + elevation_rad
    return (off <= off[board].max() + azimuth_rad) & (elevation >= low) & (elevation <= high)


def log_scan_points(rec: rr.RecordingStream, scan: Scan, entity: str = "world/sensor/scan",
                    color_by: str = "intensity", every: int = 1,
                    keep: np.ndarray | None = None) -> int:
    """The scan's returns in {L} (firings with no return are left out), coloured by intensity or
    ring; ``every`` > 1 keeps every n-th return (smaller recordings) except those in ``keep`` (a
    mask of firings logged whole: the board's neighbourhood). Returns the points logged.
    """
    import rerun as rr

    mask = scan.valid
    if every > 1:
        rest = mask if keep is None else mask & ~keep
        idx = np.flatnonzero(rest)[::every]
        mask = mask & keep if keep is not None else np.zeros(len(scan), dtype=bool)
        mask[idx] = True
    # float32: rerun stores positions as f32 anyway; converting here halves the copy.
    xyz = scan.points(mask).astype(np.float32)
    rec.log(entity, rr.Points3D(xyz, colors=scan_colors(scan, mask, color_by),
                                radii=rr.Radius.ui_points(1.5)))
    return len(xyz)


def _indices(used: Mapping[str, Any] | None, key: str, n: int) -> np.ndarray:
    """Firing indices of ``used[key]`` that fall in a scan of n firings (flattened: the rays
    method gives hit/miss pairs), or an empty array."""
    if not used or used.get(key) is None:
        return np.zeros(0, dtype=np.int64)
    idx = np.asarray(used[key]).reshape(-1)
    if idx.dtype == bool:
        idx = np.flatnonzero(idx)
    idx = idx.astype(np.int64)
    return idx[(idx >= 0) & (idx < n)]


def log_used(rec: rr.RecordingStream, scan: Scan, used: Mapping[str, Any] | None,
             entity: str = "world/sensor") -> tuple[int, int]:
    """What the estimator used: the segmented board returns, the feature firings and the plane
    through the board returns (a patch over their extent, with its normal). Feature firings
    without a return (the "miss" side of an edge) are drawn where the ray would have met the
    board plane, so an edge's hit/miss pair is visible. Returns (board points, features)."""
    import rerun as rr

    n = len(scan)
    board = _indices(used, "board", n)
    feats = _indices(used, "features", n)
    if len(board):
        pts = scan.points(board)
        rec.log(f"{entity}/board_points", rr.Points3D(pts.astype(np.float32),
                                                      colors=[BOARD_POINTS_COLOR],
                                                      radii=rr.Radius.ui_points(2.5)))
        plane = fit_lsq(pts) if len(pts) >= 3 else None
    else:
        rec.log(f"{entity}/board_points", rr.Clear(recursive=False))
        plane = None
    if plane is not None:
        rec.log(f"{entity}/plane", *plane_archetypes(pts, *plane))
    else:
        rec.log(f"{entity}/plane", rr.Clear(recursive=False))
    if len(feats):
        fpts = scan.points(feats)
        miss = ~scan.valid[feats]
        if miss.any() and plane is not None:
            # Where a missing ray crosses the plane: o + s u with n.(o + s u) = d0.
            normal, d0 = plane
            o = scan.origins()[feats[miss]]
            dirs = scan.directions()[feats[miss]]
            den = dirs @ normal
            s = np.where(np.abs(den) > 1e-9, (d0 - o @ normal) / np.where(den == 0, 1, den), 0)
            fpts[miss] = o + s[:, None] * dirs
        colors = np.where(miss[:, None], np.array([[255, 255, 255]]), np.array([FEATURE_COLOR]))
        rec.log(f"{entity}/features", rr.Points3D(fpts.astype(np.float32),
                                                  colors=colors.astype(np.uint8),
                                                  radii=rr.Radius.ui_points(5.0)))
    else:
        rec.log(f"{entity}/features", rr.Clear(recursive=False))
    return len(board), len(feats)


def plane_archetypes(points: np.ndarray, normal: np.ndarray, d: float) -> list[Any]:
    """A translucent rectangle over the points' extent in the plane n.p = d (`align.plane`'s
    convention: n points away from the sensor), and the plane's normal towards the sensor."""
    import rerun as rr

    c = points.mean(axis=0)
    # In-plane axes: horizontal (perpendicular to Z_L and n), then vertical.
    u = np.cross([0.0, 0.0, 1.0], normal)
    u = u / np.linalg.norm(u) if np.linalg.norm(u) > 1e-9 else np.array([1.0, 0.0, 0.0])
    v = np.cross(normal, u)
    a, b = (points - c) @ u, (points - c) @ v
    c = c - (normal @ c - d) * normal  # on the plane
    corners = [c + a.min() * u + b.min() * v, c + a.max() * u + b.min() * v,
               c + a.max() * u + b.max() * v, c + a.min() * u + b.max() * v]
    return [rr.Mesh3D(vertex_positions=np.array(corners, dtype=np.float32),
                      triangle_indices=[[0, 1, 2], [0, 2, 3]], albedo_factor=PLANE_COLOR),
            rr.Arrows3D(origins=[c], vectors=[-0.15 * normal], colors=[BOARD_POINTS_COLOR])]


def log_errors(rec: rr.RecordingStream, estimate: Pose | None, truth: Pose | None,
               tolerances: Mapping[str, float] | None = None,
               root: str = "plots") -> np.ndarray | None:
    """Per-axis series: estimate - truth (mm, deg) on ``plots/error/<axis>`` when the truth is
    known, else the estimate itself on ``plots/estimate/<axis>``. Every error row carries the
    tolerance band (+tol, -tol) beside the error, so the band is drawn over exactly the span of
    the plotted errors. A failed estimate logs nothing: the series shows a gap.

    ``tolerances``: per-axis limits in edge units (see `tolerance_band`). Returns the errors.
    """
    import rerun as rr

    if estimate is None:
        return None
    tol = dict(tolerances or {})
    est = pose_edge(estimate)
    if truth is None:
        for axis, v in zip(AXES, est, strict=True):
            rec.log(f"{root}/estimate/{axis}", rr.Scalars([v]))
        return None
    err = est - pose_edge(truth)
    for axis, e in zip(AXES, err, strict=True):
        t = tol.get(axis)
        values = [e] if t is None else [e, t, -t]
        rec.log(f"{root}/error/{axis}", rr.Scalars(values))
    return err


def log_series_style(rec: rr.RecordingStream, tolerances: Mapping[str, float] | None = None,
                     truth: bool = True, root: str = "plots") -> None:
    """Names and colours of the series (static): the error line and its tolerance band (with
    ``truth``), or the estimate's line (without)."""
    import rerun as rr

    tol = dict(tolerances or {})
    for axis in AXES:
        if not truth:
            rec.log(f"{root}/estimate/{axis}",
                    rr.SeriesLines(names=[axis], colors=[ESTIMATE_COLOR]), static=True)
        elif axis in tol:
            rec.log(f"{root}/error/{axis}",
                    rr.SeriesLines(names=[f"error {axis}", "+tolerance", "-tolerance"],
                                   colors=[ESTIMATE_COLOR, TOLERANCE_COLOR, TOLERANCE_COLOR],
                                   widths=[1.5, 1.0, 1.0]), static=True)
        else:
            rec.log(f"{root}/error/{axis}", rr.SeriesLines(
                names=[f"error {axis}"], colors=[ESTIMATE_COLOR], widths=[1.5]), static=True)


def tolerance_band(angle_deg: float | None = 0.2, x_mm: float | None = 4.0) -> dict[str, float]:
    """The report's pass/fail limits per axis (edge units): angles share ``angle_deg``; the
    report judges x only, so y and z carry no band."""
    out: dict[str, float] = {}
    if angle_deg is not None:
        out.update({a: float(angle_deg) for a in ("roll_deg", "tilt_deg", "yaw_deg")})
    if x_mm is not None:
        out["x_mm"] = float(x_mm)
    return out


def log_text(rec: rr.RecordingStream, text: str, level: str = "INFO",
             entity: str = "log") -> None:
    """A text annotation (levels: rerun's TRACE, DEBUG, INFO, WARN, ERROR, CRITICAL)."""
    import rerun as rr

    rec.log(entity, rr.TextLog(text, level=level))


def scan_annotations(scan: Scan | None, status: str, success: bool,
                     diagnostics: Mapping[str, Any] | None = None,
                     missing_packets: int | None = None,
                     complete: bool | None = None) -> list[tuple[str, str]]:
    """The (level, text) annotations a scan deserves: dropped packets, a partial scan, a failed
    estimate (with the estimator's reason)."""
    out: list[tuple[str, str]] = []
    if scan is not None:
        missing_packets = scan.missing_packets if missing_packets is None else missing_packets
        complete = scan.complete if complete is None else complete
    if missing_packets:
        out.append(("WARN", f"{int(missing_packets)} packet(s) dropped in this scan"))
    elif complete is False:
        out.append(("WARN", "incomplete scan"))
    if not success:
        reason = ""
        for key in ("reason", "message", "error"):
            if diagnostics and diagnostics.get(key):
                reason = f": {diagnostics[key]}"
                break
        out.append(("WARN", f"no pose (status {status}){reason}"))
    return out


# ---------------------------------------------------------------------------------------------
# Blueprint
# ---------------------------------------------------------------------------------------------
def blueprint(truth: bool = True, live: bool = False) -> rrb.Blueprint:
    """The layout a recording opens with: the bench in 3-D (left), per-axis plots (right, top) and
    the log (right, bottom). ``truth``: plot errors (twin) or the estimates (hardware).

    On the ``scan`` timeline; ``live`` (a stream to a viewer) follows the newest scan, otherwise
    (a file) the viewer plays the scans once from the start at ``fps`` scans per second and stops
    on the last one with every plot complete."""
    import rerun.blueprint as rrb

    kind = "error" if truth else "estimate"
    unit = {"mm": "mm", "deg": "deg"}
    plots = [rrb.TimeSeriesView(origin=f"/plots/{kind}/{axis}",
                                name=f"{kind} {axis.split('_')[0]} ({unit[axis.split('_')[1]]})",
                                plot_legend=rrb.PlotLegend(visible=False))
             for axis in AXES]
    view3d = rrb.Spatial3DView(
        origin="/world", name="bench (board frame)",
        eye_controls=rrb.EyeControls3D(position=[1.6, -4.3, 1.4], look_target=[0.35, -1.2, 0.0],
                                       eye_up=[0.0, 0.0, 1.0]),
        line_grid=rrb.LineGrid3D(visible=False))
    return rrb.Blueprint(
        rrb.Horizontal(
            view3d,
            rrb.Vertical(rrb.Grid(*plots, grid_columns=2),
                         rrb.TextLogView(origin="/log", name="log"), row_shares=[3, 1]),
            column_shares=[3, 2]),
        rrb.TimePanel(state="collapsed", timeline="scan",
                      play_state="following" if live else "playing", loop_mode="off", fps=30.0),
        rrb.SelectionPanel(state="collapsed"),
        rrb.BlueprintPanel(state="collapsed"),
        collapse_panels=False,
    )


def new_recording(name: str | None = None, recording_id: str | None = None) -> rr.RecordingStream:
    """A fresh recording stream (not the global one) with aimbench's application id."""
    import rerun as rr

    rec = rr.RecordingStream(APP_ID, recording_id=recording_id)
    if name:
        rec.send_recording_name(name)
    return rec
