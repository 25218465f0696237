"""VLP-16 facts from the Velodyne VLP-16 user manual (63-9243 Rev. E), in SI units.

Everything that depends on the sensor model lives here so that the decoder, the encoder and the
ray-cast emulation cannot disagree about it.
"""

from __future__ import annotations

import numpy as np

from twin.core.lasers import LaserTable

N_LASERS = 16
#: Laser elevations by laser id (manual, table 9-1), rad.
ELEVATION_DEG = np.array(
    [-15, 1, -13, 3, -11, 5, -9, 7, -7, 9, -5, 11, -3, 13, -1, 15], dtype=np.float64
)
ELEVATION = np.deg2rad(ELEVATION_DEG)
#: Vertical offset of each laser's origin along Z_L (manual, table 9-1 "vertical correction"), m.
VERTICAL_OFFSET = 1e-3 * np.array(
    [11.2, -0.7, 9.7, -2.2, 8.1, -3.7, 6.6, -5.1, 5.1, -6.6, 3.7, -8.1, 2.2, -9.7, 0.7, -11.2],
    dtype=np.float64,
)
#: The VLP-16's laser table (what a `Scan` of this sensor carries).
LASERS = LaserTable("VLP-16", ELEVATION, VERTICAL_OFFSET)
#: ring = index in elevation order (0 = lowest, -15 deg); laser id -> ring.
RING_OF_LASER = LASERS.ring_of_laser
#: ring -> laser id.
LASER_OF_RING = LASERS.laser_of_ring

# Firing timing (manual, section 9.5).
LASER_PERIOD = 2.304e-6  # s between consecutive lasers of one sequence
SEQUENCE_PERIOD = 55.296e-6  # s per firing sequence (16 firings + recharge)
SEQUENCES_PER_BLOCK = 2
BLOCKS_PER_PACKET = 12
SEQUENCES_PER_PACKET = SEQUENCES_PER_BLOCK * BLOCKS_PER_PACKET
#: One packet spans 24 sequences in single-return mode: about 754 packets/s at any rpm.
PACKET_PERIOD = SEQUENCES_PER_PACKET * SEQUENCE_PERIOD
PACKET_RATE = 1.0 / PACKET_PERIOD

# Packet format (manual, section 9.3).
DATA_PORT = 2368
POSITION_PORT = 8308
DATA_PAYLOAD_SIZE = 1206
POSITION_PAYLOAD_SIZE = 512
BLOCK_FLAG = b"\xff\xee"
BLOCK_SIZE = 100
DISTANCE_UNIT = 0.002  # m per count
AZIMUTH_UNIT_DEG = 0.01  # deg per count

RETURN_MODE_STRONGEST = 0x37
RETURN_MODE_LAST = 0x38
RETURN_MODE_DUAL = 0x39
PRODUCT_ID_VLP16 = 0x22
#: Older VLP-16 firmware reports 0x21 (the HDL-32E's id) on real VLP-16 data.
PRODUCT_ID_VLP16_OLD_FIRMWARE = 0x21

# Operating envelope (datasheet 63-9229 Rev. D).
RPM_MIN = 300.0
RPM_MAX = 1200.0
RANGE_MAX = 100.0  # m
#: Closest reported return, m (assumed: the datasheet gives none); the emulation may set it
RANGE_MIN = 0.5
BEAM_DIVERGENCE_H = 3.0e-3  # rad, horizontal (datasheet: 3.0 mrad)
BEAM_DIVERGENCE_V = 1.5e-3  # rad, vertical (datasheet: 1.5 mrad)


def firing_offsets() -> np.ndarray:
    """Time of each firing relative to its block's timestamp, shape (2, 16), s (manual 9.5)."""
    seq = np.arange(SEQUENCES_PER_BLOCK)[:, None] * SEQUENCE_PERIOD
    laser = np.arange(N_LASERS)[None, :] * LASER_PERIOD
    return seq + laser
