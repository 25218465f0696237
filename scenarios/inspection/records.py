"""The per-unit record store: one SQLite file for a line's inspections, crash-safe.

Like the run store (`scenarios.store`, whose helpers it uses): write-ahead log with
``synchronous=FULL``, so a committed record survives a SIGKILL or a power cut; the file is built
whole in a temporary file and renamed into place, so a kill while creating leaves no store or
a complete one; and it is checked (SQLite's integrity check, a file cut short, its tables and
schema) before it is trusted. A record is written in one transaction once the unit's verdict is
known, and the verdict is shown only after that commit: a run killed at any instant holds
exactly the units it reported, none half-written. ``UNIQUE(unit, trial)`` numbers the
inspections of one unit (a re-test is a new trial, never an overwrite).

Table ``inspection``, one row per inspection (SI units; the exports add mm and deg): id, unit,
trial, times, station (name, SHA-256 of its JSON, the JSON), operator, software version and git
commit, calibration identity (JSON: each file's path and SHA-256), sensor (model, serial where
it reports one, JSON), source, the raw capture's path and SHA-256, status, verdict, rule,
coverage factor, scans used and rejected, board found, rings and points on the board; per axis
(x, y, z, roll, tilt, yaw) the mounting error ``err_<axis>``, the estimator's sigma
``u_est_<axis>``, the system term ``u_sys_<axis>``, the combined ``u_<axis>``, the limit
``limit_<axis>`` and the verdict ``verdict_<axis>`` (NULL where not judged), the twin's true
error ``true_<axis>``; the pose in the station frame, the covariance, attempts, diagnostics and
timings (JSON); ``batch`` (a simulated line's or a study's name, for resuming it).
"""

from __future__ import annotations

import contextlib
import csv
import hashlib
import json
import math
import os
import sqlite3
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from scenarios.store import dumps, file_problems, fsync_dir, process_alive, sqlite_header
from twin.core.errors import AimbenchError

SCHEMA_VERSION = 1
AXES = ("x", "y", "z", "roll", "tilt", "yaw")
UNIT = {"x": "mm", "y": "mm", "z": "mm", "roll": "deg", "tilt": "deg", "yaw": "deg"}
SCALE = {"x": 1e3, "y": 1e3, "z": 1e3, "roll": 180 / math.pi, "tilt": 180 / math.pi,
          "yaw": 180 / math.pi}
#: Per-axis columns and whether they scale to edge units.
_AXIS_COLS = (("err", True), ("u_est", True), ("u_sys", True), ("u", True), ("limit", True),
              ("true", True), ("verdict", False))
JSON_COLS = ("station_json", "calibration", "sensor", "pose_in_station", "nominal",
              "covariance", "attempts", "diagnostics", "timings")

_SCHEMA = f"""
CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE inspection (
    id INTEGER PRIMARY KEY,
    unit TEXT NOT NULL,
    trial INTEGER NOT NULL,
    started_at REAL NOT NULL,
    finished_at REAL NOT NULL,
    station TEXT NOT NULL,
    station_sha256 TEXT NOT NULL,
    station_json TEXT NOT NULL,
    operator TEXT,
    software_version TEXT,
    git_commit TEXT,
    calibration TEXT,
    sensor_model TEXT,
    sensor_serial TEXT,
    sensor TEXT,
    source TEXT NOT NULL,
    capture_path TEXT,
    capture_sha256 TEXT,
    status TEXT NOT NULL,
    verdict TEXT NOT NULL CHECK (verdict IN ('pass', 'fail', 'inconclusive')),
    rule TEXT NOT NULL,
    coverage_k REAL NOT NULL,
    scans INTEGER NOT NULL,
    rejected_scans INTEGER,
    board_found INTEGER,
    rings INTEGER,
    board_points INTEGER,
    {", ".join(f"{c}_{a} {'TEXT' if c == 'verdict' else 'REAL'}" for a in AXES
               for c, _ in _AXIS_COLS)},
    pose_in_station TEXT,
    nominal TEXT,
    covariance TEXT,
    attempts TEXT,
    diagnostics TEXT,
    timings TEXT,
    message TEXT,
    batch TEXT,
    UNIQUE (unit, trial)
);
CREATE INDEX inspection_batch ON inspection (batch, unit);
"""
_TABLES = {"meta", "inspection"}
#: The line station's audit trail: every trigger, refusal, login, change and recovery.
_AUDIT_SCHEMA = """CREATE TABLE IF NOT EXISTS audit (
    id INTEGER PRIMARY KEY, at REAL NOT NULL, who TEXT, role TEXT, action TEXT NOT NULL,
    detail TEXT NOT NULL CHECK (json_valid(detail)))"""
_TEMP_SUFFIX = ".creating-"


class RecordError(AimbenchError):
    """A record store that cannot be created, opened or trusted, or a record not there."""


class _Locked(Exception):
    """The store stayed locked by another program for `Records.lock_wait_s`."""


#: `Records.lock_wait_s` and `Records.lock_notice_s` (s): a store is locked for a moment by
#: another inspect or an export; five minutes of it is a program left holding it.
LOCK_WAIT_S = 300.0
LOCK_NOTICE_S = 10.0


#: How long a statement waits for another connection's lock, s (`Records.add` waits longer).
BUSY_TIMEOUT_S = 30.0


def _connect(path: Path) -> sqlite3.Connection:
    conn = sqlite3.connect(path, isolation_level=None, timeout=BUSY_TIMEOUT_S)
    conn.row_factory = sqlite3.Row
    conn.execute("PRAGMA journal_mode=WAL")
    conn.execute("PRAGMA synchronous=FULL")
    return conn


def _create(path: Path) -> None:
    """Build a new store in a temporary file beside `path` and rename it into place."""
    folder = path.parent
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise RecordError(f"cannot create the folder of {path}: {exc.strerror}") from None
    for stale in folder.glob(f".{path.name}{_TEMP_SUFFIX}*"):
        pid = stale.name.rpartition("-")[2]
        if pid.isdigit() and not process_alive(int(pid)):
            stale.unlink(missing_ok=True)
    tmp = folder / f".{path.name}{_TEMP_SUFFIX}{os.getpid()}"
    try:
        conn = sqlite3.connect(tmp, isolation_level=None)
        try:
            conn.execute("PRAGMA synchronous=FULL")
            conn.executescript(_SCHEMA)
            conn.execute("BEGIN IMMEDIATE")
            conn.executemany("INSERT INTO meta (key, value) VALUES (?, ?)", [
                ("schema_version", dumps(SCHEMA_VERSION)), ("kind", dumps("aimbench.inspections")),
                ("created_at", dumps(time.time()))])
            conn.execute("COMMIT")
        finally:
            conn.close()
        with tmp.open("rb+") as f:
            os.fsync(f.fileno())
        if path.exists():  # another process created it meanwhile: theirs stands
            tmp.unlink()
            return
        os.replace(tmp, path)
        fsync_dir(folder)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def check(path: Path) -> list[str]:
    """What is wrong with the record store at `path` (empty: nothing), read-only."""
    if not sqlite_header(path):
        return ["not an SQLite file"]
    problems = file_problems(path)
    if problems:
        return problems
    conn = sqlite3.connect(f"file:{path}?mode=ro", uri=True, timeout=30.0)
    try:
        rows = [r[0] for r in conn.execute("PRAGMA integrity_check")]
        if rows != ["ok"]:
            return ["SQLite's integrity check fails: " + " / ".join(rows[:3])]
        tables = {r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type='table'")}
        if not tables >= _TABLES:
            return [f"not an inspection record store (tables {sorted(_TABLES - tables)} "
                    "missing)"]
        kind = conn.execute("SELECT value FROM meta WHERE key='kind'").fetchone()
        version = conn.execute("SELECT value FROM meta WHERE key='schema_version'").fetchone()
        if kind is None or json.loads(kind[0]) != "aimbench.inspections":
            return ["not an inspection record store (no kind aimbench.inspections in meta)"]
        if version is None or json.loads(version[0]) != SCHEMA_VERSION:
            return [f"unknown schema {version and version[0]}; this aimbench reads version "
                    f"{SCHEMA_VERSION}"]
        valid = " AND ".join(f"({c} IS NULL OR json_valid({c}))" for c in JSON_COLS)
        broken = conn.execute(f"SELECT COUNT(*), MIN(id) FROM inspection WHERE NOT ({valid})"
                              ).fetchone()
        if broken[0]:
            return [f"{broken[0]} records with unreadable JSON (first: id {broken[1]})"]
    except sqlite3.DatabaseError as exc:
        return [f"unreadable: {exc}"]
    finally:
        conn.close()
    return []


class Records:
    """The record store of one file: `Records.open(path, create=True)`; use as a context."""

    def __init__(self, path: Path, conn: sqlite3.Connection) -> None:
        self.path = path
        self.conn = conn

    @classmethod
    def open(cls, path: str | Path, create: bool = False) -> Records:
        path = Path(path)
        if not path.exists():
            if not create:
                raise RecordError(f"no inspection records at {path}; inspect a unit with "
                                  f"--db {path} first")
            _create(path)
        elif path.is_dir():
            raise RecordError(f"{path} is a folder; --db takes the SQLite file of the records "
                              "(e.g. inspections.sqlite)")
        problems = check(path)
        if problems:
            raise RecordError(f"{path} is damaged or not an inspection store: "
                              f"{'; '.join(problems[:5])}; keep it as it is and give another "
                              "--db")
        records = cls(path, _connect(path))
        records.flush_pending()
        return records

    def close(self) -> None:
        self.conn.close()

    def __enter__(self) -> Records:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def captures(self) -> Path:
        """The folder the raw captures of this store's inspections are kept in."""
        return self.path.with_name(self.path.stem + ".captures")

    def capture_path(self, unit: str) -> Path:
        """A new capture file's name for a unit (unique: time and a random tag)."""
        safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in unit)[:60]
        stamp = time.strftime("%Y%m%dT%H%M%S", time.gmtime())
        tag = hashlib.sha256(os.urandom(16)).hexdigest()[:8]
        self.captures.mkdir(parents=True, exist_ok=True)
        return self.captures / f"{safe}-{stamp}-{tag}.pcap"

    # -- writing ---------------------------------------------------------------------------

    #: How long `add` waits for a store another program holds locked before it keeps the
    #: record in the `pending` folder instead (s), and how often it says it is waiting.
    lock_wait_s = LOCK_WAIT_S
    lock_notice_s = LOCK_NOTICE_S

    @property
    def pending(self) -> Path:
        """Where records wait that could not be committed because the store was locked."""
        return self.path.with_name(self.path.stem + ".pending")

    def add(self, row: dict[str, Any]) -> tuple[int, int]:
        """Commit one record (the column values of `record_row`); returns (id, trial).

        Records kept in `pending` by an earlier add are committed first, in the same
        transaction. A store another program holds locked is waited for (saying so on stderr
        every `lock_notice_s`) up to `lock_wait_s`; then the record is kept in `pending` and a
        `RecordError` says where: a unit's record is never lost to a lock (issue 37: after 30 s
        it was, with a traceback)."""
        row = dict(row)
        row.pop("trial", None)
        try:
            return self._commit(row)
        except _Locked:
            kept = self._keep_pending(row)
            raise RecordError(
                f"the record store {self.path} stayed locked by another program for "
                f"{self.lock_wait_s:g} s; unit {row.get('unit')}'s record (verdict "
                f"{row.get('verdict')}) is kept in {kept} and goes into the store with the "
                f"next record (or `aimbench inspect --db {self.path} --list`); close the "
                "program that holds the store") from None

    def flush_pending(self, wait_s: float = 0.0) -> int:
        """Commit the records kept in `pending`, waiting up to `wait_s` for a lock (still
        held: they stay); how many were committed."""
        n = len(self._pending_files())
        if not n:
            return 0
        wait, self.lock_wait_s = self.lock_wait_s, wait_s
        try:
            self._commit(None)
        except _Locked:
            return 0
        finally:
            self.lock_wait_s = wait
        return n

    def _commit(self, row: dict[str, Any] | None) -> tuple[int, int]:
        """Commit the pending records and `row` in one transaction, waiting out a lock."""
        deadline = time.monotonic() + self.lock_wait_s
        while True:
            files = self._pending_files()
            step = max(0.0, min(self.lock_notice_s, deadline - time.monotonic()))
            self.conn.execute(f"PRAGMA busy_timeout = {int(step * 1000)}")
            try:
                with self._tx() as conn:
                    for f in files:
                        self._insert(conn, json.loads(f.read_text(encoding="utf-8")))
                    rid, trial = self._insert(conn, row) if row is not None else (0, 0)
                break
            except sqlite3.OperationalError as exc:
                if "locked" not in str(exc) and "busy" not in str(exc):
                    raise
                if time.monotonic() >= deadline:
                    raise _Locked from None
                print(f"aimbench: note: the record store {self.path} is locked by another "
                      f"program; waiting (up to {max(0.0, deadline - time.monotonic()):.0f} s "
                      "more) to store the record", file=sys.stderr, flush=True)
            except sqlite3.IntegrityError as exc:
                unit = row.get("unit") if row is not None else "kept in " + str(self.pending)
                raise RecordError(f"the record of unit {unit} cannot be stored: {exc}") from None
            finally:
                self.conn.execute(f"PRAGMA busy_timeout = {int(BUSY_TIMEOUT_S * 1000)}")
        for f in files:  # committed: their copies go
            f.unlink(missing_ok=True)
        return rid, int(trial)

    @staticmethod
    def _insert(conn: sqlite3.Connection, row: dict[str, Any]) -> tuple[int, int]:
        cols = ["trial", *row]
        marks = ", ".join("?" for _ in row)
        sql = (f"INSERT INTO inspection ({', '.join(cols)}) SELECT COALESCE(MAX(trial), 0) + 1, "
               f"{marks} FROM inspection WHERE unit = ?")
        cur = conn.execute(sql, (*row.values(), row["unit"]))
        rid = int(cur.lastrowid)
        trial = conn.execute("SELECT trial FROM inspection WHERE id=?", (rid,)).fetchone()[0]
        return rid, int(trial)

    def _pending_files(self) -> list[Path]:
        return sorted(self.pending.glob("*.json")) if self.pending.is_dir() else []

    def _keep_pending(self, row: dict[str, Any]) -> Path:
        """Write `row` durably into `pending` (a temporary file renamed into place)."""
        self.pending.mkdir(parents=True, exist_ok=True)
        name = f"{time.time_ns()}-{os.getpid()}"
        tmp = self.pending / f".{name}.tmp"
        with tmp.open("w", encoding="utf-8") as f:
            f.write(dumps(row))
            f.flush()
            os.fsync(f.fileno())
        path = self.pending / f"{name}.json"
        os.replace(tmp, path)
        fsync_dir(self.pending)
        return path

    @contextlib.contextmanager
    def _tx(self) -> Iterator[sqlite3.Connection]:
        if self.conn.in_transaction:
            self.conn.execute("ROLLBACK")  # left open by an interrupt: it never committed
        self.conn.execute("BEGIN IMMEDIATE")
        try:
            yield self.conn
        except BaseException:
            self.conn.execute("ROLLBACK")
            raise
        self.conn.execute("COMMIT")

    # -- the audit trail (the line station's) --------------------------------------------------

    def ensure_audit(self) -> None:
        """Create the audit table if this store has none (a store made by `inspect` gets one
        the first time a line station opens it; `check` does not ask for it)."""
        self.conn.execute(_AUDIT_SCHEMA)

    def audit(self, who: str | None, role: str | None, action: str,
              detail: dict[str, Any] | None = None) -> int:
        """Commit one entry of the audit trail (who did what, when); returns its id."""
        with self._tx() as conn:
            cur = conn.execute(
                "INSERT INTO audit (at, who, role, action, detail) VALUES (?, ?, ?, ?, ?)",
                (time.time(), who, role, action, dumps(detail or {})))
        return int(cur.lastrowid)

    def audit_rows(self, limit: int = 200) -> list[dict[str, Any]]:
        """The latest entries of the audit trail, newest first."""
        out = []
        for r in self.conn.execute("SELECT * FROM audit ORDER BY id DESC LIMIT ?", (limit,)):
            d = dict(r)
            d["detail"] = json.loads(d["detail"]) if d["detail"] else {}
            out.append(d)
        return out

    # -- reading ---------------------------------------------------------------------------

    def count(self) -> int:
        return int(self.conn.execute("SELECT COUNT(*) FROM inspection").fetchone()[0])

    def units_of_batch(self, batch: str) -> set[str]:
        return {r[0] for r in self.conn.execute(
            "SELECT unit FROM inspection WHERE batch = ?", (batch,))}

    def batches(self) -> dict[str, int]:
        """Each batch's name and its number of records, oldest first."""
        return {r[0]: int(r[1]) for r in self.conn.execute(
            "SELECT batch, COUNT(*) FROM inspection WHERE batch IS NOT NULL GROUP BY batch "
            "ORDER BY MIN(id)")}

    def rows(self, where: str = "", params: tuple = ()) -> list[dict[str, Any]]:
        """Records as dicts (SI, JSON decoded), in the order they were made."""
        out = []
        for r in self.conn.execute(f"SELECT * FROM inspection {where} ORDER BY id", params):
            d = dict(r)
            for c in JSON_COLS:
                d[c] = json.loads(d[c]) if d[c] is not None else None
            out.append(d)
        return out

    def get(self, ident: str | int) -> dict[str, Any]:
        """One record by its id, or the latest of a unit by the unit's name."""
        rows = []
        if str(ident).isdigit():
            rows = self.rows("WHERE id = ?", (int(ident),))
        if not rows:
            rows = self.rows("WHERE unit = ?", (str(ident),))[-1:]
        if not rows:
            raise RecordError(f"no inspection {ident} in {self.path}: give a record id or a "
                              "unit's name (aimbench inspect --list shows them)")
        return rows[0]

    # -- export ----------------------------------------------------------------------------

    def export_rows(self) -> tuple[list[str], list[list[Any]]]:
        """Every record as a flat row: the scalar columns and per-axis edge-unit columns."""
        header: list[str] | None = None
        out: list[list[Any]] = []
        for d in self.rows():
            row: dict[str, Any] = {}
            for k, v in d.items():
                if k in JSON_COLS and k not in ("attempts", "diagnostics", "timings"):
                    continue
                row[k] = dumps(v) if isinstance(v, dict | list) else v
            for a in AXES:
                for c, scaled in _AXIS_COLS:
                    v = d[f"{c}_{a}"]
                    if scaled:
                        row[f"{c}_{a}_{UNIT[a]}"] = None if v is None else v * SCALE[a]
            if header is None:
                header = list(row)
            out.append([row[h] for h in header])
        return header or ["id", "unit"], out

    def export(self, path: str | Path) -> Path:
        """CSV (``.csv``) or Parquet (``.parquet``), by the file name's extension."""
        path = Path(path)
        header, rows = self.export_rows()
        if path.suffix == ".csv":
            with path.open("w", newline="", encoding="utf-8") as f:
                w = csv.writer(f)
                w.writerow(header)
                w.writerows(rows)
            return path
        if path.suffix != ".parquet":
            raise RecordError(f"--export {path}: give a .csv or .parquet file name")
        import pyarrow as pa
        import pyarrow.parquet as pq

        cols = list(zip(*rows, strict=True)) if rows else [[] for _ in header]
        arrays = {}
        for name, col in zip(header, cols, strict=True):
            if name in ("started_at", "finished_at"):
                arrays[name] = pa.array([None if v is None else round(v * 1e6) for v in col],
                                        type=pa.timestamp("us", tz="UTC"))
            elif not any(v is not None for v in col):
                arrays[name] = pa.array(list(col), type=pa.null())
            else:
                arrays[name] = pa.array(list(col))
        table = pa.table(arrays).replace_schema_metadata(
            {"aimbench.kind": "inspections", "aimbench.schema_version": str(SCHEMA_VERSION)})
        pq.write_table(table, path)
        return path


def record_row(insp: Any, *, station: Any, operator: str | None, source: str,
               capture: Path | None, capture_sha256: str | None, sensor: dict[str, Any],
               calibration: dict[str, Any], started_at: float, batch: str | None = None
               ) -> dict[str, Any]:
    """The column values of an `scenarios.inspection.procedure.Inspection`'s record."""
    from scenarios.inspection.identity import git_commit, software_version, station_hash

    st = station.to_dict()
    diag = insp.diagnostics
    row: dict[str, Any] = {
        "unit": insp.unit, "started_at": started_at, "finished_at": time.time(),
        "station": station.name, "station_sha256": station_hash(st), "station_json": dumps(st),
        "operator": operator, "software_version": software_version(),
        "git_commit": git_commit(), "calibration": dumps(calibration),
        "sensor_model": sensor.get("model"), "sensor_serial": sensor.get("serial"),
        "sensor": dumps(sensor), "source": source,
        "capture_path": str(capture.resolve()) if capture is not None else None,
        "capture_sha256": capture_sha256, "status": insp.status, "verdict": str(insp.verdict),
        "rule": insp.rule, "coverage_k": insp.k, "scans": insp.scans_used,
        "rejected_scans": diag.get("rejected_scans"), "board_found": int(diag["board_found"]),
        "rings": diag.get("rings"), "board_points": diag.get("board_points"),
    }
    judged = {j.axis: j for j in insp.axes}
    for i, a in enumerate(AXES):
        j = judged.get(a)
        row[f"err_{a}"] = None if insp.error is None else _finite(insp.error[i])
        row[f"u_est_{a}"] = None if insp.covariance is None else _finite(
            math.sqrt(max(float(insp.covariance[i, i]), 0.0)))
        row[f"u_sys_{a}"] = None if j is None else j.u_system
        row[f"u_{a}"] = None if j is None else _finite(j.u)
        row[f"limit_{a}"] = None if j is None else j.limit
        row[f"verdict_{a}"] = None if j is None else str(j.verdict)
        row[f"true_{a}"] = None if insp.truth_error is None else float(insp.truth_error[i])
    edge = insp.to_edge()
    row.update({
        "pose_in_station": dumps(edge.get("pose_in_station")),
        "nominal": dumps({**(edge.get("nominal") or {}), "from": insp.nominal_from}),
        "covariance": dumps(insp.covariance) if insp.covariance is not None else None,
        "attempts": dumps(insp.attempts), "diagnostics": dumps(diag),
        "timings": dumps(insp.timings), "message": insp.message, "batch": batch,
    })
    return row


def _finite(v: float) -> float | None:
    f = float(v)
    return f if math.isfinite(f) else None
