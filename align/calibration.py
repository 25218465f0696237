"""Per-laser corrections from scans of the board at known bench poses, and applying them.

Why: the paper measured range offsets up to 5 mm per laser; +-5 mm spread over the six rings on
the board tilts the fitted plane by about 0.35 deg, far above the estimator's precision. With the
board at known poses (the twin's truth, or the bench's stage readings with a surveyed mount),
every return on the board's interior has a known true range: the mean residual per laser is its
range offset. A laser's elevation error moves its ring up or down the board; it is observable
only where the ring crosses the board's top or bottom edge (there the hit/miss transition along
the ring pins the ring's height to the edge), so it is reported only for those lasers, and as
"not observed" (None) for the others.

File format (JSON, `save` / `load`): ``{"format": "aimbench.laser_calibration", "version": 1,
"lasers": [{"laser_id", "elevation_deg", "range_offset_m", "range_offset_std_m",
"elevation_offset_rad", "elevation_offset_std_rad", "returns", "edge_crossings"} x 16],
"source": {...}}``. Offsets are measured minus true: the corrected range is distance - offset.
`apply` is pure; `load` and `save` are the only functions here that touch a file.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from align.board import BoardSpec
from align.geometry import board_coordinates
from twin.core import vlp16
from twin.core.pose import Pose
from twin.core.scan import Scan, points_from_polar

FORMAT = "aimbench.laser_calibration"
VERSION = 1
#: Returns used for range offsets: at least this far inside the board's edges, m.
INTERIOR_MARGIN = 0.03
#: A return within this of the true range is on the board, m (5 sigma of 14 mm noise).
ON_BOARD = 0.07


@dataclass(frozen=True)
class LaserCalibration:
    """Per-laser corrections, indexed by laser id (0..15). SI units.

    ``elevation_offset`` holds NaN where the scans could not observe it.
    """

    range_offset: np.ndarray
    range_offset_std: np.ndarray
    elevation_offset: np.ndarray = field(default_factory=lambda: np.full(16, np.nan))
    elevation_offset_std: np.ndarray = field(default_factory=lambda: np.full(16, np.nan))
    returns: np.ndarray = field(default_factory=lambda: np.zeros(16, dtype=np.int64))
    edge_crossings: np.ndarray = field(default_factory=lambda: np.zeros(16, dtype=np.int64))
    source: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        def f(v: float) -> float | None:
            return None if not np.isfinite(v) else float(v)

        lasers = [{
            "laser_id": i,
            "elevation_deg": float(vlp16.ELEVATION_DEG[i]),
            "range_offset_m": f(self.range_offset[i]),
            "range_offset_std_m": f(self.range_offset_std[i]),
            "elevation_offset_rad": f(self.elevation_offset[i]),
            "elevation_offset_std_rad": f(self.elevation_offset_std[i]),
            "returns": int(self.returns[i]),
            "edge_crossings": int(self.edge_crossings[i]),
        } for i in range(vlp16.N_LASERS)]
        return {"format": FORMAT, "version": VERSION, "lasers": lasers, "source": self.source}

    @classmethod
    def from_dict(cls, d: dict) -> LaserCalibration:
        if d.get("format") != FORMAT or d.get("version") != VERSION:
            raise ValueError(f"not an {FORMAT} v{VERSION} file "
                             f"(format={d.get('format')!r}, version={d.get('version')!r})")
        lasers = sorted(d["lasers"], key=lambda r: r["laser_id"])
        if [r["laser_id"] for r in lasers] != list(range(vlp16.N_LASERS)):
            raise ValueError("a laser calibration needs exactly the laser ids 0..15")

        def col(key: str) -> np.ndarray:
            return np.array([np.nan if r.get(key) is None else r[key] for r in lasers], float)

        return cls(col("range_offset_m"), col("range_offset_std_m"), col("elevation_offset_rad"),
                   col("elevation_offset_std_rad"),
                   np.array([r.get("returns", 0) for r in lasers], dtype=np.int64),
                   np.array([r.get("edge_crossings", 0) for r in lasers], dtype=np.int64),
                   d.get("source", {}))


def save(cal: LaserCalibration, path: str | Path) -> None:
    """Write the calibration file (JSON)."""
    Path(path).write_text(json.dumps(cal.to_dict(), indent=1) + "\n")


def load(path: str | Path) -> LaserCalibration:
    """Read a calibration file written by `save` (ValueError if it is not one)."""
    return LaserCalibration.from_dict(json.loads(Path(path).read_text()))


def apply(scan: Scan, cal: LaserCalibration) -> Scan:
    """The scan with per-laser range offsets removed and x, y, z recomputed (pure).

    Elevation offsets are applied to x, y, z where known; the scan's ``elevation`` (and so
    `Scan.directions`) stays the nominal one of its laser id, which is what the estimator uses.
    """
    off = np.nan_to_num(cal.range_offset, nan=0.0)[scan.laser_id]
    ret = scan.distance > 0
    dist = np.where(ret, np.maximum(scan.distance - off, 0.0), 0.0)
    x, y, z = points_from_polar(dist, scan.azimuth, scan.laser_id,
                                vertical_offsets=scan.vertical_offsets_applied)
    d_el = np.nan_to_num(cal.elevation_offset, nan=0.0)[scan.laser_id]
    if np.any(d_el != 0):
        w = vlp16.ELEVATION[scan.laser_id] + d_el
        rc = dist * np.cos(w)
        x, y = rc * np.sin(scan.azimuth), rc * np.cos(scan.azimuth)
        z = dist * np.sin(w) + np.where(ret & scan.vertical_offsets_applied,
                                         vlp16.VERTICAL_OFFSET[scan.laser_id], 0.0)
    meta = dict(scan.meta)
    meta["laser_calibration"] = cal.source.get("name", "applied")
    return replace(scan, distance=dist, x=x, y=y, z=z, meta=meta)


def _directions(azimuth: np.ndarray, elevation: np.ndarray) -> np.ndarray:
    ce = np.cos(elevation)
    return np.column_stack((ce * np.sin(azimuth), ce * np.cos(azimuth), np.sin(elevation)))


def estimate(scans: Sequence[Scan], poses: Sequence[Pose], board: BoardSpec = BoardSpec(),  # noqa: B008
             name: str = "") -> LaserCalibration:
    """Per-laser range offsets (and elevation offsets where observable) from board scans.

    ``poses``: the true LiDAR pose in the board frame for each scan. Range offset of laser l:
    the mean of measured minus true range over its returns on the board's interior, with its
    standard error. Elevation offset of laser l: from each hit/miss pair along its ring where
    the ring crosses the top or bottom edge, the elevation change that puts the edge at the
    middle of the pair; their mean and standard error (at least two crossings).
    """
    res: list[list[float]] = [[] for _ in range(vlp16.N_LASERS)]
    el: list[list[float]] = [[] for _ in range(vlp16.N_LASERS)]
    w2, h2 = board.width / 2, board.height / 2
    for scan, pose in zip(scans, poses, strict=True):
        theta = pose.as_array()
        o, u = scan.origins(), scan.directions()
        x, z, lam = board_coordinates(theta, o, u)
        inside = (lam > 0) & (np.abs(x) < w2 - INTERIOR_MARGIN) & (np.abs(z) < h2 - INTERIOR_MARGIN)
        on = inside & (scan.distance > 0) & (np.abs(scan.distance - lam) < ON_BOARD)
        for lid in range(vlp16.N_LASERS):
            m = on & (scan.laser_id == lid)
            res[lid].extend((scan.distance[m] - lam[m]).tolist())
        # ring crossings of the top / bottom edge: consecutive firings of a laser, one on the
        # board and one off, both within the side edges and near the horizontal edge
        hit = (scan.distance > 0) & (np.abs(scan.distance - lam) < ON_BOARD) & (lam > 0)
        near = (lam > 0) & (np.abs(x) < w2 - INTERIOR_MARGIN) & (np.abs(np.abs(z) - h2) < 0.02)
        for lid in range(vlp16.N_LASERS):
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
                e2 = vlp16.ELEVATION[lid] + eps
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
    return LaserCalibration(mean, std, el_mean, el_std, n, ne, source)
