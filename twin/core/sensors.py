"""The spinning Velodyne sensors aimbench knows, one `SensorModel` each, from their manuals.

VLP-16, Puck Hi-Res (VLP-16 Hi-Res), VLP-32C and HDL-32E share the 1206-byte data packet (12
blocks of a flag, an azimuth and 32 channels, then a timestamp and the factory bytes) and differ
in their lasers, their firing timing and their distance unit. A `SensorModel` holds everything
that differs, so that the decoder, the scan assembler, the emulation and the estimator read the
same numbers. SI units (m, rad, s).

Sources, cited next to each number:
- VLP-16: user manual 63-9243 Rev. E (table 9-1, sections 9.3, 9.5), datasheet 63-9229 Rev. D
  (the constants of `twin.core.vlp16`).
- Puck Hi-Res: VLP-16 Hi-Res user manual 63-9318 Rev. B (its laser table; the VLP-16's timing and
  packet, section 9), datasheet 63-9317 (range, accuracy); vertical offsets from Velodyne's
  envelope drawing 86-0129 Rev. A.
- VLP-32C: user manual 63-9325 Rev. C (table 9-2 laser table with azimuth offsets, section 9.5
  "precision azimuth", figures 9-7/9-8 timing: lasers fire in pairs); datasheet 63-9378.
- HDL-32E: user manual 63-9113 Rev. H (laser table "vertical angle", "laser timing": 1.152 us per
  laser, 46.08 us per cycle, one cycle per block; specifications); vertical offsets from the
  envelope drawing 86-0106 Rev. B.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from twin.core import sensor_names as names
from twin.core import vlp16
from twin.core.lasers import LaserTable

#: Blocks and channels of every model's data packet (all four manuals, "data packet format").
BLOCKS_PER_PACKET = 12
CHANNELS_PER_BLOCK = 32
#: Return-mode bytes (factory byte 1): strongest, last, dual (VLP-16 manual 9.3.1.3; the
#: VLP-32C and HDL-32E manuals use the same values).
STRONGEST, LAST, DUAL = vlp16.RETURN_MODE_STRONGEST, vlp16.RETURN_MODE_LAST, vlp16.RETURN_MODE_DUAL


@dataclass(frozen=True, eq=False)
class SensorModel:
    """One sensor model: its lasers, firing timing, packet layout and envelope.

    Timing: the sensor fires its lasers in *sequences* (one firing of every laser), one every
    ``sequence_period``; laser ``l`` fires ``firing_offset[l]`` after its sequence starts. A
    packet block holds ``sequences_per_block`` sequences (2 for the 16-laser models, whose 32
    channels are two sequences of 16; 1 for the 32-laser ones). Channel ``c`` of a block is
    laser ``c % n_lasers`` of sequence ``c // n_lasers``.
    """

    name: str
    product_id: int
    lasers: LaserTable
    firing_offset: np.ndarray  # (n_lasers,) s after the sequence's start
    sequence_period: float  # s
    distance_unit: float  # m per distance count
    rpm_min: float
    rpm_max: float
    range_max: float  # m, the datasheet's
    range_min: float  # m, the closest return reported
    range_accuracy: float  # m, the datasheet's "typical" (1 sigma where it says so)
    beam_divergence_h: float  # rad, full angle
    beam_divergence_v: float  # rad, full angle
    return_modes: tuple[int, ...] = (STRONGEST, LAST, DUAL)
    manual: str = ""
    aliases: tuple[str, ...] = ()
    laser_of_channel: np.ndarray = field(init=False, repr=False)
    sequence_of_channel: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        n = self.lasers.n_lasers
        if CHANNELS_PER_BLOCK % n:
            raise ValueError(f"{self.name}: {n} lasers do not divide a block's 32 channels")
        off = np.array(self.firing_offset, dtype=np.float64)
        if off.shape != (n,):
            raise ValueError(f"{self.name}: firing_offset needs one time per laser ({n})")
        off.setflags(write=False)
        object.__setattr__(self, "firing_offset", off)
        ch = np.arange(CHANNELS_PER_BLOCK)
        for name, values in (("laser_of_channel", (ch % n).astype(np.uint8)),
                             ("sequence_of_channel", ch // n)):
            values.setflags(write=False)
            object.__setattr__(self, name, values)

    # -- derived timing ---------------------------------------------------------------------
    @property
    def n_lasers(self) -> int:
        return self.lasers.n_lasers

    @property
    def sequences_per_block(self) -> int:
        return CHANNELS_PER_BLOCK // self.n_lasers

    @property
    def block_period(self) -> float:
        """Time between the first firings of consecutive blocks in single-return mode, s."""
        return self.sequences_per_block * self.sequence_period

    @property
    def sequences_per_packet(self) -> int:
        """Firing sequences in a single-return packet (half in dual mode)."""
        return self.sequences_per_block * BLOCKS_PER_PACKET

    def packet_period(self, return_mode: int = STRONGEST) -> float:
        """Time between consecutive data packets, s (half in dual mode: blocks come in pairs)."""
        blocks = BLOCKS_PER_PACKET // (2 if return_mode == DUAL else 1)
        return blocks * self.block_period

    def packet_rate(self, return_mode: int = STRONGEST) -> float:
        return 1.0 / self.packet_period(return_mode)

    def channel_offsets(self) -> np.ndarray:
        """Time of each channel's firing after its block's first firing, (32,) s."""
        return (self.sequence_of_channel * self.sequence_period
                + self.firing_offset[self.laser_of_channel])

    def firing_time_offsets(self, return_mode: int = STRONGEST) -> np.ndarray:
        """Time of each firing after the packet's timestamp, (12, 32) s. In dual mode block
        ``b`` holds echoes of the firings of block ``b // 2`` of a single-return packet."""
        block = np.arange(BLOCKS_PER_PACKET)
        if return_mode == DUAL:
            block = block // 2
        return block[:, None] * self.block_period + self.channel_offsets()[None, :]

    def with_lasers(self, lasers: LaserTable) -> SensorModel:
        """The same model with another laser table (a unit's calibration file)."""
        if lasers.n_lasers != self.n_lasers:
            raise ValueError(f"a {self.name} has {self.n_lasers} lasers; the table has "
                             f"{lasers.n_lasers}")
        kwargs = {k: getattr(self, k) for k in self.__dataclass_fields__
                  if self.__dataclass_fields__[k].init}
        kwargs["lasers"] = lasers
        return SensorModel(**kwargs)


def _table(name: str, elevation_deg, vertical_offset_m, azimuth_offset_deg=None) -> LaserTable:
    az = None if azimuth_offset_deg is None else np.deg2rad(azimuth_offset_deg)
    return LaserTable(name, np.deg2rad(np.asarray(elevation_deg, dtype=float)),
                      np.asarray(vertical_offset_m, dtype=float), az)


VLP16 = SensorModel(
    name=names.VLP16, product_id=vlp16.PRODUCT_ID_VLP16, lasers=vlp16.LASERS,
    # Manual 9.5: lasers 2.304 us apart, a sequence every 55.296 us (16 firings + recharge).
    firing_offset=np.arange(16) * vlp16.LASER_PERIOD, sequence_period=vlp16.SEQUENCE_PERIOD,
    distance_unit=vlp16.DISTANCE_UNIT,  # manual 9.3.1.4: 2 mm
    rpm_min=vlp16.RPM_MIN, rpm_max=vlp16.RPM_MAX,  # datasheet: 5-20 Hz
    range_max=vlp16.RANGE_MAX, range_min=vlp16.RANGE_MIN,
    range_accuracy=0.03,  # datasheet: +-3 cm (typical)
    beam_divergence_h=vlp16.BEAM_DIVERGENCE_H, beam_divergence_v=vlp16.BEAM_DIVERGENCE_V,
    manual="VLP-16 user manual 63-9243 Rev. E", aliases=("VLP16", "PUCK"),
)

PUCK_HIRES = SensorModel(
    name=names.PUCK_HIRES, product_id=0x24,  # Hi-Res manual 9.3.1.5: factory byte 0x24
    lasers=_table(
        "Puck Hi-Res",
        # Hi-Res manual, laser table: -10..+10 deg in 1.33 deg steps, interleaved like the VLP-16.
        [-10.0, 0.667, -8.667, 2.0, -7.333, 3.333, -6.0, 4.667,
         -4.667, 6.0, -3.333, 7.333, -2.0, 8.667, -0.667, 10.0],
        # Envelope drawing 86-0129 Rev. A: each laser's origin along Z_L, mm.
        1e-3 * np.array([7.4, -0.9, 6.5, -1.8, 5.5, -2.7, 4.6, -3.7,
                         3.7, -4.6, 2.7, -5.5, 1.8, -6.5, 0.9, -7.4])),
    # Hi-Res manual section 9: the VLP-16's timing and packet.
    firing_offset=np.arange(16) * vlp16.LASER_PERIOD, sequence_period=vlp16.SEQUENCE_PERIOD,
    distance_unit=0.002, rpm_min=300.0, rpm_max=1200.0,
    range_max=100.0, range_min=vlp16.RANGE_MIN,
    range_accuracy=0.03,  # datasheet 63-9317: +-3 cm (typical)
    # Same laser and optics as the VLP-16 (datasheet: "same as VLP-16"): its divergence.
    beam_divergence_h=vlp16.BEAM_DIVERGENCE_H, beam_divergence_v=vlp16.BEAM_DIVERGENCE_V,
    manual="VLP-16 Hi-Res user manual 63-9318 Rev. B",
    aliases=("PUCKHIRES", "VLP16HIRES", "HIRES", "PUCKHI-RES"),
)

#: VLP-32C manual table 9-2 by laser id: elevation, deg, and azimuth offset delta, deg (the
#: beam points delta clockwise of the block azimuth; section 9.5: precise azimuth = alpha + delta).
_VLP32C_TABLE = np.array([
    (-25.0, 1.4), (-1.0, -4.2), (-1.667, 1.4), (-15.639, -1.4), (-11.31, 1.4), (0.0, -1.4),
    (-0.667, 4.2), (-8.843, -1.4), (-7.254, 1.4), (0.333, -4.2), (-0.333, 1.4), (-6.148, -1.4),
    (-5.333, 4.2), (1.333, -1.4), (0.667, 4.2), (-4.0, -1.4), (-4.667, 1.4), (1.667, -4.2),
    (1.0, 1.4), (-3.667, -4.2), (-3.333, 4.2), (3.333, -1.4), (2.333, 1.4), (-2.667, -1.4),
    (-3.0, 1.4), (7.0, -1.4), (4.667, 1.4), (-2.333, -4.2), (-2.0, 4.2), (15.0, -1.4),
    (10.333, 1.4), (-1.333, -1.4),
])
#: The VLP-32C's lasers sit around a focal point this far from the optical centre, so a laser's
#: origin lies focal x tan(-elevation) along Z_L, m. The manual gives no vertical offsets; 42.4 mm
#: is velodyne_decoder's (calib_db.cpp) for the VLP-32C, after its envelope drawing (manual
#: appendix C, figure C-2); the VLP-16's 41.9 mm gives the VLP-16 manual's offsets the same way.
VLP32C_FOCAL_DISTANCE = 42.4e-3

VLP32C = SensorModel(
    name=names.VLP32C, product_id=0x28,  # manual 9.3.1.5: factory byte 0x28
    lasers=_table("VLP-32C", _VLP32C_TABLE[:, 0],
                  VLP32C_FOCAL_DISTANCE * np.tan(-np.deg2rad(_VLP32C_TABLE[:, 0])),
                  _VLP32C_TABLE[:, 1]),
    # Manual figure 9-7: 16 firing groups 2.304 us apart, two lasers each (ids 2k, 2k + 1),
    # a sequence every 55.296 us; one sequence of all 32 lasers per block.
    firing_offset=(np.arange(32) // 2) * 2.304e-6, sequence_period=55.296e-6,
    distance_unit=0.004,  # manual 9.3.1.4: 4 mm
    rpm_min=300.0, rpm_max=1200.0,  # manual: 5-20 Hz
    range_max=200.0, range_min=vlp16.RANGE_MIN,  # datasheet: up to 200 m
    range_accuracy=0.03,  # datasheet: up to +-3 cm (typical)
    # The manual gives no figure; the VLP-16 / VLS-128 family's 3.0 x 1.5 mrad (assumed).
    beam_divergence_h=3.0e-3, beam_divergence_v=1.5e-3,
    manual="VLP-32C user manual 63-9325 Rev. C", aliases=("VLP32C", "VLP32", "ULTRAPUCK"),
)

HDL32E = SensorModel(
    name=names.HDL32E, product_id=0x21,  # manual appendix B: factory byte 0x21
    lasers=_table(
        "HDL-32E",
        # Manual, "vertical angle" table by laser id: -30.67..+10.67 deg, interleaved.
        [-30.67, -9.33, -29.33, -8.0, -28.0, -6.67, -26.67, -5.33, -25.33, -4.0, -24.0, -2.67,
         -22.67, -1.33, -21.33, 0.0, -20.0, 1.33, -18.67, 2.67, -17.33, 4.0, -16.0, 5.33,
         -14.67, 6.67, -13.33, 8.0, -12.0, 9.33, -10.67, 10.67],
        # Envelope drawing 86-0106 Rev. B: each laser's origin along Z_L, mm.
        1e-3 * np.array([17.17, 4.76, 16.27, 4.07, 15.4, 3.38, 14.54, 2.7, 13.71, 2.02, 12.89,
                         1.35, 12.09, 0.67, 11.31, 0.0, 10.54, -0.67, 9.78, -1.35, 9.04, -2.02,
                         8.3, -2.7, 7.58, -3.38, 6.86, -4.07, 6.15, -4.76, 5.45, -5.45])),
    # Manual, "laser timing": 1.152 us per laser, 32 firings + 9.216 us recharge = 46.08 us a
    # cycle, one cycle per block.
    firing_offset=np.arange(32) * 1.152e-6, sequence_period=46.08e-6,
    distance_unit=0.002,  # manual appendix B: 2 mm increments
    rpm_min=300.0, rpm_max=1200.0,  # manual specifications: 5-20 Hz
    range_max=100.0, range_min=0.05,  # manual: valid data 5 cm to 100 m
    range_accuracy=0.02,  # manual specifications: < 2 cm (1 sigma at 25 m)
    # The manual's laser spot appendix gives no divergence angle: the VLP-16's (assumed).
    beam_divergence_h=vlp16.BEAM_DIVERGENCE_H, beam_divergence_v=vlp16.BEAM_DIVERGENCE_V,
    manual="HDL-32E user manual 63-9113 Rev. H", aliases=("HDL32E", "HDL32"),
)

#: Every model, by name (`twin.core.sensor_names.VELODYNE_NAMES`, which the command line
#: offers without importing this module).
MODELS: dict[str, SensorModel] = {m.name: m for m in (VLP16, PUCK_HIRES, VLP32C, HDL32E)}
#: Product ids of the factory byte (the four models' manuals, and the VLS-128's and
#: Velarray's for a clear refusal).
PRODUCT_NAMES = {0x21: names.HDL32E, 0x22: names.VLP16, 0x24: names.PUCK_HIRES,
                 0x28: names.VLP32C, 0x31: "Velarray", 0xA1: "VLS-128"}


def _key(name: str) -> str:
    return "".join(ch for ch in name.upper() if ch.isalnum())


_BY_KEY = {_key(alias): m for m in MODELS.values() for alias in (m.name, *m.aliases)}


def model_named(name: str) -> SensorModel:
    """The model of a name as users write it (``VLP-32C``, ``vlp32c``, ``Puck Hi-Res``...);
    ``KeyError`` naming the known ones otherwise."""
    try:
        return _BY_KEY[_key(name)]
    except KeyError:
        raise KeyError(f"unknown sensor model {name!r}: aimbench knows "
                       f"{', '.join(MODELS)}") from None


def model_of_product_id(product_id: int) -> SensorModel | None:
    """The model whose packets carry this factory byte (0x21: the HDL-32E's; old VLP-16
    firmware sends it too, which only the packets' timing tells apart)."""
    for m in MODELS.values():
        if m.product_id == product_id:
            return m
    return None
