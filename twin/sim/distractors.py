"""Distractors: the board-like things a real station has around its board, for the twin.

Issue 34 asks for a gauge that never vouches for the wrong object. The twin's random scenes
(`twin.sim.params.random_scene`) hold boxes of clutter, none of them board-like; a real bench
stands in a room with a second calibration panel, a door, a whiteboard, a monitor, a cabinet.
This module builds those as `SceneBox` clutter (world frame {W}) at named places relative to
the board as the LiDAR sees it, so an estimator can be run against each and its answers
counted: right, wrong, ambiguous or failed (`benchmarks/bench_align.py --distractors`).

Kinds (`KINDS`): realistic sizes and diffuse reflectances, each drawn where a real one varies.
Placements (`PLACEMENTS`), relative to the line of sight from the LiDAR's optical centre to the
board's centre, horizontally:

- ``front``: nearer than the board (0.35-0.8 of its distance) and across part of its
  silhouette: the distractor's edge nearest the line of sight lies between a quarter and 0.9
  of the board's angular half width from it, so it hides part of the board, never its centre
  ray.
- ``beside``: at the board's distance, 0.3-1.5 m of gap between the board's edge and its own.
- ``behind``: 0.3-1.5 m further than the board, anywhere from straight behind it (seen around
  it: at least 0.05 rad of it beyond the board's silhouette) to 0.8 m clear of it.
- ``nearer``: between the LiDAR and the board (0.3-0.7 of its distance, at least 0.8 m from
  the LiDAR), off the line of sight: wholly clear of the board's silhouette by 0.05-0.5 rad.

Every distractor stands square to somewhere between the board's plane and the LiDAR, 10 deg
either way: a door, a whiteboard or a cabinet is square to the room, a monitor or a second
panel is turned by whoever put it there. Nothing is drawn from a global generator: every
function takes a `numpy.random.Generator`. SI units (m, rad).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from twin.sim.params import BenchParams, SceneBox

#: Where a distractor goes relative to the board (module docstring).
PLACEMENTS = ("front", "beside", "behind", "nearer")

#: Least of a distractor behind the board seen beyond its silhouette, rad (18 cm at 3.5 m).
VISIBLE_BEYOND = 0.05
#: Floor of the gap between a distractor's near edge and the line of sight of the board's
#: centre, rad, whatever the draw: the centre ray is never hidden.
CENTRE_RAY_CLEAR = 0.02
#: Nearest a distractor's centre is put to the LiDAR, m (the estimator's nearest return is
#: 0.5 m; nearer still a panel fills the view, which is another test).
NEAREST = 0.8
#: A wall pushed back to make room stands this far behind the furthest distractor, m.
WALL_CLEARANCE = 0.1


@dataclass(frozen=True)
class Kind:
    """A kind of board-like object: its size (full width and height across its face, depth
    along its normal, m; None: the board's own), the span its diffuse reflectance is drawn
    from, and how it stands:

    - ``"board"``: centred at the board's height, turned about its normal as the board is (a
      second calibration panel, hung the same way);
    - ``"floor"``: standing on the floor;
    - ``"sensor"``: its centre 0.1 m below to 0.15 m above the LiDAR's optical centre (a
      monitor on a desk or an arm), on a post from the floor (``stand``) half the time;
    - ``"view"``: its centre 0.6-1.1 m above the floor, across the middle of the sensor's +-15
      deg of elevation at the bench's distances (a mobile whiteboard; one hung higher would
      be out of the view and test nothing).
    """

    name: str
    width: float | None
    height: float | None
    depth: float
    reflectivity: tuple[float, float]
    mount: str
    note: str


#: The kinds a real station has about its board (issue 34).
KINDS: dict[str, Kind] = {k.name: k for k in (
    Kind("panel", None, None, 0.01, (0.4, 0.8), "board",
         "a second board-sized panel, bare or painted metal: the board's twin"),
    Kind("door", 0.9, 2.0, 0.04, (0.2, 0.7), "floor", "a door leaf, painted wood"),
    Kind("whiteboard", 1.2, 0.9, 0.02, (0.6, 0.9), "view", "a mobile whiteboard, bright"),
    Kind("monitor", 0.6, 0.35, 0.05, (0.03, 0.15), "sensor",
         "a 27 in monitor, its dark screen to the LiDAR"),
    Kind("cabinet", 0.8, 1.8, 0.45, (0.3, 0.8), "floor", "a metal cabinet, its face and sides"),
)}


@dataclass(frozen=True)
class Sight:
    """The board as the LiDAR sees it, horizontally: what every placement is relative to.
    ``sensor``, ``board``: the optical centre and the board's centre in {W}, m; ``ahead``,
    ``right``: horizontal unit vectors along the line of sight and to its right (as the LiDAR
    sees it); ``distance``: horizontal range to the board's centre, m; ``half_width``: the
    board's half extent across the line of sight (its corners projected), m."""

    sensor: np.ndarray
    board: np.ndarray
    ahead: np.ndarray
    right: np.ndarray
    distance: float
    half_width: float

    @classmethod
    def of(cls, params: BenchParams, sensor: np.ndarray) -> Sight:
        """The sight of ``params``' board from the optical centre ``sensor`` ({W}, m)."""
        from twin.sim.params import quat_wxyz  # the convention the model is built with

        sensor = np.asarray(sensor, dtype=float)
        board = np.asarray(params.board_position, dtype=float)
        flat = (board - sensor) * np.array([1.0, 1.0, 0.0])
        distance = float(np.linalg.norm(flat))
        ahead = flat / distance
        right = np.array([ahead[1], -ahead[0], 0.0])
        w, x, y, z = quat_wxyz(params.board_roll, params.board_tilt, params.board_yaw)
        from scipy.spatial.transform import Rotation

        r = Rotation.from_quat([x, y, z, w]).as_matrix()
        corners = np.array([[sx * params.board_width / 2, 0.0, sz * params.board_height / 2]
                            for sx in (-1, 1) for sz in (-1, 1)]) @ r.T
        return cls(sensor, board, ahead, right, distance, float(np.max(np.abs(corners @ right))))

    @property
    def half_angle(self) -> float:
        """The board's angular half width as the LiDAR sees it, rad."""
        return math.atan2(self.half_width, self.distance)


@dataclass(frozen=True)
class Distractor:
    """One distractor placed: its kind and placement, the boxes that make it (its body first,
    then any stand), its face's centre in {W} (m) and the horizontal direction its face looks
    (unit, {W}: towards the LiDAR, give or take the turn drawn)."""

    kind: str
    placement: str
    boxes: tuple[SceneBox, ...]
    centre: tuple[float, float, float]
    facing: tuple[float, float, float]


def lidar_in_world(params: BenchParams, x_m: float = 0.0, yaw_rad: float = 0.0
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The LiDAR's optical centre (3,) and axes (3, 3: {L} in {W}) with the stages at (x m,
    yaw rad): where the twin puts it (the model compiled, the stages set, no physics run).
    A distractor is placed from where the LiDAR is before the scene with it is built."""
    from twin.sim.physics import BenchPhysics

    phys = BenchPhysics(params)
    phys.set_stage_positions(x_m=x_m, yaw_rad=yaw_rad)
    return phys.lidar_pose_world()


def returns_on(points_l: np.ndarray, lidar: tuple[np.ndarray, np.ndarray], box: SceneBox,
               margin: float = 0.06) -> int:
    """How many of the returns ``points_l`` ((n, 3) in {L}, m) lie on ``box`` (a world-frame
    `SceneBox`) or within ``margin`` m of it (the range noise: 14 mm 1-sigma): a distractor
    the scan saw, counted."""
    from scipy.spatial.transform import Rotation

    pos, rot = lidar
    w, x, y, z = box.quat()
    r_box = Rotation.from_quat([x, y, z, w]).as_matrix()
    local = ((np.asarray(points_l) @ rot.T + pos) - np.asarray(box.pos)) @ r_box
    return int(np.sum(np.all(np.abs(local) <= np.asarray(box.size) + margin, axis=1)))


def _size(kind: Kind, params: BenchParams) -> tuple[float, float, float]:
    """Full width, height, depth of ``kind`` beside this board, m."""
    return (params.board_width if kind.width is None else kind.width,
            params.board_height if kind.height is None else kind.height, kind.depth)


def _yaw(rng: np.random.Generator, sight: Sight, where: np.ndarray,
         params: BenchParams) -> float:
    """A yaw between square to the board's plane and square to the LiDAR, +-10 deg: the box's
    +Y (its back) points away from the LiDAR."""
    v = where - sight.sensor
    facing_sensor = math.atan2(-v[0], v[1])
    d = (params.board_yaw - facing_sensor + math.pi) % (2 * math.pi) - math.pi
    return float(facing_sensor + rng.uniform(0.0, 1.0) * d + np.deg2rad(rng.uniform(-10, 10)))


def _across(width: float, depth: float, yaw: float, sight: Sight, where: np.ndarray) -> float:
    """Half extent across the line of sight to ``where`` of a box of full ``width`` x
    ``depth`` turned by ``yaw``, m."""
    v = where - sight.sensor
    v = v[:2] / np.linalg.norm(v[:2])
    across = np.array([v[1], -v[0]])
    ax = np.array([math.cos(yaw), math.sin(yaw)])  # the box's X in {W}
    ay = np.array([-math.sin(yaw), math.cos(yaw)])  # its Y
    return 0.5 * (width * abs(float(ax @ across)) + depth * abs(float(ay @ across)))


def _height(kind: Kind, rng: np.random.Generator, h: float, sight: Sight) -> float:
    """The centre's height above the floor, m (`Kind`'s mounts)."""
    if kind.mount == "board":
        return float(sight.board[2] + rng.uniform(-0.1, 0.1))
    if kind.mount == "floor":
        return h / 2
    if kind.mount == "sensor":
        return float(sight.sensor[2] + rng.uniform(-0.1, 0.15))
    return float(rng.uniform(0.6, 1.1))


def _corners(box: SceneBox) -> np.ndarray:
    """The eight corners of a world-frame box, (8, 3) m."""
    from scipy.spatial.transform import Rotation

    w, x, y, z = box.quat()
    r = Rotation.from_quat([x, y, z, w]).as_matrix()
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    return np.asarray(box.pos) + (signs * np.asarray(box.size)) @ r.T


def near_edge(box: SceneBox, sight: Sight, side: float) -> float:
    """The angle from the line of sight to the box's edge nearest it, as the LiDAR sees it
    from above, rad: positive on ``side`` (+1 right, -1 left) of it; negative where the box
    reaches across the line of sight."""
    c = _corners(box) - sight.sensor
    return float(np.min(np.arctan2(side * (c @ sight.right), c @ sight.ahead)))


def _near_edge_target(placement: str, rng: np.random.Generator, sight: Sight, along: float,
                      half: float) -> float:
    """The angle of a distractor's near edge from the line of sight (`near_edge`), rad, for
    ``placement`` (module docstring), ``along`` m down it with ``half`` m across it."""
    a_b = sight.half_angle
    if placement == "front":  # within the board's silhouette, off its centre ray
        return max(rng.uniform(0.25, 0.9) * a_b, CENTRE_RAY_CLEAR)
    if placement == "behind":  # from straight behind (seen around it) to 0.8 m clear
        width = 2 * math.atan2(half, along)
        return rng.uniform(a_b + VISIBLE_BEYOND - width, a_b + math.atan2(0.8, along))
    if placement == "nearer":  # wholly clear of the board's silhouette
        return a_b + rng.uniform(VISIBLE_BEYOND, 0.5)
    raise ValueError(f"placement {placement!r} has no near-edge rule")


def _at(box: SceneBox, lateral: float, sight: Sight, along: float, depth: float) -> SceneBox:
    """``box`` moved to stand ``lateral`` m across the line of sight, ``along`` m down it (its
    face's centre there, the box half its depth behind)."""
    back = np.array([-math.sin(box.yaw), math.cos(box.yaw), 0.0])
    face = sight.sensor + along * sight.ahead + lateral * sight.right
    centre = face + 0.5 * depth * back
    return replace(box, pos=(float(centre[0]), float(centre[1]), box.pos[2]))


def _solve_lateral(box: SceneBox, target: float, side: float, sight: Sight, along: float,
                   depth: float, start: float) -> float:
    """The lateral offset (signed) that puts ``box``'s near edge at ``target`` rad from the
    line of sight (`near_edge`): a few Newton steps from ``start`` (the angle moves by about
    1 / along per m across)."""
    lateral = start
    for _ in range(8):
        err = target - near_edge(_at(box, lateral, sight, along, depth), sight, side)
        if abs(err) < 1e-6:
            break
        lateral += side * err * along
    return lateral


def _along(placement: str, rng: np.random.Generator, sight: Sight) -> float:
    """How far down the line of sight the distractor's centre stands, m."""
    d = sight.distance
    if placement == "front":
        return max(rng.uniform(0.35, 0.8) * d, NEAREST)
    if placement == "beside":
        return d + rng.uniform(-0.1, 0.1)
    if placement == "behind":
        return d + rng.uniform(0.3, 1.5)
    if placement == "nearer":
        return max(rng.uniform(0.3, 0.7) * d, NEAREST)
    raise ValueError(f"placement {placement!r} is not one of {', '.join(PLACEMENTS)}")


def place(kind: str, placement: str, rng: np.random.Generator, params: BenchParams,
          sensor: np.ndarray) -> Distractor:
    """One distractor of ``kind`` (`KINDS`) at ``placement`` (`PLACEMENTS`) relative to
    ``params``' board as seen from the optical centre ``sensor`` ({W}, m; `lidar_in_world`),
    its side (left or right), distances, turn, height and reflectance drawn from ``rng``."""
    k = KINDS[kind]
    if placement not in PLACEMENTS:
        raise ValueError(f"placement {placement!r} is not one of {', '.join(PLACEMENTS)}")
    sight = Sight.of(params, sensor)
    width, height, depth = _size(k, params)
    side = 1.0 if rng.uniform() < 0.5 else -1.0
    along = _along(placement, rng, sight)
    zc = _height(k, rng, height, sight)
    refl = float(rng.uniform(*k.reflectivity))
    # the turn depends on where it stands and its extent across the sight on the turn: drawn
    # once on the line of sight at its distance, and kept where it is put
    first = sight.sensor + along * sight.ahead
    yaw = _yaw(rng, sight, first, params)
    half = _across(width, depth, yaw, sight, first)
    roll = params.board_roll if k.mount == "board" else 0.0
    body = SceneBox((0.0, 0.0, zc), (width / 2, depth / 2, height / 2), yaw=yaw,
                    reflectivity=refl, roll=float(roll))
    if placement == "beside":  # a gap of 0.3-1.5 m between the board's edge and its own
        lateral = side * (sight.half_width + rng.uniform(0.3, 1.5) + half)
    else:  # the near edge's angle drawn, the offset solved for it exactly (corners and all)
        target = _near_edge_target(placement, rng, sight, along, half)
        start = side * (along * math.tan(target) + half)
        lateral = _solve_lateral(body, target, side, sight, along, depth, start)
    body = _at(body, lateral, sight, along, depth)
    back = np.array([-math.sin(yaw), math.cos(yaw), 0.0])
    centre = np.asarray(body.pos)
    face = centre - 0.5 * depth * back
    boxes = [body]
    if k.mount == "sensor" and rng.uniform() < 0.5:
        # on a stand: a post from the floor to its lower edge and a foot, dark grey, behind
        # the screen (an arm's monitor floats: the draw above keeps the generator's sequence)
        bottom = zc - height / 2
        post = centre + 0.5 * (depth + 0.04) * back
        post[2] = bottom / 2
        boxes.append(SceneBox(tuple(float(v) for v in post), (0.03, 0.02, bottom / 2),
                              yaw=yaw, reflectivity=0.1))
        foot = centre + 0.5 * depth * back
        foot[2] = 0.01
        boxes.append(SceneBox(tuple(float(v) for v in foot), (0.12, 0.1, 0.01),
                              yaw=yaw, reflectivity=0.1))
    return Distractor(kind, placement, tuple(boxes), tuple(float(v) for v in face),
                      tuple(float(v) for v in -back))


#: The placement functions by name, each ``(kind, rng, params, sensor) -> Distractor``.
PLACE: dict[str, Callable[..., Distractor]] = {
    p: (lambda kind, rng, params, sensor, _p=p: place(kind, _p, rng, params, sensor))
    for p in PLACEMENTS}


def _reach_behind(params: BenchParams, boxes: tuple[SceneBox, ...]) -> float:
    """How far behind the board's nominal face plane (Y_W of its position) the furthest box
    corner reaches, m."""
    by = params.board_position[1]
    far = -math.inf
    for b in boxes:
        for sx in (-1, 1):
            for sy in (-1, 1):
                # a box's footprint corner, turned by its yaw (a roll keeps it within its
                # circumscribed footprint: the larger of width and height across)
                wx = max(b.size[0], b.size[2]) if b.roll else b.size[0]
                y = (b.pos[1] + sx * wx * math.sin(b.yaw) + sy * b.size[1] * math.cos(b.yaw))
                far = max(far, y - by)
    return far


def room_for(params: BenchParams, distractor: Distractor) -> BenchParams:
    """``params`` with the wall moved back where it stands in front of any part of the
    distractor (`WALL_CLEARANCE` behind it), and nothing else changed: the scene the
    distractor's scene is compared against (the same wall, without it)."""
    wall = 1.5 if params.wall_distance is None else params.wall_distance
    need = _reach_behind(params, distractor.boxes) + WALL_CLEARANCE
    return params if need <= wall else replace(params, wall_distance=float(need))


def with_distractor(params: BenchParams, distractor: Distractor) -> BenchParams:
    """``params`` (from `room_for`) with the distractor's boxes added to its clutter."""
    return replace(params, clutter=params.clutter + distractor.boxes)


def diamond(params: BenchParams, angle: float = math.radians(45.0),
            clearance: float = 0.2) -> BenchParams:
    """``params``' board hung as a diamond: turned by ``angle`` (rad) about its normal, raised
    with the LiDAR (its lever arm) so its lowest corner stays ``clearance`` m above the floor
    and its centre level with the optical centre, as `tests/test_align_boards.py`'s
    `board_sim` does."""
    w2, h2 = params.board_width / 2, params.board_height / 2
    reach = w2 * abs(math.sin(angle)) + h2 * abs(math.cos(angle))
    bx, by, bz = params.board_position
    lift = max(0.0, reach + clearance - bz)
    lx, ly, lz = params.lever_arm
    return replace(params, board_roll=float(angle), board_position=(bx, by, bz + lift),
                   lever_arm=(lx, ly, lz + lift))
