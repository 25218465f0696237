"""Per-laser corrections from scans of the board at known bench poses, and applying them.

Why: the paper measured range offsets up to 5 mm per laser; +-5 mm spread over the six rings on
the board tilts the fitted plane by about 0.35 deg, far above the estimator's precision. With the
board at known poses (the twin's truth, or the bench's stage readings with a surveyed mount),
every return on the board's interior has a known true range: the mean residual per laser is its
range offset. A laser's elevation error moves its ring up or down the board; it is observable
only where the ring crosses the board's top or bottom edge (there the hit/miss transition along
the ring pins the ring's height to the edge), so it is reported only for those lasers, and as
"not observed" (None) for the others.

File format (JSON; `scenarios.calibrate.write` / `read` write and read it, `to_dict` /
`from_dict` are its content): ``{"format": "aimbench.laser_calibration", "version": 2,
"sensor": {"id", "model", "n_lasers"}, "made": {...}, "lasers": [{"laser_id", "elevation_deg",
"range_offset_m", "range_offset_std_m", "elevation_offset_rad", "elevation_offset_std_rad",
"returns", "edge_crossings"} per laser], "source": {...}}``. Offsets are measured minus true: the
corrected range is distance - offset.

Identity (version 2): ``sensor`` says which unit the file is for: ``id`` (its serial number, or
an id the user gave it; None when nobody said), ``model`` (the scans' laser table, e.g. VLP-16)
and ``n_lasers``. ``made`` says when and how: ``at`` (UTC, ISO 8601), ``how`` (e.g. "sim bench",
"capture"), ``poses`` (the distinct true poses, edge units), ``scans``, ``residuals`` (RMS of
measured minus true range on the board's interior before and after the correction, m, and the
returns counted), and whatever the caller adds (the software's version). Version 1 files (no
identity) still load, with an unknown sensor. `identity_warnings` and `ring_bias` are the pieces
of the check that a capture fits a calibration (`scenarios.calibrate.check`).

Pure, as the rest of align/: no function here touches a file.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from align.board import BoardSpec
from align.geometry import board_coordinates
from twin.core import vlp16
from twin.core.pose import Pose
from twin.core.scan import Scan

FORMAT = "aimbench.laser_calibration"
VERSION = 2
#: Versions `from_dict` reads (1: before the sensor's identity was recorded).
READS = (1, 2)
#: Distinct poses kept in ``made["poses"]`` (a calibration visits a few; a capture may hold many).
MAX_POSES = 50
#: Returns used for range offsets: at least this far inside the board's edges, m.
INTERIOR_MARGIN = 0.03
#: A return within this of the true range is on the board, m (5 sigma of 14 mm noise).
ON_BOARD = 0.07


@dataclass(frozen=True)
class LaserCalibration:
    """Per-laser corrections, indexed by laser id (as many as the sensor has). SI units.

    ``elevation_offset`` holds NaN where the scans could not observe it; ``elevation_deg`` is
    the nominal elevation of each laser (from the scans' laser table; the VLP-16's by default),
    kept so that a file says which lasers it is about.
    """

    range_offset: np.ndarray
    range_offset_std: np.ndarray
    elevation_offset: np.ndarray | None = None
    elevation_offset_std: np.ndarray | None = None
    returns: np.ndarray | None = None
    edge_crossings: np.ndarray | None = None
    source: dict = field(default_factory=dict)
    elevation_deg: np.ndarray | None = None
    #: Which unit: {"id": serial or user id or None, "model": ..., "n_lasers": ...}.
    sensor: dict = field(default_factory=dict)
    #: When and how it was made (see the module docstring).
    made: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        n = len(self.range_offset)
        defaults = {"elevation_offset": np.full(n, np.nan), "elevation_offset_std":
                    np.full(n, np.nan), "returns": np.zeros(n, dtype=np.int64),
                    "edge_crossings": np.zeros(n, dtype=np.int64),
                    "elevation_deg": (vlp16.ELEVATION_DEG if n == vlp16.N_LASERS
                                      else np.full(n, np.nan))}
        for name, default in defaults.items():
            if getattr(self, name) is None:
                object.__setattr__(self, name, default)
            elif len(getattr(self, name)) != n:
                raise ValueError(f"LaserCalibration.{name} has {len(getattr(self, name))} "
                                 f"entries for {n} lasers")

    @property
    def n_lasers(self) -> int:
        return len(self.range_offset)

    @property
    def sensor_id(self) -> str | None:
        return self.sensor.get("id")

    @property
    def model(self) -> str | None:
        return self.sensor.get("model")

    def describe(self) -> str:
        """One line naming the calibration: the sensor, when and how it was made."""
        who = f"{self.model or 'unknown model'} " + (f"{self.sensor_id!r}" if self.sensor_id
                                                     else "(no sensor id)")
        made = self.made
        if not made:
            return f"{who}, {self.source.get('name') or 'origin not recorded'} (a version 1 file)"
        res = made.get("residuals") or {}
        how = (f", made {made.get('at', '?')} from {made.get('how', '?')}: "
               f"{len(made.get('poses', []))} poses, {made.get('scans', '?')} scans")
        if res.get("rms_before_m") is not None and res.get("rms_after_m") is not None:
            how += (f", range residual {res['rms_before_m'] * 1e3:.1f} -> "
                    f"{res['rms_after_m'] * 1e3:.1f} mm RMS")
        return who + how

    def to_dict(self) -> dict:
        def f(v: float) -> float | None:
            return None if not np.isfinite(v) else float(v)

        lasers = [{
            "laser_id": i,
            "elevation_deg": f(self.elevation_deg[i]),
            "range_offset_m": f(self.range_offset[i]),
            "range_offset_std_m": f(self.range_offset_std[i]),
            "elevation_offset_rad": f(self.elevation_offset[i]),
            "elevation_offset_std_rad": f(self.elevation_offset_std[i]),
            "returns": int(self.returns[i]),
            "edge_crossings": int(self.edge_crossings[i]),
        } for i in range(self.n_lasers)]
        return {"format": FORMAT, "version": VERSION,
                "sensor": {"id": self.sensor_id, "model": self.model,
                           "n_lasers": self.n_lasers},
                "made": self.made, "lasers": lasers, "source": self.source}

    @classmethod
    def from_dict(cls, d: dict) -> LaserCalibration:
        if d.get("format") != FORMAT or d.get("version") not in READS:
            raise ValueError(f"not an {FORMAT} file of version {' or '.join(map(str, READS))} "
                             f"(format={d.get('format')!r}, version={d.get('version')!r})")
        lasers = sorted(d["lasers"], key=lambda r: r["laser_id"])
        if not lasers or [r["laser_id"] for r in lasers] != list(range(len(lasers))):
            raise ValueError("a laser calibration needs every laser id from 0 up, once each")

        def col(key: str) -> np.ndarray:
            return np.array([np.nan if r.get(key) is None else r[key] for r in lasers], float)

        return cls(col("range_offset_m"), col("range_offset_std_m"), col("elevation_offset_rad"),
                   col("elevation_offset_std_rad"),
                   np.array([r.get("returns", 0) for r in lasers], dtype=np.int64),
                   np.array([r.get("edge_crossings", 0) for r in lasers], dtype=np.int64),
                   d.get("source", {}), col("elevation_deg"), dict(d.get("sensor") or {}),
                   dict(d.get("made") or {}))


def apply(scan: Scan, cal: LaserCalibration) -> Scan:
    """The scan with per-laser range offsets removed and x, y, z recomputed (pure).

    Elevation offsets are applied to x, y, z where known; the scan's ``elevation`` (and so
    `Scan.directions`) stays the nominal one of its laser id, which is what the estimator uses.
    """
    if cal.n_lasers != scan.lasers.n_lasers:
        raise ValueError(f"a calibration of {cal.n_lasers} lasers cannot correct a scan of "
                         f"{scan.lasers.n_lasers} ({scan.lasers.model}): it is another sensor's")
    off = np.nan_to_num(cal.range_offset, nan=0.0)[scan.laser_id]
    ret = scan.distance > 0
    dist = np.where(ret, np.maximum(scan.distance - off, 0.0), 0.0)
    d_el = np.nan_to_num(cal.elevation_offset, nan=0.0)[scan.laser_id]
    if not np.any(d_el != 0):
        x, y, z = _along_rays(scan, dist, ret)
    else:
        w = scan.lasers.elevation[scan.laser_id] + d_el
        rc = dist * np.cos(w)
        x, y = rc * np.sin(scan.azimuth), rc * np.cos(scan.azimuth)
        z = dist * np.sin(w) + np.where(ret & scan.vertical_offsets_applied,
                                         scan.lasers.vertical_offset[scan.laser_id], 0.0)
    meta = dict(scan.meta)
    meta["laser_calibration"] = cal.sensor_id or cal.source.get("name") or "applied"
    return replace(scan, distance=dist, x=x, y=y, z=z, meta=meta)


def _along_rays(scan: Scan, dist: np.ndarray, ret: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """x, y, z of the returns moved along their own rays to the ranges ``dist``, m: each
    point's offset from its laser's origin scaled by the new range over the old. The same
    points as `points_from_polar` of the new ranges (to a few 1e-16 m), without its
    trigonometry per firing (most of a scan's correction, and the demo corrects every scan
    of its sweep). Firings without a return stay at 0."""
    scale = np.divide(dist, scan.distance, out=np.zeros_like(dist), where=ret)
    lift = np.where(ret & scan.vertical_offsets_applied,
                    scan.lasers.vertical_offset[scan.laser_id], 0.0)
    if scan.vertical_offsets_applied and scan.lasers.horizontal_offset.any():
        o = np.where(ret[:, None], scan.origins(), 0.0)  # origins off the beam (an Ouster's)
        return ((scan.x - o[:, 0]) * scale + o[:, 0], (scan.y - o[:, 1]) * scale + o[:, 1],
                (scan.z - lift) * scale + lift)
    return scan.x * scale, scan.y * scale, (scan.z - lift) * scale + lift


def _directions(azimuth: np.ndarray, elevation: np.ndarray) -> np.ndarray:
    ce = np.cos(elevation)
    return np.column_stack((ce * np.sin(azimuth), ce * np.cos(azimuth), np.sin(elevation)))


def fit_laser_offsets(scans: Sequence[Scan], poses: Sequence[Pose],
                      board: BoardSpec = BoardSpec(),  # noqa: B008
                      name: str = "", sensor_id: str | None = None,
                      made: dict | None = None) -> LaserCalibration:
    """Per-laser range offsets (and elevation offsets where observable) from board scans.

    ``poses``: the true LiDAR pose in the board frame for each scan. Range offset of laser l:
    the mean of measured minus true range over its returns on the board's interior, with its
    standard error. Elevation offset of laser l: from each hit/miss pair along its ring where
    the ring crosses the top or bottom edge, the elevation change that puts the edge at the
    middle of the pair; their mean and standard error (at least two crossings).

    ``sensor_id`` names the unit; the model comes from the scans' laser table. ``made``: what
    the caller knows of how it was made (when, how); the poses, the scans and the residuals
    before and after the correction are added here.
    """
    lasers = scans[0].lasers if scans else vlp16.LASERS
    n_lasers = lasers.n_lasers
    res: list[list[float]] = [[] for _ in range(n_lasers)]
    el: list[list[float]] = [[] for _ in range(n_lasers)]
    w2, h2 = board.width / 2, board.height / 2
    for scan, pose in zip(scans, poses, strict=True):
        theta = pose.as_array()
        o, u = scan.origins(), scan.directions()
        x, z, lam = board_coordinates(theta, o, u)
        inside = (lam > 0) & (np.abs(x) < w2 - INTERIOR_MARGIN) & (np.abs(z) < h2 - INTERIOR_MARGIN)
        on = inside & (scan.distance > 0) & (np.abs(scan.distance - lam) < ON_BOARD)
        for lid in range(n_lasers):
            m = on & (scan.laser_id == lid)
            res[lid].extend((scan.distance[m] - lam[m]).tolist())
        # ring crossings of the top / bottom edge: consecutive firings of a laser, one on the
        # board and one off, both within the side edges and near the horizontal edge
        hit = (scan.distance > 0) & (np.abs(scan.distance - lam) < ON_BOARD) & (lam > 0)
        near = (lam > 0) & (np.abs(x) < w2 - INTERIOR_MARGIN) & (np.abs(np.abs(z) - h2) < 0.02)
        for lid in range(n_lasers):
            idx = np.flatnonzero((scan.laser_id == lid) & near)
            if len(idx) < 2:
                continue
            idx = idx[np.argsort(scan.azimuth[idx])]
            a, b = idx[:-1], idx[1:]
            ch = (hit[a] != hit[b]) & (np.abs(scan.azimuth[b] - scan.azimuth[a]) < np.deg2rad(0.5))
            for i, k in zip(a[ch], b[ch], strict=True):
                zm = 0.5 * (z[i] + z[k])
                edge = np.sign(zm) * h2
                # dZ/d(elevation) of the pair's midpoint, numerically
                eps = 1e-5
                e2 = lasers.elevation[lid] + eps
                u2 = _directions(scan.azimuth[[i, k]], np.full(2, e2))
                _, z2, _ = board_coordinates(theta, o[[i, k]], u2)
                dzde = (0.5 * (z2[0] + z2[1]) - zm) / eps
                if abs(dzde) > 0.1:
                    # the elevation offset that moved the observed crossing to the true edge
                    el[lid].append((zm - edge) / dzde)
    n = np.array([len(r) for r in res])
    mean = np.array([np.mean(r) if r else np.nan for r in res])
    std = np.array([np.std(r, ddof=1) / np.sqrt(len(r)) if len(r) > 1 else np.nan for r in res])
    ne = np.array([len(e) for e in el])
    el_mean = np.array([np.mean(e) if len(e) >= 2 else np.nan for e in el])
    # a crossing brackets the edge uniformly: each value's sd is (bracket width)/sqrt(12) in
    # height; the scatter of the values estimates it
    el_std = np.array([np.std(e, ddof=1) / np.sqrt(len(e)) if len(e) >= 2 else np.nan
                       for e in el])
    source = {"name": name, "scans": len(scans), "board_m": [board.width, board.height]}
    sensor = {"id": sensor_id, "model": lasers.model, "n_lasers": n_lasers}
    return LaserCalibration(mean, std, el_mean, el_std, n, ne, source, lasers.elevation_deg,
                            sensor, {**(made or {}), "poses": _distinct(poses),
                                     "scans": len(scans), "residuals": _residuals(res)})


def _distinct(poses: Sequence[Pose]) -> list[dict[str, float]]:
    """The distinct poses (edge units, rounded to 1 um / 1e-6 deg), at most `MAX_POSES`."""
    seen: dict[tuple, dict[str, float]] = {}
    for pose in poses:
        edge = {k: round(v, 6) for k, v in pose.to_edge().items()}
        seen.setdefault(tuple(edge.values()), edge)
    return list(seen.values())[:MAX_POSES]


def _residuals(res: list[list[float]]) -> dict[str, float | int | None]:
    """RMS of measured minus true range before and after removing each laser's mean, m."""
    every = [np.asarray(r) for r in res if r]
    if not every:
        return {"rms_before_m": None, "rms_after_m": None, "returns": 0}
    before = np.concatenate(every)
    after = np.concatenate([r - r.mean() for r in every])
    return {"rms_before_m": float(np.sqrt(np.mean(before ** 2))),
            "rms_after_m": float(np.sqrt(np.mean(after ** 2))), "returns": int(before.size)}


def identity_warnings(cal: LaserCalibration, model: str | None,
                      sensor_id: str | None = None) -> list[str]:
    """Why the calibration may not be this sensor's: another model, another unit (when both
    ids are known), or no identity at all (a version 1 file). Empty when nothing says so."""
    out = []
    if model is not None and cal.model is not None and model != cal.model:
        out.append(f"the calibration is for a {cal.model}, the scans come from a {model}")
    if sensor_id is not None and cal.sensor_id is not None and sensor_id != cal.sensor_id:
        out.append(f"the calibration was made for sensor {cal.sensor_id!r}, this is "
                   f"{sensor_id!r}: another unit's offsets make tilt worse, not better")
    if not cal.sensor:
        out.append("the calibration file does not say which sensor it is for (a version 1 "
                   "file); remake it with `aimbench calibrate --sensor-id ID`")
    return out


#: A laser needs this many board returns for its ring's bias to count in `ring_bias`.
MIN_RING_RETURNS = 20


def ring_bias(scans: Sequence[Scan], board_indices: np.ndarray) -> float | None:
    """How much the lasers' rings disagree about the board: the RMS over lasers of each ring's
    mean range offset from the plane fitted to all the board returns, m (None with fewer than
    three rings). A right calibration shrinks it (the rings then agree); another unit's offsets
    do not. Pure: the board returns come from the caller (e.g. an estimate's ``used["board"]``,
    indices into the concatenated scans)."""
    whole = Scan.concatenate(list(scans))
    idx = np.asarray(board_indices, dtype=np.int64)
    if idx.size < 3 * MIN_RING_RETURNS:
        return None
    pts, lid, u = whole.xyz[idx], whole.laser_id[idx], whole.directions()[idx]
    centre = pts.mean(axis=0)
    normal = np.linalg.svd(pts - centre)[2][2]
    along = u @ normal
    keep = np.abs(along) > 0.1  # rays nearly parallel to the board say little about range
    off = ((pts - centre) @ normal)[keep] / along[keep]  # signed distance along the ray
    lid = lid[keep]
    means = [off[lid == k].mean() for k in np.unique(lid)
             if np.count_nonzero(lid == k) >= MIN_RING_RETURNS]
    if len(means) < 3:
        return None
    m = np.asarray(means)
    return float(np.sqrt(np.mean((m - m.mean()) ** 2)))
