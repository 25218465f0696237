"""The line station's engine: one inspection at a time, whatever triggers it.

Every front end (the operator's page, the HTTP/JSON endpoint, the PLC over OPC UA) calls
`StationEngine.trigger`; the first to take the lock inspects, any other gets `Busy` (a clear
refusal naming the unit in progress) until the verdict is out. The inspection itself is the
inspection package's pipeline, unchanged: `acquire.open_acquisition` -> `procedure.inspect_unit`
-> `records.record_row` -> `Records.add` (crash-safe SQLite). The scanning and estimating run in
one worker *process* (the twin's kernels and the estimator hold the interpreter's lock for long
stretches: in a thread they starved the pages and the OPC UA server until a PLC's requests timed
out); the record is committed by the station's own process, so a worker that dies loses no
record and leaves none half-written.

The state every front end shows (`Snapshot`): ``idle``, ``busy`` (with the unit, who triggered
it, the phase and the scans so far), ``done`` (the last result) or ``error`` (with the message).
Each change is pushed to the listeners (`subscribe`) on the event loop.

The audit trail (the store's ``audit`` table) holds every trigger, refusal, start and end of an
inspection, login and change. A start is committed before the first scan, its end after the
record: a station killed in between finds, when started again, a start without its record, and
comes up in ``error`` naming the unit (no record was made; inspect it again), which the PLC
reads as Error before it triggers the next part.
"""

from __future__ import annotations

import asyncio
import hashlib
import os
import sqlite3
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from scenarios.inspection import records as rec_mod
from scenarios.inspection import spc
from scenarios.inspection.acquire import open_acquisition
from scenarios.inspection.identity import calibration_identity, software_version, station_hash
from scenarios.inspection.line import DEFAULT_SPREAD
from scenarios.inspection.procedure import DEFAULT_SCANS, inspect_unit
from scenarios.inspection.verdict import EDGE_SCALE, edge_key, limits_si
from twin.core.errors import AimbenchError

#: The longest unit id accepted (a VIN is 17 characters; serials and barcodes a few dozen).
MAX_UNIT_LEN = 64
#: The records the SPC alarms look back over.
SPC_WINDOW = 200


class Busy(AimbenchError):
    """A trigger while an inspection is in progress: refused, nothing started."""


@dataclass
class Snapshot:
    """What every front end shows: the state, the unit in progress, the last result."""

    state: str = "idle"                  # idle | busy | done | error
    unit: str | None = None              # in progress (busy) or last (done, error)
    origin: str | None = None            # web | http | opcua
    who: str | None = None
    phase: str = ""
    scans: int = 0
    started_at: float | None = None
    message: str = ""
    result: dict[str, Any] | None = None
    results: int = 0                     # results published since the station started
    batch: str | None = None
    alarms: list[dict[str, Any]] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def twin_unit(station: Any, unit: str, spread: float = DEFAULT_SPREAD
              ) -> tuple[dict[str, float], int]:
    """The twin unit behind a unit id (source ``sim``): its mounting misalignment (uniform
    within +-spread x each limit, as a simulated line's) and its sensor's seed, both drawn
    from the id alone, so the same id is the same unit every time."""
    key = int.from_bytes(hashlib.sha256(unit.encode()).digest()[:8], "little")
    rng = np.random.default_rng((key, 1606))
    mis = {edge_key(a): float(rng.uniform(-spread, spread) * lim * EDGE_SCALE[a])
           for a, lim in limits_si(station.tolerances).items()}
    return mis, int(rng.integers(0, 2**31 - 1))


def check_unit(unit: Any) -> str:
    """A unit id as typed or scanned: stripped, printable, not empty, not too long."""
    if not isinstance(unit, str):
        raise AimbenchError("the unit id must be text (a VIN, a serial, a barcode)")
    u = unit.strip()
    if not u:
        raise AimbenchError("no unit id: scan or type the unit's id, then Enter")
    if len(u) > MAX_UNIT_LEN or not u.isprintable():
        raise AimbenchError(f"the unit id {u[:20]!r}... is not an id: at most {MAX_UNIT_LEN} "
                            "printable characters")
    return u


class StationEngine:
    """One station: its station file, record store and source (module docstring)."""

    def __init__(self, station: Any, db: str | Path, source: str = "sim", *,
                 scans: int = DEFAULT_SCANS, max_scans: int | None = None,
                 calibration: str | None = None, batch: str | None = None,
                 board_view: Path | None = None) -> None:
        from scenarios import calibrate

        self.station = station
        self.db = Path(db)
        self.source = source
        self.scans = scans
        self.max_scans = max_scans
        self.cal_file = calibration or station.sensor.range_calibration
        self.calibration = calibrate.read(self.cal_file) if self.cal_file else None
        self.board_view = board_view
        self.snapshot = Snapshot(batch=batch)
        self._lock = threading.Lock()
        self._db_lock = threading.Lock()
        self._listeners: list[Callable[[Snapshot], Any]] = []
        self._loop: asyncio.AbstractEventLoop | None = None
        # one worker: the inspections and every write to the store happen there, in order
        self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="inspection")
        self._pool: Any = None
        with rec_mod.Records.open(self.db, create=True) as r:
            r.ensure_audit()
        self._records = rec_mod.Records(self.db, self._connect())
        self._recover()

    # -- the store -----------------------------------------------------------------------------

    def _connect(self) -> sqlite3.Connection:
        # one connection for the station, used under `_db_lock` from the worker and the loop
        conn = sqlite3.connect(self.db, isolation_level=None, timeout=30.0,
                               check_same_thread=False)
        conn.row_factory = sqlite3.Row
        conn.execute("PRAGMA journal_mode=WAL")
        conn.execute("PRAGMA synchronous=FULL")
        return conn

    def rows(self, where: str = "", params: tuple = ()) -> list[dict[str, Any]]:
        with self._db_lock:
            return self._records.rows(where, params)

    def audit(self, who: str | None, role: str | None, action: str,
              detail: dict[str, Any] | None = None) -> None:
        with self._db_lock:
            self._records.audit(who, role, action, detail)

    def audit_rows(self, limit: int = 200) -> list[dict[str, Any]]:
        with self._db_lock:
            return self._records.audit_rows(limit)

    def batches(self) -> dict[str, int]:
        with self._db_lock:
            return self._records.batches()

    def close(self) -> None:
        self._worker.shutdown(wait=True)
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
        with self._db_lock:
            self._records.close()

    def _recover(self) -> None:
        """After a kill: a started inspection without its record is an error to show."""
        # an inspection that failed is concluded too (its error was shown and logged)
        starts = [a for a in self.audit_rows(50)
                  if a["action"] in ("start", "end", "recovered", "error")]
        self.audit(None, "station", "station started", {
            "software_version": software_version(), "source": self.source,
            "station": self.station.name,
            "station_sha256": station_hash(self.station.to_dict())})
        if not starts or starts[0]["action"] != "start":
            return
        last = starts[0]
        unit, before = last["detail"]["unit"], last["detail"]["last_record"]
        made = self.rows("WHERE unit = ? AND id > ?", (unit, before))
        if made:  # killed after the commit, before the audit's end: the record stands
            self.audit(None, "station", "end", {"unit": unit, "record": made[0]["id"],
                                                "recovered": True})
            return
        msg = (f"the station stopped during the inspection of unit {unit} (no record was "
               "made); inspect it again")
        self.snapshot.state, self.snapshot.unit, self.snapshot.message = "error", unit, msg
        self.audit(None, "station", "recovered", {"unit": unit, "message": msg})

    # -- listeners -------------------------------------------------------------------------------

    def subscribe(self, fn: Callable[[Snapshot], Any]) -> None:
        """Call `fn(snapshot)` on the event loop at every change (a coroutine is awaited)."""
        self._listeners.append(fn)

    def _notify(self) -> None:
        if self._loop is None:
            return
        snap = Snapshot(**{**self.snapshot.__dict__})
        for fn in self._listeners:
            res = fn(snap)
            if asyncio.iscoroutine(res):
                self._loop.create_task(res)

    def _notify_threadsafe(self) -> None:
        if self._loop is not None:
            self._loop.call_soon_threadsafe(self._notify)

    # -- the one inspection ------------------------------------------------------------------------

    @property
    def busy(self) -> bool:
        return self._lock.locked()

    def set_batch(self, batch: str | None, who: str, role: str) -> None:
        old = self.snapshot.batch
        self.snapshot.batch = (batch or "").strip() or None
        self.audit(who, role, "set batch", {"from": old, "to": self.snapshot.batch})
        self._notify()

    async def trigger(self, unit: Any, origin: str, who: str | None = None,
                      role: str | None = None) -> dict[str, Any]:
        """Inspect `unit` now and return its result (`result_dict`); `Busy` if an inspection
        is in progress, an `AimbenchError` for a bad id or a failed inspection (the state
        shows it then)."""
        self._loop = asyncio.get_running_loop()
        try:
            unit = check_unit(unit)
        except AimbenchError as exc:
            self.audit(who, role, "refused", {"origin": origin, "why": str(exc)})
            raise
        if not self._lock.acquire(blocking=False):
            cur = self.snapshot.unit
            msg = (f"busy: inspecting unit {cur} (triggered by {self.snapshot.origin}); "
                   f"{unit} was not started, trigger it again when the station is done")
            self.audit(who, role, "refused", {"origin": origin, "unit": unit, "why": "busy"})
            raise Busy(msg)
        try:
            s = self.snapshot
            s.state, s.unit, s.origin, s.who = "busy", unit, origin, who
            s.phase, s.scans, s.started_at, s.message = "scanning", 0, time.time(), ""
            self._notify()
            try:
                result = await self._loop.run_in_executor(self._worker, self._inspect, unit,
                                                          origin, who)
            except Exception as exc:
                s.state, s.phase = "error", ""
                s.message = str(exc) if isinstance(exc, AimbenchError) else (
                    f"the inspection of {unit} failed: {type(exc).__name__}: {exc}")
                self.audit(who, role, "error", {"unit": unit, "message": s.message})
                self._notify()
                raise AimbenchError(s.message) from None
            s.state, s.phase, s.result = "done", "", result
            s.results += 1
            s.message = result["message"]
            s.alarms = result.pop("alarms")
            self._notify()
            return result
        finally:
            self._lock.release()

    def _inspect(self, unit: str, origin: str, who: str | None) -> dict[str, Any]:
        """One unit, in the worker thread: audit start, measure (in the worker process),
        record, audit end."""
        with self._db_lock:
            last = self._records.conn.execute("SELECT COALESCE(MAX(id), 0) FROM inspection"
                                              ).fetchone()[0]
            self._records.audit(who, None, "start", {"unit": unit, "origin": origin,
                                                     "last_record": int(last)})
        keep = self.source == "sim" or self.source.startswith("udp://")
        capture = self._records.capture_path(unit) if keep else None
        job = dict(station=self.station.to_dict(), source=self.source, unit=unit,
                   scans=self.scans, max_scans=self.max_scans, cal_file=self.cal_file,
                   capture=None if capture is None else str(capture), operator=who,
                   batch=self.snapshot.batch,
                   view=None if self.board_view is None else str(self.board_view))
        row, view = self._process().submit(measure, job).result()
        with self._db_lock:
            rid, _ = self._records.add(row)
            self._records.audit(who, None, "end", {"unit": unit, "record": rid,
                                                   "verdict": row["verdict"]})
            stored = self._records.get(rid)
        out = result_dict(stored)
        out["origin"] = origin
        out["alarms"] = self.alarms()  # here, off the event loop
        if view is not None:
            out["board_view"] = view
        return out

    def _process(self) -> Any:
        """The worker process (started once, on first use; a new one if it died)."""
        from concurrent.futures import ProcessPoolExecutor
        from multiprocessing import get_context

        if self._pool is None or getattr(self._pool, "_broken", False):
            # spawn: a fresh interpreter, never a fork of this one's threads and sockets
            self._pool = ProcessPoolExecutor(max_workers=1, mp_context=get_context("spawn"),
                                             initializer=_follow_parent,
                                             initargs=(os.getpid(),))
        return self._pool

    def warm_up(self) -> None:
        """Start the worker process and load its imports now, not at the first unit."""
        self._process().submit(_warm).result()

    # -- SPC -----------------------------------------------------------------------------------

    def recent(self, n: int = SPC_WINDOW, light: bool = False) -> list[dict[str, Any]]:
        """The latest n records (of the current batch if one is set), oldest first; ``light``:
        only the columns SPC reads (no JSON to decode)."""
        b = self.snapshot.batch
        where = ("WHERE id IN (SELECT id FROM inspection " + ("WHERE batch = ? " if b else "")
                 + "ORDER BY id DESC LIMIT ?)")
        params = (b, n) if b else (n,)
        if not light:
            return self.rows(where, params)
        from scenarios.inspection.verdict import AXES

        cols = ", ".join(["id", "status"] + [f"{c}_{a}" for a in AXES for c in ("err", "limit")])
        with self._db_lock:
            cur = self._records.conn.execute(
                f"SELECT {cols} FROM inspection {where} ORDER BY id", params)
            return [dict(r) for r in cur]

    def alarms(self) -> list[dict[str, Any]]:
        """The run rules the latest record breaks, per axis (Nelson's rules on the I chart,
        and the MR chart's upper limit)."""
        out = []
        for ax in spc.line_spc(self.recent(light=True), last_only=True):
            if ax.chart is None:
                continue
            last = len(ax.chart.values) - 1
            for sig in ax.chart.signals:
                if sig.index == last:
                    out.append({"axis": ax.axis, "rule": f"Nelson {sig.rule}", "text": sig.text})
            if last in ax.chart.mr_signals:
                out.append({"axis": ax.axis, "rule": "MR", "text": "moving range above its "
                            "upper control limit"})
        return out


def _follow_parent(parent: int) -> None:
    """In the worker process: end when the station's process is gone (a kill -9 of the
    station must not leave a worker behind holding the sensor or a core)."""
    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(0.5)
        os._exit(0)

    threading.Thread(target=watch, daemon=True).start()


def _warm() -> None:
    import scenarios.inspection.procedure  # noqa: F401  (align, numba's cached kernels)
    import twin.sim.bench  # noqa: F401


def measure(job: dict[str, Any]) -> tuple[dict[str, Any], str | None]:
    """In the worker process: acquire, inspect and make the record's row (not committed),
    and the board's picture if asked. The pipeline of `aimbench inspect`, unchanged."""
    import json

    from scenarios import calibrate
    from scenarios import station as stations

    station = stations.from_dict(job["station"], "the station")
    unit, source = job["unit"], job["source"]
    misalignment, seed = twin_unit(station, unit) if source == "sim" else ({}, 0)
    capture = None if job["capture"] is None else Path(job["capture"])
    calibration = calibrate.read(job["cal_file"]) if job["cal_file"] else None
    started = time.time()
    acq = open_acquisition(source, station, capture, misalignment=misalignment, seed=seed)
    try:
        insp = inspect_unit(acq, station, unit, scans=job["scans"],
                            max_scans=job["max_scans"], calibration=calibration)
    except BaseException:
        acq.close(complete=False)
        raise
    acq.close()
    row = rec_mod.record_row(
        insp, station=station, operator=job["operator"], source=source, capture=acq.capture,
        capture_sha256=acq.capture_sha256(), sensor=acq.sensor,
        calibration=calibration_identity(station, job["cal_file"]), started_at=started,
        batch=job["batch"])
    view = None
    if job["view"]:
        from scenarios.inspection.report import unit_figure

        try:  # the picture is a nicety: never lose a verdict over it
            folder = Path(job["view"])
            folder.mkdir(parents=True, exist_ok=True)
            name = f"{hashlib.sha256(f'{unit}{started}'.encode()).hexdigest()[:16]}.png"
            shown = {k: (json.loads(v) if k in rec_mod.JSON_COLS and isinstance(v, str)
                         else v) for k, v in row.items()}
            unit_figure(shown, insp, folder / name)
            view = name
        except Exception:
            view = None
    return row, view


def result_dict(row: dict[str, Any]) -> dict[str, Any]:
    """A record as the front ends show it: edge units, per judged axis value, U, limit and
    verdict."""
    from scenarios.inspection.verdict import AXES, EDGE_UNIT

    axes = []
    for a in AXES:
        if row[f"limit_{a}"] is None:
            continue
        s = EDGE_SCALE[a]
        err, u = row[f"err_{a}"], row[f"u_{a}"]
        axes.append({"axis": edge_key(a), "unit": EDGE_UNIT[a],
                     "value": None if err is None else err * s,
                     "U": None if u is None else u * row["coverage_k"] * s,
                     "limit": row[f"limit_{a}"] * s, "verdict": row[f"verdict_{a}"]})
    return {"record": row["id"], "unit": row["unit"], "trial": row["trial"],
            "verdict": row["verdict"], "status": row["status"], "message": row["message"],
            "rule": row["rule"], "k": row["coverage_k"], "scans": row["scans"],
            "batch": row["batch"], "operator": row["operator"],
            "software_version": row["software_version"], "git_commit": row["git_commit"],
            "station_sha256": row["station_sha256"], "finished_at": row["finished_at"],
            "total_s": (row["timings"] or {}).get("total_s"), "axes": axes}
