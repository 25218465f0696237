"""The result store of one run: an SQLite file in the run folder, crash-safe and resumable.

Why SQLite: it is in the standard library, a single file per run, and its write-ahead log (WAL)
with ``synchronous=FULL`` means a committed transaction survives a SIGKILL or a power cut. Each
scan's result is committed in its own transaction, so an interrupted run loses at most the scan
that was being estimated, and ``UNIQUE(reference, scan)`` makes a duplicate impossible: `--resume`
asks the store which scans are done and takes only the rest.

Layout of ``run.sqlite`` (SI units throughout; the CSV/Parquet exports add edge-unit columns):

- ``meta(key, value)``: JSON values: ``plan`` (the `Plan`), ``config`` (command-line settings:
  bench, method, seed, ...), ``bench`` (what the bench says about itself), ``versions``
  (software), ``status`` (created, running, interrupted, failed, completed), ``failure`` (where and
  why a run failed), ``created_at``/``updated_at`` (Unix time, s).
- ``reference``: one row per plan reference: the commanded yaw_rad/x_m, mount and via (JSON),
  label, status (pending, running, done, failed), where the stages said they arrived, times, error.
- ``scan``: one row per (reference, scan): the estimate's status and pose (m, rad), its standard
  deviations and covariance (JSON 6x6, order x, y, z, roll, tilt, yaw), the twin's truth where
  there is one, scan facts (points, completeness), timing (s) and diagnostics (JSON).
- ``event``: a log of what happened (moves, failures, interruptions, resumes).
"""

from __future__ import annotations

import contextlib
import csv
import json
import math
import os
import sqlite3
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from scenarios.plans import Plan, Reference
from twin.core.errors import AimbenchError
from twin.core.pose import POSE_FIELDS, Pose, StagePose

if TYPE_CHECKING:
    from align import PoseEstimate

#: File name of the store inside a run folder.
STORE_NAME = "run.sqlite"
SCHEMA_VERSION = 1

#: Run statuses, in the order a run normally goes through them.
RUN_STATUSES = ("created", "running", "interrupted", "failed", "completed")

_POSE_COLS = ("x_m", "y_m", "z_m", "roll_rad", "tilt_rad", "yaw_rad")
_STD_COLS = tuple(f"std_{c}" for c in _POSE_COLS)
_TRUTH_COLS = tuple(f"truth_{c}" for c in _POSE_COLS)

_SCHEMA = f"""
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS reference (
    reference INTEGER PRIMARY KEY,
    yaw_rad REAL NOT NULL,
    x_m REAL NOT NULL,
    mount TEXT,
    via TEXT,
    label TEXT NOT NULL DEFAULT '',
    status TEXT NOT NULL DEFAULT 'pending',
    stage_yaw_rad REAL,
    stage_x_m REAL,
    started_at REAL,
    finished_at REAL,
    error TEXT
);
CREATE TABLE IF NOT EXISTS scan (
    reference INTEGER NOT NULL REFERENCES reference(reference),
    scan INTEGER NOT NULL,
    status TEXT NOT NULL,
    success INTEGER NOT NULL,
    {", ".join(f"{c} REAL" for c in _POSE_COLS + _STD_COLS + _TRUTH_COLS)},
    covariance TEXT,
    stage_yaw_rad REAL,
    stage_x_m REAL,
    points INTEGER,
    complete INTEGER,
    missing_packets INTEGER,
    acquired_at REAL,
    scan_s REAL,
    estimate_s REAL,
    diagnostics TEXT,
    timings TEXT,
    UNIQUE (reference, scan)
);
CREATE TABLE IF NOT EXISTS event (
    id INTEGER PRIMARY KEY,
    at REAL NOT NULL,
    level TEXT NOT NULL,
    reference INTEGER,
    message TEXT NOT NULL
);
"""


class StoreError(AimbenchError):
    """A run folder that cannot be created, opened or resumed."""

#: Name prefix of the temporary file a store is built in before it becomes ``run.sqlite``.
_TEMP_PREFIX = f".{STORE_NAME}.creating-"
#: Metadata every store has from its creation on.
_REQUIRED_META = ("schema_version", "plan", "config", "status", "created_at")
#: JSON columns of the scan table (checked with SQLite's json_valid, row by row).
_JSON_COLS = ("covariance", "diagnostics", "timings")
#: Most problems `check_store` names in one message.
_MAX_PROBLEMS = 5


def _build(tmp: Path, plan: Plan, config: dict | None, bench: dict | None,
           versions: dict | None) -> None:
    """Write a complete store (schema, metadata, references) into `tmp`, synced to disk.

    Everything a store needs is encoded before the file is touched, so a plan it cannot hold
    (a NaN, an object JSON cannot write) fails here with nothing written."""
    now = time.time()
    try:
        meta = [(k, dumps(v)) for k, v in {
            "schema_version": SCHEMA_VERSION, "plan": plan.to_dict(),
            "config": config or {}, "bench": bench or {}, "versions": versions or {},
            "status": "created", "created_at": now, "updated_at": now}.items()]
        refs = [(i, _finite_real(r.yaw_rad, f"reference {i}: yaw"),
                 _finite_real(r.x_m, f"reference {i}: x"),
                 dumps(r.mount) if r.mount else None,
                 dumps(r.to_dict()["via"]) if r.via else None, r.label)
                for i, r in enumerate(plan.references)]
    except (TypeError, ValueError) as exc:
        raise StoreError(f"the plan {plan.name!r} cannot be stored: {exc}") from None
    tmp.unlink(missing_ok=True)
    conn = sqlite3.connect(tmp, isolation_level=None)
    try:
        # A rollback journal while it is private; the WAL is switched on once it is the store.
        conn.execute("PRAGMA synchronous=FULL")
        conn.executescript(_SCHEMA)
        conn.execute("BEGIN IMMEDIATE")
        conn.executemany("INSERT INTO meta (key, value) VALUES (?, ?)", meta)
        conn.executemany("INSERT INTO reference (reference, yaw_rad, x_m, mount, via, label) "
                         "VALUES (?, ?, ?, ?, ?, ?)", refs)
        conn.execute("INSERT INTO event (at, level, reference, message) VALUES (?,?,?,?)",
                     (now, "info", None, f"created: {plan.name}, {len(plan)} references x "
                                         f"{plan.scans} scans"))
        conn.execute("COMMIT")
    finally:
        conn.close()
    with tmp.open("rb+") as f:
        os.fsync(f.fileno())


def _finite_real(v: float, what: str) -> float:
    f = float(v)
    if not math.isfinite(f):
        raise ValueError(f"{what} is {f}, not a finite number")
    return f


def fsync_dir(folder: Path) -> None:
    """Make a rename in `folder` durable (a power cut after it keeps the new name)."""
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _remove_stale_temps(folder: Path) -> None:
    """Remove the temporary stores of creations that were killed (their process is gone): they
    never became a store and hold no results."""
    for tmp in folder.glob(f"{_TEMP_PREFIX}*"):
        pid = tmp.name[len(_TEMP_PREFIX):]
        if not pid.isdigit() or not process_alive(int(pid)):
            tmp.unlink(missing_ok=True)


def process_alive(pid: int) -> bool:
    """Whether process `pid` still runs (one of another user's counts: it cannot be signalled
    but exists), so that a lock it left is not taken over."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _is_unborn(path: Path) -> bool:
    """True for a ``run.sqlite`` that a run killed while creating its store left behind (before
    stores were created atomically): empty, or an SQLite file without the ``meta`` table and
    without a single scan. It holds no results, so a new run may replace it."""
    try:
        if path.stat().st_size == 0:
            return True
        conn = sqlite3.connect(f"file:{path}?mode=ro", uri=True, timeout=5.0)
    except (OSError, sqlite3.DatabaseError):
        return False
    try:
        tables = {r[0] for r in conn.execute(
            "SELECT name FROM sqlite_master WHERE type='table'")}
        if "meta" in tables and conn.execute("SELECT COUNT(*) FROM meta").fetchone()[0]:
            return False
        return "scan" not in tables or not conn.execute("SELECT COUNT(*) FROM scan").fetchone()[0]
    except sqlite3.DatabaseError:
        return False
    finally:
        conn.close()


def _never_started(path: Path) -> bool:
    """True for the store of a run that failed before its bench opened (no bench recorded, no
    scan): a hardware start without the board plugged in left one, and the same command, run
    again once it was, was refused as "already holds a run" (issue 37). It holds no results;
    a new run replaces it."""
    try:
        conn = sqlite3.connect(f"file:{path}?mode=ro", uri=True, timeout=5.0)
    except sqlite3.DatabaseError:
        return False
    try:
        meta = dict(conn.execute("SELECT key, value FROM meta").fetchall())
        scans = conn.execute("SELECT COUNT(*) FROM scan").fetchone()[0]
        return (_json_or_none(meta.get("status")) == "failed" and scans == 0
                and not _json_or_none(meta.get("bench", "null"))
                and not _json_or_none(meta.get("bench_resumed", "null")))
    except sqlite3.DatabaseError:
        return False
    finally:
        conn.close()


def _json_or_none(text: object) -> object:
    try:
        return json.loads(text) if isinstance(text, str | bytes) else None
    except (json.JSONDecodeError, UnicodeDecodeError):
        return None


def writable(path: Path) -> bool:
    """Whether the SQLite file `path` and its folder (its -wal and -shm files) can be written:
    not on a read-only filesystem, not in a folder of someone else's."""
    return os.access(path.parent, os.W_OK) and os.access(path, os.W_OK)


def _connect_read_only(path: Path) -> sqlite3.Connection:
    """A connection to a store that cannot be written (a read-only filesystem, a CD, a folder
    of another user's). SQLite cannot open a WAL file there (it needs the -shm file), and then
    said "unable to open database file", which was reported as a damaged store (issue 37); a
    store closed cleanly has no WAL left and is read as immutable."""
    wal = path.with_name(path.name + "-wal")
    if wal.is_file() and wal.stat().st_size > 0:
        raise StoreError(f"{path} cannot be written here (a read-only filesystem or folder) "
                         f"and its last results are still in {wal.name}, which SQLite can read "
                         "only where it may write; copy the run folder somewhere writable and "
                         "give that")
    return sqlite3.connect(f"file:{path}?mode=ro&immutable=1", uri=True, isolation_level=None)


def _damaged(path: Path, problems: list[str]) -> str:
    shown = "; ".join(problems[:_MAX_PROBLEMS])
    more = f" (and {len(problems) - _MAX_PROBLEMS} more)" if len(problems) > _MAX_PROBLEMS else ""
    return (f"{path} is damaged: {shown}{more}; its results cannot be trusted. Keep the file "
            "as it is (a copy of it may be salvaged with sqlite3's .recover) and run the "
            "sweep again into another --out")


def check_store(path: Path, conn: sqlite3.Connection) -> list[str]:
    """What is damaged in the store at `path` (an empty list: nothing), read-only.

    SQLite's ``PRAGMA integrity_check`` catches broken pages and indexes but not a file cut
    short inside its last page (it reads the missing bytes as zeros), so the file's length is
    checked against its pages too; then the metadata must decode and the rows must fit the plan
    (one reference row per plan reference, scans numbered within the plan, valid JSON)."""
    problems = file_problems(path)
    if problems:
        return problems  # the rows of a truncated file are not worth reading
    try:
        rows = [r[0] for r in conn.execute("PRAGMA integrity_check")]
    except sqlite3.DatabaseError as exc:
        rows = [str(exc)]
    if rows != ["ok"]:
        return ["SQLite's integrity check fails: " + " / ".join(rows[:3])]
    tables = {r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type='table'")}
    if not {"meta", "reference", "scan", "event"} <= tables:
        return [f"tables {sorted({'meta', 'reference', 'scan', 'event'} - tables)} missing"]
    meta = dict(conn.execute("SELECT key, value FROM meta").fetchall())
    missing = [k for k in _REQUIRED_META if k not in meta]
    if missing:
        problems.append(f"metadata {', '.join(missing)} missing")
    bad = [k for k, v in meta.items() if _json_or_none(v) is None and v != "null"]
    if bad:
        problems.append(f"metadata {', '.join(sorted(bad))} unreadable (not JSON)")
    try:
        plan = Plan.from_dict(json.loads(meta["plan"]))
    except (KeyError, TypeError, ValueError, AimbenchError, json.JSONDecodeError) as exc:
        problems.append(f"its plan cannot be read ({type(exc).__name__}: {exc})")
        return problems
    return problems + _row_problems(conn, plan)


_MAGIC = b"SQLite format 3\x00"


def sqlite_header(path: Path) -> bool:
    """Whether `path` begins like an SQLite file (empty files do not)."""
    with path.open("rb") as f:
        return f.read(len(_MAGIC)) == _MAGIC


def file_problems(path: Path) -> list[str]:
    """A file cut short, from its own header (SQLite's file format, section 1.3: page size at
    byte 16, page count at 28, valid when the change counter at 24 equals the one at 92), read
    without SQLite, which fails on such a file with a bare "malformed"."""
    size = path.stat().st_size
    with path.open("rb") as f:
        head = f.read(100)
    if len(head) < 100 or not head.startswith(_MAGIC):
        return ["not an SQLite file (its first bytes are not SQLite's header)"]
    page = int.from_bytes(head[16:18], "big")
    page = 65536 if page == 1 else page
    pages = int.from_bytes(head[28:32], "big")
    counted = head[24:28] == head[92:96] and pages > 0
    wal = path.with_name(path.name + "-wal")
    in_wal = wal.is_file() and wal.stat().st_size > 0
    if page < 512 or page & (page - 1):
        return [f"its header is damaged (page size {page})"]
    if size % page:
        return [f"the file is cut short ({size} bytes, not a whole number of its "
                f"{page}-byte pages: truncated)"]
    if counted and not in_wal and size < pages * page:
        return [f"the file is cut short ({size} of the {pages * page} bytes its {pages} "
                "pages take: truncated)"]
    return []


def _row_problems(conn: sqlite3.Connection, plan: Plan) -> list[str]:
    """The reference and scan rows against the plan."""
    problems = []
    refs = [r[0] for r in conn.execute("SELECT reference FROM reference ORDER BY reference")]
    if refs != list(range(len(plan))):
        problems.append(f"{len(refs)} reference rows where the plan has {len(plan)}")
    outside = conn.execute(
        "SELECT COUNT(*), MIN(reference), MIN(scan) FROM scan WHERE reference < 0 OR "
        "reference >= ? OR scan < 0 OR scan >= ?", (len(plan), plan.scans)).fetchone()
    if outside[0]:
        problems.append(f"{outside[0]} scan rows outside the plan's {len(plan)} references x "
                        f"{plan.scans} scans (first: reference {outside[1]}, scan {outside[2]})")
    valid = " AND ".join(f"({c} IS NULL OR json_valid({c}))" for c in _JSON_COLS)
    broken = conn.execute(f"SELECT COUNT(*), MIN(reference), MIN(scan) FROM scan "
                          f"WHERE NOT ({valid})").fetchone()
    if broken[0]:
        problems.append(f"{broken[0]} scan rows with unreadable JSON (first: reference "
                        f"{broken[1]}, scan {broken[2]})")
    return problems



def _json_default(obj: object) -> object:
    """JSON for what estimators put in diagnostics: numpy scalars and arrays, Poses, the rest."""
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Pose):
        return obj.to_edge()
    if isinstance(obj, Path):
        return str(obj)
    if hasattr(obj, "to_dict"):
        return obj.to_dict()
    return repr(obj)


def dumps(obj: object) -> str:
    """JSON text, numpy-aware; NaN/inf become null so every JSON reader can load it."""
    return json.dumps(_finite(obj), default=_json_default, allow_nan=False)


def _finite(obj: object) -> object:
    if isinstance(obj, float | np.floating):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): _finite(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_finite(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _finite(obj.tolist())
    return obj


@dataclass
class ScanResult:
    """One scan's outcome, as the store keeps it (SI units).

    estimate: align's answer (`align.PoseEstimate`): its status, its pose (kept only when the
        estimate succeeded), its covariance and sigma in the order of
        `twin.core.pose.POSE_FIELDS` (m, rad), its diagnostics and timings.
    truth: the twin's true LiDAR pose in the board frame for this scan (None on hardware).
    stage: where the stages reported they were while the scan was taken, if they did.
    scan_s: wall time to acquire the scan; estimate_s: wall time of the estimator (s).
    """

    reference: int
    scan: int
    estimate: PoseEstimate
    truth: Pose | None = None
    stage: StagePose | None = None
    points: int | None = None
    complete: bool | None = None
    missing_packets: int | None = None
    acquired_at: float | None = None
    scan_s: float | None = None
    estimate_s: float | None = None

    def row(self) -> dict[str, object]:
        """The column values of this result's row in ``scan``."""
        est = self.estimate
        nan6 = [None] * 6
        pose = list(est.pose.as_array()) if est.success else nan6
        std = list(est.std) if est.std is not None else nan6
        truth = list(self.truth.as_array()) if self.truth is not None else nan6
        row: dict[str, object] = {
            "reference": int(self.reference), "scan": int(self.scan),
            "status": str(est.status), "success": int(est.success),
        }
        for cols, values in ((_POSE_COLS, pose), (_STD_COLS, std), (_TRUTH_COLS, truth)):
            row.update({c: _real(v) for c, v in zip(cols, values, strict=True)})
        row.update({
            "covariance": dumps(np.asarray(est.covariance, float))
            if est.covariance is not None else None,
            "stage_yaw_rad": _real(self.stage.yaw_rad) if self.stage else None,
            "stage_x_m": _real(self.stage.x_m) if self.stage else None,
            "points": self.points, "complete": None if self.complete is None
            else int(self.complete),
            "missing_packets": self.missing_packets, "acquired_at": self.acquired_at,
            "scan_s": self.scan_s, "estimate_s": self.estimate_s,
            "diagnostics": dumps(est.diagnostics), "timings": dumps(est.timings),
        })
        return row


def _real(v: object) -> float | None:
    if v is None:
        return None
    f = float(v)
    return f if math.isfinite(f) else None


class Store:
    """One run's store. Create with `Store.create`, reopen with `Store.open`; use as a context.

    All writes go through short transactions; the connection runs in autocommit mode and each
    method opens and commits its own (``BEGIN IMMEDIATE`` so a concurrent reader never blocks a
    commit half-way).
    """

    def __init__(self, path: Path, conn: sqlite3.Connection, read_only: bool = False) -> None:
        self.path = path
        self.conn = conn
        #: Opened where it cannot be written (a read-only filesystem or folder): read it only.
        self.read_only = read_only

    # -- opening ---------------------------------------------------------------------------

    @staticmethod
    def _connect(path: Path) -> sqlite3.Connection:
        conn = sqlite3.connect(path, isolation_level=None, timeout=30.0)
        conn.row_factory = sqlite3.Row
        # WAL: a crash mid-write leaves the last committed state; readers (a report while the
        # sweep runs) do not block the writer. FULL: each commit is fsynced, so a committed scan
        # also survives a power cut, not just a killed process (costs ~ms per scan; scans take
        # 100 ms on the real sensor).
        conn.execute("PRAGMA journal_mode=WAL")
        conn.execute("PRAGMA synchronous=FULL")
        conn.execute("PRAGMA foreign_keys=ON")
        return conn

    @classmethod
    def create(cls, run_dir: str | Path, plan: Plan, config: dict | None = None,
               bench: dict | None = None, versions: dict | None = None) -> Store:
        """A new store in `run_dir` (created if needed) for `plan`.

        Refuses a folder that already holds a run: a new run never overwrites results; use
        `Store.open` (``--resume``) to continue one, or another ``--out``.

        Atomic: the store is built whole (schema, plan, references) in a temporary file beside
        it and renamed to ``run.sqlite`` only then, so a kill at any instant leaves either no
        store or a complete one, and a plan the store cannot hold leaves nothing at all.
        """
        run_dir = Path(run_dir)
        path = run_dir / STORE_NAME
        if path.exists() and not _is_unborn(path) and not _never_started(path):
            raise StoreError(f"{run_dir} already holds a run; continue it with --resume or "
                             "choose another --out")
        made_dir = not run_dir.exists()
        try:
            run_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise StoreError(f"cannot create the run folder {run_dir}: {exc.strerror}") from None
        _remove_stale_temps(run_dir)
        tmp = run_dir / f"{_TEMP_PREFIX}{os.getpid()}"
        try:
            _build(tmp, plan, config, bench, versions)
            # The rename is atomic on POSIX: run.sqlite appears complete or not at all.
            for side in ("-wal", "-shm"):  # of a never-started run this replaces
                path.with_name(path.name + side).unlink(missing_ok=True)
            os.replace(tmp, path)
            fsync_dir(run_dir)
        except BaseException:
            tmp.unlink(missing_ok=True)
            if made_dir:
                with contextlib.suppress(OSError):
                    run_dir.rmdir()  # only if empty: nothing of anyone's is removed
            raise
        return cls(path, cls._connect(path))

    @classmethod
    def open(cls, run_dir: str | Path, check: bool = True) -> Store:
        """The store of an existing run (to resume it, report on it or export it).

        check: before anything is trusted, verify the file (`check_store`: SQLite's own
        integrity check, a file cut short, the metadata, the rows against the plan) and refuse
        a damaged store with a `StoreError` saying what is damaged. Nothing is written first.
        """
        run_dir = Path(run_dir)
        path = run_dir / STORE_NAME if run_dir.is_dir() or not run_dir.suffix else run_dir
        if not path.is_file():
            raise StoreError(f"no run in {run_dir} (no {STORE_NAME}); run a sweep with --out "
                             f"{run_dir} first")
        if _is_unborn(path):
            raise StoreError(f"{path} was never initialised (its run was stopped while the "
                             "store was being created) and holds no results; start the run "
                             f"again: a new sweep with --out {path.parent} replaces it")
        if not sqlite_header(path):
            raise StoreError(f"{path} is not a readable aimbench run store: not an SQLite "
                             "file; give the folder of a run that aimbench sweep made")
        read_only = not writable(path)
        try:
            conn = _connect_read_only(path) if read_only else sqlite3.connect(
                path, isolation_level=None, timeout=30.0)
        except sqlite3.DatabaseError as exc:
            raise StoreError(f"{path} is not a readable aimbench run store: {exc}") from None
        try:
            try:
                problems = check_store(path, conn) if check else []
                if problems:
                    raise StoreError(_damaged(path, problems))
                version = conn.execute(
                    "SELECT value FROM meta WHERE key='schema_version'").fetchone()
            except sqlite3.DatabaseError as exc:
                raise StoreError(f"{path} is not a readable aimbench run store: {exc}") from None
            if version is None or _json_or_none(version[0]) != SCHEMA_VERSION:
                raise StoreError(f"{path}: unknown store schema {version and version[0]}; "
                                 f"this aimbench reads version {SCHEMA_VERSION}")
        finally:
            if not read_only:
                conn.close()
        if read_only:
            conn.row_factory = sqlite3.Row
            return cls(path, conn, read_only=True)
        return cls(path, cls._connect(path))

    def close(self) -> None:
        self.conn.close()

    def __enter__(self) -> Store:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def run_dir(self) -> Path:
        return self.path.parent

    # -- transactions ----------------------------------------------------------------------

    class _Tx:
        def __init__(self, conn: sqlite3.Connection) -> None:
            self.conn = conn

        def __enter__(self) -> sqlite3.Connection:
            if self.conn.in_transaction:
                # A transaction left open by an interrupt between its INSERT and its COMMIT
                # (a second Ctrl-C): it never committed, so it is dropped, and resume retakes it.
                self.conn.execute("ROLLBACK")
            self.conn.execute("BEGIN IMMEDIATE")
            return self.conn

        def __exit__(self, exc_type: object, *rest: object) -> None:
            self.conn.execute("ROLLBACK" if exc_type else "COMMIT")

    def _tx(self) -> Store._Tx:
        return Store._Tx(self.conn)

    @staticmethod
    def _put_many(conn: sqlite3.Connection, values: dict) -> None:
        conn.executemany("INSERT OR REPLACE INTO meta (key, value) VALUES (?, ?)",
                         [(k, dumps(v)) for k, v in values.items()])

    # -- metadata --------------------------------------------------------------------------

    def get(self, key: str, default: object = None) -> object:
        row = self.conn.execute("SELECT value FROM meta WHERE key=?", (key,)).fetchone()
        return json.loads(row[0]) if row else default

    def put(self, **values: object) -> None:
        """Set metadata keys (JSON values) in one transaction."""
        with self._tx() as conn:
            self._put_many(conn, {**values, "updated_at": time.time()})

    @property
    def plan(self) -> Plan:
        return Plan.from_dict(self.get("plan"))

    @property
    def status(self) -> str:
        return str(self.get("status"))

    def set_status(self, status: str, message: str | None = None,
                   reference: int | None = None, scan: int | None = None) -> None:
        """Mark the run `status`; a failure also records where (reference, scan) and why."""
        if status not in RUN_STATUSES:
            raise ValueError(f"unknown run status {status!r}")
        values: dict = {"status": status, "updated_at": time.time()}
        if status == "failed":
            values["failure"] = {"reference": reference, "scan": scan, "message": message}
        with self._tx() as conn:
            self._put_many(conn, values)
            if message or status != "running":
                conn.execute("INSERT INTO event (at, level, reference, message) VALUES "
                             "(?,?,?,?)", (time.time(), "error" if status == "failed" else "info",
                                           reference, f"{status}: {message or ''}".rstrip(": ")))

    def log(self, message: str, level: str = "info", reference: int | None = None) -> None:
        with self._tx() as conn:
            conn.execute("INSERT INTO event (at, level, reference, message) VALUES (?,?,?,?)",
                         (time.time(), level, reference, message))

    def events(self) -> list[dict]:
        return [dict(r) for r in self.conn.execute("SELECT * FROM event ORDER BY id")]

    # -- references ------------------------------------------------------------------------

    def references(self) -> list[dict]:
        """Every reference row (dicts, SI units), in plan order."""
        rows = []
        for r in self.conn.execute("SELECT * FROM reference ORDER BY reference"):
            d = dict(r)
            d["mount"] = json.loads(d["mount"]) if d["mount"] else None
            d["via"] = json.loads(d["via"]) if d["via"] else None
            rows.append(d)
        return rows

    def reference(self, index: int) -> Reference:
        return self.plan.references[index]

    def start_reference(self, index: int, stage: StagePose | None = None) -> None:
        """The stages are at reference `index` (at `stage` if they said where)."""
        yaw, x = (stage.yaw_rad, stage.x_m) if stage is not None else (None, None)
        with self._tx() as conn:
            conn.execute(
                "UPDATE reference SET status='running', started_at=COALESCE(started_at, ?), "
                "stage_yaw_rad=?, stage_x_m=?, error=NULL WHERE reference=?",
                (time.time(), _real(yaw), _real(x), index))

    def finish_reference(self, index: int, status: str = "done",
                         error: str | None = None) -> None:
        if status not in ("done", "failed", "pending"):
            raise ValueError(f"unknown reference status {status!r}")
        with self._tx() as conn:
            conn.execute("UPDATE reference SET status=?, finished_at=?, error=? "
                         "WHERE reference=?", (status, time.time(), error, index))

    # -- scans -----------------------------------------------------------------------------

    def add_scan(self, result: ScanResult) -> None:
        """Commit one scan's result in its own transaction.

        Raises `StoreError` if (reference, scan) is already stored: the runner never asks for a
        scan it has, so a duplicate is a bug to see, not to paper over.
        """
        self.add_scans([result])

    def add_scans(self, results: Sequence[ScanResult]) -> None:
        """Commit several scans' results in one transaction: all of them or, on any error,
        none (a duplicate (reference, scan) raises `StoreError` as `add_scan` does).

        Why: every commit is fsynced (``synchronous=FULL``), some milliseconds of a busy disk
        each; the parallel sweep's scans arrive faster than that from its workers, so it
        commits what has arrived together. A kill before the commit loses only results the
        store never had, which a resume takes again (the same scans: they are seeded)."""
        if not results:
            return
        rows = [r.row() for r in results]
        cols = ", ".join(rows[0])
        marks = ", ".join("?" for _ in rows[0])
        try:
            with self._tx() as conn:
                conn.executemany(f"INSERT INTO scan ({cols}) VALUES ({marks})",
                                 [tuple(row.values()) for row in rows])
        except sqlite3.IntegrityError as exc:
            seen = set(map(tuple, self.conn.execute("SELECT reference, scan FROM scan")))
            dup = results[0]
            for r in results:  # the first already stored, or twice in this batch
                if (r.reference, r.scan) in seen:
                    dup = r
                    break
                seen.add((r.reference, r.scan))
            raise StoreError(f"scan {dup.scan} of reference {dup.reference} is already "
                             f"stored ({exc})") from None

    def done_scans(self, reference: int) -> list[int]:
        """Indices of the scans stored for `reference`, ascending."""
        return [r[0] for r in self.conn.execute(
            "SELECT scan FROM scan WHERE reference=? ORDER BY scan", (reference,))]

    def scan_count(self) -> int:
        return int(self.conn.execute("SELECT COUNT(*) FROM scan").fetchone()[0])

    def iter_scans(self) -> Iterator[dict]:
        """Every scan row as a dict (SI units, JSON fields decoded), by reference then scan."""
        for r in self.conn.execute("SELECT * FROM scan ORDER BY reference, scan"):
            d = dict(r)
            for key in ("diagnostics", "timings", "covariance"):
                d[key] = json.loads(d[key]) if d[key] else None
            yield d

    def columns(self) -> dict[str, np.ndarray]:
        """The scan table as numpy columns (float NaN where a value is missing), for reports.

        Adds per-scan reference columns ``ref_yaw_rad`` and ``ref_x_m`` (the commanded stage
        position) and ``ref_mount_*`` (edge units, NaN without a mount).
        """
        refs = {r["reference"]: r for r in self.references()}
        rows = list(self.conn.execute(
            f"SELECT reference, scan, status, success, {', '.join(_POSE_COLS + _STD_COLS)}, "
            f"{', '.join(_TRUTH_COLS)}, stage_yaw_rad, stage_x_m, scan_s, estimate_s "
            "FROM scan ORDER BY reference, scan"))
        names = ["reference", "scan", "status", "success", *_POSE_COLS, *_STD_COLS,
                 *_TRUTH_COLS, "stage_yaw_rad", "stage_x_m", "scan_s", "estimate_s"]
        out: dict[str, np.ndarray] = {}
        for j, name in enumerate(names):
            values = [r[j] for r in rows]
            if name == "status":
                out[name] = np.array(values, dtype=object)
            elif name in ("reference", "scan"):
                out[name] = np.array(values, dtype=np.int64)
            elif name == "success":
                out[name] = np.array(values, dtype=bool)
            else:
                out[name] = np.array([np.nan if v is None else v for v in values], dtype=float)
        ref_ids = out["reference"]
        out["ref_yaw_rad"] = np.array([refs[i]["yaw_rad"] for i in ref_ids], dtype=float)
        out["ref_x_m"] = np.array([refs[i]["x_m"] for i in ref_ids], dtype=float)
        for key in ("roll_deg", "tilt_deg", "yaw_deg", "x_mm"):
            out[f"ref_mount_{key}"] = np.array(
                [(refs[i]["mount"] or {}).get(key, np.nan) for i in ref_ids], dtype=float)
        return out

    # -- export ----------------------------------------------------------------------------

    def _export_rows(self) -> tuple[list[str], list[list[object]]]:
        """One row per scan with the reference and the estimate in SI and in edge units."""
        refs = {r["reference"]: r for r in self.references()}
        header: list[str] | None = None
        rows: list[list[object]] = []
        for d in self.iter_scans():
            ref = refs[d["reference"]]
            row: dict[str, object] = {
                "reference": d["reference"], "scan": d["scan"], "label": ref["label"],
                # Rounded below any stage's resolution: the plan's -6 deg, stored in rad,
                # came back as -6.000000000000001 (issue 37).
                "ref_yaw_deg": round(math.degrees(ref["yaw_rad"]), EDGE_DIGITS),
                "ref_x_mm": round(ref["x_m"] * 1e3, EDGE_DIGITS),
                **{f"ref_mount_{k}": (ref["mount"] or {}).get(k) for k in
                   ("roll_deg", "tilt_deg", "yaw_deg", "x_mm")},
                "status": d["status"], "success": bool(d["success"]),
            }
            for prefix in ("", "std_", "truth_"):
                for name, col in zip(POSE_FIELDS, _POSE_COLS, strict=True):
                    v = d[prefix + col]
                    edge = f"{prefix}{name}_mm" if col.endswith("_m") else f"{prefix}{name}_deg"
                    scale = 1e3 if col.endswith("_m") else 180.0 / math.pi
                    row[edge] = None if v is None else v * scale
            for prefix in ("", "std_", "truth_"):
                row.update({prefix + c: d[prefix + c] for c in _POSE_COLS})
            row.update({
                "stage_yaw_deg": None if d["stage_yaw_rad"] is None
                else math.degrees(d["stage_yaw_rad"]),
                "stage_x_mm": None if d["stage_x_m"] is None else d["stage_x_m"] * 1e3,
                "points": d["points"], "complete": d["complete"],
                "missing_packets": d["missing_packets"], "acquired_at": d["acquired_at"],
                "scan_s": d["scan_s"], "estimate_s": d["estimate_s"],
                "diagnostics": dumps(d["diagnostics"]) if d["diagnostics"] is not None else None,
                "timings": dumps(d["timings"]) if d["timings"] is not None else None,
            })
            if header is None:
                header = list(row)
            rows.append(list(row.values()))
        if header is None:
            header = ["reference", "scan"]
        return header, rows

    def export_csv(self, path: str | Path) -> Path:
        """Every scan as a CSV row (edge and SI columns); returns the path written."""
        path = Path(path)
        header, rows = self._export_rows()
        with path.open("w", newline="", encoding="utf-8") as f:
            w = csv.writer(f)
            w.writerow(header)
            w.writerows(rows)
        return path

    def export_parquet(self, path: str | Path) -> Path:
        """Every scan as a Parquet row (same columns as the CSV) with the run's metadata."""
        import pyarrow as pa
        import pyarrow.parquet as pq

        path = Path(path)
        header, rows = self._export_rows()
        columns = list(zip(*rows, strict=True)) if rows else [[] for _ in header]
        table = pa.table({name: _arrow_column(pa, name, list(col)) for name, col in
                          zip(header, columns, strict=True)})
        meta = {k: dumps(self.get(k)) for k in ("plan", "config", "bench", "versions", "status")}
        table = table.replace_schema_metadata({f"aimbench.{k}": v for k, v in meta.items()})
        pq.write_table(table, path)
        return path


#: Export columns that are instants (Unix time, s), written to Parquet as UTC timestamps.
TIMESTAMP_COLUMNS = ("acquired_at",)
#: Export columns of text; every other column is a number (or a flag) when it has values.
TEXT_COLUMNS = ("label", "status", "diagnostics", "timings")
#: Decimals the references are exported with (deg, mm): far below any stage's resolution.
EDGE_DIGITS = 9


def _arrow_column(pa: object, name: str, values: list[object]) -> object:
    """One Parquet column: instants as ``timestamp[us, UTC]`` (a reader sees times, not
    floats: pandas, DuckDB and Polars all take them as such), the rest as inferred."""
    if name in TIMESTAMP_COLUMNS:
        micros = [None if v is None else round(float(v) * 1e6) for v in values]
        return pa.array(micros, type=pa.timestamp("us", tz="UTC"))
    column = pa.array(values)
    if column.type == pa.null():
        # Every value missing (no run had a mount, say): typed as the column's values are
        # when present, not as Parquet's null type that readers cannot compute with.
        kind = pa.string() if name in TEXT_COLUMNS else pa.float64()
        column = pa.array(values, type=kind)
    return column
