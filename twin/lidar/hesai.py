"""Hesai PandarXT32 and PandarQT128 (QT128C2X) data packets, from the published layouts and the
angle-correction file.

Both start with the same 12-byte header and carry blocks of an azimuth (uint16, 0.01 deg) and
one unit a channel (uint16 distance in the header's unit, uint8 reflectivity, one byte
reserved or confidence); tier4/nebula's ``hesai_packet.hpp`` (``Header12B``, ``Block<Unit4B>``)
lays the shared part out, its ``pandar_xt32.hpp`` and ``pandar_qt128.hpp`` the rest.
Little-endian throughout.

PandarXT32 (Hesai's XT32 user manual, "point cloud data packet"), 1080 bytes:

    header  12 B: 0xEE 0xFF | protocol 2 B | 2 reserved | lasers (32) | blocks (8) | reserved |
                  distance unit (mm) | returns (1 or 2) | flags
    body    8 blocks x (uint16 azimuth, 0.01 deg | 32 x (uint16 distance, uint8 reflectivity,
                  1 reserved byte))
    tail    24 B: 10 reserved | return mode | uint16 motor speed (rpm) | date and time (6 B,
                  years since 1900) | uint32 timestamp (us) | factory byte
    uint32 UDP sequence number

PandarQT128C2X (nebula's ``PacketQT128C2X``, protocol 3.2), 1127 bytes (1095 without the
optional cyber-security signature):

    header  12 B as above (128 lasers, 2 blocks)
    body    2 blocks x (uint16 azimuth | 128 x (distance, reflectivity, confidence)) | uint32 CRC
    functional safety 17 B: version | state, fault type, rolling counter | fault count and id |
                  uint16 fault code | 8 reserved | uint32 CRC
    tail    34 B: 5 reserved | mode flag | 6 reserved | return mode | uint16 motor speed |
                  date and time (years since 1900) | uint32 timestamp (us) | factory byte |
                  uint32 UDP sequence | uint32 CRC
    cyber security 32 B (zero when signing is off)

The three CRCs are CRC-32/MPEG-2 (polynomial 0x04C11DB7, initial 0xFFFFFFFF, not reflected, no
final xor), over the body's blocks, the functional safety's bytes 1-12 and the tail's bytes
before its CRC: measured on the real unit's packets (tests/test_hesai_qt128.py), which nebula
leaves unchecked. A QT128 fires its channels in two alternating loops (nebula's
``pandar_qt128.hpp`` ``loop1``/``loop2``, Hesai's firing-time table): loop 1 leaves channels
1-32 (0-based 0-31) dark, loop 2 channels 33-64, channels 65-128 fire in both. In single-return
mode block 0 is loop 1 and block 1 loop 2; in dual-return mode both blocks are one firing, and
the tail's mode flag (bit 0) says which loop. A dark channel is not a firing: it reads
distance 0 in the packet and is left out of the scans (a miss would tell the estimator that
ray passed the board by).

In dual-return mode consecutive blocks are the two returns of one firing (first block: the
last / strongest return, as the return mode byte says). A channel's azimuth is its block's plus
its azimuth offset, its elevation the file's (``Channel,Elevation,Azimuth``, degrees, channel
1..N); a return at range r lies at r (cos w sin a, cos w cos a, sin w): Hesai's own frame, y
forward and x right as aimbench's {L} (nebula's hesai_decoder.hpp computes the same). The
firing times: XT32 (nebula's pandar_xt32.hpp) 368 + 1512 x channel ns after the block's start,
the blocks 50 us apart; QT128 the loop tables' offsets, firings 111.11 us apart (0.4 deg at
600 rpm).

The head turns while a firing's channels fire one after another, so a channel's ray is not at
its block's azimuth: ``decode_hesai`` puts the rotation in by default (``firetime=True``), a
channel's azimuth = block azimuth + omega x firetime[channel] + azimuth offset, omega from the
packet's motor speed (rpm). That is what Hesai's own SDK does when given a firetime correction
file (HesaiLidar_SDK_2.0, libhesai/UdpParser/src/udp6_1_parser.cc for the XT32 and
udp3_2_parser.cc for the QT128: ``azimuth += (rotation_flag > 0 ? 1 : -1) *
GetFiretimesCorrection(channel, motor speed)``, general_parser.cc: ``firetime_correction_[ch] *
speed * 6E-6`` degrees, i.e. firetime in us x rpm x 6 deg/s; rotation_flag > 0 when the block
azimuths increase, as they do on these units), and what aimbench does with a Velodyne's firing
delays (`twin.lidar.packets`). The firetimes are Hesai's files in that SDK
(correction/firetime_correction/): ``PandarXT-32_Firetime Correction File.csv``, 6 us + 1.512 us
x (channel - 1), and ``QT128C2X_Firetime Correction File.csv``, nebula's loop tables exactly.
The XT32's is nebula's channel time plus a constant 5.632 us: nebula's pandar_xt32.hpp puts
``block_offset_ns = 5632 - 50000 * ...`` + ``channel_offset_ns = 368 + 1512 * channel`` in each
point's ``time_stamp``, the same firing time as the SDK's (``block_ns_offset`` + firetime,
udp6_1_parser.cc). nebula (hesai_decoder.hpp) and Hesai's SDK without that file leave the
rotation out of the azimuth and the points: ``firetime=False`` decodes exactly as they do (the
tests hold it to nebula's real clouds). At 600 rpm the rotation is 0.02 to 0.19 deg across an
XT32's channels, 0.002 to 0.36 deg on a QT128.

Bytes in, arrays out: the pcap and socket readers are elsewhere.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from twin.core.errors import AimbenchError
from twin.core.lasers import LaserTable
from twin.core.scan import ReturnType, Scan
from twin.core.sensor_names import PANDAR_QT128, PANDAR_XT32

#: Hesai's default data port.
DATA_PORT = 2368
#: Return-mode bytes of the tail (the XT32 manual): 0x37 strongest, 0x38 last, 0x39 last and
#: strongest, 0x3B first, 0x3C last and first, 0x3D first and strongest.
SINGLE_MODES = {0x33: "first", 0x37: "strongest", 0x38: "last", 0x3B: "first"}
#: The QT128's single-return bytes (nebula's hesai_packet.hpp ``return_mode``, the QT128C2X
#: manual): 0x33 first, 0x34 second, 0x37 strongest, 0x38 last; 0x3B there is dual first and
#: last, not the XT32's first.
QT128_SINGLE_MODES = {0x33: "first", 0x34: "second", 0x37: "strongest", 0x38: "last"}

_HEADER = [
    ("sop", "<u2"), ("protocol", "u1", (2,)), ("reserved1", "u1", (2,)), ("laser_num", "u1"),
    ("block_num", "u1"), ("reserved2", "u1"), ("dis_unit", "u1"), ("return_num", "u1"),
    ("flags", "u1")]
_UNIT = np.dtype([("distance", "<u2"), ("reflectivity", "u1"), ("reserved", "u1")])


def _block(n_channels: int) -> np.dtype:
    return np.dtype([("azimuth", "<u2"), ("units", _UNIT, (n_channels,))])


# ---- PandarXT32 -------------------------------------------------------------------------------
PACKET_BYTES = 1080
N_CHANNELS = 32
N_BLOCKS = 8
PACKET_DTYPE = np.dtype([
    *_HEADER, ("blocks", _block(N_CHANNELS), (N_BLOCKS,)), ("reserved3", "u1", (10,)),
    ("return_mode", "u1"), ("motor_speed", "<u2"), ("date_time", "u1", (6,)),
    ("timestamp", "<u4"), ("factory", "u1"), ("udp_sequence", "<u4"),
])
assert PACKET_DTYPE.itemsize == PACKET_BYTES

# ---- PandarQT128C2X ---------------------------------------------------------------------------
QT128_CHANNELS = 128
QT128_BLOCKS = 2
#: Without the cyber-security signature, and with it (what the unit sends by default).
QT128_BYTES = 1095
QT128_SIGNED_BYTES = 1127
QT128_DTYPE = np.dtype([
    *_HEADER, ("blocks", _block(QT128_CHANNELS), (QT128_BLOCKS,)), ("crc_body", "<u4"),
    ("fs_version", "u1"), ("fs_state", "u1"), ("fs_faults", "u1"), ("fs_fault_code", "<u2"),
    ("fs_reserved", "u1", (8,)), ("crc_fs", "<u4"),
    ("reserved3", "u1", (5,)), ("mode_flag", "u1"), ("reserved4", "u1", (6,)),
    ("return_mode", "u1"), ("motor_speed", "<u2"), ("date_time", "u1", (6,)),
    ("timestamp", "<u4"), ("factory", "u1"), ("udp_sequence", "<u4"), ("crc_tail", "<u4"),
])
assert QT128_DTYPE.itemsize == QT128_BYTES
#: ns after a block's start each channel fires in loop 1 and loop 2 (0: dark in that loop);
#: nebula's pandar_qt128.hpp ``loop1``/``loop2``, from Hesai's QT128C2X firing-time table.
QT128_LOOP1_NS = np.array([0] * 32 + [
    27656, 53000, 2312, 78344, 81512, 5480, 56168, 30824, 33992, 59336, 8648, 84680, 87848,
    11816, 62504, 37160, 40328, 65672, 14984, 91016, 94184, 18152, 68840, 43496, 46664, 72008,
    21320, 97352, 100520, 24488, 75176, 49832, 1456, 77488, 26800, 52144, 55312, 29968, 80656,
    4624, 7792, 83824, 33136, 58480, 61648, 36304, 86992, 10960, 14128, 90160, 39472, 64816,
    67984, 42640, 93328, 17296, 20464, 96496, 45808, 71152, 74320, 48976, 99664, 23632, 25944,
    51288, 600, 76632, 79800, 3768, 54456, 29112, 32280, 57624, 6936, 82968, 86136, 10104,
    60792, 35448, 38616, 63960, 13272, 89304, 92472, 16440, 67128, 41784, 44952, 70296, 19608,
    95640, 98808, 22776, 73464, 48120])
QT128_LOOP2_NS = np.array([
    2312, 78344, 27656, 53000, 56168, 30824, 81512, 5480, 8648, 84680, 33992, 59336, 62504,
    37160, 87848, 11816, 14984, 91016, 40328, 65672, 68840, 43496, 94184, 18152, 21320, 97352,
    46664, 72008, 75176, 49832, 100520, 24488] + [0] * 32 + [
    600, 76632, 25944, 51288, 54456, 29112, 79800, 3768, 6936, 82968, 32280, 57624, 60792,
    35448, 86136, 10104, 13272, 89304, 38616, 63960, 67128, 41784, 92472, 16440, 19608, 95640,
    44952, 70296, 73464, 48120, 98808, 22776, 26800, 52144, 1456, 77488, 80656, 4624, 55312,
    29968, 33136, 58480, 7792, 83824, 86992, 10960, 61648, 36304, 39472, 64816, 14128, 90160,
    93328, 17296, 67984, 42640, 45808, 71152, 20464, 96496, 99664, 23632, 74320, 48976])
assert len(QT128_LOOP1_NS) == len(QT128_LOOP2_NS) == QT128_CHANNELS
QT128_FIRED = np.stack([np.arange(QT128_CHANNELS) >= 32,
                        (np.arange(QT128_CHANNELS) < 32) | (np.arange(QT128_CHANNELS) >= 64)])


@dataclass(frozen=True, eq=False)
class HesaiModel:
    """What differs between the Hesai models aimbench reads: the packet's record, its sizes,
    and the firing (s between two firings; each channel's time within one, per loop)."""

    name: str
    n_channels: int
    n_blocks: int
    dtype: np.dtype
    sizes: tuple[int, ...]  # payload sizes accepted (the record is their first dtype.itemsize)
    firing_period: float  # s between consecutive firings at 600 rpm (single return)
    channel_time: np.ndarray  # (loops, channels) s after the firing's start (nebula's)
    firetime: np.ndarray  # (loops, channels) s after the block's azimuth (Hesai's SDK 2.0 file)
    min_range: float  # m, nebula's SensorT::min_range: the twin returns nothing nearer
    max_range: float  # m, nebula's SensorT::max_range
    single_modes: dict[int, str]  # the return-mode bytes of one return a firing

    @property
    def packet_bytes(self) -> int:
        return max(self.sizes)

    def accepts(self, payload: bytes | bytearray | memoryview) -> bool:
        return len(payload) in self.sizes and payload[:2] == b"\xee\xff"


#: The XT32's channel n (0-based) fires 368 + 1512 n ns after its block's start (nebula's
#: pandar_xt32.hpp ``channel_offset_ns``) and 6 + 1.512 n us after the block's azimuth (Hesai's
#: ``PandarXT-32_Firetime Correction File.csv``, HesaiLidar_SDK_2.0: nebula's 5632 ns block
#: offset plus its channel offset).
XT32_CHANNEL_TIME = 368e-9 + 1512e-9 * np.arange(N_CHANNELS)
XT32_FIRETIME = 6e-6 + 1.512e-6 * np.arange(N_CHANNELS)
#: The QT128C2X's loop tables are its firetime file (``QT128C2X_Firetime Correction File.csv``,
#: loop by loop, to the ns), s.
QT128_LOOP_TIME = np.stack([QT128_LOOP1_NS, QT128_LOOP2_NS]) * 1e-9

XT32 = HesaiModel(PANDAR_XT32, N_CHANNELS, N_BLOCKS, PACKET_DTYPE, (PACKET_BYTES,), 50e-6,
                  XT32_CHANNEL_TIME[None, :], XT32_FIRETIME[None, :], 0.05, 120.0,
                  SINGLE_MODES)
QT128 = HesaiModel(PANDAR_QT128, QT128_CHANNELS, QT128_BLOCKS, QT128_DTYPE,
                   (QT128_BYTES, QT128_SIGNED_BYTES), 1.0 / 9000.0,
                   QT128_LOOP_TIME, QT128_LOOP_TIME, 0.05, 50.0, QT128_SINGLE_MODES)
#: The models by name (`twin.core.sensor_names.HESAI_NAMES`, which the command line offers).
HESAI_MODELS = {m.name: m for m in (XT32, QT128)}


def hesai_model(name: str) -> HesaiModel | None:
    """The Hesai model a name means (``PandarQT128``, ``QT128``, ``Pandar QT128``, any case),
    or None."""
    key = "".join(ch for ch in name.upper() if ch.isalnum())
    for model in HESAI_MODELS.values():
        if key in (model.name.upper(), model.name.upper().removeprefix("PANDAR")):
            return model
    return None


class HesaiError(AimbenchError):
    """Hesai packets or an angle-correction file that cannot be read."""


@dataclass(frozen=True, eq=False)
class HesaiAngles:
    """A unit's angle corrections, degrees, by channel (0-based), and the model they are of."""

    elevation_deg: np.ndarray
    azimuth_deg: np.ndarray
    source: str = "angle correction"
    model: HesaiModel = XT32

    @classmethod
    def from_csv(cls, path: str | Path, model: HesaiModel | str = XT32) -> HesaiAngles:
        m = model if isinstance(model, HesaiModel) else hesai_model(model)
        if m is None:
            raise HesaiError(f"{model!r}: not a Hesai model aimbench reads "
                             f"({', '.join(HESAI_MODELS)})")
        path = Path(path)
        try:
            rows = [line.split(",") for line in path.read_text().splitlines()[1:] if line.strip()]
            ch = np.array([int(r[0]) for r in rows])
            el = np.array([float(r[1]) for r in rows])
            az = np.array([float(r[2]) for r in rows])
        except (OSError, ValueError, IndexError) as exc:
            raise HesaiError(f"{path}: not a Hesai angle-correction file (Channel,Elevation,"
                             f"Azimuth; {exc})") from None
        if sorted(ch.tolist()) != list(range(1, m.n_channels + 1)):
            raise HesaiError(f"{path}: {len(ch)} channels, a {m.name} has {m.n_channels} "
                             f"(1..{m.n_channels})")
        order = np.argsort(ch)
        return cls(el[order], az[order], str(path), m)

    def lasers(self) -> LaserTable:
        return LaserTable(self.model.name, np.radians(self.elevation_deg),
                          np.zeros(self.model.n_channels), np.radians(self.azimuth_deg))


#: The PandarXT32's name before the QT128 came (its angles and packets are the same types).
XT32Angles = HesaiAngles


@dataclass(frozen=True, eq=False)
class HesaiPackets:
    """Decoded packets: per packet (n,), per firing (n, blocks, channels)."""

    timestamp_us: np.ndarray
    return_mode: np.ndarray
    motor_rpm: np.ndarray
    block_azimuth_cdeg: np.ndarray  # (n, blocks)
    distance: np.ndarray  # m, 0 = none
    reflectivity: np.ndarray
    azimuth: np.ndarray  # rad, block + rotation until the channel fires + channel offset
    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    loop: np.ndarray | None = None  # (n, blocks): the firing loop of each block (QT128), 0 or 1
    firetime: bool = True  # whether ``azimuth`` has the head's rotation during the firing in it


XT32Packets = HesaiPackets


def _loops(rec: np.ndarray, model: HesaiModel) -> np.ndarray | None:
    """Each block's firing loop (0: loop 1, 1: loop 2), None for a model with one loop."""
    if model.channel_time.shape[0] == 1:
        return None
    single = np.isin(rec["return_mode"], list(model.single_modes))
    # nebula's pandar_qt128.hpp: single return, block 0 loop 1 and block 1 loop 2; dual return,
    # both blocks the loop the mode flag's bit 0 says (1: loop 1)
    by_block = np.broadcast_to(np.arange(model.n_blocks) % 2, (len(rec), model.n_blocks))
    by_flag = np.broadcast_to((1 - (rec["mode_flag"] & 1))[:, None], by_block.shape)
    return np.where(single[:, None], by_block, by_flag).astype(np.uint8)


def firing_rotation(motor_rpm: np.ndarray, loop: np.ndarray | None, model: HesaiModel
                    ) -> np.ndarray:
    """How far the head turned from each block's azimuth to each channel's firing, rad,
    (n, blocks, channels): omega (the packet's motor speed) x the channel's firetime in its
    block's loop. Positive: the units turn the way their azimuth increases."""
    omega = np.asarray(motor_rpm, dtype=np.float64) * (2.0 * math.pi / 60.0)  # rad/s
    n = len(omega)
    times = (model.firetime[np.zeros((n, model.n_blocks), dtype=np.intp)] if loop is None
             else model.firetime[loop])
    return omega[:, None, None] * times


def decode_hesai(payloads: list[bytes], angles: HesaiAngles, *, firetime: bool = True
                 ) -> HesaiPackets:
    """Decode the packets of ``angles.model`` (payloads of another size or start are skipped).

    ``firetime``: put the head's rotation until each channel fires in its azimuth (Hesai's SDK
    2.0 with its firetime file; the rays the unit cast); False: leave it out, as nebula does
    (module docstring)."""
    model = angles.model
    size = model.dtype.itemsize
    good = [bytes(p[:size]) for p in payloads if model.accepts(p)]
    rec = np.frombuffer(b"".join(good), dtype=model.dtype)
    if len(rec) and not np.all(rec["laser_num"] == model.n_channels):
        raise HesaiError(f"packets of {int(rec['laser_num'][0])} lasers: not a {model.name}'s")
    blocks = rec["blocks"]
    az_cdeg = blocks["azimuth"].astype(np.int64)
    distance = blocks["units"]["distance"] * (rec["dis_unit"].astype(np.float64)[:, None, None]
                                              * 1e-3)
    loop = _loops(rec, model)
    a = np.radians(az_cdeg / 100.0)[:, :, None] + np.radians(angles.azimuth_deg)
    if firetime:
        a = a + firing_rotation(rec["motor_speed"], loop, model)
    a %= 2 * math.pi
    el = np.radians(angles.elevation_deg)
    xy = distance * np.cos(el)
    return HesaiPackets(
        timestamp_us=rec["timestamp"].astype(np.int64), return_mode=rec["return_mode"].copy(),
        motor_rpm=rec["motor_speed"].astype(np.float64), block_azimuth_cdeg=az_cdeg,
        distance=distance, reflectivity=blocks["units"]["reflectivity"].copy(), azimuth=a,
        x=xy * np.sin(a), y=xy * np.cos(a), z=distance * np.sin(el), loop=loop,
        firetime=firetime)


def decode_xt32(payloads: list[bytes], angles: HesaiAngles, *, firetime: bool = True
                ) -> HesaiPackets:
    """Decode PandarXT32 packets (payloads of another size or start are skipped)."""
    return decode_hesai(payloads, angles, firetime=firetime)


_FIELDS = ("distance", "reflectivity", "azimuth", "x", "y", "z")


def scans_from_hesai(dec: HesaiPackets, angles: HesaiAngles, *, cut_cdeg: int = 18000
                     ) -> list[Scan]:
    """Whole rotations (cut where the block azimuth passes ``cut_cdeg``), every firing kept
    (misses at distance 0; a QT128's dark channels, which did not fire, left out); in
    dual-return mode each firing's strongest return (the second block of a pair when the two
    differ: the sensor writes last, then strongest)."""
    model = angles.model
    nc, nb = model.n_channels, model.n_blocks
    n = len(dec.timestamp_us)
    pair = np.array([m not in model.single_modes for m in dec.return_mode.tolist()],
                    dtype=bool)
    if pair.any() and not pair.all():
        raise HesaiError("packets of single and dual return mode mixed: record one mode")
    step = 2 if pair.all() and n else 1
    # one firing per block (single) or per block pair (dual: the second block, strongest)
    take = np.arange(step - 1, nb, step)
    az = dec.block_azimuth_cdeg[:, take].ravel()
    fields = {k: getattr(dec, k)[:, take].reshape(-1, nc) for k in _FIELDS}
    if step == 2:  # a miss in the strongest block but a return in the last: keep the last
        other = {k: getattr(dec, k)[:, take - 1].reshape(-1, nc) for k in _FIELDS}
        use = (fields["distance"] == 0) & (other["distance"] > 0)
        for k in fields:
            fields[k] = np.where(use, other[k], fields[k])
    loop = (np.zeros(len(az), dtype=np.uint8) if dec.loop is None
            else dec.loop[:, take].ravel())
    rel = (az - cut_cdeg) % 36000
    starts = np.flatnonzero(np.diff(rel) < -18000) + 1
    scans = []
    # the XT32's dual-return pairs are read as firings 100 us apart, as before the QT128 came;
    # the QT128 fires once a packet in dual return, once a block in single, 111.11 us apart
    t_firing = model.firing_period * (step if model is XT32 else 1)
    lasers = angles.lasers()
    for i, (lo, hi) in enumerate(itertools.pairwise(starts)):
        m = hi - lo
        fired = (np.ones((m, nc), dtype=bool) if dec.loop is None
                 else QT128_FIRED[loop[lo:hi]])
        lid = np.broadcast_to(np.arange(nc, dtype=np.uint8), (m, nc))[fired]
        # each channel's firing time from the block's azimuth (Hesai's firetime): the time the
        # azimuth's rotation is (with ``dec.firetime``) omega times
        time = (np.arange(m)[:, None] * t_firing + model.firetime[loop[lo:hi]])[fired]
        cols = {k: fields[k][lo:hi][fired] for k in _FIELDS}
        scans.append(Scan(
            distance=cols["distance"], azimuth=cols["azimuth"], laser_id=lid,
            intensity=cols["reflectivity"].astype(np.uint8), time=time,
            return_type=np.full(len(lid), int(ReturnType.STRONGEST), dtype=np.uint8),
            x=cols["x"], y=cols["y"], z=cols["z"], index=i, complete=True, packets=0,
            product_id=0, vertical_offsets_applied=False, lasers=lasers,
            meta={"model": model.name, "rpm": float(np.median(dec.motor_rpm)),
                  "angles": angles.source, "firetime": dec.firetime}))
    return scans


def scans_from_xt32(dec: HesaiPackets, angles: HesaiAngles, *, cut_cdeg: int = 18000
                    ) -> list[Scan]:
    """`scans_from_hesai` of PandarXT32 packets."""
    return scans_from_hesai(dec, angles, cut_cdeg=cut_cdeg)


_ANGLES_DIR = Path(__file__).with_name("hesai_angles")
#: The default angle corrections (nebula's PandarXT32.csv): a unit's own file is better.
DEFAULT_ANGLES = _ANGLES_DIR / "PandarXT32.csv"


def default_angles(model: HesaiModel | str) -> Path:
    """A model's default angle-correction file (nebula's): a unit's own file is better."""
    m = model if isinstance(model, HesaiModel) else hesai_model(model)
    if m is None:
        raise HesaiError(f"{model!r}: not a Hesai model aimbench reads ({', '.join(HESAI_MODELS)})")
    return _ANGLES_DIR / f"{m.name}.csv"


class HesaiScans:
    """Whole rotations from a stream of datagrams (``payload`` attributes or bytes), decoded a
    rotation at a time, and a summary. ``firetime``: as `decode_hesai`'s (False: nebula's
    azimuths, the firing rotation left out)."""

    def __init__(self, packets, angles: HesaiAngles, cut_cdeg: int = 18000, *,
                 firetime: bool = True) -> None:
        self.packets = packets
        self.angles = angles
        self.firetime = firetime
        self.cut = cut_cdeg  # where one rotation ends and the next begins, 0.01 deg
        self.counts = {"packets": 0, "other_datagrams": 0, "scans": 0, "firings": 0,
                       "returns": 0, "return_mode": None, "rpm": None}

    def __iter__(self):
        model = self.angles.model
        buf: list[bytes] = []
        index = 0
        last_az = None
        for p in self.packets:
            payload = p if isinstance(p, bytes | bytearray | memoryview) else p.payload
            if not model.accepts(payload):
                self.counts["other_datagrams"] += 1
                continue
            self.counts["packets"] += 1
            buf.append(bytes(payload))
            # the first block's azimuth: right after the 12-byte header in every model
            az = int.from_bytes(payload[12:14], "little")
            # a rotation passed the cut (180 deg) within the packets held: decode them
            if last_az is not None and (last_az - self.cut) % 36000 > (az - self.cut) % 36000 \
                    and len(buf) > 2:
                for s in self._scans(buf, index):
                    index += 1
                    yield s
                buf = buf[-2:]  # the rotation that began within them
            last_az = az

    def _scans(self, buf: list[bytes], index: int):
        dec = decode_hesai(buf, self.angles, firetime=self.firetime)
        self.counts["return_mode"] = int(dec.return_mode[-1])
        self.counts["rpm"] = float(np.median(dec.motor_rpm))
        for s in scans_from_hesai(dec, self.angles, cut_cdeg=self.cut):
            s = Scan(**{k: getattr(s, k) for k in ("distance", "azimuth", "laser_id",
                                                  "intensity", "time", "return_type", "x",
                                                  "y", "z")},
                     index=index, complete=True, packets=len(buf),
                     vertical_offsets_applied=False, lasers=s.lasers, product_id=0, meta=s.meta)
            self.counts["scans"] += 1
            self.counts["firings"] += len(s)
            self.counts["returns"] += int(s.valid.sum())
            yield s

    def summary(self) -> dict:
        c = self.counts
        return {"model": self.angles.model.name, "product_id": None,
                "return_mode": c["return_mode"], "lasers": self.angles.model.n_channels,
                "laser_table": self.angles.source, "rpm": c["rpm"],
                "data_packets": c["packets"], "other_datagrams": c["other_datagrams"],
                "scans": c["scans"], "complete_scans": c["scans"], "partial_scans": 0,
                "points": c["firings"], "returns": c["returns"], "warnings": []}


XT32Scans = HesaiScans


def _date_time(timestamp_us: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The tail's date and time (years since 1900, month, day, hour, minute, second): 2025-01-01
    12:00 plus the whole seconds of the timestamp; and the microseconds within that second."""
    n = len(timestamp_us)
    sec = np.asarray(timestamp_us) // 1_000_000
    return (np.column_stack((np.full(n, 125), np.ones(n), np.ones(n), np.full(n, 12),
                             (sec // 60) % 60, sec % 60)),
            np.asarray(timestamp_us) % 1_000_000)


def encode_xt32(block_azimuth_cdeg: np.ndarray, distance_m: np.ndarray,
                reflectivity: np.ndarray, timestamp_us: np.ndarray, *, rpm: float = 600.0,
                return_mode: int = 0x37, first_sequence: int = 0) -> list[bytes]:
    """Single-return PandarXT32 packets: ``block_azimuth_cdeg`` (n, 8), ``distance_m`` and
    ``reflectivity`` (n, 8, 32), ``timestamp_us`` (n,): the layout `decode_xt32` reads, the
    distance in 4 mm units (0: no return)."""
    n = len(block_azimuth_cdeg)
    rec = np.zeros(n, dtype=PACKET_DTYPE)
    rec["sop"] = 0xFFEE  # 0xEE 0xFF on the wire
    rec["protocol"] = (6, 1)
    rec["laser_num"], rec["block_num"], rec["dis_unit"], rec["return_num"] = N_CHANNELS, 8, 4, 1
    rec["blocks"]["azimuth"] = block_azimuth_cdeg
    rec["blocks"]["units"]["distance"] = np.clip(np.rint(distance_m / 0.004), 0, 65535)
    rec["blocks"]["units"]["reflectivity"] = reflectivity
    rec["return_mode"] = return_mode
    rec["motor_speed"] = round(rpm)
    rec["date_time"], rec["timestamp"] = _date_time(timestamp_us)
    rec["udp_sequence"] = (first_sequence + np.arange(n)) % (1 << 32)
    raw = rec.tobytes()
    return [raw[i:i + PACKET_BYTES] for i in range(0, len(raw), PACKET_BYTES)]


def _crc_table() -> np.ndarray:
    table = np.zeros(256, dtype=np.uint32)
    for i in range(256):
        c = i << 24
        for _ in range(8):
            c = ((c << 1) ^ 0x04C11DB7) & 0xFFFFFFFF if c & 0x80000000 else (c << 1) & 0xFFFFFFFF
        table[i] = c
    return table


_CRC_TABLE = _crc_table()


def crc32_mpeg2(rows: np.ndarray) -> np.ndarray:
    """CRC-32/MPEG-2 of each row of a (n, bytes) uint8 array (the QT128's three CRCs): one
    table step a byte column, vectorised over the rows (n packets cost one pass, not n)."""
    rows = np.asarray(rows, dtype=np.uint8)
    crc = np.full(len(rows), 0xFFFFFFFF, dtype=np.uint32)
    for j in range(rows.shape[1]):
        crc = (crc << np.uint32(8)) ^ _CRC_TABLE[(crc >> np.uint32(24)) ^ rows[:, j]]
    return crc


#: Byte ranges the QT128's CRCs cover (nebula's PacketQT128C2X offsets; measured on the real
#: unit): the body's blocks, functional safety bytes 1-12, the tail up to its CRC.
QT128_CRC_SPANS = {"crc_body": (12, 1040), "crc_fs": (1045, 1057), "crc_tail": (1061, 1091)}


def encode_qt128(block_azimuth_cdeg: np.ndarray, distance_m: np.ndarray,
                 reflectivity: np.ndarray, timestamp_us: np.ndarray, loop: np.ndarray, *,
                 rpm: float = 600.0, return_mode: int = 0x39, first_sequence: int = 0,
                 signed: bool = True) -> list[bytes]:
    """PandarQT128C2X packets: ``block_azimuth_cdeg`` (n, 2), ``distance_m`` and
    ``reflectivity`` (n, 2, 128), ``timestamp_us`` (n,), ``loop`` (n,) each packet's firing
    loop in dual-return mode (0: loop 1, written as mode flag 1; single return: block 0 loop 1,
    block 1 loop 2, flag 1 whatever given); the layout `decode_hesai` reads, distance in 4 mm
    units (0: no return; a dark channel's is written 0 whatever given), the three CRCs filled,
    the 32 bytes of cyber security zero (signing off) when ``signed``."""
    n = len(block_azimuth_cdeg)
    rec = np.zeros(n, dtype=QT128_DTYPE)
    rec["sop"] = 0xFFEE  # 0xEE 0xFF on the wire
    rec["protocol"] = (3, 2)
    rec["reserved1"], rec["reserved2"] = (3, 0), 1  # as the real unit writes them
    dual = return_mode not in QT128_SINGLE_MODES
    rec["laser_num"], rec["block_num"], rec["dis_unit"] = QT128_CHANNELS, QT128_BLOCKS, 4
    rec["return_num"] = 2 if dual else 1
    rec["flags"] = 0x1D  # as the real unit's: UDP sequence, functional safety, signature...
    rec["blocks"]["azimuth"] = block_azimuth_cdeg
    loop = np.asarray(loop, dtype=np.int64)
    block_loop = (np.broadcast_to(loop[:, None], (n, QT128_BLOCKS)) if dual
                  else np.broadcast_to(np.arange(QT128_BLOCKS) % 2, (n, QT128_BLOCKS)))
    fired = QT128_FIRED[block_loop]
    rec["blocks"]["units"]["distance"] = np.where(
        fired, np.clip(np.rint(distance_m / 0.004), 0, 65535), 0)
    rec["blocks"]["units"]["reflectivity"] = np.where(fired, reflectivity, 0)
    rec["fs_version"] = 1
    # lidar state 1 (normal) in bits 5-7, the rolling counter (bits 0-2) counting the
    # functional-safety cycles of 5 ms (nebula's update_cycle_ns)
    rec["fs_state"] = (1 << 5) | ((np.asarray(timestamp_us) // 5000) % 8)
    # dual: bit 0 the packet's loop (1: loop 1); single: block 0 is loop 1, block 1 loop 2, and
    # the flag says so (Hesai's SDK, udp3_2_parser.cc, takes block b's loop from ``(mode_flag +
    # b + 1) % 2``: 1 agrees with nebula, which takes it from the block alone)
    rec["mode_flag"] = np.where(dual, 1 - loop, 1)
    rec["return_mode"] = return_mode
    rec["motor_speed"] = round(rpm)
    rec["date_time"], rec["timestamp"] = _date_time(timestamp_us)
    rec["factory"] = 0x42  # the real unit's factory byte
    rec["udp_sequence"] = (first_sequence + np.arange(n)) % (1 << 32)
    raw = np.frombuffer(rec.tobytes(), dtype=np.uint8).reshape(n, QT128_BYTES)
    for name, (lo, hi) in QT128_CRC_SPANS.items():
        rec[name] = crc32_mpeg2(raw[:, lo:hi])
    size = QT128_SIGNED_BYTES if signed else QT128_BYTES
    out = np.zeros((n, size), dtype=np.uint8)
    out[:, :QT128_BYTES] = np.frombuffer(rec.tobytes(), dtype=np.uint8).reshape(n, QT128_BYTES)
    return [row.tobytes() for row in out]
