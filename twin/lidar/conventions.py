"""How each driver writes a Velodyne's point cloud: its fields, its frame, and how it turned
each laser's point, so that `twin.lidar.clouds` can rebuild the firing grid from any of them.

What people save is a driver's point cloud, and the drivers differ (read in their sources):

==================  ==========================  ===============================================
convention          fields                      azimuth of a laser's point
==================  ==========================  ===============================================
``aimbench``        x y z intensity ring time   the block's azimuth + the rotation during the
                    scan (`aimbench decode`)    laser's firing delay (manual 9.5) + its
                                                azimuth offset: the firing's own azimuth
``velodyne-decoder`` x y z intensity time       as aimbench (valgur/velodyne_decoder
                    column ring return_type     packet_decoder.cpp: the packet's mean rate
                                                times the manual's timing table), rounded to
                                                0.01 deg; ``column`` numbers the firing
                                                sequences
``ros-velodyne``    x y z intensity ring        16 lasers: as aimbench, rounded to 0.01 deg
                    [time] (XYZIR, XYZIRT;      (rawdata.cc unpack_vlp16). 32 lasers (VLP-32C,
                    ROS 1 and ROS 2 alike)      HDL-32E): the block's azimuth + the azimuth
                                                offset only: every laser of a block at one
                                                azimuth, the firing delay left out
                                                (rawdata.cc unpack)
``nebula``          x y z intensity             16 lasers: as aimbench, rounded. 32 lasers:
                    return_type channel         the block's azimuth + channel index x 2.304 us
                    azimuth elevation distance  of the block's 55.296 us step (the manual fires
                    time_stamp (ns)             lasers in pairs: odd channels half a firing
                                                too far), except the packet's last block, turned
                                                by nothing (vlp32_decoder.cpp); ``azimuth`` is
                                                the block's encoder azimuth
==================  ==========================  ===============================================

All write the ROS frame (x forward, y left, z up); none keeps the rays that missed except the
ROS driver's organised cloud (NaN points). The ROS driver and nebula leave the lasers' vertical
offsets out (their calibration files set them to 0); velodyne_decoder and aimbench put them in
(`twin.lidar.clouds` tells which from the points).

Hesai clouds are not rebuilt here but in `twin.lidar.hesai_clouds`: nebula's PandarXT32 and
PandarQT128 (dual return) clouds
(hesai_decoder.hpp: Hesai's own frame, fields x y z intensity return_type channel azimuth
elevation distance time_stamp, no misses) are read back as the scans their packets give, the head's
rotation until each channel fires, which nebula leaves out (up to 0.19 deg at 600 rpm), put
back; `twin.lidar.sources` sends a cloud there when ``--model`` names a Hesai or a PCD file's
fields and elevations are a Hesai's. Hesai's own ROS driver's PandarXT32 clouds (x y z intensity
ring timestamp, the misses at the origin, Hesai's frame unless its transform turned them) are
read by `twin.lidar.hesai_ros_clouds` (conventions ``hesai-ros``, ``hesai-ros-ros-frame``,
`twin.lidar.format_names.HESAI_CLOUD_CONVENTIONS`).

Ouster clouds are not rebuilt either, nor need to be: ouster-ros's (and ouster-sdk's XYZLut's)
cloud is organised, every pixel kept, and `twin.lidar.ouster_clouds` reads it with the sensor's
metadata into the packets' own scan (`twin.lidar.sources` tries it first on an organised cloud).

A cloud's convention is told by its fields where they tell it (``column``: velodyne_decoder;
``channel``: nebula; ``scan``: aimbench), from its points otherwise (the rotation under which
each firing sequence's returns line up, `twin.lidar.clouds`), or given (``--cloud-convention``).
The functions `ros_velodyne_cloud` and `nebula_cloud` write the cloud those drivers write from
decoded packets, following their sources line by line: the tests and
benchmarks/bench_cloud_rebuild.py hold the rebuilt scans to the packets' own.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from twin.core.errors import AimbenchError
from twin.core.sensors import SensorModel
from twin.lidar import format_names as names

#: nebula's and the ROS driver's VLP-32 constants (velodyne_scan_decoder.hpp,
#: rawdata.cc buildTimings): one channel every 2.304 us of a 55.296 us block.
NEBULA_CHANNEL_DURATION = 2.304e-6
NEBULA_SEQUENCE_DURATION = 55.296e-6


class CloudConventionError(AimbenchError):
    """An unknown cloud convention name."""


@dataclass(frozen=True)
class CloudConvention:
    """One driver's way of writing a cloud (module docstring).

    ``ring_field``: the field holding each point's laser in elevation order; ``time_field`` and
    ``time_unit`` (s per count): each point's time; ``sequence_field``: a field numbering the
    firing sequences, when the driver writes one.
    """

    name: str
    driver: str
    ring_field: str = "ring"
    time_field: str = "time"
    time_unit: float = 1.0
    sequence_field: str | None = None

    def rotation(self, n_lasers: int, true: np.ndarray) -> np.ndarray:
        """How far the driver turned each laser's point past its sequence's (or block's) encoder
        azimuth, as a share of the step between sequences, by laser id; ``true``: the model's
        own (each laser's firing delay over the sequence period)."""
        if self.name == "ros-velodyne" and n_lasers == 32:
            return np.zeros(n_lasers)
        if self.name == "nebula" and n_lasers == 32:
            return np.arange(32) * (NEBULA_CHANNEL_DURATION / NEBULA_SEQUENCE_DURATION)
        return np.asarray(true, dtype=np.float64)


#: The conventions by name (`twin.lidar.format_names.CLOUD_CONVENTIONS`, which the command line
#: offers).
CONVENTIONS: dict[str, CloudConvention] = {c.name: c for c in (
    CloudConvention(names.AIMBENCH, "aimbench decode / export"),
    CloudConvention(names.VELODYNE_DECODER, "valgur/velodyne_decoder", sequence_field="column"),
    CloudConvention(names.ROS_VELODYNE, "ros-drivers/velodyne velodyne_pointcloud (ROS 1 and 2)"),
    CloudConvention(names.NEBULA, "tier4/nebula", ring_field="channel", time_field="time_stamp",
                    time_unit=1e-9),
)}


def convention_named(name: str | CloudConvention | None) -> CloudConvention | None:
    """The convention of a name (``ros-velodyne``, ``nebula``...), None for None."""
    if name is None or isinstance(name, CloudConvention):
        return name
    key = name.strip().lower().replace("_", "-")
    if key not in CONVENTIONS:
        raise CloudConventionError(f"unknown cloud convention {name!r}: give one of "
                                   f"{', '.join(CONVENTIONS)}")
    return CONVENTIONS[key]


def convention_of_fields(names: tuple[str, ...] | list[str]) -> CloudConvention | None:
    """The convention a cloud's field names tell, or None when they fit several drivers (x y z
    intensity ring [time] is the ROS driver's, and anyone's who copied it)."""
    names = set(names or ())
    if "column" in names and "ring" in names:
        return CONVENTIONS["velodyne-decoder"]
    if "channel" in names and "ring" not in names:
        return CONVENTIONS["nebula"]
    if "scan" in names and "ring" in names:
        return CONVENTIONS["aimbench"]
    return None


#: Field names read as intensity, first found wins (ROS drivers write intensity; Ouster and
#: some others reflectivity).
INTENSITY_FIELDS = ("intensity", "reflectivity")


def cloud_fields(rec: np.ndarray, convention: CloudConvention | None = None
                 ) -> tuple[dict, str | None]:
    """The per-point arrays a `twin.lidar.clouds.Cloud` takes from a record array besides x, y,
    z (fields by name, as ``convention`` names them), and how the convention was told
    (``option``, ``fields``, or None: to be told from the points)."""
    names = rec.dtype.names or ()
    told = "option" if convention is not None else None
    if convention is None:
        convention = convention_of_fields(names)
        told = "fields" if convention is not None else None
    ring_field = convention.ring_field if convention else "ring"
    if ring_field not in names:  # a convention given for a cloud that names its ring otherwise
        ring_field = next((f for f in ("ring", "channel") if f in names), ring_field)
    time_field, unit = ((convention.time_field, convention.time_unit) if convention
                        else ("time", 1.0))
    if time_field not in names:
        time_field, unit = next(((f, u) for f, u in (("time", 1.0), ("time_stamp", 1e-9),
                                                    ("timestamp", 1e-9), ("t", 1e-9))
                                 if f in names), (None, 1.0))
    nebula = convention is not None and convention.name == "nebula"
    return {
        "intensity": next((rec[f] for f in INTENSITY_FIELDS if f in names), None),
        "ring": rec[ring_field] if ring_field in names else None,
        "time": None if time_field is None else rec[time_field].astype(np.float64) * unit,
        "convention": convention.name if convention else None,
        "block_azimuth": rec["azimuth"] if nebula and "azimuth" in names else None,
    }, told


# ----------------------------------------------------------------------------------------------
# The drivers' clouds from decoded packets (their sources, line by line)


def _packet_arrays(decoded) -> tuple[np.ndarray, np.ndarray, SensorModel, np.ndarray]:
    """Block azimuths (n, 12) in 0.01 deg, distances (n, 12, 32) m, the sensor, and packet
    times (n,) s of single-return `twin.lidar.packets.DecodedPackets`."""
    if np.any(decoded.return_mode == 0x39):
        raise ValueError("the drivers' clouds are written here for single-return packets only")
    n = len(decoded)
    return (decoded.block_azimuth_cdeg.astype(np.int64), decoded.distance.reshape(n, 12, 32),
            decoded.sensor, decoded.timestamp_us * 1e-6)


def _ros_frame(distance: np.ndarray, azimuth: np.ndarray, elevation: np.ndarray,
               vertical: np.ndarray | float = 0.0) -> tuple[np.ndarray, ...]:
    """x forward, y left, z up of returns at ``azimuth`` (rad, clockwise from forward)."""
    xy = distance * np.cos(elevation)
    return (xy * np.cos(azimuth), -xy * np.sin(azimuth), distance * np.sin(elevation) + vertical)


def _ros_timing(sensor: SensorModel) -> np.ndarray:
    """rawdata.cc buildTimings: each (block, channel)'s time after the packet's stamp, s. For
    the HDL-32E the ROS driver counts the lasers in pairs, as for the VLP-32C (its table's
    ``y / 2``), though the HDL-32E fires them one by one."""
    b, j = np.meshgrid(np.arange(12), np.arange(32), indexing="ij")
    if sensor.n_lasers == 16:
        return (2 * b + j // 16) * 55.296e-6 + (j % 16) * 2.304e-6
    if sensor.name == "HDL-32E":
        return b * 46.08e-6 + (j // 2) * 1.152e-6
    return b * 55.296e-6 + (j // 2) * 2.304e-6


def _round(x: np.ndarray) -> np.ndarray:
    """C++'s std::round of positive values: halves away from zero (numpy's rint goes to even)."""
    return np.floor(x + 0.5)


def _block_diffs(az: np.ndarray, last_is_zero: bool) -> np.ndarray:
    """Each block's azimuth step to the next block (0.01 deg), as rawdata.cc / nebula take it:
    the packet's last block repeats the one before (ROS) or gets 0 (nebula's VLP-32)."""
    diff = np.empty(az.shape, dtype=np.float64)
    raw = az[:, 1:] - az[:, :-1]
    diff[:, :-1] = (36000 + raw) % 36000
    diff[:, -1] = 0.0 if last_is_zero else diff[:, -2]
    return diff


def ros_velodyne_cloud(decoded, *, organized: bool = False) -> np.ndarray:
    """The ROS velodyne driver's XYZIRT cloud of decoded packets (velodyne_pointcloud
    rawdata.cc, ROS 1 master and ROS 2 alike, with its shipped calibration files: no vertical
    offsets, rot_correction = -azimuth offset). ``organized``: one row per block, misses NaN
    (organized_cloudXYZIRT; 32-laser models)."""
    az, dist, sensor, stamp = _packet_arrays(decoded)
    lasers = sensor.lasers
    lid = sensor.laser_of_channel
    n = len(az)
    if sensor.n_lasers == 16:
        # unpack_vlp16: the firing delay's rotation, rounded to 0.01 deg.
        diff = _block_diffs(az, last_is_zero=False)
        j = np.arange(32)
        t = (j % 16) * 2.304 + (j // 16) * 55.296
        a_cdeg = _round(az[:, :, None] + diff[:, :, None] * t / 110.592) % 36000
    else:  # unpack: every laser of a block at the block's azimuth
        a_cdeg = np.broadcast_to(az[:, :, None], (n, 12, 32)).astype(np.float64)
    a = np.radians(a_cdeg / 100.0) + lasers.azimuth_offset[lid]
    x, y, z = _ros_frame(dist, a, lasers.elevation[lid])
    time = _ros_timing(sensor)[None] + (stamp - stamp[0])[:, None, None]
    ring = np.broadcast_to(lasers.ring_of_laser[lid], dist.shape)
    inten = decoded.intensity.reshape(dist.shape).astype(np.float32)
    dtype = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"), ("ring", "<u2"),
             ("time", "<f4")]
    out = np.zeros(dist.shape, dtype=dtype)
    for name, v in (("x", x), ("y", y), ("z", z), ("intensity", inten), ("ring", ring),
                    ("time", time)):
        out[name] = v
    if not organized:
        return out[dist > 0]
    if sensor.n_lasers != 32:
        raise ValueError("organised clouds are written here for 32-laser models only")
    for name in ("x", "y", "z", "intensity"):
        out[name][dist == 0] = np.nan
    # addPoint writes each laser at its ring's column: a row per block.
    rows = np.empty_like(out)
    rows[:, :, lasers.ring_of_laser[lid]] = out
    return rows.reshape(n * 12, 32)


def nebula_cloud(decoded) -> np.ndarray:
    """nebula's PointXYZIRCAEDT cloud of decoded packets (nebula_velodyne_decoders
    vlp32_decoder.cpp / vlp16_decoder.cpp, its shipped calibration: no vertical offsets)."""
    az, dist, sensor, stamp = _packet_arrays(decoded)
    lasers = sensor.lasers
    lid = sensor.laser_of_channel
    delta_cdeg = np.degrees(lasers.azimuth_offset[lid]) * 100.0
    if sensor.n_lasers == 16:
        diff = _block_diffs(az, last_is_zero=False)
        j = np.arange(32)
        t = (j % 16) * 2.304 + (j // 16) * 55.296
        a_cdeg = az[:, :, None] + diff[:, :, None] * t / 110.592 + delta_cdeg
        a_cdeg = _round(np.where(a_cdeg < 0, a_cdeg + 36000, a_cdeg)) % 36000
        azimuth_field = np.radians(a_cdeg / 100.0)
    else:
        # In float32 as nebula computes it (its rounding to 0.01 deg depends on it):
        # azimuth + azimuth_diff * 2.304f / 55.296f * j - rot_correction (double, in 0.01 deg).
        f32 = np.float32
        diff = _block_diffs(az, last_is_zero=True).astype(f32)
        share = diff[:, :, None] * f32(2.304) / f32(55.296) * np.arange(32, dtype=f32)
        rot = (-lasers.azimuth_offset[lid]).astype(f32).astype(np.float64) * 180.0 / math.pi * 100
        a_cdeg = ((az[:, :, None].astype(f32) + share).astype(np.float64) - rot).astype(f32)
        a_cdeg = _round(np.where(a_cdeg < 0, a_cdeg + f32(36000), a_cdeg)) % 36000
        azimuth_field = np.broadcast_to(np.radians(az / 100.0)[:, :, None], dist.shape)
    el = lasers.elevation[lid]
    x, y, z = _ros_frame(dist, np.radians(a_cdeg / 100.0), el)
    dtype = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "u1"),
             ("return_type", "u1"), ("channel", "<u2"), ("azimuth", "<f4"),
             ("elevation", "<f4"), ("distance", "<f4"), ("time_stamp", "<u4")]
    out = np.zeros(dist.shape, dtype=dtype)
    timing = (np.arange(12)[:, None] * 55.296e-6 + (np.arange(32)[None, :] // 2) * 2.304e-6
              if sensor.n_lasers == 32 else _ros_timing(sensor))
    ts = timing[None] + (stamp - stamp[0])[:, None, None]
    inten = decoded.intensity.reshape(dist.shape)
    for name, v in (("x", x), ("y", y), ("z", z), ("intensity", inten),
                    ("return_type", 1), ("channel", lasers.ring_of_laser[lid]),
                    ("azimuth", azimuth_field), ("elevation", np.sin(el)), ("distance", dist),
                    ("time_stamp", np.rint(ts * 1e9))):
        out[name] = v
    return out[dist > 0]


def turn(x: np.ndarray, y: np.ndarray, angle: np.ndarray | float) -> tuple[np.ndarray, ...]:
    """Points of {L} turned clockwise (azimuth growing) by ``angle`` rad about Z_L."""
    c, s = np.cos(angle), np.sin(angle)
    return x * c + y * s, y * c - x * s


__all__ = ["CONVENTIONS", "CloudConvention", "CloudConventionError", "cloud_fields",
           "convention_named", "convention_of_fields", "nebula_cloud", "ros_velodyne_cloud",
           "turn"]
