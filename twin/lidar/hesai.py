"""Hesai PandarXT32 data packets, from the published layout and the angle-correction file.

The packet (Hesai's PandarXT32 user manual, "point cloud data packet"; tier4/nebula's
``pandar_xt32.hpp`` and ``hesai_packet.hpp`` lay it out the same), 1080 bytes, little-endian:

    header  12 B: 0xEE 0xFF | protocol 2 B | 2 reserved | lasers (32) | blocks (8) | reserved |
                  distance unit (mm) | returns (1 or 2) | flags
    body    8 blocks x (uint16 azimuth, 0.01 deg | 32 x (uint16 distance, uint8 reflectivity,
                  1 reserved byte))
    tail    24 B: 10 reserved | return mode | uint16 motor speed (rpm) | date and time (6 B,
                  years since 1900) | uint32 timestamp (us) | factory byte
    uint32 UDP sequence number

In dual-return mode consecutive blocks are the two returns of one firing (first block: the
last / strongest return, as the return mode byte says). A channel's azimuth is its block's plus
its azimuth offset, its elevation the file's (``Channel,Elevation,Azimuth``, degrees, channel
1..32); a return at range r lies at r (cos w sin a, cos w cos a, sin w): Hesai's own frame, y
forward and x right as aimbench's {L} (nebula's hesai_decoder.hpp computes the same). The
firing times (nebula's pandar_xt32.hpp): 368 + 1512 x channel ns after the block's start, the
blocks 50 us apart ending 5.632 us before the timestamp; the decoder leaves the head's rotation
during them (up to 0.17 deg at 10 Hz) out of the azimuth, as Hesai's and nebula's do.

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

PACKET_BYTES = 1080
N_CHANNELS = 32
N_BLOCKS = 8
#: Hesai's default data port.
DATA_PORT = 2368
#: Return-mode bytes of the tail (the XT32 manual): 0x37 strongest, 0x38 last, 0x39 last and
#: strongest, 0x3B first, 0x3C last and first, 0x3D first and strongest.
SINGLE_MODES = {0x33: "first", 0x37: "strongest", 0x38: "last", 0x3B: "first"}

_UNIT = np.dtype([("distance", "<u2"), ("reflectivity", "u1"), ("reserved", "u1")])
_BLOCK = np.dtype([("azimuth", "<u2"), ("units", _UNIT, (N_CHANNELS,))])
PACKET_DTYPE = np.dtype([
    ("sop", "<u2"), ("protocol", "u1", (2,)), ("reserved1", "u1", (2,)), ("laser_num", "u1"),
    ("block_num", "u1"), ("reserved2", "u1"), ("dis_unit", "u1"), ("return_num", "u1"),
    ("flags", "u1"), ("blocks", _BLOCK, (N_BLOCKS,)), ("reserved3", "u1", (10,)),
    ("return_mode", "u1"), ("motor_speed", "<u2"), ("date_time", "u1", (6,)),
    ("timestamp", "<u4"), ("factory", "u1"), ("udp_sequence", "<u4"),
])
assert PACKET_DTYPE.itemsize == PACKET_BYTES


class HesaiError(AimbenchError):
    """Hesai packets or an angle-correction file that cannot be read."""


@dataclass(frozen=True, eq=False)
class XT32Angles:
    """A unit's angle corrections, degrees, by channel (0-based)."""

    elevation_deg: np.ndarray
    azimuth_deg: np.ndarray
    source: str = "angle correction"

    @classmethod
    def from_csv(cls, path: str | Path) -> XT32Angles:
        path = Path(path)
        try:
            rows = [line.split(",") for line in path.read_text().splitlines()[1:] if line.strip()]
            ch = np.array([int(r[0]) for r in rows])
            el = np.array([float(r[1]) for r in rows])
            az = np.array([float(r[2]) for r in rows])
        except (OSError, ValueError, IndexError) as exc:
            raise HesaiError(f"{path}: not a Hesai angle-correction file (Channel,Elevation,"
                             f"Azimuth; {exc})") from None
        if sorted(ch.tolist()) != list(range(1, N_CHANNELS + 1)):
            raise HesaiError(f"{path}: {len(ch)} channels, a PandarXT32 has 32 (1..32)")
        order = np.argsort(ch)
        return cls(el[order], az[order], str(path))

    def lasers(self) -> LaserTable:
        return LaserTable("PandarXT32", np.radians(self.elevation_deg), np.zeros(N_CHANNELS),
                          np.radians(self.azimuth_deg))


@dataclass(frozen=True, eq=False)
class XT32Packets:
    """Decoded packets: per packet (n,), per firing (n, blocks, 32)."""

    timestamp_us: np.ndarray
    return_mode: np.ndarray
    motor_rpm: np.ndarray
    block_azimuth_cdeg: np.ndarray  # (n, 8)
    distance: np.ndarray  # m, 0 = none
    reflectivity: np.ndarray
    azimuth: np.ndarray  # rad, block + channel offset
    x: np.ndarray
    y: np.ndarray
    z: np.ndarray


def decode_xt32(payloads: list[bytes], angles: XT32Angles) -> XT32Packets:
    """Decode PandarXT32 packets (payloads of another size or start are skipped)."""
    good = [p for p in payloads if len(p) == PACKET_BYTES and p[:2] == b"\xee\xff"]
    rec = np.frombuffer(b"".join(good), dtype=PACKET_DTYPE)
    if len(rec) and not np.all(rec["laser_num"] == N_CHANNELS):
        raise HesaiError(f"packets of {int(rec['laser_num'][0])} lasers: not a PandarXT32's")
    blocks = rec["blocks"]
    az_cdeg = blocks["azimuth"].astype(np.int64)
    distance = blocks["units"]["distance"] * (rec["dis_unit"].astype(np.float64)[:, None, None]
                                              * 1e-3)
    a = (np.radians(az_cdeg / 100.0)[:, :, None] + np.radians(angles.azimuth_deg)) % (2 * math.pi)
    el = np.radians(angles.elevation_deg)
    xy = distance * np.cos(el)
    return XT32Packets(
        timestamp_us=rec["timestamp"].astype(np.int64), return_mode=rec["return_mode"].copy(),
        motor_rpm=rec["motor_speed"].astype(np.float64), block_azimuth_cdeg=az_cdeg,
        distance=distance, reflectivity=blocks["units"]["reflectivity"].copy(), azimuth=a,
        x=xy * np.sin(a), y=xy * np.cos(a), z=distance * np.sin(el))


def scans_from_xt32(dec: XT32Packets, angles: XT32Angles, *, cut_cdeg: int = 18000
                    ) -> list[Scan]:
    """Whole rotations (cut where the block azimuth passes ``cut_cdeg``), every firing kept
    (misses at distance 0); in dual-return mode each firing's strongest return (the second
    block of a pair when the two differ: the XT32 writes last, then strongest)."""
    n = len(dec.timestamp_us)
    pair = np.array([m not in SINGLE_MODES for m in dec.return_mode.tolist()], dtype=bool)
    if pair.any() and not pair.all():
        raise HesaiError("packets of single and dual return mode mixed: record one mode")
    step = 2 if pair.all() and n else 1
    # one firing per block (single) or per block pair (dual: the second block, strongest)
    take = np.arange(step - 1, N_BLOCKS, step)
    az = dec.block_azimuth_cdeg[:, take].ravel()
    fields = {k: getattr(dec, k)[:, take].reshape(-1, N_CHANNELS)
              for k in ("distance", "reflectivity", "azimuth", "x", "y", "z")}
    if step == 2:  # a miss in the strongest block but a return in the last: keep the last
        other = {k: getattr(dec, k)[:, take - 1].reshape(-1, N_CHANNELS)
                 for k in ("distance", "reflectivity", "azimuth", "x", "y", "z")}
        use = (fields["distance"] == 0) & (other["distance"] > 0)
        for k in fields:
            fields[k] = np.where(use, other[k], fields[k])
    rel = (az - cut_cdeg) % 36000
    starts = np.flatnonzero(np.diff(rel) < -18000) + 1
    scans = []
    t_block = 50e-6 * step
    for i, (lo, hi) in enumerate(itertools.pairwise(starts)):
        m = hi - lo
        lid = np.tile(np.arange(N_CHANNELS, dtype=np.uint8), m)
        dist = fields["distance"][lo:hi].ravel()
        time = (np.repeat(np.arange(m) * t_block, N_CHANNELS)
                + np.tile(368e-9 + 1512e-9 * np.arange(N_CHANNELS), m))
        scans.append(Scan(
            distance=dist, azimuth=fields["azimuth"][lo:hi].ravel(), laser_id=lid,
            intensity=fields["reflectivity"][lo:hi].ravel().astype(np.uint8), time=time,
            return_type=np.full(len(lid), int(ReturnType.STRONGEST), dtype=np.uint8),
            x=fields["x"][lo:hi].ravel(), y=fields["y"][lo:hi].ravel(),
            z=fields["z"][lo:hi].ravel(), index=i, complete=True, packets=0,
            product_id=0, vertical_offsets_applied=False, lasers=angles.lasers(),
            meta={"model": "PandarXT32", "rpm": float(np.median(dec.motor_rpm)),
                  "angles": angles.source}))
    return scans


#: The default angle corrections (nebula's PandarXT32.csv): a unit's own file is better.
DEFAULT_ANGLES = Path(__file__).with_name("hesai_angles") / "PandarXT32.csv"


class XT32Scans:
    """Whole rotations from a stream of datagrams (``payload`` attributes or bytes), decoded a
    rotation at a time, and a summary."""

    def __init__(self, packets, angles: XT32Angles, cut_cdeg: int = 18000) -> None:
        self.packets = packets
        self.angles = angles
        self.cut = cut_cdeg  # where one rotation ends and the next begins, 0.01 deg
        self.counts = {"packets": 0, "other_datagrams": 0, "scans": 0, "firings": 0,
                       "returns": 0, "return_mode": None, "rpm": None}

    def __iter__(self):
        buf: list[bytes] = []
        index = 0
        last_az = None
        for p in self.packets:
            payload = p if isinstance(p, bytes | bytearray | memoryview) else p.payload
            if len(payload) != PACKET_BYTES or payload[:2] != b"\xee\xff":
                self.counts["other_datagrams"] += 1
                continue
            self.counts["packets"] += 1
            buf.append(bytes(payload))
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
        dec = decode_xt32(buf, self.angles)
        self.counts["return_mode"] = int(dec.return_mode[-1])
        self.counts["rpm"] = float(np.median(dec.motor_rpm))
        for s in scans_from_xt32(dec, self.angles, cut_cdeg=self.cut):
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
        return {"model": "PandarXT32", "product_id": None, "return_mode": c["return_mode"],
                "lasers": N_CHANNELS, "laser_table": self.angles.source, "rpm": c["rpm"],
                "data_packets": c["packets"], "other_datagrams": c["other_datagrams"],
                "scans": c["scans"], "complete_scans": c["scans"], "partial_scans": 0,
                "points": c["firings"], "returns": c["returns"], "warnings": []}


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
    # date and time (years since 1900, month, day, hour, minute, second): 2025-01-01 12:00
    # plus the whole seconds of the timestamp; the timestamp the microseconds within it
    sec = np.asarray(timestamp_us) // 1_000_000
    rec["date_time"] = np.column_stack((np.full(n, 125), np.ones(n), np.ones(n),
                                        np.full(n, 12), (sec // 60) % 60, sec % 60))
    rec["timestamp"] = np.asarray(timestamp_us) % 1_000_000
    rec["udp_sequence"] = (first_sequence + np.arange(n)) % (1 << 32)
    raw = rec.tobytes()
    return [raw[i:i + PACKET_BYTES] for i in range(0, len(raw), PACKET_BYTES)]
