"""Ouster OS0 / OS1 / OS2 lidar packets: the sensor's metadata, decoding, frames, and scans.

An Ouster sensor needs its metadata to be read at all (the packet holds ranges, not angles):
the JSON file the sensor serves (``/api/v1/sensor/metadata``) and every recording tool saves
beside its pcap. `OusterInfo.from_json` reads both the flat format of firmware 2.0-2.3 and the
nested one of later firmware and ouster-sdk (``sensor_info``, ``beam_intrinsics``,
``lidar_data_format``, ``config_params``, ``lidar_intrinsics``).

Packets (Ouster's software user manual, "lidar data format"; ouster-sdk's ``types.cpp``): the
``LEGACY`` profile, which every firmware speaks: 16 columns a packet, each column a 16-byte
header (timestamp u64 ns, measurement id u16, frame id u16, encoder count u32), one 12-byte
pixel per beam (range u32 of which 20 bits are mm, reflectivity u16 of which ouster-sdk keeps
the low byte, signal u16, near-IR u16, 2 unused bytes) and a status u32 (0xFFFFFFFF when the
column is valid). Little-endian. The other profiles (`PROFILES`: RNG19_RFL8_SIG16_NIR16, the
default of recent firmware, its _DUAL, RNG15_RFL8_NIR8 and the two RNG15 dual ones) wrap
the columns in a 32-byte packet header (packet type, frame id, init id, serial number, alert
flags, thermal and shot-limiting countdowns and states) and a 32-byte footer (its last 8 bytes
a CRC64 in firmware 3.x); a column is a 12-byte header (timestamp u64 ns, measurement id u16,
status u16, bit 0 valid) and the pixels, packed bit fields per profile (ouster-sdk's
``parsing.cpp``). A dual profile's first return is the strongest, its second the second
strongest: the `Scan` keeps the first, or the second where the first has no range
(`scan_from_frame`), the `Frame` both.

A frame is W columns (512, 1024 or 2048) of H beams (32, 64 or 128), as fired: pixel (row,
column) is beam ``row`` fired at column ``column`` (ouster-sdk's "staggered" frame). Its points
(ouster-sdk ``xyzlut.cpp``): encoder angle e = 2 pi (1 - column / W), beam azimuth a = -2 pi
beam_azimuth / 360, altitude phi; with n = lidar_origin_to_beam_origin_mm,

    p = (r - n) (cos(e + a) cos phi, sin(e + a) cos phi, sin phi) + n (cos e, sin e, 0)

in the lidar frame (x towards the connector), turned by lidar_to_sensor_transform's rotation
(180 deg about z). aimbench's {L} is that frame with y forward: X_L = -y, Y_L = x; its origin
the lidar frame's (the optical centre, not the sensor frame's origin 36 mm lower: the
transform's translation is left out). So a pixel's azimuth in {L} is 2 pi column / W + beam
azimuth - pi: column 0 points backwards (at the connector) and the columns turn clockwise.

A `Scan` of a frame keeps every pixel, returns or not, destaggered column by destaggered
column (`pixel_order`: the firing grid the estimator reads, a column of every beam at one
azimuth a firing sequence, a beam a laser; each pixel keeps its own column's time). Decoding
is bytes in, arrays out; the pcap and socket readers are `twin.lidar.pcap` and
`twin.lidar.udp`.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from twin.core.errors import AimbenchError
from twin.core.lasers import LaserTable
from twin.core.scan import ReturnType, Scan
from twin.core.sensor_names import LIDAR_MODES, OUSTER_MODELS

# OUSTER_MODELS and LIDAR_MODES are named in twin.core.sensor_names: the command line lists them
# without importing this module.

#: The lidar data port of every Ouster sensor (the IMU's is 7503).
LIDAR_PORT = 7502
#: Valid column status of the LEGACY profile.
COLUMN_VALID = 0xFFFFFFFF
RANGE_MASK = 0x000FFFFF


class OusterError(AimbenchError):
    """Ouster metadata or packets that cannot be read (a bad file, an unsupported profile)."""


# ----------------------------------------------------------------------------------------------
# Packet profiles (ouster-sdk's parsing.cpp: each field's first bit, width and upshift)


@dataclass(frozen=True)
class PixelField:
    """One channel of a pixel: ``bits`` bits from bit ``shift`` of the little-endian word of
    ``word`` bytes at byte ``byte``, shifted up by ``upshift`` (the low-bandwidth profiles send
    range in 8 mm and near-IR in 16 counts), stored as ``dtype`` (ouster-sdk's frame's)."""

    name: str
    byte: int
    word: int
    shift: int
    bits: int
    dtype: type
    upshift: int = 0


@dataclass(frozen=True)
class Profile:
    """A lidar packet profile: the size of its pixel and the channels in it (`Frame`'s names)."""

    name: str
    pixel_bytes: int
    fields: tuple[PixelField, ...]

    @property
    def legacy(self) -> bool:
        return self.name == "LEGACY"

    @property
    def dual(self) -> bool:
        return any(f.name == "range2_mm" for f in self.fields)


def _f(name: str, byte: int, word: int, shift: int, bits: int, dtype: type,
       upshift: int = 0) -> PixelField:
    return PixelField(name, byte, word, shift, bits, dtype, upshift)


_RNG15_FIRST = (  # RNG15_RFL8_NIR8 and the first return of its dual forms
    _f("range_mm", 0, 2, 0, 15, np.uint32, 3), _f("flags", 1, 1, 7, 1, np.uint8),
    _f("reflectivity", 2, 1, 0, 8, np.uint8), _f("near_ir", 3, 1, 0, 8, np.uint16, 4))
_RNG15_DUAL = (
    *_RNG15_FIRST, _f("range2_mm", 4, 2, 0, 15, np.uint32, 3), _f("flags2", 5, 1, 7, 1, np.uint8),
    _f("reflectivity2", 6, 1, 0, 8, np.uint8))

#: The profiles decoded (named in `twin.core.sensor_names.OUSTER_PROFILES` too, for the
#: command line); LEGACY's pixel is read by `column_dtype` as it always was.
PROFILES: dict[str, Profile] = {p.name: p for p in (
    Profile("LEGACY", 12, ()),
    Profile("RNG19_RFL8_SIG16_NIR16", 12, (
        _f("range_mm", 0, 4, 0, 19, np.uint32), _f("flags", 2, 1, 3, 5, np.uint8),
        _f("reflectivity", 4, 1, 0, 8, np.uint8), _f("signal", 6, 2, 0, 16, np.uint16),
        _f("near_ir", 8, 2, 0, 16, np.uint16))),
    Profile("RNG19_RFL8_SIG16_NIR16_DUAL", 16, (
        _f("range_mm", 0, 4, 0, 19, np.uint32), _f("flags", 2, 1, 3, 5, np.uint8),
        _f("reflectivity", 3, 1, 0, 8, np.uint8),
        _f("range2_mm", 4, 4, 0, 19, np.uint32), _f("flags2", 6, 1, 3, 5, np.uint8),
        _f("reflectivity2", 7, 1, 0, 8, np.uint8), _f("signal", 8, 2, 0, 16, np.uint16),
        _f("signal2", 10, 2, 0, 16, np.uint16), _f("near_ir", 12, 2, 0, 16, np.uint16))),
    Profile("RNG15_RFL8_NIR8", 4, _RNG15_FIRST),
    Profile("RNG15_RFL8_NIR8_DUAL", 8, _RNG15_DUAL),
    Profile("FUSA_RNG15_RFL8_NIR8_DUAL", 8, _RNG15_DUAL),
)}
#: The non-LEGACY packet's header and footer, and its column header (bytes).
PACKET_HEADER_BYTES = 32
PACKET_FOOTER_BYTES = 32
COLUMN_HEADER_BYTES = 12


def profile_of(name: str, source: str = "metadata") -> Profile:
    """The `Profile` of a profile's name; `OusterError` in one line naming those read."""
    try:
        return PROFILES[name]
    except KeyError:
        raise OusterError(f"{source}: the sensor sends the {name} lidar packet profile, which "
                          f"aimbench does not decode; set udp_profile_lidar to one of "
                          f"{', '.join(PROFILES)} on the sensor") from None


@dataclass(frozen=True, eq=False)
class OusterInfo:
    """What a sensor's metadata says, in the units it says it (deg, mm)."""

    prod_line: str
    lidar_mode: str
    columns_per_frame: int
    pixels_per_column: int
    columns_per_packet: int
    column_window: tuple[int, int]
    pixel_shift_by_row: np.ndarray
    beam_altitude_deg: np.ndarray
    beam_azimuth_deg: np.ndarray
    beam_to_lidar_mm: tuple[float, float]  # (x, z) of beam_to_lidar_transform
    lidar_to_sensor: np.ndarray  # 4 x 4, mm
    udp_profile_lidar: str = "LEGACY"
    udp_port_lidar: int = LIDAR_PORT
    #: STANDARD, or FUSA (a 32-bit frame id elsewhere in the packet header: firmware 3.1's
    #: FUSA_RNG15_RFL8_NIR8_DUAL, or the metadata's own lidar_data_format.header_type)
    header_type: str = "STANDARD"
    serial: str = ""
    firmware: str = ""
    source: str = "metadata"
    #: What a reader should be told about how this metadata was come by (its summary's
    #: warnings): a model's nominal beams standing in for a unit's, say.
    notes: list = field(default_factory=list, repr=False)
    lasers: LaserTable = field(init=False, repr=False)

    def __post_init__(self) -> None:
        h = self.pixels_per_column
        for name in ("pixel_shift_by_row", "beam_altitude_deg", "beam_azimuth_deg"):
            if len(getattr(self, name)) != h:
                raise OusterError(f"{self.source}: {name} has {len(getattr(self, name))} entries "
                                  f"for {h} beams: a damaged metadata file")
        # A beam leaves from n = lidar_origin_to_beam_origin off the axis, along the encoder's
        # horizontal direction, b = the beam's azimuth offset aside of its own: n cos b along
        # it, which puts its line through the axis at z = -n cos b tan(altitude) (as a
        # VLP-32C's lasers about its focal point: the "vertical offset" rays start from), and
        # n sin b across it (the horizontal offset, < 1.3 mm on an OS1).
        alt, b = np.radians(self.beam_altitude_deg), np.radians(self.beam_azimuth_deg)
        n_m = float(np.hypot(*self.beam_to_lidar_mm)) * 1e-3
        object.__setattr__(self, "lasers", LaserTable(
            self.prod_line, alt, -n_m * np.cos(b) * np.tan(alt) + self.beam_to_lidar_mm[1] * 1e-3,
            b, n_m * np.sin(b)))

    # -- derived ---------------------------------------------------------------------------
    @property
    def rate_hz(self) -> float:
        """Frames a second, from the lidar mode (``1024x10``: 10 Hz)."""
        return float(self.lidar_mode.split("x")[1])

    @property
    def profile(self) -> Profile:
        """The lidar packet profile (`OusterError` for one aimbench does not decode)."""
        return profile_of(self.udp_profile_lidar, self.source)

    @property
    def column_bytes(self) -> int:
        if self.udp_profile_lidar == "LEGACY":  # header, pixels, status word
            return 16 + 12 * self.pixels_per_column + 4
        return COLUMN_HEADER_BYTES + self.profile.pixel_bytes * self.pixels_per_column

    @property
    def packet_bytes(self) -> int:
        if self.udp_profile_lidar == "LEGACY":
            return self.columns_per_packet * self.column_bytes
        return PACKET_HEADER_BYTES + self.columns_per_packet * self.column_bytes + \
            PACKET_FOOTER_BYTES

    @property
    def model(self) -> str:
        """``OS1-32``-style name of the product line (``OS-1-32-G`` -> ``OS1-32``)."""
        parts = self.prod_line.split("-")
        if len(parts) >= 3 and parts[0] == "OS":
            return f"OS{parts[1]}-{parts[2]}"
        return self.prod_line

    # -- reading ---------------------------------------------------------------------------
    @classmethod
    def from_json(cls, text: str | bytes | Path, source: str | None = None) -> OusterInfo:
        """The metadata of a JSON text or file (flat firmware 2.x format or nested)."""
        if isinstance(text, Path):
            source = source or str(text)
            try:
                text = text.read_text()
            except OSError as exc:
                raise OusterError(f"{text}: cannot read the Ouster metadata file "
                                  f"({exc.strerror or exc})") from None
        source = source or "metadata"
        try:
            d = json.loads(text)
        except (ValueError, UnicodeDecodeError) as exc:
            raise OusterError(f"{source}: not a JSON file ({exc}); give the sensor's metadata "
                              "JSON (saved beside its pcap)") from None
        try:
            return cls._parse(d, source)
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            raise OusterError(f"{source}: not an Ouster sensor's metadata (missing or bad "
                              f"{exc}); give the JSON the sensor serves at "
                              "/api/v1/sensor/metadata") from None

    @classmethod
    def _parse(cls, d: dict, source: str) -> OusterInfo:
        if "sensor_info" in d:  # nested: firmware 2.4+ and ouster-sdk's own files
            si, bi = d["sensor_info"], d["beam_intrinsics"]
            fmt, cfg = d["lidar_data_format"], d.get("config_params", {})
            li = d.get("lidar_intrinsics", {})
            prod, serial, fw = si["prod_line"], str(si.get("prod_sn", "")), si.get("build_rev", "")
            mode = cfg.get("lidar_mode", f"{fmt['columns_per_frame']}x10")
            profile = fmt.get("udp_profile_lidar", cfg.get("udp_profile_lidar", "LEGACY"))
            port = int(cfg.get("udp_port_lidar", LIDAR_PORT))
            lts = li.get("lidar_to_sensor_transform")
            header = fmt.get("header_type")
        else:  # flat: firmware 2.0-2.3
            bi, fmt = d, d["data_format"]
            prod, serial, fw = d["prod_line"], str(d.get("prod_sn", "")), d.get("build_rev", "")
            mode = d.get("lidar_mode", f"{fmt['columns_per_frame']}x10")
            profile = fmt.get("udp_profile_lidar", "LEGACY")
            port = int(d.get("udp_port_lidar", LIDAR_PORT))
            lts = d.get("lidar_to_sensor_transform")
            header = fmt.get("header_type")
        if header is None:  # firmware before 3.2 does not say: FUSA's profile implies it
            header = "FUSA" if profile == "FUSA_RNG15_RFL8_NIR8_DUAL" else "STANDARD"
        if "beam_to_lidar_transform" in bi:
            b2l = np.asarray(bi["beam_to_lidar_transform"], dtype=float).reshape(4, 4)
            beam = (float(b2l[0, 3]), float(b2l[2, 3]))
        else:
            beam = (float(bi["lidar_origin_to_beam_origin_mm"]), 0.0)
        lts = (np.diag([-1.0, -1.0, 1.0, 1.0]) if lts is None
               else np.asarray(lts, dtype=float).reshape(4, 4))
        return cls(
            prod_line=prod, lidar_mode=mode,
            columns_per_frame=int(fmt["columns_per_frame"]),
            pixels_per_column=int(fmt["pixels_per_column"]),
            columns_per_packet=int(fmt["columns_per_packet"]),
            column_window=tuple(int(v) for v in fmt.get(
                "column_window", (0, int(fmt["columns_per_frame"]) - 1))),
            pixel_shift_by_row=np.asarray(fmt["pixel_shift_by_row"], dtype=np.int64),
            beam_altitude_deg=np.asarray(bi["beam_altitude_angles"], dtype=float),
            beam_azimuth_deg=np.asarray(bi["beam_azimuth_angles"], dtype=float),
            beam_to_lidar_mm=beam, lidar_to_sensor=lts, udp_profile_lidar=profile,
            udp_port_lidar=port, header_type=str(header), serial=serial, firmware=fw,
            source=source)


def metadata_beside(pcap: str | Path) -> Path | None:
    """The metadata JSON recorded beside a pcap (same name, ``.json``), if there is one."""
    p = Path(pcap).with_suffix(".json")
    return p if p.is_file() else None


# ----------------------------------------------------------------------------------------------
# Packets


def column_dtype(info: OusterInfo) -> np.dtype:
    """One column of a LEGACY packet as a NumPy record."""
    pixel = np.dtype([("range", "<u4"), ("reflectivity", "<u2"), ("signal", "<u2"),
                      ("near_ir", "<u2"), ("unused", "<u2")])
    return np.dtype([("timestamp", "<u8"), ("measurement_id", "<u2"), ("frame_id", "<u2"),
                     ("encoder", "<u4"), ("pixels", pixel, (info.pixels_per_column,)),
                     ("status", "<u4")])


def decode_packets(payloads: Iterable[bytes], info: OusterInfo) -> np.ndarray:
    """The columns of lidar packets in the metadata's profile, (n_packets * columns_per_packet,)
    read-only records: LEGACY's `column_dtype` (the range word as sent: `frames` keeps its 20
    bits), the other profiles' `profile_column_dtype` (each column with its packet header's
    fields). Payloads of another size that are not this sensor's lidar packets are skipped (IMU
    packets, other sensors); one that is, cut short or of another profile's size, is an
    `OusterError` naming it (`packet_problem`)."""
    size = info.packet_bytes  # (an unknown profile: OusterError, in one line)
    good = []
    for p in payloads:
        if len(p) == size:
            good.append(p)
            continue
        problem = packet_problem(p, info)
        if problem is not None:
            raise OusterError(problem)
    if info.udp_profile_lidar == "LEGACY":
        return np.frombuffer(b"".join(good), dtype=column_dtype(info))
    return _profile_columns(b"".join(good), info)


def _packet_size(info: OusterInfo, profile: Profile) -> int:
    """The lidar packet size of this sensor (beams, columns a packet) in another profile."""
    h, cpp = info.pixels_per_column, info.columns_per_packet
    if profile.legacy:
        return cpp * (16 + 12 * h + 4)
    return PACKET_HEADER_BYTES + cpp * (COLUMN_HEADER_BYTES + profile.pixel_bytes * h) + \
        PACKET_FOOTER_BYTES


def packet_problem(payload: bytes, info: OusterInfo) -> str | None:
    """What is wrong with a payload that is not a whole lidar packet of the metadata's profile
    but is one of this sensor's lidar packets, in one line; None for anything else (an IMU
    packet, another device's datagram), which readers skip. A non-LEGACY packet says it is a
    lidar packet (packet type 1); a LEGACY one is told by its size alone."""
    n, size = len(payload), info.packet_bytes
    if n == size:
        return None
    h, cpp, name = info.pixels_per_column, info.columns_per_packet, info.udp_profile_lidar
    stated = (f"the {size} bytes the metadata's {name} profile makes with {h} beams and {cpp} "
              "columns a packet")
    others = [p.name for p in PROFILES.values()
              if p.name != name and _packet_size(info, p) == n]
    if others:
        return (f"{info.source}: a {n}-byte lidar packet, the size of {' or '.join(others)}'s, "
                f"not {stated}: the metadata is not this capture's (or the sensor's "
                "udp_profile_lidar was changed after it was saved); give the metadata saved "
                "with these packets")
    if name == "LEGACY":
        lidar = info.column_bytes <= n < size
    else:
        lidar = n >= PACKET_HEADER_BYTES and (
            payload[0] == 1 if info.header_type == "FUSA" else payload[0:2] == b"\x01\x00")
    if not lidar:
        return None
    if n < size:
        return (f"{info.source}: a lidar packet cut short, {n} bytes of {stated}: the capture's "
                f"snap length or the network's MTU is below {size} bytes (record with tcpdump "
                f"-s 0; give the host's interface an MTU of at least {size + 28})")
    return (f"{info.source}: a {n}-byte lidar packet, not {stated}: the metadata is not this "
            "capture's (columns_per_packet or pixels_per_column differ); give the metadata "
            "saved with these packets")


def packet_frame_id(payload: bytes, info: OusterInfo) -> int:
    """The frame id of a whole lidar packet (LEGACY: its first column's; the others: the
    packet header's, 32 bits in the FUSA header) and, above bit 32, the non-LEGACY init id,
    which a sensor's restart changes (`frames` cuts there too)."""
    if info.udp_profile_lidar == "LEGACY":
        return int.from_bytes(payload[10:12], "little")
    if info.header_type == "FUSA":
        fid, init = payload[4:8], payload[1:4]
    else:
        fid, init = payload[2:4], payload[4:7]
    return int.from_bytes(fid, "little") | int.from_bytes(init, "little") << 32


def _crc64_table() -> tuple[int, ...]:
    """CRC-64/XZ's table (ECMA-182's polynomial, reflected: ouster-sdk's crc64_init)."""
    poly, table = 0xC96C5795D7870F42, []
    for i in range(256):
        crc = i
        for _ in range(8):
            crc = (crc >> 1) ^ (poly if crc & 1 else 0)
        table.append(crc)
    return tuple(table)


_CRC64 = _crc64_table()


def crc64(data: bytes) -> int:
    """CRC-64/XZ of some bytes, as the sensor computes a packet's (ouster-sdk crc64_compute)."""
    crc = 0xFFFFFFFFFFFFFFFF
    for byte in data:
        crc = _CRC64[(crc ^ byte) & 0xFF] ^ (crc >> 8)
    return crc ^ 0xFFFFFFFFFFFFFFFF


def footer_crc_ok(payload: bytes) -> bool:
    """Whether a non-LEGACY packet's last 8 bytes are the CRC64 of the rest: firmware 3.x sends
    one, 2.x leaves the footer 0 (and this False). Not checked while decoding, as ouster-sdk's
    batcher does not (a pure-Python CRC of 640 packets a second would not keep up); for a
    capture's check (tests/test_ouster_profiles.py)."""
    return crc64(payload[:-8]) == int.from_bytes(payload[-8:], "little")


def profile_column_dtype(info: OusterInfo) -> np.dtype:
    """One column of a non-LEGACY packet as `decode_packets` gives it: its packet header's
    fields (repeated in each of the packet's columns), its column header, its pixels' bytes."""
    return np.dtype([
        ("frame_id", "<u4"), ("init_id", "<u4"), ("prod_sn", "<u8"), ("alert_flags", "u1"),
        ("shutdown_countdown", "u1"), ("shot_limiting_countdown", "u1"),
        ("thermal_shutdown", "u1"), ("shot_limiting", "u1"),
        ("timestamp", "<u8"), ("measurement_id", "<u2"), ("status", "<u2"),
        ("pixels", "u1", (info.pixels_per_column, info.profile.pixel_bytes))])


def _le(header: np.ndarray, byte: int, n: int) -> np.ndarray:
    """The little-endian unsigned integer of ``n`` bytes at ``byte`` of each header row."""
    out = np.zeros(len(header), dtype=np.uint64)
    for i in range(n):
        out |= header[:, byte + i].astype(np.uint64) << np.uint64(8 * i)
    return out


def _packet_header(header: np.ndarray, info: OusterInfo) -> dict[str, np.ndarray]:
    """The fields of (n, 32) packet headers (ouster-sdk's parsing.cpp: STANDARD, or FUSA with
    its 32-bit frame id after a one-byte packet type and the init id)."""
    if info.header_type == "FUSA":
        ids = {"frame_id": _le(header, 4, 4), "init_id": _le(header, 1, 3),
               "prod_sn": _le(header, 11, 5), "alert_flags": header[:, 8]}
    else:
        ids = {"frame_id": _le(header, 2, 2), "init_id": _le(header, 4, 3),
               "prod_sn": _le(header, 7, 5), "alert_flags": header[:, 12]}
    return ids | {"shutdown_countdown": header[:, 16], "shot_limiting_countdown": header[:, 17],
                  "thermal_shutdown": header[:, 18] & 0x0F,
                  "shot_limiting": header[:, 19] & 0x0F}


def _profile_columns(raw: bytes, info: OusterInfo) -> np.ndarray:
    """The `profile_column_dtype` records of whole non-LEGACY packets, joined."""
    out_dtype = profile_column_dtype(info)
    column = np.dtype([(name, out_dtype[name]) for name in
                       ("timestamp", "measurement_id", "status", "pixels")])
    packet = np.dtype([("header", "u1", (PACKET_HEADER_BYTES,)),
                       ("columns", column, (info.columns_per_packet,)),
                       ("footer", "u1", (PACKET_FOOTER_BYTES,))])
    packets = np.frombuffer(raw, dtype=packet)
    out = np.empty((len(packets), info.columns_per_packet), dtype=out_dtype)
    for name in column.names:
        out[name] = packets["columns"][name]
    for name, values in _packet_header(packets["header"], info).items():
        out[name] = values[:, None]
    out.flags.writeable = False
    return out.reshape(-1)


def encode_packets(cols: np.ndarray, info: OusterInfo) -> list[bytes]:
    """LEGACY packets of columns (`decode_packets`' records), ``columns_per_packet`` a packet."""
    cpp = info.columns_per_packet
    if len(cols) % cpp:
        raise ValueError(f"{len(cols)} columns do not fill packets of {cpp}")
    raw = np.ascontiguousarray(cols.astype(column_dtype(info))).tobytes()
    size = info.packet_bytes
    return [raw[i:i + size] for i in range(0, len(raw), size)]


@dataclass(frozen=True, eq=False)
class Frame:
    """One frame as the sensor sent it: (H, W) fields by (beam, measurement id), per-column
    headers (W,), and which columns arrived valid."""

    frame_id: int
    range_mm: np.ndarray
    reflectivity: np.ndarray
    signal: np.ndarray
    near_ir: np.ndarray
    timestamp_ns: np.ndarray
    measurement_id: np.ndarray
    status: np.ndarray
    received: np.ndarray
    packets: int
    # What only the non-LEGACY profiles send (None, 0 in a LEGACY frame): each pixel's flags;
    # a dual profile's second return (the second strongest); the frame's packet header as
    # its first packet gives it (as ouster-sdk's batcher takes it), and each packet's alert
    # flags ((W / columns_per_packet,), by packet: measurement id // columns_per_packet).
    flags: np.ndarray | None = None
    range2_mm: np.ndarray | None = None
    reflectivity2: np.ndarray | None = None
    signal2: np.ndarray | None = None
    flags2: np.ndarray | None = None
    init_id: int = 0
    prod_sn: int = 0
    thermal_shutdown: int = 0
    shot_limiting: int = 0
    shutdown_countdown: int = 0
    shot_limiting_countdown: int = 0
    alert_flags: np.ndarray | None = None


def frames(columns: np.ndarray, info: OusterInfo) -> Iterator[Frame]:
    """The frames of decoded columns, in order (a new frame id starts a new frame)."""
    if not len(columns):
        return
    fid = columns["frame_id"].astype(np.int64)
    legacy = info.udp_profile_lidar == "LEGACY"
    if not legacy:  # a sensor restarted (a new init id) starts a new frame too, as in ouster-sdk
        fid = fid | (columns["init_id"].astype(np.int64) << 32)
    starts = np.flatnonzero(np.concatenate(([True], fid[1:] != fid[:-1])))
    ends = np.concatenate((starts[1:], [len(columns)]))
    make = _frame if legacy else _profile_frame
    for a, b in zip(starts, ends, strict=True):
        yield make(columns[a:b], info)


def packet_frames(raw: bytes, info: OusterInfo) -> Iterator[Frame]:
    """The frames of whole lidar packets of the metadata's size, joined in ``raw``: the frames
    of ``decode_packets``' columns, without making those records first (a non-LEGACY packet's
    fields are read through views of its bytes)."""
    if info.udp_profile_lidar == "LEGACY":
        yield from frames(np.frombuffer(raw, dtype=column_dtype(info)), info)
        return
    packets = np.frombuffer(raw, dtype=np.uint8).reshape(-1, info.packet_bytes)
    if not len(packets):
        return
    header = _packet_header(packets[:, :PACKET_HEADER_BYTES], info)
    fid = header["frame_id"].astype(np.int64) | (header["init_id"].astype(np.int64) << 32)
    starts = np.flatnonzero(np.concatenate(([True], fid[1:] != fid[:-1])))
    ends = np.concatenate((starts[1:], [len(packets)]))
    cpp, cb = info.columns_per_packet, info.column_bytes
    for a, b in zip(starts, ends, strict=True):
        cols = packets[a:b, PACKET_HEADER_BYTES:PACKET_HEADER_BYTES + cpp * cb].reshape(
            b - a, cpp, cb)
        yield _assemble_profile_frame(
            {name: v[a:b] for name, v in header.items()}, _le_view(cols, 0, 8).reshape(-1),
            _le_view(cols, 8, 2).reshape(-1), _le_view(cols, 10, 2).reshape(-1),
            cols[:, :, COLUMN_HEADER_BYTES:].reshape(
                b - a, cpp, info.pixels_per_column, info.profile.pixel_bytes), info)


def _le_view(u8: np.ndarray, byte: int, n: int) -> np.ndarray:
    """The little-endian unsigned integers of ``n`` bytes at ``byte`` of the last axis of some
    bytes, a view (the last axis dropped)."""
    return u8[..., byte:byte + n].view(f"<u{n}")[..., 0]


class _Placement:
    """Where a frame's received columns go: those kept (measurement id within the frame,
    status valid) and their measurement ids ``m``; ``whole`` when every column came, once, in
    order (then a field is its columns as they are)."""

    def __init__(self, mid: np.ndarray, valid: np.ndarray, w: int) -> None:
        m = mid.astype(np.intp)
        keep = (m < w) & valid
        self.w = w
        self.idx = None if keep.all() else np.flatnonzero(keep)
        self.m = m if self.idx is None else m[self.idx]
        self.whole = (self.idx is None and len(m) == w
                      and bool((m == np.arange(w)).all()))

    @property
    def n(self) -> int:
        return len(self.m)

    def place(self, values: np.ndarray, dtype, *, owned: bool = False) -> np.ndarray:
        """(W, ...) of ``dtype``: each kept column's ``values`` at its measurement id, else 0
        (``owned``: values the caller made for this, returned themselves where they can be)."""
        if self.whole:
            if owned and values.dtype == dtype and values.flags.c_contiguous:
                return values
            return values.astype(dtype, order="C")
        out = np.zeros((self.w, *values.shape[1:]), dtype=dtype)
        out[self.m] = values if self.idx is None else values[self.idx]
        return out

    def first(self, values: np.ndarray):
        """The first kept column's value (of all the columns' ``values``)."""
        return values[0 if self.idx is None else self.idx[0]]


def _frame(cols: np.ndarray, info: OusterInfo) -> Frame:
    w = info.columns_per_frame
    at = _Placement(cols["measurement_id"], cols["status"] == COLUMN_VALID, w)
    # filled column by column, (W, H) in memory; the fields are their (H, W) views
    px = cols["pixels"]  # (n, h)
    out = {name: at.place(px[src], dt) for name, src, dt in (
        ("range_mm", "range", np.uint32), ("reflectivity", "reflectivity", np.uint8),
        ("signal", "signal", np.uint16), ("near_ir", "near_ir", np.uint16))}
    out["range_mm"] &= RANGE_MASK
    out = {name: a.T for name, a in out.items()}
    ts, mid, status, received = _column_headers(
        at, cols["timestamp"], cols["measurement_id"], cols["status"], np.uint32)
    return Frame(int(at.first(cols["frame_id"])) if at.n else -1, **out, timestamp_ns=ts,
                 measurement_id=mid, status=status, received=received,
                 packets=int(np.ceil(at.n / info.columns_per_packet)))


def _column_headers(at: _Placement, timestamp: np.ndarray, measurement_id: np.ndarray,
                    status: np.ndarray, status_dtype
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A frame's per-column timestamp (ns), measurement id, status and whether the column
    arrived, (w,) each, from its kept columns (0 elsewhere)."""
    received = np.ones(at.w, dtype=bool) if at.whole else np.zeros(at.w, dtype=bool)
    received[at.m] = True
    return (at.place(timestamp, np.uint64), at.place(measurement_id, np.uint16),
            at.place(status, status_dtype), received)


def _pixel_field(pixels: np.ndarray, f: PixelField) -> np.ndarray:
    """One channel of (..., H, pixel_bytes) pixel bytes, (..., H) as ``f.dtype``."""
    return _field_of_words(_le_view(pixels, f.byte, f.word), f)


def _field_of_words(value: np.ndarray, f: PixelField) -> np.ndarray:
    """A channel's values of its little-endian words (a view of the bytes, or words already
    copied out): shifted and masked in the word's own width (the bits kept fit it), then
    widened and shifted up (in ``f.dtype``: the same bits as shifting in 32 and narrowing
    after)."""
    mask = value.dtype.type((1 << f.bits) - 1)
    if f.shift:
        value = value >> np.uint8(f.shift)
        if f.bits < 8 * f.word - f.shift:
            value &= mask
    elif f.bits < 8 * f.word:
        if value.flags.owndata and value.flags.writeable:  # (words copied out: in place)
            value &= mask
        else:
            value = value & mask
    value = value.astype(f.dtype, copy=not value.flags.owndata)
    if f.upshift:
        value <<= value.dtype.type(f.upshift)
    return value


def _profile_frame(cols: np.ndarray, info: OusterInfo) -> Frame:
    """The `Frame` of one frame's `profile_column_dtype` columns (`_assemble_profile_frame`)."""
    header = {name: cols[name][::info.columns_per_packet] for name in (
        "frame_id", "init_id", "prod_sn", "alert_flags", "shutdown_countdown",
        "shot_limiting_countdown", "thermal_shutdown", "shot_limiting")}
    return _assemble_profile_frame(header, cols["timestamp"], cols["measurement_id"],
                                   cols["status"], cols["pixels"], info)


def _assemble_profile_frame(header: dict[str, np.ndarray], timestamp: np.ndarray,
                            measurement_id: np.ndarray, status: np.ndarray,
                            pixels: np.ndarray, info: OusterInfo) -> Frame:
    """The `Frame` of one frame's non-LEGACY packets: their headers' fields (by packet), their
    columns' headers (by column) and pixel bytes (..., H, pixel_bytes). As `_frame`, a column
    kept when its status's bit 0 says valid (ouster-sdk's batcher; 0 elsewhere); the frame's
    header from its first packet, the alert flags of each."""
    h, w, cpp = info.pixels_per_column, info.columns_per_frame, info.columns_per_packet
    alert = np.zeros(w // cpp, dtype=np.uint8)
    pid = measurement_id[::cpp].astype(np.intp) // cpp
    alert[pid[pid < len(alert)]] = header["alert_flags"][pid < len(alert)]
    at = _Placement(measurement_id, (status & 1) == 1, w)
    out = {"signal": None}  # (the RNG15 profiles send none)
    for f in info.profile.fields:
        out[f.name] = at.place(_pixel_field(pixels, f).reshape(-1, h), f.dtype, owned=True)
    if out["signal"] is None:
        out["signal"] = np.zeros((w, h), dtype=np.uint16)
    if "range2_mm" in out and "signal2" not in out:  # (nor for RNG15's second return)
        out["signal2"] = np.zeros((w, h), dtype=np.uint16)
    out = {name: a.T for name, a in out.items()}  # (H, W) views of columns filled as (W, H)
    ts, mid, status, received = _column_headers(at, timestamp, measurement_id, status,
                                                np.uint32)
    return Frame(
        int(header["frame_id"][0]), **out, timestamp_ns=ts, measurement_id=mid, status=status,
        received=received, packets=int(np.ceil(at.n / cpp)),
        init_id=int(header["init_id"][0]), prod_sn=int(header["prod_sn"][0]),
        thermal_shutdown=int(header["thermal_shutdown"][0]),
        shot_limiting=int(header["shot_limiting"][0]),
        shutdown_countdown=int(header["shutdown_countdown"][0]),
        shot_limiting_countdown=int(header["shot_limiting_countdown"][0]), alert_flags=alert)


# ----------------------------------------------------------------------------------------------
# Points and scans


def beam_geometry(info: OusterInfo, beam: np.ndarray, col: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Unit direction and offset (mm) of pixels (beam, column), (..., 3) each in the sensor
    frame's axes: a return at range r (mm) lies at r direction + offset (ouster-sdk's
    xyzlut.cpp, module docstring; the transform's translation left out)."""
    w = info.columns_per_frame
    enc = 2.0 * np.pi - col * (2.0 * np.pi / w)
    a = enc - np.radians(info.beam_azimuth_deg)[beam]
    alt = np.radians(info.beam_altitude_deg)[beam]
    d = np.stack((np.cos(a) * np.cos(alt), np.sin(a) * np.cos(alt), np.sin(alt)), axis=-1)
    bx, bz = info.beam_to_lidar_mm
    n = math.hypot(bx, bz) if bz else bx
    off = np.stack((np.cos(enc) * bx - d[..., 0] * n, np.sin(enc) * bx - d[..., 1] * n,
                    -d[..., 2] * n + bz), axis=-1)
    rot = info.lidar_to_sensor[:3, :3]
    return d @ rot.T, off @ rot.T


def xyz_lidar(range_mm: np.ndarray, info: OusterInfo) -> np.ndarray:
    """(H, W, 3) points in mm, ouster-sdk's cartesian() without the transform's translation
    (module docstring); pixels without a return at 0."""
    h, w = info.pixels_per_column, info.columns_per_frame
    beam, col = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    d, off = beam_geometry(info, beam, col)
    p = range_mm[..., None].astype(np.float64) * d + off
    p[range_mm == 0] = 0.0
    return p


def pixel_order(info: OusterInfo) -> tuple[np.ndarray, np.ndarray]:
    """(beam, column) of each firing of a frame's `Scan`, in the scan's order: destaggered
    columns (ouster-sdk's ``destagger``: beam b's pixel at column c goes to column
    c + pixel_shift_by_row[b]), each with its beams in order. So one "firing sequence" of the
    scan holds every beam at (nearly) one azimuth, as the estimator's firing grid has it (its
    neighbours across rings are neighbours in space: the beams' azimuth offsets, up to 8.5 deg
    apart on an OS1, are taken out), and every column of the window is kept."""
    h, w = info.pixels_per_column, info.columns_per_frame
    lo, hi = info.column_window
    window = np.zeros(w, dtype=bool)
    window[np.arange(lo, hi + 1) if lo <= hi else np.r_[lo:w, 0:hi + 1]] = True
    shift = info.pixel_shift_by_row
    start = int(shift.max())  # the first destaggered column every beam has fired
    j = (np.arange(w) + start) % w  # destaggered columns, from the cut behind the sensor
    beam = np.tile(np.arange(h), w)
    col = (np.repeat(j, h) - shift[beam]) % w
    keep = window[col]
    return beam[keep], col[keep]


@dataclass(frozen=True, eq=False)
class _ScanTable:
    """What every frame of a sensor shares, in the scan's firing order (`pixel_order`): each
    firing's beam, column, azimuth and the unit ray from its origin on the axis in {L}, with
    the point's offset from that ray's start per mm of range (computed once per metadata:
    ouster-sdk's XYZLut). Each axis is its own contiguous array, and each firing's index into
    a frame's (H, W) field, flat, in either memory order (`_gather`)."""

    beam: np.ndarray
    col: np.ndarray
    azimuth: np.ndarray
    direction: tuple[np.ndarray, np.ndarray, np.ndarray]  # {L}, of the sensor frame's xyz per mm
    offset: tuple[np.ndarray, np.ndarray, np.ndarray]  # {L}, mm
    origin_z: np.ndarray  # (N,) m, the firing's vertical offset
    laser_id: np.ndarray  # (N,) uint8, the beam
    flat_c: np.ndarray  # beam * W + column: into an (H, W) C-ordered field
    flat_f: np.ndarray  # column * H + beam: into the (H, W) view of a (W, H) one (`_frame`'s)
    window_cols: np.ndarray  # the columns of the column window


#: The tables of the metadata read lately, by the geometry they are made of (`_table_key`): a
#: capture opened again, with its metadata read again, does not build its table again.
_TABLES: dict[tuple, _ScanTable] = {}


def _table_key(info: OusterInfo) -> tuple:
    """Everything a `_ScanTable` is computed from."""
    return (info.pixels_per_column, info.columns_per_frame, tuple(info.column_window),
            tuple(info.beam_to_lidar_mm), info.prod_line,
            *((a.dtype.str, a.shape, np.ascontiguousarray(a).tobytes()) for a in (
                np.asarray(info.pixel_shift_by_row), np.asarray(info.beam_altitude_deg),
                np.asarray(info.beam_azimuth_deg), np.asarray(info.lidar_to_sensor),
                np.asarray(info.lasers.vertical_offset))))


def _scan_table(info: OusterInfo) -> _ScanTable:
    key = _table_key(info)
    table = _TABLES.get(key)
    if table is not None:
        return table
    h, w = info.pixels_per_column, info.columns_per_frame
    beam, col = pixel_order(info)
    d, off = beam_geometry(info, beam, col)
    to_l = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    d, off = d @ to_l.T, off @ to_l.T
    lo, hi = info.column_window
    table = _ScanTable(
        beam=beam, col=col,
        azimuth=(2.0 * np.pi * col / w + np.radians(info.beam_azimuth_deg)[beam] - np.pi)
        % (2.0 * np.pi),
        direction=tuple(np.ascontiguousarray(d[:, i]) for i in range(3)),
        offset=tuple(np.ascontiguousarray(off[:, i]) for i in range(3)),
        origin_z=info.lasers.vertical_offset[beam], laser_id=beam.astype(np.uint8),
        flat_c=beam * w + col, flat_f=col * h + beam,
        window_cols=np.arange(lo, hi + 1) if lo <= hi else np.r_[lo:w, 0:hi + 1])
    for a in (table.beam, table.col, table.azimuth, *table.direction, *table.offset,
              table.origin_z, table.laser_id, table.flat_c, table.flat_f, table.window_cols):
        a.flags.writeable = False
    if len(_TABLES) > 16:
        _TABLES.clear()
    _TABLES[key] = table
    return table


def _gather(field: np.ndarray, t: _ScanTable) -> np.ndarray:
    """``field[t.beam, t.col]`` of an (H, W) field, through its flat memory where it has one
    (a `Frame`'s fields are the (H, W) views of (W, H) arrays, filled column by column)."""
    if field.flags.f_contiguous:
        return np.take(field.ravel(order="F"), t.flat_f)
    if field.flags.c_contiguous:
        return np.take(field.ravel(), t.flat_c)
    return field[t.beam, t.col]


def _one_return(frame: Frame, t: _ScanTable) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Range (mm), reflectivity and `ReturnType` of each firing (`_returns`)."""
    second = None if frame.range2_mm is None else (
        _gather(frame.range2_mm, t), _gather(frame.reflectivity2, t))
    return _returns(_gather(frame.range_mm, t), _gather(frame.reflectivity, t), second)


def _returns(rng: np.ndarray, refl: np.ndarray,
             second: tuple[np.ndarray, np.ndarray] | None
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Range (mm), reflectivity and `ReturnType` of each firing of its first and (a dual
    profile's) second returns': the first return, which the sensor sends as the strongest; in
    a dual profile, where the first has no range and the second does, the second (flagged
    SECOND_STRONGEST), as a Velodyne's or Hesai's dual-return firing keeps its strongest echo
    and falls back to the other where the strongest missed: the beam did meet something, and
    a miss there would tell the estimator otherwise (115 of the real OS0-32 dual frame's 32768
    pixels: a first return with signal but no range)."""
    refl = refl.astype(np.uint8, copy=False)
    kind = np.full(len(rng), int(ReturnType.STRONGEST), dtype=np.uint8)
    if second is None:
        return rng, refl, kind
    rng2, refl2 = second
    is_second = rng == 0
    is_second &= rng2 > 0
    kind += np.multiply(is_second, np.uint8(int(ReturnType.SECOND_STRONGEST)
                                            - int(ReturnType.STRONGEST)), dtype=np.uint8)
    # the second's range where the first has none, else the first's (| 0); the gathered
    # reflectivities are this scan's own: the second's copied in where it is kept
    out = np.multiply(rng2, is_second, dtype=np.result_type(rng, rng2))
    out |= rng
    refl = refl.copy() if refl.base is not None else refl
    np.copyto(refl, refl2, where=is_second, casting="unsafe")
    return out, refl, kind


def scan_from_frame(frame: Frame, info: OusterInfo, *, index: int = 0) -> Scan:
    """The `Scan` of a frame: every pixel of the column window in {L}, in `pixel_order`."""
    t = _scan_table(info)
    rng, intensity, kind = _one_return(frame, t)
    missing = int((~frame.received[t.window_cols]).sum())
    return _scan(t, info, rng, intensity, kind, frame.timestamp_ns, missing, frame.packets,
                 frame.frame_id, index)


def _scan(t: _ScanTable, info: OusterInfo, rng: np.ndarray, intensity: np.ndarray,
          kind: np.ndarray, timestamp_ns: np.ndarray, missing: int, packets: int,
          frame_id: int, index: int) -> Scan:
    """The `Scan` of a frame's firings (range in mm, in `pixel_order`), its columns' times
    (ns, by column) and the columns of its window that did not come."""
    # p = r d + offset (xyz_lidar), in m; {L}: y forward, x right; 0.0 where there is no
    # return: the bits of each value anded with all ones where there is one, else none
    keep = np.negative(rng > 0, dtype=np.uint64)
    r = rng.astype(np.float64)
    # the scan's float arrays: the rows of one block (one allocation a frame, not six: with
    # six, glibc's malloc gave the memory back and took it again each frame, 700-850 page
    # faults a frame of an OS1-128, a third of the CPU time; 130 with one)
    block = np.empty((6, len(rng)))
    x, y, z, distance, time, azimuth = block
    for p, d, o in zip((x, y, z), t.direction, t.offset, strict=True):
        np.multiply(r, d, out=p)
        p += o
        p *= 1e-3
        np.bitwise_and(p.view(np.uint64), keep, out=p.view(np.uint64))
    np.multiply(x, x, out=distance)
    distance += np.multiply(y, y, out=r)
    zo = np.subtract(z, t.origin_z, out=r)
    distance += np.multiply(zo, zo, out=r)
    np.sqrt(distance, out=distance)
    np.bitwise_and(distance.view(np.uint64), keep, out=distance.view(np.uint64))
    np.take(timestamp_ns.astype(np.float64) * 1e-9, t.col, out=time, mode="clip")  # (in range)
    azimuth[:] = t.azimuth
    return Scan(
        distance=distance, azimuth=azimuth, laser_id=t.laser_id.copy(),
        intensity=intensity, time=time, return_type=kind,
        x=x, y=y, z=z, index=index, complete=missing == 0, packets=packets,
        missing_packets=int(np.ceil(missing / info.columns_per_packet)), product_id=0,
        vertical_offsets_applied=True, lasers=info.lasers,
        meta={"model": info.model, "prod_line": info.prod_line, "frame_id": frame_id,
              "rpm": 60.0 * info.rate_hz, "lidar_mode": info.lidar_mode,
              "missing_columns": missing, "partial": missing > 0})


#: LEGACY's two channels a scan reads, as `PixelField`s of its 12-byte pixel: the range word's
#: 20 bits, the reflectivity word's low byte (`_frame` keeps them so).
_LEGACY_SCAN_FIELDS = (PixelField("range_mm", 0, 4, 0, 20, np.uint32),
                       PixelField("reflectivity", 4, 1, 0, 8, np.uint8))
_SCAN_CHANNELS = ("range_mm", "reflectivity", "range2_mm", "reflectivity2")

#: Per geometry and packet layout (`_packet_index`): each scan channel's field and where each
#: firing's word of it is in a whole frame's packets, joined (an index into the packets' bytes
#: viewed as words of its size); None where a word is not aligned to its size.
_PACKET_INDEX: dict[tuple, dict[str, tuple[PixelField, np.ndarray]] | None] = {}


def _packet_index(info: OusterInfo, t: _ScanTable
                  ) -> dict[str, tuple[PixelField, np.ndarray]] | None:
    key = (_table_key(info), info.udp_profile_lidar, info.columns_per_packet)
    if key in _PACKET_INDEX:
        return _PACKET_INDEX[key]
    legacy, cpp = info.udp_profile_lidar == "LEGACY", info.columns_per_packet
    fields = _LEGACY_SCAN_FIELDS if legacy else tuple(
        f for f in info.profile.fields if f.name in _SCAN_CHANNELS)
    first = 0 if legacy else PACKET_HEADER_BYTES  # the packet's first column
    if legacy:  # where `column_dtype` puts a column's pixels, and a pixel's size
        col = column_dtype(info)
        column_header, pixel = col.fields["pixels"][1], col["pixels"].base.itemsize
    else:
        column_header, pixel = COLUMN_HEADER_BYTES, info.profile.pixel_bytes
    base = (t.col // cpp * info.packet_bytes + first + t.col % cpp * info.column_bytes
            + column_header + t.beam * pixel)
    index = {}
    for f in fields:
        at = base + f.byte
        if (at % f.word).any():
            index = None
            break
        index[f.name] = (f, at // f.word)
    if len(_PACKET_INDEX) > 16:
        _PACKET_INDEX.clear()
    _PACKET_INDEX[key] = index
    return index


def _whole_frame_scan(raw: bytes, info: OusterInfo, index: int
                      ) -> tuple[Scan, int, int] | None:
    """The `Scan` of one frame's packets (``raw``, whole packets of the metadata's size,
    joined) and its first packet's shot-limiting and thermal-shutdown states, read straight
    from the packets' bytes, without its `Frame`, when they hold one frame whole: each of its
    columns once, in order, valid, of one frame id (init id). Else None (`packet_frames`
    then makes its frames). The same scan as `scan_from_frame` of the frame."""
    w, cpp, size = info.columns_per_frame, info.columns_per_packet, info.packet_bytes
    if w % cpp or size % 4 or len(raw) != w // cpp * size:
        return None
    u8 = np.frombuffer(raw, dtype=np.uint8)
    if info.udp_profile_lidar == "LEGACY":
        cols = u8.view(column_dtype(info))
        fid = cols["frame_id"]
        if (fid != fid[0]).any() or (cols["status"] != COLUMN_VALID).any():
            return None
        mid, ts = cols["measurement_id"], cols["timestamp"]
        frame_id, shot_limiting, thermal_shutdown = int(fid[0]), 0, 0
    else:
        packets = u8.reshape(-1, size)
        header = _packet_header(packets[:, :PACKET_HEADER_BYTES], info)
        fid = header["frame_id"] | (header["init_id"] << np.uint64(32))
        cols = packets[:, PACKET_HEADER_BYTES:PACKET_HEADER_BYTES + cpp * info.column_bytes
                       ].reshape(-1, cpp, info.column_bytes)
        mid = _le_view(cols, 8, 2).reshape(-1)
        if (fid != fid[0]).any() or ((_le_view(cols, 10, 2) & 1) != 1).any():
            return None
        ts = _le_view(cols, 0, 8).reshape(-1)
        frame_id = int(header["frame_id"][0])
        shot_limiting = int(header["shot_limiting"][0])
        thermal_shutdown = int(header["thermal_shutdown"][0])
    if (mid != np.arange(w)).any():
        return None
    t = _scan_table(info)
    where = _packet_index(info, t)
    if where is None:
        return None
    words = {1: u8, 2: u8.view("<u2"), 4: u8.view("<u4")}
    channel = {name: _field_of_words(np.take(words[f.word], at), f)
               for name, (f, at) in where.items()}
    second = (channel["range2_mm"], channel["reflectivity2"]) if "range2_mm" in channel else None
    rng, intensity, kind = _returns(channel["range_mm"], channel["reflectivity"], second)
    scan = _scan(t, info, rng, intensity, kind, ts, 0, w // cpp, frame_id, index)
    return scan, shot_limiting, thermal_shutdown


def scans_from_payloads(payloads: Iterable[bytes], info: OusterInfo) -> list[Scan]:
    """Every frame of some lidar packets as a `Scan`."""
    return [scan_from_frame(f, info, index=i)
            for i, f in enumerate(frames(decode_packets(payloads, info), info))]


class OusterScans:
    """Scans from a stream of datagrams (anything with a ``payload``, or bytes), each yielded
    as soon as its frame ends (the next frame id arrives, or the stream does), and a summary.
    A frame with columns missing (the first of a live stream, joined mid-rotation; lost
    packets) is flagged partial, never presented as whole. A frame that came whole is read
    straight from its packets' bytes (`_whole_frame_scan`), any other through its `Frame`
    (`packet_frames`, `scan_from_frame`): the same scans either way."""

    def __init__(self, packets: Iterable, info: OusterInfo) -> None:
        self.packets = packets
        self.info = info
        self.counts = {"packets": 0, "other_datagrams": 0, "frames": 0, "complete": 0,
                       "firings": 0, "returns": 0, "missing_columns": 0,
                       "shot_limiting_frames": 0, "thermal_shutdown_frames": 0}

    def __iter__(self) -> Iterator[Scan]:
        size = self.info.packet_bytes
        frame: list[bytes] = []  # the packets of the frame being received
        current = None
        index = 0
        for p in self.packets:
            payload = p if isinstance(p, bytes | bytearray | memoryview) else p.payload
            if len(payload) != size:
                problem = packet_problem(payload, self.info)
                if problem is not None:  # this sensor's, and unreadable: say so, once
                    raise OusterError(problem)
                self.counts["other_datagrams"] += 1
                continue
            self.counts["packets"] += 1
            fid = packet_frame_id(payload, self.info)
            if fid != current and frame:
                yield from self._scans_of(frame, index)
                index += 1
                frame = []
            current = fid
            frame.append(bytes(payload))
        if frame:
            yield from self._scans_of(frame, index)

    def _scans_of(self, payloads: list[bytes], index: int) -> Iterator[Scan]:
        # (whole packets of the metadata's size: `decode_packets` would keep them all)
        raw = b"".join(payloads)
        whole = _whole_frame_scan(raw, self.info, index)  # (the usual frame: no Frame made)
        if whole is not None:
            yield self._count(*whole)
            return
        for f in packet_frames(raw, self.info):
            yield self._scan(f, index)

    def _scan(self, f: Frame, index: int) -> Scan:
        return self._count(scan_from_frame(f, self.info, index=index), f.shot_limiting,
                           f.thermal_shutdown)

    def _count(self, s: Scan, shot_limiting: int, thermal_shutdown: int) -> Scan:
        c = self.counts
        c["frames"] += 1
        c["complete"] += int(s.complete)
        c["firings"] += len(s)
        c["returns"] += int(s.valid.sum())
        c["missing_columns"] += s.meta["missing_columns"]
        # the packet header's states (non-LEGACY profiles): a sensor limiting its shots or
        # about to shut down for heat measures less well, which a reader should be told
        c["shot_limiting_frames"] += int(shot_limiting != 0)
        c["thermal_shutdown_frames"] += int(thermal_shutdown != 0)
        return s

    def summary(self) -> dict:
        c, i = self.counts, self.info
        return {
            "model": i.model, "prod_line": i.prod_line, "lidar_mode": i.lidar_mode,
            "profile": i.udp_profile_lidar, "serial": i.serial, "firmware": i.firmware,
            "product_id": None,
            # (a dual profile's scans keep the first, strongest, return: scan_from_frame)
            "return_mode": "dual" if _is_dual(i) else "single", "lasers": i.pixels_per_column,
            "laser_table": i.prod_line, "rpm": 60.0 * i.rate_hz, "data_packets": c["packets"],
            "other_datagrams": c["other_datagrams"], "scans": c["frames"],
            "complete_scans": c["complete"], "partial_scans": c["frames"] - c["complete"],
            "points": c["firings"], "returns": c["returns"],
            "missing_columns": c["missing_columns"], "metadata": i.source,
            "warnings": list(i.notes) + _state_warnings(c),
        }


def _state_warnings(counts: dict) -> list[str]:
    """What the frames' packet headers said of the sensor's state, for the summary."""
    out = []
    for key, what in (("shot_limiting_frames", "shot-limiting state set (the sensor limiting "
                       "its laser's shots: a weaker signal)"),
                      ("thermal_shutdown_frames", "thermal-shutdown state set (the sensor "
                       "overheating, near shutting down)")):
        if counts.get(key):
            out.append(f"{counts[key]} of {counts['frames']} frames with the packet header's "
                       f"{what}")
    return out


def _is_dual(info: OusterInfo) -> bool:
    profile = PROFILES.get(info.udp_profile_lidar)  # (an OSF's may be one not decoded here)
    return profile is not None and profile.dual


# ----------------------------------------------------------------------------------------------
# Models: real units' metadata (ouster-sdk's test captures), for the twin and as nominal tables

#: Metadata of a real unit of each line and beam count (ouster_metadata/SOURCE.md); 64 beams:
#: the 128's every second beam (a 64-beam unit's uniform layout spans the same field of view).
_METADATA_FILES = {
    ("OS0", 32): "OS-0-32-U1_v2.2.0_1024x10.json", ("OS0", 128): "OS-0-128-U1_v2.3.0_1024x10.json",
    ("OS1", 32): "OS-1-32-G_v2.1.1_1024x10.json", ("OS1", 128): "OS-1-128_v2.3.0_1024x10.json",
    ("OS2", 32): "OS-2-32-U0_v2.0.0_1024x10.json", ("OS2", 128): "OS-2-128-U1_v2.3.0_1024x10.json",
}


def is_ouster_model(name: str) -> bool:
    return _ouster_key(name) is not None


def ouster_model_name(name: str) -> str | None:
    """The model's name as aimbench writes it (``os1-64``, ``OS-1-64`` -> ``OS1-64``), None
    when it is not an Ouster's."""
    key = _ouster_key(name)
    return None if key is None else f"{key[0]}-{key[1]}"


def _ouster_key(name: str) -> tuple[str, int] | None:
    key = "".join(ch for ch in str(name).upper() if ch.isalnum())  # OS164, OS-1-64 -> OS164
    for model in OUSTER_MODELS:
        line, beams = model.split("-")
        if key == line + beams:
            return line, int(beams)
    return None


def nominal_info(model: str, lidar_mode: str = "1024x10",
                 udp_profile: str = "LEGACY") -> OusterInfo:
    """The metadata of a model (``OS1-64``...) in a lidar mode, from a real unit's file
    (`_METADATA_FILES`), sending packets of ``udp_profile`` (LEGACY by default) on port
    7502."""
    profile_of(udp_profile, f"--udp-profile {udp_profile}")
    key = _ouster_key(model)
    if key is None:
        raise OusterError(f"unknown Ouster model {model!r}: aimbench knows "
                          f"{', '.join(OUSTER_MODELS)}")
    if lidar_mode not in LIDAR_MODES:
        raise OusterError(f"unknown lidar mode {lidar_mode!r}: give one of "
                          f"{', '.join(LIDAR_MODES)}")
    line, beams = key
    path = Path(__file__).with_name("ouster_metadata") / _METADATA_FILES[
        (line, 128 if beams == 64 else beams)]
    base = OusterInfo.from_json(path)
    rows = np.arange(0, base.pixels_per_column, base.pixels_per_column // beams)
    w = int(lidar_mode.split("x")[0])
    return OusterInfo(
        prod_line=f"OS-{line[2]}-{beams}", lidar_mode=lidar_mode, columns_per_frame=w,
        pixels_per_column=beams, columns_per_packet=16, column_window=(0, w - 1),
        pixel_shift_by_row=base.pixel_shift_by_row[rows] * w // base.columns_per_frame,
        beam_altitude_deg=base.beam_altitude_deg[rows],
        beam_azimuth_deg=base.beam_azimuth_deg[rows], beam_to_lidar_mm=base.beam_to_lidar_mm,
        lidar_to_sensor=base.lidar_to_sensor, udp_profile_lidar=udp_profile,
        udp_port_lidar=LIDAR_PORT, serial="twin", firmware=base.firmware,
        source=f"{path.name} ({model}, {lidar_mode})")


def info_json(info: OusterInfo) -> str:
    """The metadata as the flat JSON of firmware 2.x (ouster-sdk and `OusterInfo` read it)."""
    return json.dumps({
        "prod_line": info.prod_line, "prod_sn": info.serial, "build_rev": info.firmware,
        "lidar_mode": info.lidar_mode,
        "beam_altitude_angles": info.beam_altitude_deg.tolist(),
        "beam_azimuth_angles": info.beam_azimuth_deg.tolist(),
        "lidar_origin_to_beam_origin_mm": info.beam_to_lidar_mm[0],
        "lidar_to_sensor_transform": info.lidar_to_sensor.ravel().tolist(),
        "data_format": {
            "columns_per_frame": info.columns_per_frame,
            "columns_per_packet": info.columns_per_packet,
            "pixels_per_column": info.pixels_per_column,
            "pixel_shift_by_row": info.pixel_shift_by_row.tolist(),
            "column_window": list(info.column_window),
            "udp_profile_lidar": info.udp_profile_lidar,
        },
        "udp_port_lidar": info.udp_port_lidar,
    }, indent=1)


def columns_from_frame(frame: Frame, info: OusterInfo) -> np.ndarray:
    """The LEGACY columns of a frame, in measurement-id order (`encode_packets` writes them)."""
    w = info.columns_per_frame
    cols = np.zeros(w, dtype=column_dtype(info))
    cols["timestamp"] = frame.timestamp_ns
    cols["measurement_id"] = np.arange(w)
    cols["frame_id"] = frame.frame_id
    cols["encoder"] = np.arange(w) * (90112 // w)  # encoder ticks, 90112 a turn (deprecated)
    cols["status"] = np.where(frame.received, COLUMN_VALID, 0)
    px = cols["pixels"]
    px["range"] = frame.range_mm.T
    px["reflectivity"] = frame.reflectivity.T
    px["signal"] = frame.signal.T
    px["near_ir"] = frame.near_ir.T
    return cols


def encode_frame(frame: Frame, info: OusterInfo, *, init_id: int = 0,
                 prod_sn: int = 0) -> list[bytes]:
    """The packets of a frame in the metadata's non-LEGACY profile (`decode_packets`' inverse,
    measurement-id order): the packet header with the frame id, ``init_id`` and ``prod_sn``
    (no alert, thermal or shot-limiting state), each column's header (status 1 when received,
    else 0), the pixels' bit fields (a field's low bits dropped where the profile sends it
    coarser: RNG15's range in 8 mm), a zero footer (firmware 2.x's; 3.x puts a CRC64 there).
    A field the frame lacks (a second return, flags) is sent as 0."""
    profile = info.profile
    if profile.legacy:
        raise ValueError("encode_frame writes the non-LEGACY profiles; LEGACY: encode_packets")
    h, w, cpp = info.pixels_per_column, info.columns_per_frame, info.columns_per_packet
    pixels = np.zeros((w, h, profile.pixel_bytes), dtype=np.uint8)
    for f in profile.fields:
        values = getattr(frame, f.name)
        if values is None:
            continue
        word = (values.T.astype(np.uint64) >> np.uint64(f.upshift)) & np.uint64((1 << f.bits) - 1)
        word <<= np.uint64(f.shift)
        for i in range(f.word):
            pixels[:, :, f.byte + i] |= ((word >> np.uint64(8 * i)) & np.uint64(0xFF)).astype(
                np.uint8)
    cols = np.zeros(w, dtype=[("timestamp", "<u8"), ("measurement_id", "<u2"),
                              ("status", "<u2"), ("pixels", "u1", (h, profile.pixel_bytes))])
    cols["timestamp"] = frame.timestamp_ns
    cols["measurement_id"] = np.arange(w)
    cols["status"] = frame.received.astype(np.uint16)
    cols["pixels"] = pixels
    header = bytearray(PACKET_HEADER_BYTES)
    if info.header_type == "FUSA":
        header[0] = 1  # packet type: lidar
        header[1:4] = init_id.to_bytes(3, "little")
        header[4:8] = (frame.frame_id % 2**32).to_bytes(4, "little")
        header[11:16] = prod_sn.to_bytes(5, "little")
    else:
        header[0:2] = (1).to_bytes(2, "little")
        header[2:4] = (frame.frame_id % 2**16).to_bytes(2, "little")
        header[4:7] = init_id.to_bytes(3, "little")
        header[7:12] = prod_sn.to_bytes(5, "little")
    footer = bytes(PACKET_FOOTER_BYTES)
    raw = cols.tobytes()
    step = cpp * info.column_bytes
    return [bytes(header) + raw[i:i + step] + footer for i in range(0, len(raw), step)]
