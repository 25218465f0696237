"""The `Scan`: one rotation of VLP-16 firings as per-firing arrays.

Both the packet decoder (real sensor, pcap) and the ray-cast emulation (the twin) produce this
type, and the estimator consumes it without knowing which made it. Every fired laser is kept,
including those with no return (``distance == 0``): the estimator learns the board's edges from
the rays that miss it as much as from those that hit it.

Units: SI. Positions in the LiDAR frame {L} of DESIGN.md (X_L right = azimuth 90 deg, Y_L forward
= azimuth 0, Z_L up), azimuth in rad growing clockwise seen from above, time in s.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field, replace

import numpy as np

from twin.core import vlp16
from twin.core.lasers import LaserTable


class ReturnType(enum.IntFlag):
    """What a return is, as bit flags: a single echo in dual mode is both strongest and last."""

    STRONGEST = 1
    LAST = 2
    SECOND_STRONGEST = 4


#: The per-firing array fields of a `Scan`, in order.
ARRAY_FIELDS = (
    "distance", "azimuth", "laser_id", "intensity", "time", "return_type", "x", "y", "z",
)


@dataclass(frozen=True, eq=False)
class Scan:
    """One rotation of firings.

    Per-firing arrays (all the same length N):

    ===========  =======  ================================================================
    field        dtype    meaning
    ===========  =======  ================================================================
    distance     float64  range, m; 0 means no return
    azimuth      float64  azimuth of the firing, rad in [0, 2*pi)
    laser_id     uint8    laser id, an index of ``lasers`` (firing order; `ring` gives
                          elevation order)
    intensity    uint8    calibrated reflectivity 0..255
    time         float64  firing time, s (sensor clock: seconds past the hour; counts on
                          past 3600 across an hour's rollover so times only grow)
    return_type  uint8    `ReturnType` flags
    x, y, z      float64  position in {L}, m (0 where there is no return)
    ===========  =======  ================================================================

    Scan-level metadata says how whole the scan is: a scan assembled with packets missing is
    flagged (``complete=False``, ``missing_packets > 0``), never presented as whole. ``lasers``
    is the laser table of the sensor that made the scan (`twin.core.lasers.LaserTable`; the
    VLP-16's by default): every geometric property below reads its elevations and offsets.
    """

    distance: np.ndarray
    azimuth: np.ndarray
    laser_id: np.ndarray
    intensity: np.ndarray
    time: np.ndarray
    return_type: np.ndarray
    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    index: int = 0
    complete: bool = True
    packets: int = 0
    missing_packets: int = 0
    return_mode: int = vlp16.RETURN_MODE_STRONGEST
    product_id: int = vlp16.PRODUCT_ID_VLP16
    vertical_offsets_applied: bool = True
    meta: dict = field(default_factory=dict)
    lasers: LaserTable = vlp16.LASERS

    def __post_init__(self) -> None:
        n = len(self.distance)
        for name in ARRAY_FIELDS:
            if len(getattr(self, name)) != n:
                raise ValueError(f"Scan field {name!r} has {len(getattr(self, name))} entries, "
                                 f"expected {n} like 'distance'")

    def __len__(self) -> int:
        return len(self.distance)

    @property
    def valid(self) -> np.ndarray:
        """Mask of firings that returned (distance > 0)."""
        return self.distance > 0

    @property
    def ring(self) -> np.ndarray:
        """Elevation-ordered ring of each firing (0 = the lowest beam)."""
        return self.lasers.ring_of_laser[self.laser_id]

    @property
    def elevation(self) -> np.ndarray:
        """Elevation of each firing's laser, rad."""
        return self.lasers.elevation[self.laser_id]

    @property
    def xyz(self) -> np.ndarray:
        """Positions as an (N, 3) array in {L}, m."""
        return np.column_stack((self.x, self.y, self.z))

    def points(self, idx: np.ndarray) -> np.ndarray:
        """The positions of the firings ``idx`` (indices or a mask) as an (n, 3) array in {L},
        m: `xyz` of those alone, without stacking every firing first."""
        return np.column_stack((self.x[idx], self.y[idx], self.z[idx]))

    def directions(self) -> np.ndarray:
        """Unit direction of every fired ray in {L}, (N, 3), returns or not."""
        ce = np.cos(self.elevation)
        return np.column_stack(
            (ce * np.sin(self.azimuth), ce * np.cos(self.azimuth), np.sin(self.elevation))
        )

    def origins(self) -> np.ndarray:
        """Origin of every fired ray in {L}, (N, 3): the laser's offsets from the optical
        centre, if applied to the points (`vertical_offsets_applied`): its vertical offset
        along Z_L, and its horizontal offset h across the beam, (-h cos a, h sin a) in (X_L,
        Y_L) at the ray's azimuth a (as the decoders put it into the points: an Ouster's n sin b,
        up to 1.2 mm on an OS1; 0 for the VLP-16)."""
        if not self.vertical_offsets_applied:
            return np.zeros((len(self), 3))
        return self.lasers.origins(self.laser_id, self.azimuth)

    def select(self, mask: np.ndarray) -> Scan:
        """A scan with only the firings where ``mask`` is true (or at the given indices)."""
        return replace(self, **{name: getattr(self, name)[mask] for name in ARRAY_FIELDS})

    def hits(self) -> Scan:
        """Only the firings that returned."""
        return self.select(self.valid)

    @classmethod
    def empty(cls, **meta) -> Scan:
        arrays = {name: np.zeros(0, dtype=_DTYPES[name]) for name in ARRAY_FIELDS}
        return cls(**arrays, **meta)

    @classmethod
    def concatenate(cls, scans: list[Scan]) -> Scan:
        """Join scans (for example N scans of a static pose); metadata from the first."""
        if not scans:
            return cls.empty()
        arrays = {name: np.concatenate([getattr(s, name) for s in scans]) for name in ARRAY_FIELDS}
        return replace(
            scans[0],
            **arrays,
            complete=all(s.complete for s in scans),
            packets=sum(s.packets for s in scans),
            missing_packets=sum(s.missing_packets for s in scans),
        )


_DTYPES = {
    "distance": np.float64, "azimuth": np.float64, "laser_id": np.uint8, "intensity": np.uint8,
    "time": np.float64, "return_type": np.uint8, "x": np.float64, "y": np.float64,
    "z": np.float64,
}


def points_from_polar(
    distance: np.ndarray,
    azimuth: np.ndarray,
    laser_id: np.ndarray,
    vertical_offsets: bool = True,
    lasers: LaserTable = vlp16.LASERS,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """x, y, z in {L} from range, azimuth and laser id (DESIGN.md; zero where distance is 0).

    r * (cos w sin a, cos w cos a, sin w), plus the laser's vertical offset along Z_L; w and the
    offset are the laser's in ``lasers``.
    """
    w = lasers.elevation[laser_id]
    rc = distance * np.cos(w)
    x = rc * np.sin(azimuth)
    y = rc * np.cos(azimuth)
    z = distance * np.sin(w)
    if vertical_offsets:
        z = z + np.where(distance > 0, lasers.vertical_offset[laser_id], 0.0)
    return x, y, z

