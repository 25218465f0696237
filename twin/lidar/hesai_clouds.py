"""nebula's Hesai point clouds (PandarXT32, PandarQT128) read back as the scans their packets
give.

What nebula writes (tier4/nebula, read at its main branch):

- ``nebula_core_common/point_types.hpp``: ``PointXYZIRCAEDT``, fields x y z (float32, m)
  intensity (uint8) return_type (uint8) channel (uint16, the laser, 0-based) azimuth elevation
  (float32, rad) distance (float32, m) time_stamp (uint32, ns after the cloud's stamp).
- ``nebula_hesai_decoders/decoders/hesai_decoder.hpp`` ``convert_returns``: for each group of
  ``n_returns`` blocks (one firing), each channel, each return: a point unless its distance is 0
  or outside the model's and the configuration's range, unless (dual return) it is not the
  group's last block and is identical to another return (``IDENTICAL``, written once, from the
  last block) or within ``dual_return_distance_threshold`` of one. No-return points are
  dropped: the misses are not in the cloud. x = r cos(el) sin(az), y = r cos(el) cos(az),
  z = r sin(el): Hesai's own frame, y forward and x right, as aimbench's {L}. ``azimuth`` is the
  block's azimuth + the channel's azimuth offset (the angle corrector): the head's rotation
  until the channel fires is left out (`twin.lidar.hesai`'s docstring). Points are written
  firing by firing, channel by channel, return by return.
- ``pandar_xt32.hpp``: a point's time after its packet's = ``5632 - 50000 * ((8 - block - 1) /
  n_returns)`` + ``368 + 1512 * channel`` ns; ``get_return_type`` (``hesai_sensor.hpp``): in
  last-and-strongest mode (0x39) the first block's return is LAST_STRONGEST or LAST, the
  second's STRONGEST or SECONDSTRONGEST (strongest: reflectivity not below the other's).
  ``time_stamp`` = packet time (the tail's date and time + its us) - the cloud's stamp (the
  earliest point time of its first firing) + that offset.
- ``pandar_qt128.hpp``: ``9000 + 111110 * (2 - block - 1) / n_returns`` ns + the block's loop
  table (``loop1``/``loop2``: the tail's mode flag in dual return); a loop's dark channels read
  distance 0 and are dropped like any miss.

`nebula_hesai_cloud` writes that cloud from packets; `scan_from_nebula_hesai` reads one back:
each point's firing from its block azimuth (its ``azimuth`` minus the channel's offset, or
atan2(x, y) without the field), the firing grid rebuilt (a firing every 0.18 deg at 600 rpm:
the firings where every channel missed put back), the misses put back, and the head's rotation
put back into each channel's azimuth (the model's firetime at the rpm the time stamps give,
else the grid's step; a QT128's firing loops, which alternate, from the channels only one loop
fires): it writes the grid as packets (`twin.lidar.hesai.encode_xt32`, `encode_qt128`) and reads
them as the packet path does (`decode_hesai`, `scans_from_hesai`), so the scan is the packet
path's by construction. What differs from the packet path's scan: a miss's azimuth on a firing
where every channel missed is interpolated from its neighbours (the packets' is the encoder's),
a return nebula dropped as out of range is a miss, and nebula's scan cutter (hesai_decoder.hpp
``scan_cutter_``, cut per channel at the cut angle) can leave a channel of the first or last
firing in the next cloud: there it is a miss. A single-return QT128 cloud (two firings a
packet, block 0 loop 1 and block 1 loop 2) has its loops told by its time stamps, where only
the right phase of the alternation puts one packet time on both firings of each packet
(`_phase_by_time`), else by the channels one loop fires; its grid is written as packets
begun on a loop 1 firing. nebula stamps such a packet's block 0 after its block 1, so there
the cloud's order, not the stamps, orders the firings.
"""

from __future__ import annotations

import calendar
import itertools
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from twin.core.scan import Scan
from twin.lidar.hesai import (
    HESAI_MODELS,
    QT128,
    QT128_FIRED,
    QT128_LOOP_TIME,
    XT32,
    HesaiAngles,
    HesaiError,
    decode_hesai,
    encode_qt128,
    encode_xt32,
    scans_from_hesai,
)
from twin.lidar.source_base import ScanSource

#: nebula's PointXYZIRCAEDT (point_types.hpp), packed (PCD and PointCloud2 store it so).
NEBULA_POINT_DTYPE = np.dtype([
    ("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "u1"), ("return_type", "u1"),
    ("channel", "<u2"), ("azimuth", "<f4"), ("elevation", "<f4"), ("distance", "<f4"),
    ("time_stamp", "<u4")])

#: nebula_common.hpp ``ReturnType``.
LAST, FIRST, STRONGEST, IDENTICAL, SECOND, SECONDSTRONGEST, LAST_STRONGEST = 1, 2, 3, 6, 7, 8, 10
_SINGLE_TYPE = {"first": FIRST, "second": SECOND, "strongest": STRONGEST, "last": LAST}
#: Types only a dual-return cloud holds, and the ones nebula gives a last-and-strongest pair's
#: second block (hesai_sensor.hpp get_return_type).
_DUAL_ONLY = (IDENTICAL, SECONDSTRONGEST, LAST_STRONGEST)
_SECOND_BLOCK = (STRONGEST, SECONDSTRONGEST, IDENTICAL)
LAST_AND_STRONGEST = 0x39
#: nebula's test configuration for the XT32 (hesai_ros_decoder_test_main.cpp): ranges m, and
#: its default dual-return distance threshold (hesai_ros_decoder_test.hpp), m.
NEBULA_RANGE = (0.05, 120.0)
NEBULA_DUAL_THRESHOLD = 0.1
#: nebula's field names that tell its Hesai cloud (``ring`` is absent: nebula writes channel).
NEBULA_HESAI_FIELDS = ("channel", "return_type", "azimuth", "elevation", "distance",
                       "time_stamp")


def is_nebula_hesai(names) -> bool:
    """Whether a cloud's field names are nebula's PointXYZIRCAEDT (its Hesai and Velodyne
    clouds alike: the model tells which)."""
    return set(NEBULA_HESAI_FIELDS) <= set(names or ())


# ----------------------------------------------------------------------------------------------
# Writing: nebula's cloud of packets


def packet_times_ns(payloads: list[bytes], angles: HesaiAngles) -> np.ndarray:
    """Each packet's time, ns since 1970: the tail's date and time (years since 1900, UTC) plus
    its microseconds (nebula's hesai_packet::get_timestamp_ns)."""
    model = angles.model
    size = model.dtype.itemsize
    rec = np.frombuffer(b"".join(bytes(p[:size]) for p in payloads if model.accepts(p)),
                        dtype=model.dtype)
    sec = np.array([calendar.timegm((1900 + int(d[0]), int(d[1]), int(d[2]), int(d[3]),
                                     int(d[4]), int(d[5]))) for d in rec["date_time"]],
                   dtype=np.int64)
    return sec * 1_000_000_000 + rec["timestamp"].astype(np.int64) * 1000


def _xt32_offset_ns(block: np.ndarray, channel: np.ndarray, n_returns: int) -> np.ndarray:
    """pandar_xt32.hpp get_packet_relative_point_time_offset (C++ integer division)."""
    return 5632 - 50000 * ((8 - block - 1) // n_returns) + 368 + 1512 * channel


def _qt128_offset_ns(block: np.ndarray, loop: np.ndarray, n_returns: int) -> np.ndarray:
    """pandar_qt128.hpp get_packet_relative_point_time_offset: ``9000 + 111110 * (2 - block -
    1) / n_returns`` (C++ integers) + the block's loop table (``loop1``/``loop2``: the tail's
    mode flag in dual return, the block's parity in single)."""
    channel = np.rint(QT128_LOOP_TIME[loop] * 1e9).astype(np.int64)
    return 9000 + (111110 * (2 - block - 1)) // n_returns + channel


def _offset_ns(model, block: np.ndarray, loop: np.ndarray | None, n_returns: int) -> np.ndarray:
    """Each unit's time after its packet's, ns, (groups, n_returns, channels)."""
    if model is XT32:
        return _xt32_offset_ns(block[:, :, None], np.arange(model.n_channels), n_returns)
    return _qt128_offset_ns(block[:, :, None], loop, n_returns)


def _return_types(d: np.ndarray, refl: np.ndarray, mode: int, model) -> np.ndarray:
    """nebula's return type of each unit (groups, n_returns, channels)."""
    if d.shape[1] == 1:
        return np.full(d.shape, _SINGLE_TYPE[model.single_modes[mode]], dtype=np.uint8)
    if mode != LAST_AND_STRONGEST:
        raise HesaiError(f"dual return mode 0x{mode:02X}: nebula's cloud is written here for "
                         "last and strongest (0x39) only")
    other = refl[:, ::-1]
    strongest = refl >= other  # nebula: strongest unless weaker than the other
    out = np.where(strongest, np.array([LAST_STRONGEST, STRONGEST])[None, :, None],
                   np.array([LAST, SECONDSTRONGEST])[None, :, None]).astype(np.uint8)
    identical = (d == d[:, ::-1]) & (refl == other)
    return np.where(identical, IDENTICAL, out).astype(np.uint8)


def nebula_hesai_cloud(payloads: list[bytes], angles: HesaiAngles, *,
                       firings: slice = slice(None), ranges: tuple[float, float] = NEBULA_RANGE,
                       dual_threshold: float = NEBULA_DUAL_THRESHOLD) -> np.ndarray:
    """The PointXYZIRCAEDT cloud nebula writes of PandarXT32 or PandarQT128 packets (module
    docstring; a QT128's dark channels read 0 and are dropped as nebula drops them), of the
    firings ``firings`` (a slice over the packets' firings: a block, or a dual pair, each):
    nebula's own scan cutting is not followed, the caller chooses the firings."""
    model = angles.model
    dec = decode_hesai(payloads, angles, firetime=False)  # nebula's azimuths and points
    modes = set(dec.return_mode.tolist())
    if len(modes) != 1:
        raise HesaiError("packets of several return modes: record one mode")
    mode = modes.pop()
    nr = 1 if mode in model.single_modes else 2
    n, nb, nc = dec.distance.shape
    groups = n * nb // nr

    def grouped(a: np.ndarray) -> np.ndarray:  # (groups, n_returns, channels)
        return a.reshape(groups, nr, nc)

    d, refl = grouped(dec.distance), grouped(dec.reflectivity)
    rtype = _return_types(d, refl, mode, model)
    lo, hi = ranges
    keep = (d > 0) & (d >= max(lo, model.min_range)) & (d <= min(hi, model.max_range))
    if nr == 2:  # the first block's return, identical or too near the second's, is dropped
        keep[:, 0] &= (rtype[:, 0] != IDENTICAL) & (np.abs(d[:, 1] - d[:, 0]) >= dual_threshold)
    g = np.arange(groups)[firings]
    block = (g[:, None] % (nb // nr)) * nr + np.arange(nr)  # (groups, n_returns)
    loop = None if dec.loop is None else dec.loop.reshape(groups, nr)[g]
    offset = _offset_ns(model, block, loop, nr)
    t_packet = packet_times_ns(payloads, angles)[g // (nb // nr)]
    stamp = t_packet[0] + int(offset[0].min())  # on_set_timestamp: the first firing's earliest
    time_ns = t_packet[:, None, None] + offset - stamp
    # nebula's order: firing, channel, return
    sel = keep[g].transpose(0, 2, 1)
    out = np.zeros(sel.shape, dtype=NEBULA_POINT_DTYPE)
    el = np.radians(angles.elevation_deg)[None, :, None]
    for name, v in (("x", dec.x), ("y", dec.y), ("z", dec.z), ("intensity", dec.reflectivity),
                    ("azimuth", dec.azimuth), ("distance", dec.distance)):
        out[name] = grouped(v)[g].transpose(0, 2, 1)
    out["return_type"] = rtype[g].transpose(0, 2, 1)
    out["channel"] = np.arange(nc)[None, :, None]
    out["elevation"] = np.broadcast_to(el, sel.shape)
    out["time_stamp"] = time_ns.transpose(0, 2, 1)
    return out[sel]


def rotation_firings(payloads: list[bytes], angles: HesaiAngles, cut_cdeg: int = 18000
                     ) -> list[slice]:
    """The firings (as `nebula_hesai_cloud` counts them) of each whole rotation the packet path
    cuts (`twin.lidar.hesai.scans_from_hesai` at ``cut_cdeg``): to write the cloud of each."""
    dec = decode_hesai(payloads, angles, firetime=False)
    nr = 1 if set(dec.return_mode.tolist()) <= set(angles.model.single_modes) else 2
    az = dec.block_azimuth_cdeg[:, nr - 1::nr].ravel()
    starts = np.flatnonzero(np.diff((az - cut_cdeg) % 36000) < -18000) + 1
    return [slice(int(a), int(b)) for a, b in itertools.pairwise(starts)]


# ----------------------------------------------------------------------------------------------
# Reading: the packet path's scan of nebula's cloud


def _block_azimuth_cdeg(rec: np.ndarray, channel: np.ndarray, angles: HesaiAngles
                        ) -> np.ndarray:
    """Each point's block azimuth, 0.01 deg (the packets' unit): its ``azimuth`` (else
    atan2(x, y)) minus its channel's azimuth offset."""
    names = rec.dtype.names
    az = (np.degrees(rec["azimuth"].astype(np.float64)) if "azimuth" in names
          else np.degrees(np.arctan2(rec["x"].astype(np.float64), rec["y"].astype(np.float64))))
    return np.rint((az - angles.azimuth_deg[channel]) * 100.0).astype(np.int64) % 36000


def _check_angles(rec: np.ndarray, channel: np.ndarray, angles: HesaiAngles, name: str) -> None:
    """Refuse a cloud nebula wrote with other angle corrections than ``angles`` (its elevation
    field, and its azimuths less the offsets, which fall on the packets' 0.01 deg, say so):
    its firings and rays would be read wrong."""
    if "elevation" in rec.dtype.names:
        off = np.abs(np.degrees(rec["elevation"].astype(np.float64))
                     - angles.elevation_deg[channel])
        if off.max() > 0.01:
            raise HesaiError(f"{name}: the cloud's elevations differ from {angles.source}'s by up "
                             f"to {off.max():.3f} deg: it was written with another angle-"
                             "correction file; give that one (--angles)")
    if "azimuth" in rec.dtype.names:
        az = (np.degrees(rec["azimuth"].astype(np.float64)) - angles.azimuth_deg[channel]) * 100
        if np.abs(az - np.rint(az)).max() > 0.05:
            raise HesaiError(f"{name}: the cloud's azimuths less {angles.source}'s offsets are "
                             "not the packets' 0.01 deg steps: it was written with another "
                             "angle-correction file; give that one (--angles)")


def _distance(rec: np.ndarray) -> np.ndarray:
    if "distance" in rec.dtype.names:
        return rec["distance"].astype(np.float64)
    return np.sqrt(sum(rec[k].astype(np.float64) ** 2 for k in ("x", "y", "z")))


def _sweep(block_cdeg: np.ndarray, order_key: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The firings' block azimuths unwrapped along the sweep (from the earliest point's), and
    each point's firing among them."""
    first = int(block_cdeg[np.argmin(order_key)])
    rel = (block_cdeg - first) % 36000  # the earliest point's firing is the sweep's first
    firing_az, inverse = np.unique(rel, return_inverse=True)
    firing_az = firing_az + first
    return firing_az, inverse


def _grid(firing_az: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    """The rebuilt grid's azimuths (0.01 deg, unwrapped) and each found firing's index on it:
    a gap of k steps holds k - 1 firings where every channel missed, put back between."""
    k = np.maximum(np.rint(np.diff(firing_az) / step).astype(np.int64), 1)
    index = np.concatenate(([0], np.cumsum(k)))
    grid = np.interp(np.arange(index[-1] + 1), index, firing_az)
    return np.rint(grid).astype(np.int64), index


def _loops(found_firing: np.ndarray, channel: np.ndarray, n_grid: int) -> np.ndarray:
    """Each grid firing's loop (0: loop 1, 1: loop 2) of a QT128: the loops alternate, and a
    firing with a return of channels 1-32 (0-based 0-31) is loop 2's, of channels 33-64 loop
    1's (the other loop leaves them dark, `twin.lidar.hesai.QT128_FIRED`)."""
    told = np.where(channel < 32, 1, np.where(channel < 64, 0, -1))
    sel = told >= 0
    if not sel.any():
        raise HesaiError("no return of channels 1-64: the firing loops cannot be told")
    phase = int(np.argmax(np.bincount((told[sel] + found_firing[sel]) % 2, minlength=2)))
    return (phase + np.arange(n_grid)) % 2


#: Two points of one packet give its time within this, s: nebula's ns are integers and
#: Hesai's ROS driver writes one double a packet; a packet's firings are 111 us apart.
_PACKET_TIME_TOLERANCE = 1e-7


def _spread_by_packet(point_grid: np.ndarray, phase: int, t: np.ndarray) -> float:
    """The largest spread of the packet times ``t`` (s) the points of one packet give, when
    grid firing g is loop (phase + g) % 2 and so packet (g + phase) // 2's block g % 2."""
    _, packet = np.unique((point_grid + phase) // 2, return_inverse=True)
    hi = np.full(packet.max() + 1, -np.inf)
    lo = np.full(packet.max() + 1, np.inf)
    np.maximum.at(hi, packet, t)
    np.minimum.at(lo, packet, t)
    return float((hi - lo).max())


def _phase_by_time(point_grid: np.ndarray, packet_time, name: str) -> int | None:
    """A single-return QT128's phase of loops (grid firing g is loop (phase + g) % 2) from the
    points' times: ``packet_time(loop)`` gives each point's packet time (s) were its firing of
    that loop; only the right phase puts one time on all the points of each packet (its two
    firings, block 0 loop 1 and block 1 loop 2). None when both do (no packet holds points
    of both its firings: not told)."""
    fits = [_spread_by_packet(point_grid, phase, packet_time((phase + point_grid) % 2))
            <= _PACKET_TIME_TOLERANCE for phase in (0, 1)]
    if not any(fits):
        raise HesaiError(f"{name}: the time stamps put each firing in a packet of its own, not "
                         "two firings a packet: not a single-return PandarQT128 cloud (one echo "
                         "of each dual-return pair kept?)")
    return None if all(fits) else fits.index(True)


def _single_loops(point_grid: np.ndarray, channel: np.ndarray, n_grid: int, packet_time,
                  name: str) -> tuple[np.ndarray, str]:
    """Each grid firing's loop of a single-return QT128: from the time stamps where they tell
    it (`_phase_by_time`), else from the channels only one loop fires (`_loops`); a return on
    a channel its firing's loop leaves dark is refused (the loops, or the grid, read wrong).
    Also what told them: ``time stamps`` or ``channels``."""
    phase = None if packet_time is None else _phase_by_time(point_grid, packet_time, name)
    loop = (_loops(point_grid, channel, n_grid) if phase is None
            else (phase + np.arange(n_grid)) % 2)
    dark = ~QT128_FIRED[loop[point_grid], channel]
    if dark.any():
        raise HesaiError(f"{name}: {int(dark.sum())} returns on channels their firing's loop "
                         "leaves dark: the firing loops cannot be told")
    return loop, ("channels" if phase is None else "time stamps")


def head_rpm(t_firing: np.ndarray | None, point_az: np.ndarray, step: float, model) -> float:
    """The head's speed: the slope of the block azimuth against each point's firing time
    (nebula's time_stamp less its unit's offset), else the grid's step at the model's firing
    period."""
    if t_firing is not None and len(np.unique(point_az)) > 2:
        slope = np.polyfit(t_firing, point_az / 100.0, 1)[0]  # deg/s
        return float(slope / 6.0)
    return float(step / 100.0 / model.firing_period / 6.0)


def _grid_payloads(grid: np.ndarray, step: float, dist: np.ndarray, refl: np.ndarray,
                   loop: np.ndarray | None, rpm: float, dual: bool, model, lead: int = 1
                   ) -> list[bytes]:
    """Packets of the rebuilt grid with ``lead`` firings of misses before it and one after it
    (the packet path cuts exactly there) and padded with misses to whole packets; ``dist``,
    ``refl`` (lead + grid + 1, returns, channels) already so placed; ``loop`` each row's
    (QT128: in single return a packet's first row must be loop 1, hence a second lead row)."""
    nr = 2 if dual else 1
    per_packet = model.n_blocks // nr
    packets = -(-len(dist) // per_packet)
    pad = packets * per_packet - len(dist)
    az = np.concatenate((grid[0] - round(step) * np.arange(lead, 0, -1), grid,
                         grid[0] + round(step) * np.arange(pad + 1)))
    dist = np.concatenate((dist, np.zeros((pad, *dist.shape[1:]))))
    refl = np.concatenate((refl, np.zeros((pad, *refl.shape[1:]), dtype=np.uint8)))
    shape = (packets, model.n_blocks)
    block_az = np.repeat(az % 36000, nr).reshape(shape)
    args = (block_az, dist.reshape(*shape, -1), refl.reshape(*shape, -1),
            np.arange(packets) * round(per_packet * model.firing_period * 1e6))
    mode = LAST_AND_STRONGEST if dual else 0x37
    if model is XT32:
        return encode_xt32(*args, rpm=rpm, return_mode=mode)
    loop = np.concatenate((loop, (loop[-1] + 1 + np.arange(pad)) % 2))
    # a packet's loop: its first row's (dual: its only firing; single: loop 1 by the placing)
    return encode_qt128(*args, loop.reshape(packets, per_packet)[:, 0], rpm=rpm,
                        return_mode=mode)


def scan_from_nebula_hesai(rec: np.ndarray, angles: HesaiAngles, *, rpm: float | None = None,
                           index: int = 0, name: str = "nebula cloud") -> Scan:
    """The packet path's scan (`twin.lidar.hesai.scans_from_hesai`, firetime in) of one nebula
    PandarXT32 or PandarQT128 (single or dual return) cloud (a record array with nebula's
    fields; x y z and channel at least): module docstring. ``rpm``: the head's speed (None:
    from the time stamps, else the grid's step)."""
    model = angles.model
    names = rec.dtype.names or ()
    if "channel" not in names:
        raise HesaiError(f"{name}: no channel field: not nebula's Hesai cloud")
    nc = model.n_channels
    channel = rec["channel"].astype(np.int64)
    if len(rec) < 2 * nc or channel.max() >= nc:
        raise HesaiError(f"{name}: {len(rec)} points of channels up to {channel.max()}: not a "
                         f"{model.name}'s rotation")
    _check_angles(rec, channel, angles, name)
    rtype = rec["return_type"] if "return_type" in names else np.zeros(len(rec), np.uint8)
    dual = bool(np.isin(rtype, _DUAL_ONLY).any())
    nr = 2 if dual else 1
    # a single-return QT128's block is its loop (block 0 loop 1): its offset follows the loop
    single_qt = model is QT128 and not dual
    slot = np.isin(rtype, _SECOND_BLOCK).astype(np.intp) if dual else np.zeros(len(rec), np.intp)
    block = _block_azimuth_cdeg(rec, channel, angles)
    # nebula stamps a single-return QT128's block 0 (loop 1) 111.11 us after its block 1
    # (pandar_qt128.hpp: 9000 + 111110 (2 - block - 1) ns), so its stamps do not order a
    # packet's two firings: its order does (it writes firing by firing)
    order_key = (rec["time_stamp"].astype(np.float64) if "time_stamp" in names
                 and not single_qt else np.arange(len(rec), dtype=np.float64))

    def rpm_of(point_grid: np.ndarray, loop: np.ndarray | None, point_az: np.ndarray,
               step: float) -> float:
        if rpm is not None:
            return rpm
        t = None
        if "time_stamp" in names:  # the firing's time: the unit's offset in it taken off
            # (an XT32's block offset is its firing's time within the packet: kept)
            lp = None if loop is None else loop[point_grid]
            if single_qt:  # the packet's time, then its block's firing within it
                return head_rpm(_packet_time_s(rec, channel, lp) + lp * model.firing_period,
                                point_az, step, model)
            blk = (np.zeros(len(rec), np.int64) if model is XT32 else slot)[:, None]
            off = _offset_ns(model, blk, None if lp is None else lp[:, None], nr)
            off = off[np.arange(len(rec)), 0, channel]
            t = (rec["time_stamp"].astype(np.float64) - off) * 1e-9
        return head_rpm(t, point_az, step, model)

    packet_time = None
    if single_qt and "time_stamp" in names:
        def packet_time(lp: np.ndarray) -> np.ndarray:
            return _packet_time_s(rec, channel, lp)

    return scan_of_points(
        CloudPoints(block, order_key, channel, slot, _distance(rec),
                    rec["intensity"] if "intensity" in names else 0, dual, len(rec),
                    packet_time),
        angles, rpm_of, index=index, name=name, convention="nebula")


def _packet_time_s(rec: np.ndarray, channel: np.ndarray, loop: np.ndarray) -> np.ndarray:
    """Each point of a single-return QT128 cloud's packet time (s, from the cloud's stamp):
    its ``time_stamp`` less nebula's offset were its firing of ``loop`` (block = loop). A
    stamp is read as a signed 32-bit ns: a scan begun on a block 0 is stamped at that block's
    earliest point, 111 us after its block 1's (on_set_timestamp), whose points nebula's
    uint32 arithmetic (get_point_time_relative) so wraps to near 2^32."""
    # _qt128_offset_ns point by point: 9000 + 111110 (2 - block - 1) + the loop table's
    off = 9000 + 111110 * (1 - loop) + np.rint(QT128_LOOP_TIME[loop, channel] * 1e9)
    stamp = rec["time_stamp"].astype(np.uint32).view(np.int32).astype(np.float64)
    return (stamp - off) * 1e-9


@dataclass(frozen=True)
class CloudPoints:
    """A driver's cloud of one rotation as the firing grid's rebuild needs it, point by point:
    the block azimuth (0.01 deg, the packets' unit), a key ordering the points in time, the
    channel (0-based), the block of a dual-return pair (0: last, 1: strongest; 0 in single
    return), the range (m) and the reflectivity; ``dual``: the cloud is of dual return;
    ``n_cloud``: the cloud's points (misses included when the driver writes them);
    ``packet_time``: of a single-return QT128 with time stamps, each point's packet time (s)
    given each point's firing loop (0: loop 1), which tells the loops (`_phase_by_time`)."""

    block_cdeg: np.ndarray
    order_key: np.ndarray
    channel: np.ndarray
    slot: np.ndarray
    distance: np.ndarray
    intensity: np.ndarray | int
    dual: bool
    n_cloud: int
    packet_time: Callable[[np.ndarray], np.ndarray] | None = None


def scan_of_points(p: CloudPoints, angles: HesaiAngles, rpm_of, *, index: int = 0,
                   name: str = "cloud", convention: str = "nebula") -> Scan:
    """The packet path's scan of a Hesai driver's cloud (``p``, its returns): the firing grid
    rebuilt from the points' block azimuths (the firings where every channel missed put back),
    written as packets with the misses put back and read as the packet path reads them
    (module docstring). ``rpm_of(point_grid, loop, point_az, step)``: the head's speed (rpm)
    the packets are written with, from each point's grid firing, the grid's loops (QT128, else
    None), each point's firing azimuth (0.01 deg, unwrapped) and the grid's step."""
    model = angles.model
    nc = model.n_channels
    dual = p.dual
    nr = 2 if dual else 1
    channel, slot = p.channel, p.slot
    firing_az, point_firing = _sweep(p.block_cdeg, p.order_key)
    if len(firing_az) < 3:
        raise HesaiError(f"{name}: {len(firing_az)} firings: not a rotation")
    step = float(np.median(np.diff(firing_az)))
    grid, found = _grid(firing_az, step)
    if grid[-1] - grid[0] < 18000:
        raise HesaiError(f"{name}: the cloud spans {(grid[-1] - grid[0]) / 100:.1f} deg: less "
                         "than half a turn, not a rotation")
    point_grid = found[point_firing]
    single_qt = model is QT128 and not dual
    told = {}
    if model is XT32:
        loop = None
    elif single_qt:
        loop, told["loops_from"] = _single_loops(point_grid, channel, len(grid), p.packet_time,
                                                 name)
    else:
        loop = _loops(point_grid, channel, len(grid))
    rpm = rpm_of(point_grid, loop, firing_az[point_firing], step)
    # rows of misses before the grid: one, and in single return a second when the grid starts
    # on loop 1, so that every packet's block 0 is loop 1 as the unit writes it
    lead = 2 if single_qt and loop[0] == 0 else 1
    dist = np.zeros((len(grid) + 1 + lead, nr, nc))
    refl = np.zeros((len(grid) + 1 + lead, nr, nc), dtype=np.uint8)
    where = (lead + point_grid, slot, channel)
    dist[where] = p.distance
    refl[where] = p.intensity
    if dual:  # a first block nebula dropped (identical, within the threshold): as the second
        gone = (dist[:, 0] == 0) & (dist[:, 1] > 0)
        dist[:, 0][gone], refl[:, 0][gone] = dist[:, 1][gone], refl[:, 1][gone]
    rows_loop = None if loop is None else np.concatenate(
        ((loop[0] - lead + np.arange(lead)) % 2, loop, [1 - loop[-1]]))
    payloads = _grid_payloads(grid, step, dist, refl, rows_loop, rpm, dual, model, lead)
    scans = scans_from_hesai(decode_hesai(payloads, angles), angles, cut_cdeg=int(grid[0] % 36000))
    if len(scans) != 1:
        raise HesaiError(f"{name}: the rebuilt grid gave {len(scans)} rotations, not one")
    s = scans[0]
    meta = {**s.meta, "from_cloud": True, "cloud_convention": convention,
            "cloud_points": p.n_cloud, "rpm": rpm, "source": name, **told}
    return Scan(**{k: getattr(s, k) for k in ("distance", "azimuth", "laser_id", "intensity",
                                              "time", "return_type", "x", "y", "z")},
                index=index, complete=True, packets=0, product_id=0,
                vertical_offsets_applied=False, lasers=s.lasers, meta=meta)


# ----------------------------------------------------------------------------------------------
# As a source: `aimbench info / estimate CLOUD --model PandarXT32` (or PandarQT128)


def hesai_model_of_cloud(rec: np.ndarray) -> str | None:
    """The Hesai model a nebula cloud is of, told by its fields (nebula's PointXYZIRCAEDT, which
    its Velodyne clouds share), its channel count and its channels' elevations against the
    model's nominal angles (within 0.5 deg); None when they do not tell a Hesai."""
    from twin.lidar.hesai import default_angles

    names = rec.dtype.names or ()
    if not is_nebula_hesai(names) or len(rec) == 0:
        return None
    channel = rec["channel"].astype(np.int64)
    el = np.degrees(rec["elevation"].astype(np.float64))
    for model in HESAI_MODELS.values():
        if channel.max() >= model.n_channels:
            continue
        nominal = HesaiAngles.from_csv(default_angles(model), model)
        if np.abs(el - nominal.elevation_deg[channel]).max() < 0.5:
            return model.name
    return None


class HesaiCloudScanSource(ScanSource):
    """Scans of nebula's Hesai clouds (a PCD file, or a bag's PointCloud2 messages): one a
    cloud, rebuilt by `scan_from_nebula_hesai`. ``told``: how the model was told (``option``:
    --model, ``fields``: the cloud's fields and elevations)."""

    def __init__(self, name, clouds, angles: HesaiAngles, *, max_scans: int | None = None,
                 extra: dict | None = None, closer=None, told: str = "option") -> None:
        super().__init__(name, max_scans, extra, closer)
        self.clouds = clouds  # (name, record array) pairs
        self.angles = angles
        self.told = told
        self._scans_made: list[Scan] = []

    def _scans(self):
        for i, (name, rec) in enumerate(self.clouds):
            scan = scan_from_nebula_hesai(rec, self.angles, index=i, name=name)
            self._scans_made.append(scan)
            yield scan

    def _summary(self) -> dict:
        s = self._scans_made
        returns = sum(int(x.valid.sum()) for x in s)
        return {
            "model": self.angles.model.name,
            "model_from": ("given by --model" if self.told == "option"
                           else "from nebula's fields and the channels' elevations"),
            "laser_table": self.angles.source,
            "rpm": float(np.median([x.meta["rpm"] for x in s])) if s else None,
            "rpm_from": "from the clouds' time stamps, else the firings' azimuth step",
            "clouds": len(s), "scans": len(s), "complete_scans": len(s), "partial_scans": 0,
            "cloud_points": sum(int(x.meta["cloud_points"]) for x in s),
            "points": sum(len(x) for x in s), "returns": returns,
            "rebuilt_misses": sum(len(x) for x in s) - returns,
            "vertical_offsets": False,
            "cloud_convention": "nebula (Hesai: firing rotation put back)",
            "cloud_convention_from": "fields",
            "warnings": [],
        }
