"""Assemble data packets (VLP-16, Puck Hi-Res, VLP-32C, HDL-32E) into scans (one rotation
each) and account for every packet.

A `ScanAssembler` takes data-packet payloads in arrival order (from a pcap file or a socket)
and yields `twin.core.scan.Scan` objects. On the way it:

- checks each payload (size, block flags, factory bytes) and drops and counts bad ones;
- orders packets by their sensor timestamp (us past the hour, unwrapped across the hour) in a
  small reorder window, counting ``out_of_order`` arrivals, ``duplicates`` (a timestamp seen
  before) and ``late`` packets (arrived after their place in the stream was passed: dropped);
- counts ``missing`` packets from the timestamp steps (the model's packet period: 1.327 ms for
  a VLP-16, 0.664 ms for a VLP-32C, 0.553 ms for an HDL-32E; half in dual-return mode) and
  charges each missing packet to the scan(s) it belonged to, so a scan
  with holes says so (``complete=False``, ``missing_packets > 0``);
- cuts scans at a fixed azimuth (default pi: behind the sensor, opposite the board, so the board
  is never split between two scans). Every firing is kept; the first and last scans of a stream
  are emitted even if they cover less than a rotation, flagged ``meta["partial"]`` and
  ``complete=False`` (nothing is lost at the start or the end of a file).

Two cut styles: ``split="firing"`` (default) puts each firing in the rotation its own azimuth
belongs to, so a scan spans exactly [cut, cut + 360 deg); ``split="packet"`` keeps packets
whole, ending a scan with the packet whose last block passes the cut (the ROS velodyne driver
and velodyne_decoder do this; it lets the two be compared scan by scan).
"""

from __future__ import annotations

import math
import warnings
from collections import Counter, deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from twin.core import vlp16
from twin.core.lasers import LaserTable
from twin.core.scan import Scan
from twin.core.sensors import MODELS, VLP16, SensorModel, model_of_product_id
from twin.lidar.packets import (
    DATA_PACKET_DTYPE,
    FIRINGS_PER_PACKET,
    US_PER_HOUR,
    UnsupportedSensorError,
    as_packet_records,
    decode_records,
    identify_model,
    resolve_model,
    validate_records,
)

TWO_PI = 2.0 * math.pi
#: Product ids of the models aimbench knows: another of them on a stream is another sensor.
KNOWN_PRODUCT_IDS = np.array(sorted({m.product_id for m in MODELS.values()}), dtype=np.uint8)
#: Packets of another known sensor that make a stream two sensors' (at least this many, and
#: at least this share of the stream): a corrupted product id byte is rarer than that.
MIXED_MIN_PACKETS = 3
MIXED_SHARE = 0.02


class MixedSensorsError(UnsupportedSensorError):
    """Packets of two sensor models arrive on one port."""


class ModelOverrideWarning(UserWarning):
    """The packets' product id names another model than the one they are decoded as."""


def _warn_model_override(pid: int, sensor: SensorModel, model: SensorModel | None) -> None:
    """Say when a given model (``--model``, a station's sensor.model) overrides a product id
    that names another: a VLP-32C's capture decoded as a VLP-16 under ``--station paper`` was
    silently wrong (issue 37). 0x21 is also old VLP-16 firmware's: not told."""
    named = model_of_product_id(pid)
    if model is None or named is None or named.name == sensor.name:
        return
    if pid == vlp16.PRODUCT_ID_VLP16_OLD_FIRMWARE:
        return
    warnings.warn(
        f"the packets' product id 0x{pid:02x} says {named.name}, but they are decoded as a "
        f"{sensor.name} (--model or the station's sensor.model): {named.n_lasers} lasers read as "
        f"{sensor.n_lasers}; give --model '{named.name}' or a station of that sensor if the id "
        "is right", ModelOverrideWarning, stacklevel=4)
#: `ScanAssembler.push` takes payloads in groups of this many.
INBOX = 8
#: Default for `ScanAssembler.break_s`: a timestamp step longer than this is a break in the
#: timeline (clock set by PPS, long outage, corrupted timestamp), not lost packets, s.
BREAK_S = 1.0
_FIELDS = ("distance", "azimuth", "laser_id", "intensity", "time", "return_type", "x", "y", "z")


@dataclass
class StreamStats:
    """Counts over a whole stream of data packets (all counts are packets unless named)."""

    packets: int = 0  # accepted and assembled into scans
    duplicates: int = 0
    out_of_order: int = 0  # arrived after a later packet (reordered if within the window)
    late: int = 0  # arrived too late to be reordered: dropped
    missing: int = 0  # never arrived, from the timestamp steps
    gaps: int = 0  # places where packets went missing
    breaks: int = 0  # timestamp jumps longer than break_s (clock set, long outage, corruption)
    rejected: Counter = field(default_factory=Counter)  # malformed, by reason
    scans: int = 0
    incomplete_scans: int = 0
    partial_scans: int = 0

    def as_dict(self) -> dict:
        out = {k: v for k, v in self.__dict__.items() if k != "rejected"}
        out["rejected"] = {k: v for k, v in self.rejected.items() if v}
        return out


@dataclass
class _Chunk:
    """Decoded firings of consecutive released packets, with their scan ids."""

    arrays: dict[str, np.ndarray]  # per firing, flat
    sid: np.ndarray  # per firing scan id
    u: np.ndarray  # per firing unwrapped azimuth, rad
    packet_ts: np.ndarray  # per packet raw timestamp, us past the hour
    packet_sid_min: np.ndarray
    packet_sid_max: np.ndarray
    rpm: np.ndarray
    return_mode: np.ndarray
    product_id: np.ndarray


class ScanAssembler:
    """Turn a stream of VLP-16 data-packet payloads into `Scan`s.

    ``cut_azimuth``: where one scan ends and the next begins, rad in {L} (azimuth 0 = Y_L
    forward); ``None`` cuts at the azimuth of the stream's first firing (or first packet), so
    the first scan is whole. ``split``: ``"firing"`` or ``"packet"`` (module docstring).
    ``vertical_offsets``: apply the lasers' vertical offsets (default, as the manual says).
    ``model``: a model's name or `SensorModel` to decode as, whatever the product id says
    (default: from the product id, `twin.lidar.packets.identify_model`). ``lasers``: the unit's
    own laser table (a calibration file) instead of the model's; scans carry it.
    ``reorder_window``: how many packets are held back to put out-of-order arrivals in place
    (latency: window x 1.3 ms for a VLP-16).
    ``decode_batch``: released packets are decoded this many at a time. ``break_s``: a
    timestamp step longer than this is a break (counted in ``stats.breaks``, flagged on its
    scan), not that many lost packets: a single corrupted timestamp then costs nothing, but
    an outage that long is reported as a break rather than as a packet count.

    ``push(payload)`` / ``push_many(payloads)`` return the scans completed so far;
    ``finish()`` flushes the rest. ``stats`` counts everything (`StreamStats`).
    """

    def __init__(
        self,
        cut_azimuth: float | None = math.pi,
        *,
        split: Literal["firing", "packet"] = "firing",
        vertical_offsets: bool = True,
        model: str | SensorModel | None = None,
        lasers: LaserTable | None = None,
        reorder_window: int = 16,
        decode_batch: int = 32,
        break_s: float = BREAK_S,
    ) -> None:
        if split not in ("firing", "packet"):
            raise ValueError(f"split is 'firing' or 'packet', not {split!r}")
        self.cut_azimuth = None if cut_azimuth is None else float(cut_azimuth) % TWO_PI
        self.split = split
        self.vertical_offsets = vertical_offsets
        self.model = resolve_model(model)
        self.lasers = lasers
        #: The sensor the stream is decoded as (known once the first packets are in).
        self.sensor: SensorModel | None = None
        self.reorder_window = max(0, int(reorder_window))
        self.decode_batch = max(1, int(decode_batch))
        self.break_s = float(break_s)
        self.stats = StreamStats()
        self.product_id: int | None = None
        self._seen_ids = 0
        self._foreign_ids: Counter = Counter()
        self._inbox: list[bytes] = []
        # Arrival-order timestamp unwrapping.
        self._last_raw: int | None = None
        self._last_unwrapped = 0
        self._max_arrived: int | None = None
        # Reorder window and release.
        # Packets are held as raw (n, 1206) bytes: concatenating structured arrays is slow.
        self._pend_raw = np.zeros((0, vlp16.DATA_PAYLOAD_SIZE), dtype=np.uint8)
        self._pend_ts = np.zeros(0, dtype=np.int64)
        self._pend_aux = np.zeros((0, 2), dtype=np.int64)  # (hour rollovers, time break)
        self._break_shift = 0  # how far the breaks moved the timeline, us
        self._released_max: int | None = None
        self._recent = deque(maxlen=4096)
        self._recent_set: set[int] = set()
        self._rel_rec: list[np.ndarray] = []
        self._rel_ts: list[np.ndarray] = []
        self._rel_aux: list[np.ndarray] = []
        self._breaks_by_sid: Counter = Counter()
        # Scan geometry state.
        self._cut_ref: float | None = None
        self._prev_u0: float | None = None
        self._prev_az0 = 0.0
        self._prev_ulast: float | None = None
        self._prev_ts: int | None = None
        self._prev_span = 0.0
        self._first_sid: int | None = None
        self._missing_by_sid: Counter = Counter()
        self._open: list[_Chunk] = []
        self._closed_below: int | None = None  # scans below this id have been emitted

    # ---------------------------------------------------------------------------------------
    # Input

    def push(self, payload: bytes) -> list[Scan]:
        """Add one data-packet payload (1206 bytes); returns the scans it completed.

        Payloads are taken in groups of `INBOX` (about 10 ms of data), so that the per-call
        cost of the array work is shared: a live stream costs a few percent of a core.
        """
        self._inbox.append(payload)
        if len(self._inbox) < INBOX:
            return []
        batch, self._inbox = self._inbox, []
        return self.push_many(batch)

    def push_many(self, payloads: np.ndarray | Sequence[bytes]) -> list[Scan]:
        """Add many payloads in arrival order; returns the scans they completed."""
        records, _, wrong_size = as_packet_records(payloads)
        self.stats.rejected["size"] += wrong_size
        records = self._validate(records)
        if len(records):
            self._arrive(records)
        return self._release(final=False)

    def finish(self) -> list[Scan]:
        """End of stream: release everything held back and emit the remaining scans."""
        scans = self.push_many(self._inbox) if self._inbox else []
        self._inbox = []
        scans += self._release(final=True)
        scans += self._emit(final=True)
        return scans

    # ---------------------------------------------------------------------------------------
    # Validation, ordering, accounting

    def _validate(self, records: np.ndarray) -> np.ndarray:
        bad = np.zeros(len(records), dtype=bool)
        for reason, mask in validate_records(records).items():
            mask = mask & ~bad
            self.stats.rejected[reason] += int(mask.sum())
            bad |= mask
        return records[~bad] if bad.any() else records

    def _arrive(self, records: np.ndarray) -> None:
        raw = records["timestamp"].astype(np.int64)
        if self._last_raw is None:
            self._last_raw = self._last_unwrapped = int(raw[0])
        before_raw = np.concatenate(([self._last_raw], raw[:-1]))
        step = (raw - before_raw) % US_PER_HOUR
        step = np.where(step > US_PER_HOUR // 2, step - US_PER_HOUR, step)
        # A jump of more than break_s (a clock set by GPS/PPS, a long outage, a corrupted
        # timestamp) is a break in the timeline, not thousands of lost packets: the packet
        # keeps its place in arrival order and the break is counted and flagged.
        brk = np.abs(step) > self.break_s * 1e6
        self.stats.breaks += int(brk.sum())
        sensor = self.sensor or self.model or VLP16
        nominal = np.where(records["return_mode"] == vlp16.RETURN_MODE_DUAL,
                           sensor.packet_period(vlp16.RETURN_MODE_DUAL),
                           sensor.packet_period(vlp16.RETURN_MODE_STRONGEST)) * 1e6
        kept = np.where(brk, np.round(nominal).astype(np.int64), step)
        ts = self._last_unwrapped + np.cumsum(kept)
        # Whole hours since the first packet's hour: the timeline without the breaks' shifts
        # differs from the raw timestamps by whole hours only.
        shift = self._break_shift + np.cumsum(kept - step)
        hours = (ts - shift - raw) // US_PER_HOUR
        self._break_shift = int(shift[-1])
        self._last_raw, self._last_unwrapped = int(raw[-1]), int(ts[-1])
        # Out of order: earlier than something that arrived before it.
        before = np.maximum.accumulate(ts)
        if self._max_arrived is not None:
            before = np.maximum(before, self._max_arrived)
        running = np.concatenate(([self._max_arrived if self._max_arrived is not None
                                   else ts[0]], before[:-1]))
        self.stats.out_of_order += int((ts < running).sum())
        self._max_arrived = int(before[-1])
        raw = _raw(records)
        self._pend_raw = np.concatenate((self._pend_raw, raw)) if len(self._pend_raw) else raw
        self._pend_ts = np.concatenate((self._pend_ts, ts))
        self._pend_aux = np.concatenate((self._pend_aux, np.column_stack((hours, brk))))

    def _check_one_sensor(self, product_ids: np.ndarray, other: np.ndarray) -> None:
        """Refuse a stream in which another known sensor's packets keep coming: two sensors on
        one port (a VLP-16's packets were measured and a VLP-32C's dropped unsaid, issue 37).
        A corrupted byte now and then is a malformed packet, dropped and counted."""
        self._seen_ids += len(product_ids)
        foreign = other & np.isin(product_ids, KNOWN_PRODUCT_IDS)
        if not foreign.any():
            return
        self._foreign_ids.update(product_ids[foreign].tolist())
        n = sum(self._foreign_ids.values())
        if n >= MIXED_MIN_PACKETS and n >= MIXED_SHARE * self._seen_ids:
            pid, count = self._foreign_ids.most_common(1)[0]
            mine = self.sensor.name if self.sensor is not None else f"0x{self.product_id:02x}"
            raise MixedSensorsError(
                f"packets of two sensors on one port: {count} of {self._seen_ids} are a "
                f"{model_of_product_id(pid).name}'s (product id 0x{pid:02x}), the others a "
                f"{mine}'s (0x{self.product_id:02x}); give each sensor its own port (its "
                "web page's data port; docs/vlp16.md), or record one at a time")

    def _release(self, final: bool) -> list[Scan]:
        raw, ts, aux = self._pend_raw, self._pend_ts, self._pend_aux
        rec = _records(raw)
        if len(rec) == 0:
            return self._decode_released(final)
        if self.product_id is None:
            if len(rec) < 2 and not final:
                return []  # one packet cannot tell a VLP-16 with id 0x21 from an HDL-32E
            self.product_id, sensor = identify_model(
                rec["product_id"], rec["timestamp"], rec["return_mode"], self.model,
                rec["blocks"]["channels"]["distance"])
            self.sensor = sensor if self.lasers is None else _with_table(sensor, self.lasers)
            _warn_model_override(self.product_id, sensor, self.model)
        other = rec["product_id"] != self.product_id
        self._check_one_sensor(rec["product_id"], other)
        self.stats.rejected["product_id"] += int(other.sum())
        if other.any():
            raw, ts, aux = raw[~other], ts[~other], aux[~other]
        # Order by timestamp; the first of equal timestamps wins, later copies are duplicates.
        if len(ts) > 1 and not (ts[1:] > ts[:-1]).all():  # the usual case needs no copy
            order = np.argsort(ts, kind="stable")
            raw, ts, aux = raw[order], ts[order], aux[order]
        dup = np.zeros(len(ts), dtype=bool)
        dup[1:] = ts[1:] == ts[:-1]
        late = np.zeros(len(ts), dtype=bool)
        if self._released_max is not None:
            passed = np.flatnonzero((ts <= self._released_max) & ~dup)
            seen = np.fromiter((t in self._recent_set for t in ts[passed].tolist()), bool,
                               len(passed))
            dup[passed[seen]] = True
            late[passed[~seen]] = True
        self.stats.duplicates += int(dup.sum())
        self.stats.late += int(late.sum())
        keep = ~(dup | late)
        if not keep.all():
            raw, ts, aux = raw[keep], ts[keep], aux[keep]
        n_out = len(ts) if final else max(0, len(ts) - self.reorder_window)
        if n_out:
            self._rel_rec.append(raw[:n_out])
            self._rel_ts.append(ts[:n_out])
            self._rel_aux.append(aux[:n_out])
            self._released_max = int(ts[n_out - 1])
            for t in ts[max(0, n_out - self._recent.maxlen):n_out].tolist():
                if len(self._recent) == self._recent.maxlen:
                    self._recent_set.discard(self._recent[0])
                self._recent.append(t)
                self._recent_set.add(t)
        self._pend_raw, self._pend_ts, self._pend_aux = raw[n_out:], ts[n_out:], aux[n_out:]
        return self._decode_released(final)

    # ---------------------------------------------------------------------------------------
    # Decoding and scan ids

    def _decode_released(self, final: bool) -> list[Scan]:
        n = sum(len(r) for r in self._rel_rec)
        if n == 0 or (n < self.decode_batch and not final):
            return []
        rec = _records(np.concatenate(self._rel_rec))
        ts = np.concatenate(self._rel_ts)
        aux = np.concatenate(self._rel_aux)
        self._rel_rec, self._rel_ts, self._rel_aux = [], [], []
        dec = decode_records(rec, np.arange(len(rec)), self.vertical_offsets, {}, self.sensor)
        self.stats.packets += len(rec)
        chunk = self._assign(dec, ts, aux)
        self._open.append(chunk)
        return self._emit(final=False)

    def _assign(self, dec, ts: np.ndarray, aux: np.ndarray) -> _Chunk:
        """Unwrap azimuth across packets, give every firing its scan id, count gaps."""
        az0 = dec.block_azimuth_cdeg[:, 0] * (math.pi / 18000.0)
        rate = dec.azimuth_rate
        span = ((dec.block_azimuth_cdeg[:, -1] * (math.pi / 18000.0)) - az0) % TWO_PI
        prev_ts = ts[0] if self._prev_ts is None else self._prev_ts
        prev_az0 = az0[0] if self._prev_u0 is None else self._prev_az0
        dt = np.diff(np.concatenate(([prev_ts], ts))) * 1e-6
        dwrap = (az0 - np.concatenate(([prev_az0], az0[:-1]))) % TWO_PI
        # Whole turns that a long gap can hide: from the rotation rate and the time step.
        turns = np.round((rate * dt - dwrap) / TWO_PI)
        du = dwrap + TWO_PI * np.maximum(turns, 0)
        u0 = (self._prev_u0 if self._prev_u0 is not None else az0[0]) + np.cumsum(du)
        # Unwrapped azimuth of every firing: block azimuths unwrapped per packet, plus the
        # rotation since the block's first firing (as the decoder computed it).
        block_az = dec.block_azimuth_cdeg * (math.pi / 18000.0)
        ublock = u0[:, None] + (block_az - az0[:, None]) % TWO_PI  # (n, 12)
        delta = rate[:, None] * self.sensor.channel_offsets()[None, :]  # (n, 32)
        u = (ublock[:, :, None] + delta[:, None, :]).reshape(len(ts), -1)  # (n, 384)
        ulast = u0 + span
        if self._cut_ref is None:
            start = u[0, 0] if self.split == "firing" else ulast[0]
            if self.cut_azimuth is None:
                self._cut_ref = float(start)
            else:
                self._cut_ref = self.cut_azimuth + TWO_PI * math.floor(
                    (start - self.cut_azimuth) / TWO_PI)
        if self.split == "firing":
            sid = self._firing_scan_ids(u, ublock, delta)
        else:
            prev_ulast = ulast[0] if self._prev_ulast is None else self._prev_ulast
            before = np.concatenate(([prev_ulast], ulast[:-1]))
            psid = np.floor((before - self._cut_ref) / TWO_PI).astype(np.int64)
            sid = np.broadcast_to(psid[:, None], u.shape)
        if self._first_sid is None:
            self._first_sid = int(sid[0, 0])
        for k in sid[aux[:, 1] > 0, 0].tolist():
            self._breaks_by_sid[int(k)] += 1
        self._count_gaps(ts, u0, span, self.sensor.packet_period(int(dec.return_mode[0])) * 1e6)
        self._prev_ts, self._prev_az0 = int(ts[-1]), float(az0[-1])
        self._prev_u0, self._prev_ulast, self._prev_span = float(u0[-1]), float(ulast[-1]), \
            float(span[-1])
        hour = aux[:, 0] * 3600.0  # the sensor clock counts past the hour: keep counting
        arrays = {
            name: getattr(dec, name).reshape(-1) for name in _FIELDS if name != "time"
        }
        arrays["time"] = (dec.time + hour[:, None]).reshape(-1)
        arrays["laser_id"] = np.ascontiguousarray(arrays["laser_id"])
        flat_sid, flat_u = sid.reshape(-1), u.reshape(-1)
        if len(flat_sid) > 1 and (np.diff(flat_sid) < 0).any():
            # Dual mode: the two blocks of a pair share azimuths, so a cut inside a pair's
            # span interleaves scan ids; put each scan's firings together, time order kept.
            order = np.argsort(flat_sid, kind="stable")
            arrays = {name: a[order] for name, a in arrays.items()}
            flat_sid, flat_u = flat_sid[order], flat_u[order]
        return _Chunk(
            arrays=arrays,
            sid=flat_sid,
            u=flat_u,
            packet_ts=dec.timestamp_us,
            packet_sid_min=sid.min(axis=1),
            packet_sid_max=sid.max(axis=1),
            rpm=dec.rpm,
            return_mode=dec.return_mode,
            product_id=dec.product_id,
        )

    def _firing_scan_ids(
        self, u: np.ndarray, ublock: np.ndarray, delta: np.ndarray
    ) -> np.ndarray:
        """Scan id of each firing, (n, 384): which rotation past the cut its azimuth is in."""
        flat = u.reshape(-1)
        # Firings are in azimuth order when every block starts after the previous block's
        # last firing (always, in single-return mode): then a few binary searches place the
        # cuts. Otherwise (dual-return pairs, damaged azimuths) divide firing by firing.
        starts = ublock.reshape(-1)
        ends = (ublock + delta[:, -1:]).reshape(-1)
        if (starts[1:] >= ends[:-1]).all():
            k0 = math.floor((flat[0] - self._cut_ref) / TWO_PI)
            k1 = math.floor((flat[-1] - self._cut_ref) / TWO_PI)
            ks = np.arange(k0, k1 + 1)
            bounds = np.searchsorted(flat, self._cut_ref + TWO_PI * ks[1:], side="left")
            counts = np.diff(np.concatenate(([0], bounds, [len(flat)])))
            return np.repeat(ks, counts).reshape(u.shape)
        return np.floor((u - self._cut_ref) / TWO_PI).astype(np.int64)

    def _count_gaps(
        self, ts: np.ndarray, u0: np.ndarray, span: np.ndarray, period_us: float
    ) -> None:
        """Missing packets from timestamp steps, each charged to the scan(s) it spanned."""
        if self._prev_ts is None:
            prev_ts, prev_u0, prev_span = ts[:1], u0[:1], span[:1]
        else:
            prev_ts = np.array([self._prev_ts])
            prev_u0 = np.array([self._prev_u0])
            prev_span = np.array([self._prev_span])
        all_ts = np.concatenate((prev_ts, ts))
        all_u0 = np.concatenate((prev_u0, u0))
        all_span = np.concatenate((prev_span, span))
        missing = np.round(np.diff(all_ts) / period_us).astype(np.int64) - 1
        for i in np.flatnonzero(missing > 0):
            m = int(missing[i])
            self.stats.gaps += 1
            self.stats.missing += m
            # Where the missing packets were: evenly between the two that arrived.
            step = (all_u0[i + 1] - all_u0[i]) / (m + 1)
            first = all_u0[i] + step * np.arange(1, m + 1)
            last = first + 0.5 * (all_span[i] + all_span[i + 1])
            if self.split == "packet":
                # A packet's scan is set by the previous packet's last block.
                a = b = np.floor((last - step - self._cut_ref) / TWO_PI)
            else:
                a = np.floor((first - self._cut_ref) / TWO_PI)
                b = np.floor((last - self._cut_ref) / TWO_PI)
            for k in np.union1d(a, b).astype(int):
                self._missing_by_sid[int(k)] += int(((a == k) | (b == k)).sum())

    # ---------------------------------------------------------------------------------------
    # Emission

    def _emit(self, final: bool) -> list[Scan]:
        if not self._open:
            return []
        emitted_below = self._closed_below
        chunk = _in_scan_order(self._open[0] if len(self._open) == 1 else _concat(self._open),
                               emitted_below)
        self._open = []
        top = int(chunk.sid.max()) if len(chunk.sid) else 0
        close_below = top + 1 if final else top
        self._closed_below = close_below if emitted_below is None else max(close_below,
                                                                             emitted_below)
        if emitted_below is not None:
            # Holes charged (damaged azimuths) to a scan already emitted: counted in the
            # stream's stats, but that scan cannot be emitted again.
            for k in [k for k in self._missing_by_sid if k < emitted_below]:
                del self._missing_by_sid[k]
        scans = []
        sid = chunk.sid
        starts = np.concatenate(([0], np.flatnonzero(sid[1:] != sid[:-1]) + 1))  # sorted ids
        ids = sid[starts]
        ids = ids[ids < close_below]
        bounds = np.searchsorted(sid, np.concatenate((ids, [close_below])), side="left")
        for k, lo, hi in zip(ids.tolist(), bounds[:-1], bounds[1:], strict=True):
            scans.append(self._make_scan(chunk, int(k), int(lo), int(hi), final and k == top))
        # A rotation lost whole still gets its (empty, incomplete) scan: no silent hole.
        lost = [k for k in self._missing_by_sid if k < close_below and k not in set(ids.tolist())]
        scans.extend(self._lost_scan(k) for k in lost)
        scans.sort(key=lambda scan: scan.index)
        keep = int(bounds[-1])
        if keep < len(chunk.sid):
            self._open = [_tail(chunk, keep)]
        return scans

    def _lost_scan(self, k: int) -> Scan:
        missing = int(self._missing_by_sid.pop(k))
        self.stats.scans += 1
        self.stats.incomplete_scans += 1
        return Scan.empty(
            index=k - (self._first_sid or 0), complete=False, packets=0, missing_packets=missing,
            vertical_offsets_applied=self.vertical_offsets, lasers=(self.sensor or VLP16).lasers,
            meta={"partial": False, "lost": True, "split": self.split,
                  "cut_azimuth_deg": math.degrees(self._cut_ref % TWO_PI)},
        )

    def _make_scan(self, chunk: _Chunk, k: int, lo: int, hi: int, last: bool) -> Scan:
        pk = (chunk.packet_sid_min <= k) & (chunk.packet_sid_max >= k)
        rpm = float(np.median(chunk.rpm[pk])) if pk.any() else float("nan")
        sensor = self.sensor or VLP16
        block_step = TWO_PI * rpm / 60.0 * sensor.block_period
        tol = 1.5 * block_step + (TWO_PI * rpm / 60.0 * sensor.packet_period()
                                  if self.split == "packet" else 0.0)
        start_ref = self._cut_ref + TWO_PI * k
        u = chunk.u[lo:hi]
        late_start = k == self._first_sid and float(u[0]) - start_ref > tol
        early_end = last and start_ref + TWO_PI - float(u[-1]) > tol
        partial = bool(late_start or early_end)
        missing = int(self._missing_by_sid.pop(k, 0))
        breaks = int(self._breaks_by_sid.pop(k, 0))
        complete = not partial and missing == 0 and breaks == 0
        self.stats.scans += 1
        self.stats.partial_scans += partial
        self.stats.incomplete_scans += not complete
        ts = chunk.packet_ts[pk]
        arrays = {name: chunk.arrays[name][lo:hi] for name in _FIELDS}
        return Scan(
            **arrays,
            index=k - (self._first_sid or 0),
            complete=complete,
            packets=int(pk.sum()),
            missing_packets=missing,
            return_mode=int(chunk.return_mode[pk][0]) if pk.any() else 0,
            product_id=int(chunk.product_id[pk][0]) if pk.any() else 0,
            vertical_offsets_applied=self.vertical_offsets,
            lasers=sensor.lasers,
            meta={
                "rpm": rpm,
                "model": sensor.name,
                "first_packet_timestamp_us": int(ts[0]) if len(ts) else None,
                "last_packet_timestamp_us": int(ts[-1]) if len(ts) else None,
                "start_time_s": float(arrays["time"][0]),
                "end_time_s": float(arrays["time"][-1]),
                "partial": partial,
                "time_breaks": breaks,
                "azimuth_span_deg": math.degrees(float(u[-1] - u[0])),
                "cut_azimuth_deg": math.degrees(self._cut_ref % TWO_PI),
                "split": self.split,
            },
        )


def _with_table(sensor: SensorModel, lasers: LaserTable) -> SensorModel:
    """``sensor`` with a unit's own laser table, refused if the table is another sensor's."""
    if lasers.n_lasers != sensor.n_lasers:
        raise UnsupportedSensorError(
            f"the laser table {lasers.model!r} has {lasers.n_lasers} lasers, the packets are a "
            f"{sensor.name}'s ({sensor.n_lasers}): it is another sensor's calibration")
    return sensor.with_lasers(lasers)


def _raw(records: np.ndarray) -> np.ndarray:
    """Records as their raw bytes, (n, 1206) uint8 (no copy when already contiguous)."""
    return np.ascontiguousarray(records).view(np.uint8).reshape(len(records), -1)


def _records(raw: np.ndarray) -> np.ndarray:
    """Raw (n, 1206) bytes viewed as `DATA_PACKET_DTYPE` records."""
    return np.ascontiguousarray(raw).view(DATA_PACKET_DTYPE)[:, 0]


def _in_scan_order(chunk: _Chunk, closed_below: int | None) -> _Chunk:
    """The chunk's firings sorted by scan id (stable), none below ``closed_below``.

    Each decoded chunk is in scan order by itself, but damaged block azimuths can put a later
    chunk's firings into a rotation before the held-back tail of the one before, or into a scan
    already emitted. Such firings join the oldest scan still open (their azimuths are garbage
    anyway; dropping them would lose a return silently) rather than open an emitted scan again.
    """
    sid = chunk.sid
    if closed_below is not None and len(sid) and sid.min() < closed_below:
        sid = np.maximum(sid, closed_below)
    if len(sid) < 2 or (sid[1:] >= sid[:-1]).all():
        if sid is not chunk.sid:
            chunk.sid = sid
        return chunk
    order = np.argsort(sid, kind="stable")
    chunk.arrays = {name: a[order] for name, a in chunk.arrays.items()}
    chunk.sid, chunk.u = sid[order], chunk.u[order]
    return chunk


def _concat(chunks: list[_Chunk]) -> _Chunk:
    return _Chunk(
        arrays={name: np.concatenate([c.arrays[name] for c in chunks]) for name in _FIELDS},
        **{
            f: np.concatenate([getattr(c, f) for c in chunks])
            for f in ("sid", "u", "packet_ts", "packet_sid_min", "packet_sid_max", "rpm",
                      "return_mode", "product_id")
        },
    )


def _tail(chunk: _Chunk, start: int) -> _Chunk:
    """The firings from ``start`` on, with the packets that hold them."""
    first_packet = start // FIRINGS_PER_PACKET
    # Keep whole packets in the per-packet arrays; per-firing arrays start at `start`.
    kept = _Chunk(
        arrays={name: chunk.arrays[name][start:] for name in _FIELDS},
        sid=chunk.sid[start:],
        u=chunk.u[start:],
        packet_ts=chunk.packet_ts[first_packet:],
        packet_sid_min=np.maximum(chunk.packet_sid_min[first_packet:], chunk.sid[start]),
        packet_sid_max=chunk.packet_sid_max[first_packet:],
        rpm=chunk.rpm[first_packet:],
        return_mode=chunk.return_mode[first_packet:],
        product_id=chunk.product_id[first_packet:],
    )
    return kept


def scans_from_packets(
    payloads: np.ndarray | Sequence[bytes],
    cut_azimuth: float | None = math.pi,
    **options,
) -> list[Scan]:
    """All scans of a sequence of data-packet payloads (in arrival order), partial ones too.

    ``options`` go to `ScanAssembler` (``split``, ``vertical_offsets``, ``model``, ...).
    """
    asm = ScanAssembler(cut_azimuth, **options)
    return asm.push_many(payloads) + asm.finish()
