"""`LaserTable`: the lasers of a spinning LiDAR, as every layer needs them.

A table is indexed by laser id: the position of a laser's return in the sensor's firing
sequence (the channel order of its packets). Each laser has an elevation and may have an azimuth
offset (its beam points that far from the encoder azimuth of its firing) and vertical and
horizontal offsets of its origin from the optical centre. A `twin.core.scan.Scan` carries the
table of the sensor that made it, so that nothing downstream (the estimator above all) assumes a
number of lasers or their angles. SI units: rad, m.

The tables of the models aimbench knows are in their own modules (`twin.core.vlp16` for the
VLP-16); a factory calibration file of a unit overrides its model's table.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


def _frozen(values: np.ndarray | list[float] | tuple[float, ...], n: int | None,
            name: str) -> np.ndarray:
    a = np.array(values, dtype=np.float64).reshape(-1)
    if n is not None and len(a) != n:
        raise ValueError(f"LaserTable.{name} has {len(a)} entries, expected {n} (one per laser)")
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class LaserTable:
    """Per-laser geometry, indexed by laser id.

    Attributes (arrays of one entry per laser, read-only):
        model: the sensor model's name (``VLP-16``...), or a calibration's own name.
        elevation: rad, positive upward.
        vertical_offset: m, the laser's origin along Z_L from the optical centre.
        azimuth_offset: rad, the beam's azimuth minus its firing's encoder azimuth (clockwise
            seen from above, like the azimuth; 0 for the VLP-16).
        horizontal_offset: m, the laser's origin across the beam in the horizontal plane
            (0 for the VLP-16).
    Derived: ``n_lasers``; ``ring_of_laser`` (elevation order, 0 = lowest) and its inverse
    ``laser_of_ring``.
    """

    model: str
    elevation: np.ndarray
    vertical_offset: np.ndarray | None = None
    azimuth_offset: np.ndarray | None = None
    horizontal_offset: np.ndarray | None = None
    ring_of_laser: np.ndarray = field(init=False, repr=False)
    laser_of_ring: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        el = _frozen(self.elevation, None, "elevation")
        n = len(el)
        if n == 0 or n > 255:
            raise ValueError(f"a LaserTable needs 1..255 lasers, got {n}")
        object.__setattr__(self, "elevation", el)
        for name in ("vertical_offset", "azimuth_offset", "horizontal_offset"):
            v = getattr(self, name)
            object.__setattr__(self, name, _frozen(np.zeros(n) if v is None else v, n, name))
        order = np.argsort(el, kind="stable")
        ring = np.empty(n, dtype=np.uint8)
        ring[order] = np.arange(n, dtype=np.uint8)
        ring.setflags(write=False)
        laser = order.astype(np.uint8)
        laser.setflags(write=False)
        object.__setattr__(self, "ring_of_laser", ring)
        object.__setattr__(self, "laser_of_ring", laser)

    @property
    def n_lasers(self) -> int:
        return len(self.elevation)

    @property
    def elevation_deg(self) -> np.ndarray:
        return np.degrees(self.elevation)

    def origins(self, laser_id: np.ndarray, azimuth: np.ndarray) -> np.ndarray:
        """Where the rays of lasers ``laser_id`` fired at ``azimuth`` (rad) start in {L}, (N, 3),
        m: the vertical offset along Z_L, and the horizontal offset h across the beam,
        (-h cos a, h sin a) in (X_L, Y_L), as the decoders put them into the points."""
        o = np.zeros((len(laser_id), 3))
        o[:, 2] = self.vertical_offset[laser_id]
        if self.horizontal_offset.any():
            h = self.horizontal_offset[laser_id]
            o[:, 0] = -h * np.cos(azimuth)
            o[:, 1] = h * np.sin(azimuth)
        return o

    def same_geometry(self, other: LaserTable, atol: float = 1e-12) -> bool:
        """The same lasers at the same angles and offsets (the model's name aside)."""
        return self.n_lasers == other.n_lasers and all(
            np.allclose(getattr(self, k), getattr(other, k), atol=atol, rtol=0.0)
            for k in ("elevation", "vertical_offset", "azimuth_offset", "horizontal_offset"))
