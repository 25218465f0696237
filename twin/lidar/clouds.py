"""Point clouds (PCD files, ROS PointCloud2) as `Scan`s, with the firings that missed rebuilt.

A point cloud lists only the returns: the rays that missed are gone, yet the estimator learns the
board's edges from them as much as from the hits (docs/DESIGN.md, "Data flow"). A spinning
LiDAR fires on a regular grid, though: every firing sequence fires all its lasers at (nearly) one
azimuth, one sequence every 55.296 us on a VLP-16, each laser a fixed time after the sequence
starts. So the grid can be rebuilt from the returns' azimuths:

1. each point's laser from its ``ring`` (elevation order), or from its elevation when the cloud has
   no ring (with a `RingsFromElevationWarning`); a cloud whose rings or elevations are not the
   sensor's (a VLP-16's unless its model or laser table is given) is refused
   (`UnsupportedCloudError`);
2. each point's azimuth with its laser's firing delay taken off (the rotation during the delay),
   which puts the returns of one sequence at one azimuth; the returns are walked in time order
   (the ``time`` field, else the file's order when it is a sweep) so that a cloud spanning a
   little more than a turn keeps both ends;
3. the returns grouped into sequences (clusters closer than half the azimuth step), the step
   measured, and the sequences in which every laser missed put back where the step says
   (interior gaps up to `FILL_LIMIT`; a wider gap is a sector the cloud does not hold, left out
   and flagged);
4. every (sequence, laser) slot becomes a firing, in the firing order a decoded scan has
   (align/segment.py's grid): a return where the cloud has one, a miss (distance 0) at the
   grid's azimuth otherwise.

What this cannot know (docs/vlp16.md measures its cost): a hole left by lost packets looks like
rays that missed; the firing times are the grid's unless the cloud has a ``time`` field; a dual
return cloud keeps one return per firing (the strongest).

Frames: a cloud from a ROS driver or a PCD file is in the ROS convention (x forward, y left,
z up); `Cloud.from_ros` turns it into {L} (x_ros = Y_L, y_ros = -X_L; docs/DESIGN.md).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np

from twin.core import vlp16
from twin.core.errors import AimbenchError
from twin.core.lasers import LaserTable
from twin.core.scan import ReturnType, Scan
from twin.core.sensors import MODELS, SensorModel
from twin.lidar.conventions import CONVENTIONS, CloudConvention, convention_named, turn

TWO_PI = 2.0 * math.pi
#: Interior gaps of the sweep up to this wide are firings that all missed and are rebuilt; a
#: wider one is a sector the cloud does not cover (cropped, or lost), rad. 10 deg: far wider than
#: any run of all-missing sequences in a room (the lower lasers see the floor), far narrower than
#: a crop.
FILL_LIMIT = math.radians(10.0)
#: Elevation of a laser's returns may differ from the table by this before the cloud is refused
#: as another sensor's, as a share of the table's smallest ring spacing.
ELEVATION_TOLERANCE = 0.25
#: Firing timing of the models whose grids can be rebuilt: (delay of each laser after its
#: sequence's start, s, by laser id; sequence period, s), by model name: each `SensorModel`'s
#: own (`twin.core.sensors`, from its manual), so that a rebuilt grid is the decoder's.
FIRING_TIMING: dict[str, tuple[np.ndarray, float]] = {
    m.name: (m.firing_offset, m.sequence_period) for m in MODELS.values()
}


class CloudError(AimbenchError):
    """A point cloud cannot be turned into a scan (no points, no coordinates, bad fields)."""


class SparseCloudError(CloudError):
    """Too few returns to find a rotation's firing grid (a scrap of a rotation, say)."""


class UnsupportedCloudError(CloudError):
    """The cloud comes from another sensor than the laser table describes."""


class RingsFromElevationWarning(UserWarning):
    """The cloud had no ring field: each point's laser was taken from its elevation."""


class BadTimesWarning(UserWarning):
    """The cloud's time field holds NaN or infinite values: it is not used."""


@dataclass(frozen=True, eq=False)
class Cloud:
    """The returns of one rotation: per-point arrays in {L} (m), as a file or message held them.

    ``intensity``, ``ring`` (elevation order, 0 = lowest) and ``time`` (s, any origin) may be
    missing (None). ``name`` says where the cloud came from (a file, a topic and stamp).
    """

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    intensity: np.ndarray | None = None
    ring: np.ndarray | None = None
    time: np.ndarray | None = None
    name: str = "point cloud"
    meta: dict = field(default_factory=dict)
    #: The driver's convention (`twin.lidar.conventions`), when its fields tell it; None: to be
    #: told from the points.
    convention: str | None = None
    #: The encoder azimuth of each point's block, rad, when the driver writes it (nebula's
    #: ``azimuth`` field for the 32-laser models).
    block_azimuth: np.ndarray | None = None

    @classmethod
    def from_ros(cls, x: np.ndarray, y: np.ndarray, z: np.ndarray, **kwargs) -> Cloud:
        """A cloud from coordinates in the ROS convention (x forward, y left, z up)."""
        y = np.asarray(y, dtype=np.float64)
        return cls(np.negative(y), np.asarray(x, dtype=np.float64),
                   np.asarray(z, dtype=np.float64), **kwargs)

    def __len__(self) -> int:
        return len(self.x)


@dataclass
class _Points:
    """The cloud's usable returns, with what step 1 found for each."""

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    intensity: np.ndarray
    laser: np.ndarray
    azimuth: np.ndarray
    distance: np.ndarray
    time: np.ndarray | None
    order: np.ndarray  # position of each point in the sweep's time order
    block_azimuth: np.ndarray | None  # the encoder azimuth of each point's block (rad), if given


def scan_from_cloud(
    cloud: Cloud,
    lasers: LaserTable = vlp16.LASERS,
    *,
    vertical_offsets: bool | None = None,
    index: int = 0,
    model: SensorModel | None = None,
    convention: str | CloudConvention | None = None,
) -> Scan:
    """The `Scan` of a cloud's rotation with the misses rebuilt (module docstring).

    ``lasers``: the sensor's laser table (the VLP-16's by default). ``model``: the sensor whose
    firing timing the grid has (`twin.core.sensors`); None: the model ``lasers`` is named after,
    one of `FIRING_TIMING` (a unit's calibration table needs its model given).
    ``vertical_offsets``: whether the cloud's z carries the lasers' vertical offsets (our
    decoder's default) or not (the ROS velodyne driver's); None decides from the points: with
    the right choice every laser's returns lie at one elevation. ``convention``: the driver
    that wrote the cloud (`twin.lidar.conventions`: how it turned each laser's point); None:
    the cloud's own (told by its fields), else told from the points.
    """
    if model is not None:
        if model.n_lasers != lasers.n_lasers:
            raise UnsupportedCloudError(
                f"{cloud.name}: the laser table {lasers.model!r} has {lasers.n_lasers} lasers, "
                f"a {model.name} {model.n_lasers}: it is another sensor's table")
        delay, period = model.firing_offset, model.sequence_period
    elif lasers.model in FIRING_TIMING:
        delay, period = FIRING_TIMING[lasers.model]
    else:
        raise UnsupportedCloudError(
            f"{cloud.name}: cannot rebuild the firing grid of a {lasers.model}: aimbench knows "
            f"the firing timing of {', '.join(FIRING_TIMING)} only (name the model)")
    true = delay / period
    pts, offsets_applied, notes = _points(cloud, lasers, vertical_offsets)
    step0 = _azimuth_step(pts)
    conv, told, drv = _convention(cloud, convention, pts, true, step0, lasers)
    if pts.block_azimuth is not None and conv.name == "nebula" and lasers.n_lasers == 32:
        # nebula's VLP-32 decoder writes each block's encoder azimuth: one sequence each.
        anchor = pts.block_azimuth.astype(np.float64) % TWO_PI
    else:
        pts.block_azimuth = None
    # The rotation the driver put in each point, share of a step (nebula's VLP-32 decoder puts
    # none in the last block of each packet).
    rot = drv[pts.laser]
    if pts.block_azimuth is None and conv.name == "nebula" and lasers.n_lasers == 32:
        rot = _nebula_last_blocks(pts, drv, lasers, step0)
    if pts.block_azimuth is None:
        anchor = pts.azimuth - lasers.azimuth_offset[pts.laser] - step0 * rot
    seq_az, seq_index, slot_seq, step, partial, unfilled = _sequences(pts, anchor, step0)
    n_seq = int(seq_index[-1]) + 1
    nl = lasers.n_lasers
    # One return per (sequence, laser) slot: in dual-return clouds (and where the cloud's two ends
    # overlap) the strongest stays.
    slot = seq_index[slot_seq] * nl + pts.laser
    pick = np.lexsort((-pts.intensity, slot))
    first = np.ones(len(pick), dtype=bool)
    first[1:] = slot[pick][1:] != slot[pick][:-1]
    keep = pick[first]
    dropped = len(pick) - len(keep)

    # The grid: filled sequences get azimuths between their neighbours.
    grid_az = np.interp(np.arange(n_seq), seq_index, seq_az)
    lid = np.tile(np.arange(nl, dtype=np.uint8), n_seq)
    seq_of = np.repeat(np.arange(n_seq), nl)
    rate = step / period  # rad/s
    azimuth = (grid_az[seq_of] + rate * delay[lid] + lasers.azimuth_offset[lid]) % TWO_PI
    n = n_seq * nl
    arrays = {name: np.zeros(n) for name in ("distance", "x", "y", "z")}
    intensity = np.zeros(n, dtype=np.uint8)
    at = slot[keep]
    # Each return turned to its firing's azimuth: by the rotation during its laser's firing
    # delay that the driver left out (or put in wrongly), or, where the driver wrote the
    # block's azimuth, onto the grid's azimuth outright (its 0.01 deg rounding gone too).
    if pts.block_azimuth is not None:
        kept_lid = pts.laser[keep]
        target = (pts.block_azimuth[keep] + rate * delay[kept_lid]
                  + lasers.azimuth_offset[kept_lid])
        dturn = (target - pts.azimuth[keep] + math.pi) % TWO_PI - math.pi
    else:
        dturn = (true[pts.laser[keep]] - rot[keep]) * step
    azimuth[at] = (pts.azimuth[keep] + dturn) % TWO_PI
    for name in ("distance", "z"):
        arrays[name][at] = getattr(pts, name)[keep]
    arrays["x"][at], arrays["y"][at] = turn(pts.x[keep], pts.y[keep], dturn)
    intensity[at] = np.clip(np.rint(pts.intensity[keep]), 0, 255).astype(np.uint8)
    time = seq_of * period + delay[lid]
    if pts.time is not None:
        # The cloud's own times where it has returns; the grid's, on the cloud's clock, elsewhere.
        t0 = float(np.median(pts.time[keep] - time[at]))
        time = time + t0
        time[at] = pts.time[keep]
    return_type = np.full(n, int(ReturnType.STRONGEST), dtype=np.uint8)
    rpm = rate * 60.0 / TWO_PI
    span = float(grid_az[-1] - grid_az[0] + step)
    return Scan(
        **arrays, azimuth=azimuth, laser_id=lid, intensity=intensity, time=time,
        return_type=return_type, index=index, complete=not partial, packets=0,
        missing_packets=0, vertical_offsets_applied=offsets_applied, lasers=lasers,
        meta={
            "source": cloud.name,
            "from_cloud": True,
            "rpm": rpm,
            "cloud_points": len(cloud),
            "rebuilt_misses": int(n - len(keep)),
            "rebuilt_sequences": int(n_seq - len(np.unique(slot_seq))),
            "dropped_returns": int(dropped + notes.pop("unusable", 0)),
            "partial": partial,
            "unfilled_gaps_deg": [round(math.degrees(g), 3) for g in unfilled],
            "azimuth_span_deg": math.degrees(span),
            "cloud_convention": conv.name if told != "points" else _alike(drv, lasers, true),
            "cloud_convention_from": told,
            "turned_max_deg": float(np.degrees(np.abs(dturn).max())) if len(dturn) else 0.0,
            "start_time_s": float(time[0]),
            "end_time_s": float(time[-1]),
            **notes,
            **cloud.meta,
        },
    )


# ----------------------------------------------------------------------------------------------
# Step 1: lasers, azimuths, ranges


def _points(cloud: Cloud, lasers: LaserTable, vertical_offsets: bool | None
            ) -> tuple[_Points, bool, dict]:
    x, y, z = (np.asarray(a, dtype=np.float64) for a in (cloud.x, cloud.y, cloud.z))
    if not (len(x) == len(y) == len(z)):
        raise CloudError(f"{cloud.name}: x, y and z have different lengths")
    ok = np.isfinite(x) & np.isfinite(y) & np.isfinite(z) & ((x != 0) | (y != 0) | (z != 0))
    notes: dict = {}
    ring = None
    if cloud.ring is not None:
        ring = np.asarray(cloud.ring)
        if len(ring) != len(x):
            raise CloudError(f"{cloud.name}: the ring field has {len(ring)} values for "
                             f"{len(x)} points")
        ring = _whole_numbers(ring[ok], "ring", cloud.name, ring)
        top = int(ring[ok].max()) if ok.any() else 0
        if top >= lasers.n_lasers or (ok.any() and int(ring[ok].min()) < 0):
            raise UnsupportedCloudError(
                f"{cloud.name}: the cloud has rings {int(ring[ok].min())}..{top}, a "
                f"{lasers.model} {lasers.n_lasers} (0..{lasers.n_lasers - 1}): it comes from "
                "another sensor, which aimbench does not rebuild")
    notes["unusable"] = int((~ok).sum())
    if ok.sum() < 2 * lasers.n_lasers:
        raise SparseCloudError(f"{cloud.name}: {int(ok.sum())} usable points (finite, not at the "
                         "origin): too few for a scan of a rotation")
    x, y, z = x[ok], y[ok], z[ok]
    rxy = np.hypot(x, y)
    el_plain = np.arctan2(z, rxy)
    if ring is not None:
        laser = lasers.laser_of_ring[ring[ok].astype(np.intp)]
    else:
        laser = _nearest_laser(el_plain, lasers)
    if vertical_offsets is None:
        vertical_offsets = _offsets_fit_better(z, rxy, laser, lasers)
    off = lasers.vertical_offset[laser] if vertical_offsets else np.zeros(len(z))
    el = np.arctan2(z - off, rxy)
    if ring is None:
        laser = _nearest_laser(el, lasers)
        off = lasers.vertical_offset[laser] if vertical_offsets else off
        el = np.arctan2(z - off, rxy)
        warnings.warn(
            f"{cloud.name}: the cloud has no ring field; each point's laser was taken from its "
            f"elevation (nearest {lasers.model} laser): use a cloud with ring where there is one",
            RingsFromElevationWarning, stacklevel=4)
        notes["rings_from_elevation"] = True
    _check_elevations(cloud.name, el, laser, lasers)
    intensity = (np.zeros(len(x)) if cloud.intensity is None
                 else np.asarray(cloud.intensity, dtype=np.float64)[ok])
    time = None if cloud.time is None else np.asarray(cloud.time, dtype=np.float64)[ok]
    if time is not None and not np.isfinite(time).all():
        # A NaN time sorted last and the sweep wrapped a second turn over it: one rotation's
        # firings doubled (issue 37). Not a time order: the file's order is used, and said.
        bad = int((~np.isfinite(time)).sum())
        warnings.warn(f"{cloud.name}: {bad} of the time field's values are not finite; the "
                      "field is not used (the points are taken in the file's order)",
                      BadTimesWarning, stacklevel=4)
        notes["times_not_finite"] = bad
        time = None
    order = (np.arange(len(x)) if time is None else np.argsort(np.argsort(time, kind="stable")))
    extra = {name: None if getattr(cloud, name) is None else np.asarray(getattr(cloud, name))[ok]
             for name in ("block_azimuth",)}
    pts = _Points(x=x, y=y, z=z, intensity=intensity, laser=laser.astype(np.intp),
                  azimuth=np.arctan2(x, y) % TWO_PI,
                  distance=np.hypot(rxy, z - off), time=time, order=order, **extra)
    return pts, bool(vertical_offsets), notes


def _whole_numbers(values: np.ndarray, field: str, name: str, whole: np.ndarray) -> np.ndarray:
    """`whole` (a per-point field) as integers, refused naming the field if the usable
    points' `values` hold a NaN, an infinity or a fraction (a ring is a laser's number)."""
    if values.dtype.kind == "f":
        bad = ~np.isfinite(values) | (values != np.round(values))
        if bad.any():
            raise CloudError(f"{name}: the {field} field holds {int(bad.sum())} values that are "
                             f"not whole numbers (first {values[bad][0]!r}): a damaged cloud, "
                             f"or not a LiDAR's {field} numbers")
        finite = np.where(np.isfinite(whole), whole, -1)
        return finite.astype(np.int64)
    return whole


def _nearest_laser(el: np.ndarray, lasers: LaserTable) -> np.ndarray:
    """The laser whose elevation is nearest each point's."""
    by_el = lasers.elevation[lasers.laser_of_ring]
    mid = 0.5 * (by_el[1:] + by_el[:-1])
    return lasers.laser_of_ring[np.searchsorted(mid, el)]


def _offsets_fit_better(z: np.ndarray, rxy: np.ndarray, laser: np.ndarray,
                        lasers: LaserTable) -> bool:
    """Whether z carries the lasers' vertical offsets: then each laser's elevations, with the
    offset taken off, are one value (a wrong choice spreads them as offset / range)."""
    if not np.any(lasers.vertical_offset):
        return False
    spread = []
    for off in (np.zeros(len(z)), lasers.vertical_offset[laser]):
        el = np.arctan2(z - off, rxy)
        total = 0.0
        for lid in np.unique(laser):
            e = el[laser == lid]
            total += float(np.median(np.abs(e - np.median(e)))) * len(e)
        spread.append(total)
    return spread[1] < spread[0]


def _check_elevations(name: str, el: np.ndarray, laser: np.ndarray, lasers: LaserTable) -> None:
    """Refuse a cloud whose lasers do not lie at the table's elevations (another sensor)."""
    by_el = np.sort(lasers.elevation)
    tol = ELEVATION_TOLERANCE * (float(np.min(np.diff(by_el))) if len(by_el) > 1 else 0.05)
    dev = np.abs(el - lasers.elevation[laser])
    if np.mean(dev > tol) <= 0.05:
        return
    worst = int(np.argmax(np.bincount(laser, dev > tol, minlength=lasers.n_lasers)))
    med = float(np.median(el[laser == worst]))
    raise UnsupportedCloudError(
        f"{name}: the returns of ring {int(lasers.ring_of_laser[worst])} lie at "
        f"{math.degrees(med):.2f} deg where a {lasers.model}'s lie at "
        f"{math.degrees(lasers.elevation[worst]):.2f} deg ({100 * np.mean(dev > tol):.0f}% of "
        f"the points are more than {math.degrees(tol):.2f} deg off): the cloud comes from "
        "another sensor, which aimbench does not rebuild")


# ----------------------------------------------------------------------------------------------
# The driver's convention


def _convention(cloud: Cloud, given: str | CloudConvention | None, pts: _Points,
                true: np.ndarray, step0: float, lasers: LaserTable
                ) -> tuple[CloudConvention, str, np.ndarray]:
    """The convention the cloud is read by, how it was told (``option``, ``fields``,
    ``points``), and the rotation its driver put in each laser's point (share of a step)."""
    conv = convention_named(given)
    if conv is not None:
        return conv, "option", conv.rotation(lasers.n_lasers, true)
    if cloud.convention is not None:
        conv = convention_named(cloud.convention)
        return conv, "fields", conv.rotation(lasers.n_lasers, true)
    # From the points: the rotation under which each sequence's returns line up. Wrong ones
    # merge neighbouring sequences (a laser twice in a group) or split one (more groups).
    candidates: list[tuple[CloudConvention, np.ndarray]] = []
    for c in CONVENTIONS.values():
        rot = c.rotation(lasers.n_lasers, true)
        if not any(np.array_equal(rot, r) for _, r in candidates):
            candidates.append((c, rot))
    if len(candidates) == 1:
        return candidates[0][0], "points", candidates[0][1]
    costs = [_grouping_cost(pts.azimuth - lasers.azimuth_offset[pts.laser] - step0 * rot[pts.laser],
                            pts.laser, step0, lasers.n_lasers) for _, rot in candidates]
    best = int(np.argmin(costs))
    return candidates[best][0], "points", candidates[best][1]


def _nebula_last_blocks(pts: _Points, drv: np.ndarray, lasers: LaserTable,
                        step0: float) -> np.ndarray:
    """Each point's rotation in a nebula VLP-32 cloud without its ``azimuth`` field: the
    channel's share of the step, but none in the last block of every packet of 12
    (vlp32_decoder.cpp gives that block an azimuth step of 0). Those blocks are found on the
    grid the others give: the lasers whose share is far from a whole step land on a sequence
    there when not turned, and do so every 12th sequence. The lasers whose share is nearly a
    whole step (channels 19-29) land on it turned or not: two returns of one laser there are
    the two blocks', in their order; a lone one keeps the channel's share."""
    rot = drv[pts.laser].copy()
    base = pts.azimuth - lasers.azimuth_offset[pts.laser]
    seq_az, seq_index, *_ = _sequences(pts, base - step0 * rot, step0)
    rel = (base - seq_az[0]) % TWO_PI + seq_az[0]
    k0 = np.interp(rel, seq_az, seq_index.astype(np.float64))
    near = np.abs(k0 - np.rint(k0)) < 0.25
    telling = np.abs(rot - np.rint(rot)) >= 0.25
    evidence = near & telling
    if evidence.sum() < 8:
        return rot
    k = np.rint(k0).astype(np.int64)
    phase = int(np.argmax(np.bincount(k[evidence] % 12, minlength=12)))
    last = near & (k % 12 == phase)
    rot[last & telling] = 0.0
    # A laser whose share is about a whole step lands there from both blocks: the previous
    # block's point turned, this block's not. The later of the two (time, else file order:
    # nebula writes block by block) is this block's.
    pair = last & ~telling & (np.rint(drv[pts.laser]) == 1)
    idx = np.flatnonzero(pair)
    key = k[idx] * lasers.n_lasers + pts.laser[idx]
    srt = np.lexsort((pts.order[idx], key))
    twin = np.flatnonzero(np.diff(key[srt]) == 0) + 1
    rot[idx[srt][twin]] = 0.0
    return rot


def _grouping_cost(c: np.ndarray, laser: np.ndarray, step0: float, n_lasers: int) -> int:
    """Groups of returns closer than half a step, plus the returns whose laser is already in
    their group: the fewest for the rotation the driver used."""
    srt = np.argsort(c % TWO_PI, kind="stable")
    gid = np.concatenate(([0], np.cumsum(np.diff((c % TWO_PI)[srt]) > 0.5 * step0)))
    keys = gid * n_lasers + laser[srt]
    return int(gid[-1] + 1) + int(len(keys) - len(np.unique(keys)))


def _alike(rot: np.ndarray, lasers: LaserTable, true: np.ndarray) -> str:
    """The conventions that turn this model's points as ``rot`` does, one name or ``a = b``."""
    return " = ".join(c.name for c in CONVENTIONS.values()
                      if np.array_equal(c.rotation(lasers.n_lasers, true), rot))


# ----------------------------------------------------------------------------------------------
# Steps 2 and 3: the firing sequences


def _azimuth_step(pts: _Points) -> float:
    """A first azimuth step between sequences: the typical step between a laser's returns."""
    steps = []
    for lid in np.unique(pts.laser):
        a = np.sort(pts.azimuth[pts.laser == lid])
        d = np.diff(a)
        steps.append(d[(d > 0) & (d < math.radians(2.0))])
    d = np.concatenate(steps) if steps else np.zeros(0)
    if len(d) < 8:
        raise SparseCloudError("too few neighbouring returns along the rings to find the azimuth "
                               "step of the firings (is this a spinning LiDAR's rotation?)")
    return float(np.median(d))


def _sequences(pts: _Points, c: np.ndarray, step0: float
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, bool, list[float]]:
    """Group the returns into firing sequences along the sweep; ``c``: the azimuth each
    return's sequence started at, as the driver's convention gives it (step 2).

    Returns the sequences' azimuths (unwrapped, in sweep order), each sequence's index on the
    rebuilt grid (gaps filled), each point's sequence, the measured step (rad), whether the cloud
    covers less than a turn, and the widths of the gaps left unfilled (rad).
    """
    by_time = np.argsort(pts.order)
    start = float(c[by_time[0]])
    rel = (c - start + 0.5 * step0) % TWO_PI
    # A second turn begins where the sweep jumps back by more than half a turn; a cloud in no
    # time order (sorted by ring, say) jumps back all the time: then azimuth alone orders it.
    jumps = np.diff(rel[by_time]) < -math.pi
    if 0 < jumps.sum() <= 2:
        turn = np.empty(len(rel))
        turn[by_time] = np.concatenate(([0], np.cumsum(jumps)))
        rel = rel + TWO_PI * turn
    srt = np.argsort(rel, kind="stable")
    r = rel[srt]
    brk = np.diff(r) > 0.5 * step0
    cid_sorted = np.concatenate(([0], np.cumsum(brk)))
    n_cl = int(cid_sorted[-1]) + 1
    cid = np.empty(len(r), dtype=np.intp)
    cid[srt] = cid_sorted
    seq_az = np.bincount(cid, rel, n_cl) / np.bincount(cid, minlength=n_cl)
    # Sequences between the clusters where every laser missed (step 3).
    gaps = np.diff(seq_az)
    k = np.rint(gaps / step0).astype(np.int64)
    fill = gaps <= FILL_LIMIT
    unfilled = [float(g) for g in gaps[~fill]]
    # (an unfilled gap joins its two sides on the grid with nothing between them)
    seq_index = np.concatenate(([0], np.cumsum(np.where(fill, np.maximum(k, 1), 1))))
    # The step, measured over the filled runs (the unfilled gaps join nothing).
    run = np.concatenate(([0], np.cumsum(~fill)))
    step = _fit_step(seq_az, seq_index, run, step0)
    span = float(seq_az[-1] - seq_az[0]) + step
    wrap_gap = TWO_PI - span
    partial = bool(unfilled) or wrap_gap > FILL_LIMIT
    if not partial and wrap_gap > 1.5 * step:
        # The turn closes over a run of all-missing sequences: the last of them anchors the grid
        # (no return belongs to it; the grid interpolates the ones between).
        m = int(np.rint(wrap_gap / step)) - 1
        seq_az = np.concatenate((seq_az, [seq_az[-1] + m * step]))
        seq_index = np.concatenate((seq_index, [seq_index[-1] + m]))
    elif wrap_gap > FILL_LIMIT:
        unfilled.append(wrap_gap)
    return (seq_az + start - 0.5 * step0, seq_index, cid, step, partial, unfilled)


def _fit_step(seq_az: np.ndarray, seq_index: np.ndarray, run: np.ndarray, step0: float) -> float:
    """Least-squares slope of sequence azimuth against grid index, within each filled run."""
    num = den = 0.0
    for r in np.unique(run):
        sel = run == r
        if sel.sum() < 2:
            continue
        i = seq_index[sel].astype(np.float64)
        a = seq_az[sel]
        i, a = i - i.mean(), a - a.mean()
        num += float(i @ a)
        den += float(i @ i)
    return num / den if den > 0 else step0
