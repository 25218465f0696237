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
column is valid). Little-endian. Other
profiles (RNG19_RFL8_SIG16_NIR16[_DUAL], RNG15_RFL8_NIR8) are refused in one line.

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

A `Scan` of a frame keeps every pixel, returns or not, column by column (the firing grid
the estimator reads: a column is a firing sequence, a beam a laser). Decoding is bytes in,
arrays out; the pcap and socket readers are `twin.lidar.pcap` and `twin.lidar.udp`.
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

#: The lidar data port of every Ouster sensor (the IMU's is 7503).
LIDAR_PORT = 7502
#: Valid column status of the LEGACY profile.
COLUMN_VALID = 0xFFFFFFFF
RANGE_MASK = 0x000FFFFF


class OusterError(AimbenchError):
    """Ouster metadata or packets that cannot be read (a bad file, an unsupported profile)."""


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
    serial: str = ""
    firmware: str = ""
    source: str = "metadata"
    lasers: LaserTable = field(init=False, repr=False)

    def __post_init__(self) -> None:
        h = self.pixels_per_column
        for name in ("pixel_shift_by_row", "beam_altitude_deg", "beam_azimuth_deg"):
            if len(getattr(self, name)) != h:
                raise OusterError(f"{self.source}: {name} has {len(getattr(self, name))} entries "
                                  f"for {h} beams: a damaged metadata file")
        object.__setattr__(self, "lasers", LaserTable(
            self.prod_line, np.radians(self.beam_altitude_deg),
            np.zeros(h), np.radians(self.beam_azimuth_deg)))

    # -- derived ---------------------------------------------------------------------------
    @property
    def rate_hz(self) -> float:
        """Frames a second, from the lidar mode (``1024x10``: 10 Hz)."""
        return float(self.lidar_mode.split("x")[1])

    @property
    def column_bytes(self) -> int:
        return 16 + 12 * self.pixels_per_column + 4

    @property
    def packet_bytes(self) -> int:
        return self.columns_per_packet * self.column_bytes

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
        else:  # flat: firmware 2.0-2.3
            bi, fmt = d, d["data_format"]
            prod, serial, fw = d["prod_line"], str(d.get("prod_sn", "")), d.get("build_rev", "")
            mode = d.get("lidar_mode", f"{fmt['columns_per_frame']}x10")
            profile = fmt.get("udp_profile_lidar", "LEGACY")
            port = int(d.get("udp_port_lidar", LIDAR_PORT))
            lts = d.get("lidar_to_sensor_transform")
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
            udp_port_lidar=port, serial=serial, firmware=fw, source=source)


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
    """The columns of LEGACY lidar packets, (n_packets * columns_per_packet,) records (range
    masked to its 20 bits). Payloads of another size are skipped (IMU packets, other sensors)."""
    if info.udp_profile_lidar != "LEGACY":
        raise OusterError(f"{info.source}: the sensor sends the {info.udp_profile_lidar} packet "
                          "profile; aimbench decodes LEGACY only: set udp_profile_lidar to "
                          "LEGACY on the sensor")
    size = info.packet_bytes
    good = [p for p in payloads if len(p) == size]
    cols = np.frombuffer(b"".join(good), dtype=column_dtype(info)).copy()
    cols["pixels"]["range"] &= RANGE_MASK
    return cols


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


def frames(columns: np.ndarray, info: OusterInfo) -> Iterator[Frame]:
    """The frames of decoded columns, in order (a new frame id starts a new frame)."""
    if not len(columns):
        return
    fid = columns["frame_id"].astype(np.int64)
    starts = np.flatnonzero(np.concatenate(([True], fid[1:] != fid[:-1])))
    ends = np.concatenate((starts[1:], [len(columns)]))
    for a, b in zip(starts, ends, strict=True):
        yield _frame(columns[a:b], info)


def _frame(cols: np.ndarray, info: OusterInfo) -> Frame:
    h, w = info.pixels_per_column, info.columns_per_frame
    m = cols["measurement_id"].astype(np.intp)
    keep = (m < w) & (cols["status"] == COLUMN_VALID)
    cols, m = cols[keep], m[keep]
    out = {name: np.zeros((h, w), dtype=dt) for name, dt in (
        ("range_mm", np.uint32), ("reflectivity", np.uint8), ("signal", np.uint16),
        ("near_ir", np.uint16))}
    px = cols["pixels"]  # (n, h)
    for name, src in (("range_mm", "range"), ("reflectivity", "reflectivity"),
                      ("signal", "signal"), ("near_ir", "near_ir")):
        out[name][:, m] = px[src].T
    ts = np.zeros(w, dtype=np.uint64)
    ts[m] = cols["timestamp"]
    mid = np.zeros(w, dtype=np.uint16)
    mid[m] = cols["measurement_id"]
    status = np.zeros(w, dtype=np.uint32)
    status[m] = cols["status"]
    received = np.zeros(w, dtype=bool)
    received[m] = True
    return Frame(int(cols["frame_id"][0]) if len(cols) else -1, **out, timestamp_ns=ts,
                 measurement_id=mid, status=status, received=received,
                 packets=int(np.ceil(len(cols) / info.columns_per_packet)))


# ----------------------------------------------------------------------------------------------
# Points and scans


def xyz_lidar(range_mm: np.ndarray, info: OusterInfo) -> np.ndarray:
    """(H, W, 3) points in mm, ouster-sdk's cartesian() without the transform's translation
    (module docstring); pixels without a return at 0."""
    h, w = info.pixels_per_column, info.columns_per_frame
    enc = 2.0 * np.pi - np.arange(w) * (2.0 * np.pi / w)  # (W,)
    az = -np.radians(info.beam_azimuth_deg)[:, None]  # (H, 1)
    alt = np.radians(info.beam_altitude_deg)[:, None]
    d = np.stack(np.broadcast_arrays(np.cos(enc + az) * np.cos(alt),
                                     np.sin(enc + az) * np.cos(alt),
                                     np.broadcast_to(np.sin(alt), (h, w))), axis=-1)
    bx, bz = info.beam_to_lidar_mm
    n = math.hypot(bx, bz) if bz else bx
    off = np.stack(np.broadcast_arrays(np.cos(enc)[None, :] * bx - d[..., 0] * n,
                                       np.sin(enc)[None, :] * bx - d[..., 1] * n,
                                       -d[..., 2] * n + bz), axis=-1)
    p = range_mm[..., None].astype(np.float64) * d + off
    p = p @ info.lidar_to_sensor[:3, :3].T
    p[range_mm == 0] = 0.0
    return p


def scan_from_frame(frame: Frame, info: OusterInfo, *, index: int = 0) -> Scan:
    """The `Scan` of a frame: every pixel of the column window, column by column, in {L}."""
    h, w = info.pixels_per_column, info.columns_per_frame
    lo, hi = info.column_window
    cols = np.arange(lo, hi + 1) if lo <= hi else np.r_[lo:w, 0:hi + 1]
    p = xyz_lidar(frame.range_mm, info)[:, cols] * 1e-3  # (H, C, 3) m, sensor axes
    # {L}: y forward, x right (X_L = -y, Y_L = x of the sensor frame's axes)
    x, y, z = (-p[..., 1]).T.ravel(), p[..., 0].T.ravel(), p[..., 2].T.ravel()
    rng = frame.range_mm[:, cols].T.ravel()
    distance = np.where(rng > 0, np.sqrt(x * x + y * y + z * z), 0.0)
    lid = np.tile(np.arange(h, dtype=np.uint8), len(cols))
    azimuth = ((2.0 * np.pi * np.repeat(cols, h) / w + np.radians(info.beam_azimuth_deg)[lid]
                - np.pi) % (2.0 * np.pi))
    time = np.repeat(frame.timestamp_ns[cols].astype(np.float64) * 1e-9, h)
    missing = int((~frame.received[cols]).sum())
    return Scan(
        distance=distance, azimuth=azimuth, laser_id=lid,
        intensity=np.clip(frame.reflectivity[:, cols].T.ravel(), 0, 255).astype(np.uint8),
        time=time, return_type=np.full(len(lid), int(ReturnType.STRONGEST), dtype=np.uint8),
        x=x, y=y, z=z, index=index, complete=missing == 0, packets=frame.packets,
        missing_packets=int(np.ceil(missing / info.columns_per_packet)), product_id=0,
        vertical_offsets_applied=False, lasers=info.lasers,
        meta={"model": info.model, "prod_line": info.prod_line, "frame_id": frame.frame_id,
              "rpm": 60.0 * info.rate_hz, "lidar_mode": info.lidar_mode,
              "missing_columns": missing, "partial": missing > 0})


def scans_from_payloads(payloads: Iterable[bytes], info: OusterInfo) -> list[Scan]:
    """Every frame of some lidar packets as a `Scan`."""
    return [scan_from_frame(f, info, index=i)
            for i, f in enumerate(frames(decode_packets(payloads, info), info))]


class OusterScans:
    """Scans from a stream of datagrams (anything with a ``payload``, or bytes), each yielded
    as soon as its frame ends (the next frame id arrives, or the stream does), and a summary.
    A frame with columns missing (the first of a live stream, joined mid-rotation; lost
    packets) is flagged partial, never presented as whole."""

    def __init__(self, packets: Iterable, info: OusterInfo, batch: int = 64) -> None:
        self.packets = packets
        self.info = info
        self.batch = batch
        self.counts = {"packets": 0, "other_datagrams": 0, "frames": 0, "complete": 0,
                       "firings": 0, "returns": 0, "missing_columns": 0}

    def __iter__(self) -> Iterator[Scan]:
        pending: list[np.ndarray] = []
        buf: list[bytes] = []
        index = 0
        size = self.info.packet_bytes

        def flush() -> Iterator[Scan]:
            nonlocal index, pending
            cols = np.concatenate(pending) if pending else np.zeros(0, column_dtype(self.info))
            fid = cols["frame_id"]
            # every frame but the last is over; the last waits for more columns
            last = int(np.flatnonzero(np.concatenate(([True], fid[1:] != fid[:-1])))[-1])
            for f in frames(cols[:last], self.info):
                yield self._scan(f, index)
                index += 1
            pending = [cols[last:]]

        for p in self.packets:
            payload = p if isinstance(p, bytes | bytearray | memoryview) else p.payload
            if len(payload) != size:
                self.counts["other_datagrams"] += 1
                continue
            self.counts["packets"] += 1
            buf.append(bytes(payload))
            if len(buf) >= self.batch:
                pending.append(decode_packets(buf, self.info))
                buf = []
                yield from flush()
        if buf:
            pending.append(decode_packets(buf, self.info))
        cols = np.concatenate(pending) if pending else np.zeros(0, column_dtype(self.info))
        for f in frames(cols, self.info):
            yield self._scan(f, index)
            index += 1

    def _scan(self, f: Frame, index: int) -> Scan:
        s = scan_from_frame(f, self.info, index=index)
        c = self.counts
        c["frames"] += 1
        c["complete"] += int(s.complete)
        c["firings"] += len(s)
        c["returns"] += int(s.valid.sum())
        c["missing_columns"] += s.meta["missing_columns"]
        return s

    def summary(self) -> dict:
        c, i = self.counts, self.info
        return {
            "model": i.model, "prod_line": i.prod_line, "lidar_mode": i.lidar_mode,
            "profile": i.udp_profile_lidar, "serial": i.serial, "firmware": i.firmware,
            "product_id": None, "return_mode": "single", "lasers": i.pixels_per_column,
            "laser_table": i.prod_line, "rpm": 60.0 * i.rate_hz, "data_packets": c["packets"],
            "other_datagrams": c["other_datagrams"], "scans": c["frames"],
            "complete_scans": c["complete"], "partial_scans": c["frames"] - c["complete"],
            "points": c["firings"], "returns": c["returns"],
            "missing_columns": c["missing_columns"], "metadata": i.source, "warnings": [],
        }
