"""Velodyne packet format: data packets (port 2368) and position packets (port 8308).

The VLP-16, Puck Hi-Res, VLP-32C and HDL-32E share this layout; what differs between them (laser
table, firing timing, distance unit) is their `twin.core.sensors.SensorModel`, which decoding
takes from the product id (or an override) and every decoded batch carries.

Bytes in, arrays out (and back): nothing here touches a socket or a file. Decoding is vectorised
over many packets at once: a batch of payloads is viewed as a NumPy structured array
(`DATA_PACKET_DTYPE`, 1206 bytes per record) and every firing of every packet is computed in a
handful of array operations, with no per-point Python loop.

Layout of a data packet (VLP-16 user manual 63-9243 Rev. E, section 9.3), little-endian::

    12 blocks x 100 bytes: flag 0xFF 0xEE, uint16 azimuth (0.01 deg),
                           32 x (uint16 distance (2 mm), uint8 reflectivity)
    uint32 timestamp (us past the hour), uint8 return mode, uint8 product id

Firings of a block: for the 16-laser models channels 0..15 are the first firing sequence of
lasers 0..15, channels 16..31 the second; for the 32-laser models channel c is laser c.
Firing order in the arrays returned here: (packet, block, channel), i.e.
384 firings per packet in the order they appear in the bytes.

Units: SI in the arrays (m, rad, s); raw counts (2 mm, 0.01 deg, us) only where the name says so.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from twin.core import vlp16
from twin.core.errors import AimbenchError
from twin.core.lasers import LaserTable
from twin.core.scan import ReturnType
from twin.core.sensors import (
    HDL32E,
    MODELS,
    PRODUCT_NAMES,
    VLP16,
    SensorModel,
    model_named,
    model_of_product_id,
)

# --------------------------------------------------------------------------------------------
# Errors and warnings


class MalformedPacketError(AimbenchError):
    """A payload is not a valid VLP-16 packet (wrong size, bad block flag, bad factory bytes)."""


class UnsupportedSensorError(AimbenchError):
    """The packets come from a sensor aimbench does not decode (VLS-128, Velarray, ...)."""


class ProductIdWarning(UserWarning):
    """Product id 0x21 on data whose model had to be inferred (old VLP-16 firmware sends it)."""


# --------------------------------------------------------------------------------------------
# Layout

FIRINGS_PER_BLOCK = 32
FIRINGS_PER_PACKET = vlp16.BLOCKS_PER_PACKET * FIRINGS_PER_BLOCK
#: The block flag 0xFF 0xEE read as a little-endian uint16.
BLOCK_FLAG_U16 = int.from_bytes(vlp16.BLOCK_FLAG, "little")
AZIMUTH_COUNTS = 36000  # 0.01 deg counts per turn
US_PER_HOUR = 3_600_000_000

CHANNEL_DTYPE = np.dtype([("distance", "<u2"), ("reflectivity", "u1")])
BLOCK_DTYPE = np.dtype(
    [("flag", "<u2"), ("azimuth", "<u2"), ("channels", CHANNEL_DTYPE, (FIRINGS_PER_BLOCK,))]
)
DATA_PACKET_DTYPE = np.dtype(
    [
        ("blocks", BLOCK_DTYPE, (vlp16.BLOCKS_PER_PACKET,)),
        ("timestamp", "<u4"),
        ("return_mode", "u1"),
        ("product_id", "u1"),
    ]
)
assert DATA_PACKET_DTYPE.itemsize == vlp16.DATA_PAYLOAD_SIZE

RETURN_MODES = {
    vlp16.RETURN_MODE_STRONGEST: "strongest",
    vlp16.RETURN_MODE_LAST: "last",
    vlp16.RETURN_MODE_DUAL: "dual",
}

#: Time between the first firings of consecutive VLP-16 blocks in single-return mode, s.
BLOCK_PERIOD = VLP16.block_period


def packet_period(return_mode: int, sensor: SensorModel = VLP16) -> float:
    """Time between consecutive data packets, s (VLP-16: 1.327 ms; half in dual-return mode)."""
    return sensor.packet_period(return_mode)


def firing_time_offsets(return_mode: int, sensor: SensorModel = VLP16) -> np.ndarray:
    """Time of each firing after the packet's timestamp, shape (12, 32), s (VLP-16 manual 9.5,
    VLP-32C manual figures 9-7/9-8, HDL-32E manual "laser timing").

    In dual-return mode blocks come in pairs holding two echoes of the same firings, so block
    ``b`` fires at the time of block ``b // 2`` of a single-return packet.
    """
    return sensor.firing_time_offsets(return_mode)


#: The VLP-16's firing times within a block, (32,) s.
WITHIN_BLOCK_OFFSETS = VLP16.channel_offsets()


@dataclass(frozen=True, eq=False)
class _Channels:
    """A model's per-channel constants (32,) for the decoder, and per-mode firing times."""

    laser: np.ndarray
    within: np.ndarray  # s after the block's first firing
    azimuth_offset: np.ndarray  # rad
    sin_el: np.ndarray
    cos_el: np.ndarray
    vertical: np.ndarray  # m
    horizontal: np.ndarray  # m
    offsets: dict[int, np.ndarray]  # return mode -> (12, 32) s after the timestamp


_CHANNEL_CACHE: dict[int, tuple[SensorModel, _Channels]] = {}


def _channels(sensor: SensorModel) -> _Channels:
    hit = _CHANNEL_CACHE.get(id(sensor))
    if hit is not None and hit[0] is sensor:
        return hit[1]
    lasers, lid = sensor.lasers, sensor.laser_of_channel
    ch = _Channels(
        laser=lid, within=sensor.channel_offsets(), azimuth_offset=lasers.azimuth_offset[lid],
        sin_el=np.sin(lasers.elevation)[lid], cos_el=np.cos(lasers.elevation)[lid],
        vertical=lasers.vertical_offset[lid], horizontal=lasers.horizontal_offset[lid],
        offsets={mode: sensor.firing_time_offsets(mode) for mode in RETURN_MODES})
    if len(_CHANNEL_CACHE) > 64:
        _CHANNEL_CACHE.clear()
    _CHANNEL_CACHE[id(sensor)] = (sensor, ch)
    return ch


# --------------------------------------------------------------------------------------------
# Turning input into a structured array


def as_packet_records(
    payloads: np.ndarray | bytes | bytearray | memoryview | Sequence[bytes],
) -> tuple[np.ndarray, np.ndarray, int]:
    """View payloads as `DATA_PACKET_DTYPE` records without decoding them.

    Accepts an (n, 1206) or (1206,) uint8 array, one bytes-like payload, or a sequence of them.
    Returns ``(records, index, wrong_size)``: the records of the payloads that are 1206 bytes
    long, their positions in the input, and how many payloads had another size.
    """
    if isinstance(payloads, np.ndarray):
        arr = np.ascontiguousarray(payloads, dtype=np.uint8)
        if arr.ndim == 1:
            arr = arr[None, :]
        if arr.ndim != 2 or arr.shape[1] != vlp16.DATA_PAYLOAD_SIZE:
            raise MalformedPacketError(
                f"payload array has shape {payloads.shape}; a VLP-16 data packet is "
                f"{vlp16.DATA_PAYLOAD_SIZE} bytes: pass an (n, 1206) uint8 array"
            )
        return arr.view(DATA_PACKET_DTYPE)[:, 0], np.arange(len(arr)), 0
    if isinstance(payloads, bytes | bytearray | memoryview):
        payloads = [bytes(payloads)]
    sizes = np.fromiter((len(p) for p in payloads), dtype=np.int64, count=len(payloads))
    good = np.flatnonzero(sizes == vlp16.DATA_PAYLOAD_SIZE)
    if len(good) == len(payloads):
        joined = b"".join(payloads)
    else:
        joined = b"".join(payloads[i] for i in good)
    records = np.frombuffer(joined, dtype=DATA_PACKET_DTYPE)
    return records, good, int(len(payloads) - len(good))


# --------------------------------------------------------------------------------------------
# Model identification


def resolve_model(model: str | SensorModel | None) -> SensorModel | None:
    """A model override as the caller gives it (a name or a `SensorModel`), checked."""
    if model is None or isinstance(model, SensorModel):
        return model
    try:
        return model_named(model)
    except KeyError:
        raise UnsupportedSensorError(
            f"model override {model!r} is not supported: aimbench decodes "
            f"{', '.join(MODELS)} (pass one of these, or leave the model unset)") from None


def identify_model(
    product_ids: np.ndarray,
    timestamps_us: np.ndarray,
    return_modes: np.ndarray,
    model: str | SensorModel | None = None,
    distances: np.ndarray | None = None,
) -> tuple[int, SensorModel]:
    """Decide which sensor a batch of packets comes from; refuse the ones aimbench does not know.

    ``product_ids``, ``timestamps_us`` and ``return_modes`` are per-packet arrays of the batch,
    ``distances`` (n, 12, 32) the packets' raw distances (for the block-layout test below).
    ``model`` (a name or a `SensorModel`) is the override: the caller vouches for the sensor,
    whatever the factory byte says. Without it the product id decides (0x22 VLP-16, 0x24 Puck
    Hi-Res, 0x28 VLP-32C, 0x21 HDL-32E), but for 0x21: older VLP-16 firmware sends it too. The
    two differ in structure, and `_sixteen_laser_structure` tells them apart, by the timestamp
    step (HDL-32E packets 0.553 ms apart, VLP-16 1.327 ms) or, from a single packet, by the
    block layout (a VLP-16 block's channels c and c + 16 are one laser fired twice, an
    HDL-32E's are two lasers 10 deg apart). 0x21 decoded as a VLP-16 issues a
    `ProductIdWarning`; so does 0x21 with nothing to tell (then decoded as an HDL-32E).
    Anything else (0xA1 VLS-128, ...) raises `UnsupportedSensorError`.

    Returns the product id the batch is decoded as (its most common one; packets with another
    id are then dropped as malformed) and the model.
    """
    override = resolve_model(model)
    if len(product_ids) == 0:
        return (override or VLP16).product_id, override or VLP16
    # The most common id, so that one corrupted byte cannot decide for the batch.
    pid = int(np.argmax(np.bincount(np.asarray(product_ids, dtype=np.uint8), minlength=256)))
    if override is not None:
        return pid, override
    sensor = model_of_product_id(pid)
    if sensor is None:
        name = PRODUCT_NAMES.get(pid, f"unknown product id 0x{pid:02x}")
        raise UnsupportedSensorError(
            f"the packets come from a {name} (product id 0x{pid:02x}): aimbench decodes "
            f"{', '.join(MODELS)} (if this really is one of them, pass --model NAME)")
    if pid != vlp16.PRODUCT_ID_VLP16_OLD_FIRMWARE:
        return pid, sensor
    sixteen = _sixteen_laser_structure(timestamps_us, return_modes, distances)
    if sixteen:
        warnings.warn(
            "product id 0x21 (HDL-32E) on data with VLP-16 structure: older VLP-16 firmware "
            "sends it; decoding as VLP-16 (pass model='VLP-16' or --model VLP-16 to silence this)",
            ProductIdWarning, stacklevel=3)
        return pid, VLP16
    if sixteen is None:
        warnings.warn(
            "product id 0x21 on too little data to tell an HDL-32E from an old VLP-16; decoding "
            "as HDL-32E (pass --model to say which)", ProductIdWarning, stacklevel=3)
    return pid, HDL32E


def _sixteen_laser_structure(
    timestamps_us: np.ndarray, return_modes: np.ndarray, distances: np.ndarray | None,
) -> bool | None:
    """True if 0x21 packets are a VLP-16's, False if an HDL-32E's, None if nothing tells."""
    if len(timestamps_us) >= 2:
        step_us = np.diff(timestamps_us.astype(np.int64)) % US_PER_HOUR
        step_us = step_us[(step_us > 0) & (step_us < 5_000)]  # ignore gaps and reordering
        if len(step_us):
            dual = int(np.median(return_modes)) == vlp16.RETURN_MODE_DUAL
            mode = vlp16.RETURN_MODE_DUAL if dual else vlp16.RETURN_MODE_STRONGEST
            step = float(np.median(step_us)) * 1e-6
            # Closer (in ratio) to the VLP-16's packet period than to the HDL-32E's.
            return bool(abs(np.log(step / VLP16.packet_period(mode)))
                        < abs(np.log(step / HDL32E.packet_period(mode))))
    if distances is None:
        return None
    # Block layout: ranges of channel c against channel c + 16 of the same block (VLP-16: one
    # laser, one sequence apart) and against channel c of the next block (both models: the
    # same laser, one block later). Needs a few channels with returns in all three.
    d = distances.astype(np.float64)
    a, b, nxt = d[:, :-1, :16], d[:, :-1, 16:], d[:, 1:, :16]
    ok = (a > 0) & (b > 0) & (nxt > 0)
    if ok.sum() < 20:
        return None
    within = np.median(np.abs(np.log(a[ok] / b[ok])))
    across = np.median(np.abs(np.log(a[ok] / nxt[ok])))
    return bool(within <= 2.0 * across)


# --------------------------------------------------------------------------------------------
# Validation


def validate_records(records: np.ndarray) -> dict[str, np.ndarray]:
    """Per-packet masks of what is wrong with each record (True = that fault is present)."""
    blocks = records["blocks"]
    return {
        "block_flag": (blocks["flag"] != BLOCK_FLAG_U16).any(axis=1),
        "azimuth": (blocks["azimuth"] >= AZIMUTH_COUNTS).any(axis=1),
        "return_mode": (records["return_mode"] < 0x37) | (records["return_mode"] > 0x39),
    }


# --------------------------------------------------------------------------------------------
# Decoding


@dataclass(frozen=True, eq=False)
class DecodedPackets:
    """Decoded data packets: per-packet arrays (n,) and per-firing arrays (n, 384).

    Firing arrays are in byte order (block, channel). Units: distance m (0 = no return),
    azimuth rad in [0, 2 pi), time s (packet timestamp, us past the hour, / 1e6 + firing offset),
    x, y, z m in the LiDAR frame {L} (0 where there is no return).

    ``rejected`` counts the payloads that were dropped, by reason: ``size`` (not 1206 bytes),
    ``block_flag``, ``azimuth`` (>= 360 deg), ``return_mode`` (not 0x37/0x38/0x39),
    ``product_id`` (differs from the batch's sensor). ``index`` gives each kept packet's position
    in the input.
    """

    index: np.ndarray
    timestamp_us: np.ndarray
    return_mode: np.ndarray
    product_id: np.ndarray
    block_azimuth_cdeg: np.ndarray
    azimuth_rate: np.ndarray
    distance: np.ndarray
    azimuth: np.ndarray
    laser_id: np.ndarray
    intensity: np.ndarray
    time: np.ndarray
    return_type: np.ndarray
    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    vertical_offsets_applied: bool = True
    rejected: dict[str, int] = field(default_factory=dict)
    sensor: SensorModel = VLP16

    def __len__(self) -> int:
        return len(self.timestamp_us)

    @property
    def n_rejected(self) -> int:
        return sum(self.rejected.values())

    @property
    def ring(self) -> np.ndarray:
        """Elevation-ordered ring of each firing (0 = lowest beam)."""
        return self.sensor.lasers.ring_of_laser[self.laser_id]

    @property
    def rpm(self) -> np.ndarray:
        """Rotation speed measured from each packet's block azimuths, rev/min."""
        return self.azimuth_rate * 60.0 / (2.0 * np.pi)


def decode_data_packets(
    payloads: np.ndarray | bytes | Sequence[bytes],
    vertical_offsets: bool = True,
    *,
    model: str | SensorModel | None = None,
    lasers: LaserTable | None = None,
    strict: bool = False,
) -> DecodedPackets:
    """Decode data packets of a VLP-16, Puck Hi-Res, VLP-32C or HDL-32E, all at once, into
    per-firing arrays.

    ``payloads``: an (n, 1206) uint8 array, one payload, or a sequence of payloads.
    ``vertical_offsets``: add each laser's vertical offset (manual table 9-1) to z; the manual's
    model and the default (velodyne_decoder 3.x applies them too, with its built-in
    calibration; the VLP-16.yml file it ships leaves them out).
    ``model``: a model's name (``"VLP-32C"``...) or `SensorModel` forces that model whatever
    the product id (see `identify_model`). ``lasers``: a unit's own laser table (its
    calibration file, `twin.lidar.calibration_file`) instead of the model's.
    ``strict``: raise `MalformedPacketError` on the first bad payload instead of dropping and
    counting it in ``rejected``.

    Every firing is kept, including no-returns (distance 0). Azimuth of each firing: the block's
    azimuth plus the rotation rate times the firing's time within the block (manual 9.5,
    "precision azimuth"). The rate is the packet's mean block-to-block step (last block minus
    first, modulo 360 deg, over the time between them), which handles the 359.99 -> 0 wrap, the
    second firing sequence and the packet's last block alike, and averages out the 0.01 deg
    quantisation that a single block-to-block gap carries.
    """
    records, index, wrong_size = as_packet_records(payloads)
    rejected = {"size": wrong_size}
    if strict and wrong_size:
        raise MalformedPacketError(
            f"{wrong_size} payload(s) are not {vlp16.DATA_PAYLOAD_SIZE} bytes long: not VLP-16 "
            "data packets (check the port: position packets are 512 bytes on port 8308)"
        )
    faults = validate_records(records)
    bad = np.zeros(len(records), dtype=bool)
    for reason, mask in faults.items():
        mask = mask & ~bad  # count each payload once, under its first fault
        rejected[reason] = int(mask.sum())
        bad |= mask
    if strict and bad.any():
        first = int(np.argmax(bad))
        reason = next(r for r, m in faults.items() if m[first])
        raise MalformedPacketError(_describe_fault(reason, records[first], int(index[first])))
    if bad.any():  # a copy of the records only when there is something to drop
        records, index = records[~bad], index[~bad]

    pid, sensor = identify_model(records["product_id"], records["timestamp"],
                                 records["return_mode"], model,
                                 records["blocks"]["channels"]["distance"])
    if lasers is not None:
        sensor = sensor.with_lasers(lasers)
    other = records["product_id"] != pid
    rejected["product_id"] = int(other.sum())
    if strict and other.any():
        raise MalformedPacketError(
            f"packet {int(index[np.argmax(other)])} has product id "
            f"0x{int(records['product_id'][np.argmax(other)]):02x}, the batch's sensor 0x{pid:02x}:"
            " a corrupted packet or two sensors on one port (give each sensor its own port)"
        )
    if other.any():
        records, index = records[~other], index[~other]
    return decode_records(records, index, vertical_offsets, rejected, sensor)


def _describe_fault(reason: str, record: np.void, position: int) -> str:
    what = {
        "block_flag": "a block does not start with the flag 0xFF 0xEE",
        "azimuth": "a block azimuth is 360 deg or more",
        "return_mode": f"its return mode byte is 0x{int(record['return_mode']):02x}, "
        "not 0x37/0x38/0x39",
    }[reason]
    return (
        f"payload {position} is not a valid VLP-16 data packet: {what} "
        "(a corrupted capture, or not a VLP-16 data stream)"
    )


#: Packets per inner step of the decoder: its temporaries stay in the CPU cache (~100 KB each).
_CHUNK = 128


def decode_records(
    records: np.ndarray, index: np.ndarray, vertical_offsets: bool, rejected: dict[str, int],
    sensor: SensorModel = VLP16,
) -> DecodedPackets:
    """Decode `DATA_PACKET_DTYPE` records that have been checked (`validate_records`), as
    ``sensor``'s packets.

    The vectorised core of `decode_data_packets`, for callers (the scan assembler) that
    validate and order packets themselves. ``index``/``rejected`` are passed through.
    """
    n = len(records)
    blocks = records["blocks"]
    channels = blocks["channels"]
    az_cdeg = blocks["azimuth"]  # (n, 12) uint16
    mode = records["return_mode"]
    dual = mode == vlp16.RETURN_MODE_DUAL
    ts_us = records["timestamp"]
    ch = _channels(sensor)

    # Rotation rate from the packet's first and last distinct block azimuths.
    last = np.where(dual, vlp16.BLOCKS_PER_PACKET - 2, vlp16.BLOCKS_PER_PACKET - 1)
    span_cdeg = (az_cdeg[np.arange(n), last].astype(np.int64) - az_cdeg[:, 0]) % AZIMUTH_COUNTS
    span_s = np.where(dual, last // 2, last) * sensor.block_period
    rate = span_cdeg * (np.pi / 18000.0) / span_s  # rad/s

    shape = (n, vlp16.BLOCKS_PER_PACKET, FIRINGS_PER_BLOCK)
    out = {name: np.empty(shape) for name in ("distance", "azimuth", "time", "x", "y", "z")}
    for lo in range(0, n, _CHUNK):
        sl = slice(lo, min(n, lo + _CHUNK))
        _decode_chunk(channels[sl], az_cdeg[sl], ts_us[sl], dual[sl], rate[sl],
                      vertical_offsets, {k: v[sl] for k, v in out.items()}, ch,
                      sensor.distance_unit)

    flat = (n, FIRINGS_PER_PACKET)
    return DecodedPackets(
        index=index,
        timestamp_us=ts_us.copy(),
        return_mode=mode.copy(),
        product_id=records["product_id"].copy(),
        block_azimuth_cdeg=az_cdeg.copy(),
        azimuth_rate=rate,
        laser_id=np.broadcast_to(np.tile(ch.laser, vlp16.BLOCKS_PER_PACKET), flat),
        intensity=channels["reflectivity"].reshape(flat).copy(),
        return_type=_return_types(channels, mode).reshape(flat),
        **{k: v.reshape(flat) for k, v in out.items()},
        vertical_offsets_applied=vertical_offsets,
        rejected=rejected,
        sensor=sensor,
    )


def _decode_chunk(
    channels: np.ndarray, az_cdeg: np.ndarray, ts_us: np.ndarray, dual: np.ndarray,
    rate: np.ndarray, vertical_offsets: bool, out: dict[str, np.ndarray], ch: _Channels,
    unit: float,
) -> None:
    """Fill ``out`` (views of the result arrays) for a few packets; ufuncs write in place."""
    distance, azimuth, time = out["distance"], out["azimuth"], out["time"]
    x, y, z = out["x"], out["y"], out["z"]
    # Firing times: a per-mode offset table (mixed-mode batches are rare but legal).
    offsets = ch.offsets[vlp16.RETURN_MODE_STRONGEST]
    if dual.any():
        offsets = np.where(dual[:, None, None], ch.offsets[vlp16.RETURN_MODE_DUAL], offsets)
    np.add((ts_us * 1e-6)[:, None, None], offsets, out=time)

    block_az = az_cdeg * (np.pi / 18000.0)  # (m, 12)
    # Rotation since the block azimuth, plus the beam's own azimuth offset (VLP-32C manual
    # 9.5: precise azimuth = block azimuth + rotation since the first firing + delta).
    delta = rate[:, None] * ch.within[None, :] + ch.azimuth_offset  # (m, 32)
    np.add(block_az[:, :, None], delta[:, None, :], out=azimuth)
    over = np.flatnonzero(((block_az + delta.max(axis=1)[:, None] >= 2 * np.pi)
                           | (block_az + delta.min(axis=1)[:, None] < 0)).any(axis=1))
    if len(over):  # only packets whose firings pass 359.99 -> 0 need the wrap
        a = azimuth[over]
        a = np.where(a >= 2 * np.pi, a - 2 * np.pi, a)
        azimuth[over] = np.where(a < 0, a + 2 * np.pi, a)

    np.multiply(channels["distance"], unit, out=distance)
    # cos a + i sin a of every firing as one complex product e^{iA} e^{i delta}: 12 + 32
    # transcendental calls per packet instead of 384, and one pass over the firings.
    # The laser's cos(elevation) rides on the small per-channel factor, saving a pass.
    rot = np.exp(1j * block_az)[:, :, None] * (np.exp(1j * delta) * ch.cos_el)[:, None, :]
    np.multiply(distance, rot.imag, out=x)
    np.multiply(distance, rot.real, out=y)
    np.multiply(distance, ch.sin_el, out=z)
    if vertical_offsets:
        np.add(z, ch.vertical, out=z, where=distance > 0)
    if ch.horizontal.any():
        # A horizontal offset h moves the laser's origin across its beam: (-h cos a, h sin a)
        # in (X_L, Y_L) (the ROS driver's rawdata.cc, from the HDL-64E S2 manual).
        hit = distance > 0
        np.add(x, -ch.horizontal * rot.real / ch.cos_el, out=x, where=hit)
        np.add(y, ch.horizontal * rot.imag / ch.cos_el, out=y, where=hit)


def _return_types(channels: np.ndarray, mode: np.ndarray) -> np.ndarray:
    """`ReturnType` flags of each firing, (n, 12, 32) uint8.

    Dual mode (manual 9.3.1.3): even blocks hold the last return, odd blocks the strongest, or
    the second strongest when the last return is also the strongest. A pair that is identical
    means a single echo: the even block is flagged LAST | STRONGEST and the odd block's copy 0,
    so that selecting any flag never yields the same echo twice.
    """
    n = len(mode)
    out = np.empty((n, vlp16.BLOCKS_PER_PACKET, FIRINGS_PER_BLOCK), dtype=np.uint8)
    out[mode == vlp16.RETURN_MODE_STRONGEST] = ReturnType.STRONGEST
    out[mode == vlp16.RETURN_MODE_LAST] = ReturnType.LAST
    dual = mode == vlp16.RETURN_MODE_DUAL
    if dual.any():
        ch = channels[dual]
        d_last, d_odd = ch["distance"][:, 0::2], ch["distance"][:, 1::2]
        r_last, r_odd = ch["reflectivity"][:, 0::2], ch["reflectivity"][:, 1::2]
        same = (d_last == d_odd) & (r_last == r_odd)
        odd_strongest = r_odd > r_last
        even = np.where(same | ~odd_strongest, ReturnType.LAST | ReturnType.STRONGEST,
                        ReturnType.LAST)
        odd = np.where(same, 0, np.where(odd_strongest, ReturnType.STRONGEST,
                                         ReturnType.SECOND_STRONGEST))
        pair = np.empty_like(out[dual])
        pair[:, 0::2] = even
        pair[:, 1::2] = odd
        out[dual] = pair
    return out


# --------------------------------------------------------------------------------------------
# Encoding


def encode_data_packets(
    azimuth_cdeg: np.ndarray,
    distance_raw: np.ndarray,
    reflectivity: np.ndarray,
    timestamps_us: np.ndarray,
    return_mode: int = vlp16.RETURN_MODE_STRONGEST,
    product_id: int = vlp16.PRODUCT_ID_VLP16,
) -> np.ndarray:
    """Byte-exact VLP-16 data packets from per-block azimuths and per-firing ranges.

    ``azimuth_cdeg``: (n_blocks,) block azimuths, 0.01 deg counts in [0, 36000).
    ``distance_raw``: (n_blocks, 32) distances in 2 mm counts, 0 = no return; channels 0..15
    are the first firing sequence of lasers 0..15, 16..31 the second.
    ``reflectivity``: (n_blocks, 32) uint8. ``timestamps_us``: (n_packets,) us past the hour.
    ``n_blocks`` must be ``12 * n_packets``. In dual mode the caller lays out the block pairs
    (last return, then strongest or second strongest) as the manual does.

    Returns an (n_packets, 1206) uint8 array; ``bytes(out[i])`` is the UDP payload of packet i.
    """
    azimuth_cdeg = np.asarray(azimuth_cdeg)
    distance_raw = np.asarray(distance_raw)
    reflectivity = np.asarray(reflectivity)
    timestamps_us = np.asarray(timestamps_us)
    n = len(timestamps_us)
    n_blocks = vlp16.BLOCKS_PER_PACKET * n
    if azimuth_cdeg.shape != (n_blocks,):
        raise ValueError(f"azimuth_cdeg has shape {azimuth_cdeg.shape}, expected ({n_blocks},): "
                         f"12 blocks for each of the {n} timestamps")
    for name, arr in (("distance_raw", distance_raw), ("reflectivity", reflectivity)):
        if arr.shape != (n_blocks, FIRINGS_PER_BLOCK):
            raise ValueError(f"{name} has shape {arr.shape}, expected ({n_blocks}, 32)")
    if n and (azimuth_cdeg.min() < 0 or azimuth_cdeg.max() >= AZIMUTH_COUNTS):
        raise ValueError("azimuth_cdeg must lie in [0, 36000) (0.01 deg counts)")
    if n and (distance_raw.min() < 0 or distance_raw.max() > 0xFFFF):
        raise ValueError("distance_raw must fit uint16 (2 mm counts, at most 131.07 m)")
    if return_mode not in RETURN_MODES:
        raise ValueError(f"return_mode 0x{return_mode:02x} is not 0x37, 0x38 or 0x39")

    rec = np.zeros(n, dtype=DATA_PACKET_DTYPE)
    blocks = rec["blocks"]
    blocks["flag"] = BLOCK_FLAG_U16
    blocks["azimuth"] = azimuth_cdeg.reshape(n, vlp16.BLOCKS_PER_PACKET)
    shape = (n, vlp16.BLOCKS_PER_PACKET, FIRINGS_PER_BLOCK)
    blocks["channels"]["distance"] = distance_raw.reshape(shape)
    blocks["channels"]["reflectivity"] = reflectivity.reshape(shape)
    rec["timestamp"] = timestamps_us.astype(np.int64) % US_PER_HOUR
    rec["return_mode"] = return_mode
    rec["product_id"] = product_id
    return rec.view(np.uint8).reshape(n, vlp16.DATA_PAYLOAD_SIZE)


# --------------------------------------------------------------------------------------------
# Position packets

POSITION_DTYPE = np.dtype(
    [
        ("reserved", "u1", (187,)),
        ("temp_top_c", "u1"),
        ("temp_bottom_c", "u1"),
        ("temp_adc_cal_c", "u1"),
        ("temp_change_since_adc_cal_c", "<i2"),
        ("seconds_since_adc_cal", "<u4"),
        ("adc_cal_reason", "u1"),
        ("adc_cal_status", "u1"),
        ("timestamp", "<u4"),
        ("pps_status", "u1"),
        ("thermal_status", "u1"),
        ("temp_shutdown_c", "u1"),
        ("temp_powerup_c", "u1"),
        ("nmea", "S128"),
        ("unused", "u1", (178,)),
    ]
)
assert POSITION_DTYPE.itemsize == vlp16.POSITION_PAYLOAD_SIZE

PPS_STATUS = {0: "absent", 1: "synchronizing", 2: "locked", 3: "error"}


@dataclass(frozen=True)
class PositionPacket:
    """A decoded position (GPS/telemetry) packet, manual 9.4.

    ``timestamp_us``: us past the hour; ``pps_status``: 0 absent, 1 synchronizing, 2 locked,
    3 error; ``nmea``: the $GPRMC (or $GPGGA) sentence, '' if none. Temperatures in deg C are
    set by firmware since 2018 only (0 otherwise).
    """

    timestamp_us: int
    pps_status: int
    nmea: str
    temp_top_c: int = 0
    temp_bottom_c: int = 0

    @property
    def pps(self) -> str:
        return PPS_STATUS.get(self.pps_status, f"unknown ({self.pps_status})")


def decode_position_packet(payload: bytes) -> PositionPacket:
    """Decode a 512-byte position packet; `MalformedPacketError` if it is not one."""
    if len(payload) != vlp16.POSITION_PAYLOAD_SIZE:
        raise MalformedPacketError(
            f"position packet is {len(payload)} bytes, expected {vlp16.POSITION_PAYLOAD_SIZE} "
            "(data packets are 1206 bytes on port 2368)"
        )
    rec = np.frombuffer(payload, dtype=POSITION_DTYPE)[0]
    nmea = bytes(rec["nmea"]).split(b"\x00", 1)[0].decode("ascii", errors="replace").strip()
    return PositionPacket(
        timestamp_us=int(rec["timestamp"]),
        pps_status=int(rec["pps_status"]),
        nmea=nmea,
        temp_top_c=int(rec["temp_top_c"]),
        temp_bottom_c=int(rec["temp_bottom_c"]),
    )


def encode_position_packet(
    timestamp_us: int,
    pps_status: int = 2,
    nmea: str | None = None,
    temp_top_c: int = 40,
    temp_bottom_c: int = 35,
) -> bytes:
    """A 512-byte position packet (manual 9.4).

    ``nmea`` defaults to a $GPRMC sentence for the timestamp's minute and second with a valid
    checksum; pass ``""`` for none (a sensor without GPS).
    """
    if nmea is None:
        nmea = gprmc_sentence(timestamp_us)
    raw = nmea.encode("ascii")
    if len(raw) > 128:
        raise ValueError(f"NMEA sentence is {len(raw)} bytes; the packet holds 128")
    rec = np.zeros(1, dtype=POSITION_DTYPE)
    rec["temp_top_c"] = temp_top_c
    rec["temp_bottom_c"] = temp_bottom_c
    rec["timestamp"] = int(timestamp_us) % US_PER_HOUR
    rec["pps_status"] = pps_status
    rec["nmea"] = raw
    return rec.tobytes()


def gprmc_sentence(timestamp_us: int, hour: int = 12, date: str = "010125") -> str:
    """A valid $GPRMC sentence (with checksum and CR LF) for a time past the hour."""
    seconds = (int(timestamp_us) % US_PER_HOUR) // 1_000_000
    body = (f"GPRMC,{hour:02d}{seconds // 60:02d}{seconds % 60:02d},A,4807.038,N,01131.000,E,"
            f"000.0,000.0,{date},000.0,E,A")
    checksum = 0
    for ch in body.encode("ascii"):
        checksum ^= ch
    return f"${body}*{checksum:02X}\r\n"


# --------------------------------------------------------------------------------------------
# Timing helpers for emitting packets (the twin, tests)


def block_azimuths_cdeg(
    n_packets: int, rpm: float, start_cdeg: float = 0.0,
    return_mode: int = vlp16.RETURN_MODE_STRONGEST, sensor: SensorModel = VLP16,
) -> np.ndarray:
    """Block azimuths of ``n_packets`` consecutive packets of ``sensor`` at a constant ``rpm``,
    (12 n,) uint16.

    What the sensor's encoder reports: the azimuth at each block's first firing, rounded to
    0.01 deg and wrapped to [0, 36000). In dual mode the two blocks of a pair share one azimuth.
    """
    slot = np.arange(vlp16.BLOCKS_PER_PACKET * n_packets)
    if return_mode == vlp16.RETURN_MODE_DUAL:
        slot = slot // 2  # one firing time per block pair
    cdeg_per_s = rpm * 36000.0 / 60.0
    az = start_cdeg + slot * sensor.block_period * cdeg_per_s
    return (np.round(az).astype(np.int64) % AZIMUTH_COUNTS).astype(np.uint16)


def packet_timestamps_us(
    n_packets: int, start_us: int = 0, return_mode: int = vlp16.RETURN_MODE_STRONGEST,
    sensor: SensorModel = VLP16,
) -> np.ndarray:
    """Timestamps (us past the hour, wrapping at the hour) of consecutive packets, (n,) uint32."""
    t = start_us + np.round(np.arange(n_packets) * sensor.packet_period(return_mode) * 1e6)
    return (t.astype(np.int64) % US_PER_HOUR).astype(np.uint32)
