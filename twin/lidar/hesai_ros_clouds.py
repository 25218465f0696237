"""Hesai's own ROS driver's point clouds (HesaiLidar_ROS_2.0 on HesaiLidar_SDK_2.0) of a
PandarXT32 or a PandarQT128, read back as the scans their packets give.

What the driver writes (HesaiTechnology/HesaiLidar_ROS_2.0 at e7e112f, 2026-04-27, whose
``src/driver/HesaiLidar_SDK_2.0`` submodule pins SDK 9d5dc4f; the SDK read at ea7f86f,
2025-11-24, "update 2.0.11", the newest stored):

- Fields (ROS ``src/manager/source_driver_ros2.hpp`` and ``source_driver_ros1.hpp``
  ``ToRosMsg``, lines 257-320): ``x y z`` FLOAT32, ``intensity`` FLOAT32, ``ring`` UINT16,
  ``timestamp`` FLOAT64, added one after the other by ``addPointField`` (packed: offsets 0, 4,
  8, 12, 16, 18; ``point_step`` 26); ``height`` 1, ``width`` the frame's points, ``is_dense``
  false; the header's stamp the frame's start (its first packet's time), ``frame_id``
  ``hesai_lidar`` (config/config.yaml ``ros_frame_id``).
- Points (SDK ``libhesai/UdpParser/src/udp6_1_parser.cc`` ``ComputeXYZI``, lines 86-165):
  every channel of every block of every packet, in that order (packet, block, channel), a
  return or not: a channel with no return is written at distance 0, x = y = z = 0 (nothing
  drops it: no range check; ``display`` and the FOV filters keep all by default). Dual return:
  both blocks of each pair, each echo written (``echo_mode_filter`` 0 by default). The frame's
  packets are compacted into one list (``driver/hesai_lidar_sdk.hpp`` lines 303-313): the
  cloud is unorganised (height 1) but holds the whole grid unless a filter was configured.
- Geometry: azimuth (1/25600 deg) = block azimuth x 256 [+ the firetime rotation, below] +
  ``doubleToInt(azimuth_offset x 25600)`` (``doubleToInt`` is ``static_cast<int>(v +
  0.0625)``: truncation, udp_protocol_header.h line 42); elevation = ``doubleToInt(elevation x
  25600)``; x = d cos(el) sin(az), y = d cos(el) cos(az), z = d sin(el) from float tables of
  sin and cos at 1/25600 deg (general_parser.cc line 53): Hesai's own frame, y forward, x right,
  as aimbench's {L}. ``TransformPoint`` (general_parser.cc line 373) turns the points only
  when ``transform_flag`` is set (config.yaml: false; x y z roll pitch yaw, rad): a user who
  wants the ROS frame (x forward, y left) sets ``yaw: -1.5708`` (`ROS_FRAME`).
- Firetime: the head's rotation until each channel fires, ``firetime[ch] x motor rpm x 6e-6``
  deg, is added to the azimuth only when a firetime file was loaded (``get_firetime_file_``,
  udp6_1_parser.cc line 112; ``firetimes_flag`` is set true in ``FrameDecodeParam::Init``,
  lidar_types.h line 201); config.yaml's ``firetimes_path`` is a placeholder ("Your firetime
  file path") and the file is never fetched from an XT32 (lidar.cc lines 256-265: only an ATX's
  over PTC): by default it is left out, as nebula leaves it out (-0.31 deg of roll on the bench,
  docs/vlp16.md). The sign is ``rotation_flag``'s (positive once the azimuths increase).
- ``timestamp``: the packet's time, s (``set_timestamp(.., sensor_timestamp / 1e6)``, line
  156; sensor_timestamp the tail's UTC date and time + its us): the same for all 256 points of
  a packet, not the point's own firing time (that goes to ``timeSecond``/``timeNanosecond``,
  which XYZIRT has not).
- ``ring``: the channel, 0-based (``set_ring(ptinfo, channel_index)``); ``intensity``: the
  reflectivity byte as a float.
- Scan cutting (general_parser.cc ``IsNeedFrameSplit``, lines 282-336; hesai_lidar_sdk.hpp
  lines 283-370): whole packets; a frame ends before the packet whose first block azimuth
  passes ``frame_start_azimuth`` (config.yaml 0 deg; below 0 or from 360 also 0,
  ``SetFrameAzimuth``), which starts the next frame.

A PandarQT128's (``udp3_2_parser.cc`` ``ComputeXYZI``, lines 260-335) is written the same way:
every channel of both blocks, a loop's dark channels at the origin like any miss, its loop's
firetime table only with a firetime file; here it is read with the firetime rotation out
(the driver's default), in dual return the loops told as for nebula's clouds, in single
return (two firings a packet) by the firings that share a packet's ``timestamp``, else by
the channels one loop fires (`twin.lidar.hesai_clouds.scan_of_points`).

`hesai_ros_cloud` writes that cloud from packets, op for op in float32 where the SDK computes
in float. `scan_from_hesai_ros` reads one back as the packet path's scan (firetime in,
`twin.lidar.hesai.scans_from_hesai`): the points at the origin (misses) dropped, each return's
channel its ``ring`` (else the nearest of the angle file's elevations to its own), its block
azimuth its azimuth less the channel's offset (and less the firetime rotation when the cloud has
it: told from the points, which then fall on the packets' 0.01 deg steps only at the packets'
rpm, which is so found exactly), the dual-return pair told by a channel's two points on one
block azimuth; then the firing grid is rebuilt and read as `twin.lidar.hesai_clouds` does for
nebula's clouds (`scan_of_points`). The frame is told from the cut: a cloud of the default
``frame_start_azimuth`` starts at 0 deg in Hesai's frame, at 90 deg read so when turned to the
ROS frame; otherwise Hesai's frame is assumed (the driver's default) and the convention
``hesai-ros-ros-frame`` gives the other (a ROS-frame cloud cut at 270 deg starts where a
Hesai-frame one cut at 0 does: there too). The rpm the firing rotation is put back with: the
packets' own when the cloud has the firetime rotation; else the slope of the block azimuths
against the packets' ``timestamp``; else the grid's step.
"""

from __future__ import annotations

import itertools
import math

import numpy as np

from twin.core.scan import Scan
from twin.lidar import format_names as names
from twin.lidar.hesai import QT128, XT32, HesaiAngles, HesaiError
from twin.lidar.hesai_clouds import (
    CloudPoints,
    HesaiCloudScanSource,
    head_rpm,
    packet_times_ns,
    scan_of_points,
)

#: LidarPointXYZIRT as the ROS driver's PointCloud2 lays it out (packed, 26 bytes).
HESAI_ROS_POINT_DTYPE = np.dtype([
    ("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"), ("ring", "<u2"),
    ("timestamp", "<f8")])
#: The fields that tell the driver's cloud (with a Hesai's elevations: RoboSense's driver
#: writes the same PointXYZIRT).
HESAI_ROS_FIELDS = ("x", "y", "z", "intensity", "timestamp")
#: The SDK's fine angle unit: 1/25600 deg (inner_com.h kAllFineResolutionInt), and a turn in it.
FINE = 25600
CIRCLE = 36000 * 256
#: config.yaml's transform (x, y, z m; roll, pitch, yaw rad) that puts the points in the ROS
#: frame (x forward, y left): a yaw of -90 deg.
ROS_FRAME = (0.0, 0.0, 0.0, 0.0, 0.0, -math.pi / 2)
FRAMES = {names.HESAI_ROS: "hesai", names.HESAI_ROS_ROS_FRAME: "ros"}
#: How far past the cut the first firing of a frame may lie: a packet's blocks (8 x 0.18 deg
#: at 600 rpm, 2.88 deg at 1200) and a few blocks of no return, 0.01 deg.
_CUT_SLACK_CDEG = 500
#: A block azimuth read off a point lies this close to the packets' 0.01 deg steps, 0.01 deg
#: (the SDK's 1/256 steps of the offsets and its float tables: 0.004 at most).
_STEP_TOLERANCE = 0.02


def is_hesai_ros(field_names) -> bool:
    """Whether a cloud's field names are the ROS driver's (x y z intensity [ring] timestamp;
    not nebula's, whose ``channel`` and ``time_stamp`` differ)."""
    got = set(field_names or ())
    return set(HESAI_ROS_FIELDS) <= got and "channel" not in got and "time" not in got


# ----------------------------------------------------------------------------------------------
# Writing: the driver's cloud of packets


def _double_to_int(v: np.ndarray) -> np.ndarray:
    """udp_protocol_header.h ``doubleToInt``: ``static_cast<int>(v + 0.0625)`` (toward 0)."""
    return np.trunc(np.asarray(v, dtype=np.float64) + 0.0625).astype(np.int64)


def _fine_sin_cos(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The SDK's float tables at 1/25600 deg (general_parser.cc: ``std::sin(i * 2 * M_PI /
    CIRCLE)`` in double, stored as float)."""
    rad = a * (2 * math.pi / CIRCLE)
    return np.sin(rad).astype(np.float32), np.cos(rad).astype(np.float32)


def _transform(x, y, z, t: tuple[float, ...]):
    """general_parser.cc ``TransformPoint``, in float."""
    f = np.float32
    tx, ty, tz, roll, pitch, yaw = (f(v) for v in t)
    cosa, sina, cosb, sinb = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch)
    cosc, sinc = np.cos(yaw), np.sin(yaw)
    x_ = cosb * cosc * x + (sina * sinb * cosc - cosa * sinc) * y + \
        (sina * sinc + cosa * sinb * cosc) * z + tx
    y_ = cosb * sinc * x + (cosa * cosc + sina * sinb * sinc) * y + \
        (cosa * sinb * sinc - sina * cosc) * z + ty
    z_ = -sinb * x + sina * cosb * y + cosa * cosb * z + tz
    return x_.astype(np.float32), y_.astype(np.float32), z_.astype(np.float32)


def _firetime_fine(rpm: np.ndarray, model=XT32) -> np.ndarray:
    """The firetime rotation, 1/25600 deg, (packets, channels): ``doubleToInt(firetime_us x
    motor rpm x 6e-6 x 25600)`` (GetFiretimesCorrection; the file's us read as float)."""
    us = np.float32(np.round(model.firetime[0] * 1e6, 3)).astype(np.float64)
    return _double_to_int(us[None, :] * np.asarray(rpm, np.float64)[:, None] * 6e-6 * FINE)


def _offsets_fine(angles: HesaiAngles) -> tuple[np.ndarray, np.ndarray]:
    """The angle file's azimuth and elevation offsets, 1/25600 deg, as the SDK holds them
    (float x float, then ``doubleToInt``)."""
    f = np.float32
    return (_double_to_int(angles.azimuth_deg.astype(f) * f(FINE)),
            _double_to_int(angles.elevation_deg.astype(f) * f(FINE)))


def hesai_ros_cloud(payloads: list[bytes], angles: HesaiAngles, *, firetime: bool = False,
                    transform: tuple[float, ...] | None = None,
                    packets: slice = slice(None)) -> np.ndarray:
    """The cloud Hesai's ROS driver publishes of PandarXT32 or PandarQT128 packets (``packets``
    of them: one frame, the caller picks it, `frames`), as ``HESAI_ROS_POINT_DTYPE`` records in
    its order (module docstring; a QT128's, udp3_2_parser.cc, is written the same way, its dark
    channels at the origin). ``firetime``: as with a firetime file (off by default in the
    driver; the XT32's only); ``transform``: config.yaml's (x, y, z, roll, pitch, yaw) with
    ``transform_flag`` true (`ROS_FRAME`: the ROS frame)."""
    model = angles.model
    if firetime and model is not XT32:
        raise HesaiError(f"the {model.name}'s firetime rotation (its loop tables) is not written "
                         "here: the XT32's is")
    size = model.dtype.itemsize
    good = [p for p in payloads if model.accepts(p)]
    rec = np.frombuffer(b"".join(bytes(p[:size]) for p in good), dtype=model.dtype)[packets]
    time_s = (packet_times_ns(good, angles)[packets] // 1000) / 1e6  # us / 1e6
    units = rec["blocks"]["units"]
    unit = (rec["dis_unit"].astype(np.float32) / np.float32(1000.0)).astype(np.float64)
    d = (units["distance"].astype(np.float64) * unit[:, None, None]).astype(np.float32)
    az = rec["blocks"]["azimuth"].astype(np.int64)[:, :, None] * 256
    az_off, el_off = _offsets_fine(angles)
    if firetime:
        az = az + _firetime_fine(rec["motor_speed"])[:, None, :]
    az = (az + az_off) % CIRCLE
    sin_el, cos_el = _fine_sin_cos(el_off % CIRCLE)
    sin_az, cos_az = _fine_sin_cos(az)
    xy = d * cos_el
    x, y, z = xy * sin_az, xy * cos_az, d * sin_el
    if transform is not None:
        x, y, z = _transform(x, y, z, transform)
    out = np.zeros(d.shape, dtype=HESAI_ROS_POINT_DTYPE)
    out["x"], out["y"], out["z"] = x, y, z
    out["intensity"] = units["reflectivity"]
    out["ring"] = np.arange(model.n_channels)
    out["timestamp"] = time_s[:, None, None]
    return out.reshape(-1)


def frames(payloads: list[bytes], angles: HesaiAngles, start_cdeg: int = 0) -> list[slice]:
    """The packets of each whole frame the driver cuts at ``frame_start_azimuth``
    (``start_cdeg``): a frame starts at the packet whose first block azimuth passes it."""
    from twin.lidar.hesai import decode_hesai

    first = decode_hesai(payloads, angles, firetime=False).block_azimuth_cdeg[:, 0]
    starts = np.flatnonzero(np.diff((first - start_cdeg) % 36000) < -18000) + 1
    return [slice(int(a), int(b)) for a, b in itertools.pairwise(starts)]


# ----------------------------------------------------------------------------------------------
# Reading: the packet path's scan of the driver's cloud


def _channels(rec: np.ndarray, r: np.ndarray, angles: HesaiAngles, name: str) -> np.ndarray:
    """Each return's channel: its ``ring``, held to the angle file's elevations, else the
    channel of the nearest elevation (an XT32's lie 1 deg apart)."""
    el = np.degrees(np.arcsin(np.clip(rec["z"].astype(np.float64) / r, -1, 1)))
    table = angles.elevation_deg
    if "ring" in (rec.dtype.names or ()):
        ch = rec["ring"].astype(np.int64)
        if ch.max() >= len(table):
            raise HesaiError(f"{name}: rings up to {ch.max()}: not a {angles.model.name}'s cloud")
        off = np.abs(el - table[ch]).max()
        if off > 0.01:
            raise HesaiError(f"{name}: the cloud's elevations differ from {angles.source}'s by up "
                             f"to {off:.3f} deg: it was written with another angle-correction "
                             "file; give that one (--angles)")
        return ch
    ch = np.argmin(np.abs(el[:, None] - table[None, :]), axis=1)
    off = np.abs(el - table[ch]).max()
    if off > 0.05:
        raise HesaiError(f"{name}: without a ring field the channels are told by elevation, and "
                         f"some points lie {off:.2f} deg from every one of {angles.source}'s: "
                         "give the unit's angle-correction file (--angles)")
    return ch


def _off_step(v: np.ndarray) -> np.ndarray:
    return np.abs(v - np.rint(v))


def _firetime_of(d: np.ndarray, channel: np.ndarray, firetime: bool | None, name: str
                 ) -> tuple[np.ndarray, int | None]:
    """The firetime rotation in each return's azimuth (0.01 deg) and the rpm it was written at
    (None: none in it): ``d`` the azimuth less the channel's offset, 0.01 deg. Without it the
    block azimuths fall on the 0.01 deg steps; with it, only once the rotation at the packets'
    rpm (an integer) is taken off: the rpm is so found."""
    if firetime is None or firetime is False:
        if np.percentile(_off_step(d), 99) < _STEP_TOLERANCE:
            return np.zeros(len(d)), None
        if firetime is False:
            raise HesaiError(f"{name}: the azimuths less the angle file's offsets are not on the "
                             "packets' 0.01 deg steps: written with a firetime file, or another "
                             "angle-correction file (--angles)")
    pick = np.linspace(0, len(d) - 1, min(len(d), 3000)).astype(np.int64)
    rpms = np.arange(60, 1501)
    rot = _firetime_fine(rpms)[:, channel[pick]] / 256.0  # (rpms, points) 0.01 deg
    err = np.percentile(_off_step(d[pick][None, :] - rot), 99, axis=1)
    best = int(np.argmin(err))
    if err[best] >= _STEP_TOLERANCE:
        raise HesaiError(f"{name}: the azimuths less the angle file's offsets are not on the "
                         "packets' 0.01 deg steps, with or without the model's firetimes: "
                         "written with another angle-correction file (--angles) or firetime "
                         "file")
    rpm = int(rpms[best])
    return _firetime_fine(np.array([rpm]))[0, channel] / 256.0, rpm


def _frame_of(block: np.ndarray, frame: str | None) -> tuple[str, str]:
    """The frame the points are in and how it was told: the driver's default cut
    (``frame_start_azimuth`` 0) puts a frame's first firing just past 0 deg in Hesai's frame;
    read in Hesai's frame, the ROS frame's points lie 90 deg further round."""
    if frame is not None:
        return frame, "option"
    first = int(block[0])
    if first % 36000 < _CUT_SLACK_CDEG:
        return "hesai", "cut"
    if (first - 9000) % 36000 < _CUT_SLACK_CDEG:
        return "ros", "cut"
    return "hesai", "default"


def _slots(block: np.ndarray, channel: np.ndarray, nc: int, name: str
           ) -> tuple[bool, np.ndarray]:
    """Dual return, and each return's block of its pair (0: the first, last; 1: the second,
    strongest): a dual-return cloud holds a channel's two echoes on one block azimuth, in the
    blocks' order; a single echo left (its twin a miss) is read as the strongest."""
    key = block * nc + channel
    order = np.argsort(key, kind="stable")
    k = key[order]
    counts = np.bincount(np.unique(k, return_inverse=True)[1])
    if counts.max() > 2:
        raise HesaiError(f"{name}: a channel fires {counts.max()} times at one azimuth: not one "
                         "rotation's frame")
    if counts.max() == 1:
        return False, np.zeros(len(key), np.intp)
    first = np.r_[True, k[1:] != k[:-1]]
    last = np.r_[k[1:] != k[:-1], True]
    slot = np.empty(len(key), np.intp)
    slot[order] = np.where(first & ~last, 0, 1)
    return True, slot


def scan_from_hesai_ros(rec: np.ndarray, angles: HesaiAngles, *, frame: str | None = None,
                        firetime: bool | None = None, rpm: float | None = None,
                        index: int = 0, name: str = "Hesai ROS cloud") -> Scan:
    """The packet path's scan (`twin.lidar.hesai.scans_from_hesai`, firetime in) of one frame
    of Hesai's ROS driver's PandarXT32 or (firetime out) PandarQT128 cloud
    (records with x y z at least; ring, intensity and timestamp when present): module
    docstring. ``frame``: ``hesai`` or ``ros`` (None: told by
    the cut, else Hesai's); ``firetime``: whether the cloud has the firing rotation in (None:
    told from the points); ``rpm``: the head's speed (None: the packets' when the cloud has the
    firetime rotation, else from the timestamps, else the grid's step)."""
    model = angles.model
    field_names = rec.dtype.names or ()
    if not {"x", "y", "z"} <= set(field_names):
        raise HesaiError(f"{name}: no x/y/z fields: not a point cloud")
    xyz = [rec[k].astype(np.float64) for k in ("x", "y", "z")]
    r = np.sqrt(xyz[0] ** 2 + xyz[1] ** 2 + xyz[2] ** 2)
    hit = np.isfinite(r) & (r > 0)  # the driver writes a miss at the origin
    if hit.sum() < 2 * model.n_channels:
        raise HesaiError(f"{name}: {int(hit.sum())} returns: not a {model.name}'s rotation")
    ret, r = rec[hit], r[hit]
    channel = _channels(ret, r, angles, name)
    d = (np.degrees(np.arctan2(xyz[0][hit], xyz[1][hit])) - angles.azimuth_deg[channel]) * 100
    rot, rpm_packets = _firetime_of(d, channel, firetime if model is XT32 else False, name)
    block = np.rint(d - rot).astype(np.int64) % 36000
    frame, frame_told = _frame_of(block, frame)
    if frame == "ros":  # read in Hesai's frame, the ROS frame's points are 90 deg further round
        block = (block - 9000) % 36000
    # the driver cuts between packets, so a frame's last packet can reach past where its first
    # began (a phase-locked head fires there again): those firings are the next turn's
    rel = (block - block[0]) % 36000
    wrap = np.flatnonzero(np.diff(rel) < -18000)
    if wrap.size:
        turn = slice(0, int(wrap[0]) + 1)
        ret, r, channel, block = ret[turn], r[turn], channel[turn], block[turn]
    dual, slot = _slots(block, channel, model.n_channels, name)
    single_qt = model is QT128 and not dual
    intensity = (np.rint(ret["intensity"]).astype(np.uint8) if "intensity" in field_names
                 else 0)

    def rpm_of(point_grid, loop, point_az: np.ndarray, step: float) -> float:
        if rpm is not None:
            return rpm
        if rpm_packets is not None:
            return float(rpm_packets)
        t = None
        if "timestamp" in field_names:  # absolute s: from the first, or the fit loses digits
            t = ret["timestamp"].astype(np.float64)
            t = t - t.min()
            if single_qt:  # one time a packet: its block 1 (loop 2) fires a firing later
                t = t + loop[point_grid] * model.firing_period
        return head_rpm(t, point_az, step, model)

    # a single-return QT128's two firings a packet share its timestamp: that tells the loops
    packet_time = None
    if single_qt and "timestamp" in field_names:
        t_packet = ret["timestamp"].astype(np.float64)

        def packet_time(_loop: np.ndarray) -> np.ndarray:
            return t_packet

    convention = names.HESAI_ROS if frame == "hesai" else names.HESAI_ROS_ROS_FRAME
    scan = scan_of_points(
        CloudPoints(block, np.arange(len(ret), dtype=np.float64), channel, slot, r, intensity,
                    dual, len(rec), packet_time),
        angles, rpm_of, index=index, name=name, convention=convention)
    scan.meta.update({"cloud_frame_from": frame_told,
                      "cloud_firetime": rpm_packets is not None})
    return scan


# ----------------------------------------------------------------------------------------------
# As a source: `aimbench info / estimate CLOUD` (the model told by the fields and elevations, or
# --model PandarXT32; the convention by the fields, or --cloud-convention hesai-ros...)


def hesai_ros_model_of_cloud(rec: np.ndarray) -> str | None:
    """The Hesai model a cloud of the ROS driver's fields is of: its rings' elevations (from
    the points) against each model's nominal angles within 0.5 deg; None otherwise (RoboSense's
    driver writes the same fields). A QT128's is named so that its reading says it is not
    read here."""
    from twin.lidar.hesai import HESAI_MODELS, default_angles

    field_names = rec.dtype.names or ()
    if not is_hesai_ros(field_names) or "ring" not in field_names or len(rec) == 0:
        return None
    r = np.sqrt(sum(rec[k].astype(np.float64) ** 2 for k in ("x", "y", "z")))
    hit = np.isfinite(r) & (r > 0)
    if not hit.any():
        return None
    ring = rec["ring"][hit].astype(np.int64)
    el = np.degrees(np.arcsin(np.clip(rec["z"][hit].astype(np.float64) / r[hit], -1, 1)))
    for model in HESAI_MODELS.values():
        if ring.max() >= model.n_channels:
            continue
        nominal = HesaiAngles.from_csv(default_angles(model), model)
        if np.abs(el - nominal.elevation_deg[ring]).max() < 0.5:
            return model.name
    return None


_FRAME_TOLD = {
    "cut": "the frame told by the cut at the driver's default frame_start_azimuth, 0 deg",
    "default": "Hesai's frame assumed, the driver's default: --cloud-convention "
               "hesai-ros-ros-frame for the ROS frame",
    "option": "the frame given by --cloud-convention",
}


class HesaiRosCloudScanSource(HesaiCloudScanSource):
    """Scans of Hesai's ROS driver's PandarXT32 clouds, one a cloud (`scan_from_hesai_ros`).
    ``frame``: ``hesai`` or ``ros`` when given (--cloud-convention), None to tell it."""

    def __init__(self, name, clouds, angles: HesaiAngles, *, frame: str | None = None,
                 **kwargs) -> None:
        super().__init__(name, clouds, angles, **kwargs)
        self.frame = frame

    def _scans(self):
        for i, (name, rec) in enumerate(self.clouds):
            scan = scan_from_hesai_ros(rec, self.angles, frame=self.frame, index=i, name=name)
            self._scans_made.append(scan)
            yield scan

    def _summary(self) -> dict:
        out = super()._summary()
        s = self._scans_made
        conv = " / ".join(dict.fromkeys(x.meta["cloud_convention"] for x in s)) or None
        told = " / ".join(dict.fromkeys(_FRAME_TOLD[x.meta["cloud_frame_from"]] for x in s))
        fire = {x.meta["cloud_firetime"] for x in s}
        out.update({
            "model_from": ("given by --model" if self.told == "option"
                           else "from the driver's fields and the rings' elevations"),
            "rpm_from": ("the packets' own, told by the firetime rotation in the cloud"
                         if fire == {True} else "from the packets' timestamps, else the "
                         "firings' azimuth step"),
            "cloud_driver": "Hesai's ROS driver's",
            "cloud_convention": (f"{conv} (Hesai's ROS driver; firing rotation "
                                 f"{'in the cloud' if fire == {True} else 'put back'})"),
            "cloud_convention_from": (f"told by the cloud's fields; {told}" if told
                                      else "told by the cloud's fields"),
        })
        return out
