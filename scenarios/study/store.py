"""The store of one study: an SQLite file in the study folder, crash-safe and resumable.

Like the run store (scenarios/store.py, whose helpers it uses: JSON encoding, the directory
sync of an atomic creation, the check of a file cut short): write-ahead log, ``synchronous=FULL``,
created whole in a temporary file and renamed. The unit of work is a task, a block of poses at
one design point; a task's rows and its ``task`` row are committed in one transaction, and
``PRIMARY KEY (point, block)`` makes a second commit of the same task impossible: a study killed
at any instant loses at most the tasks in flight (they run again on ``--resume``) and never holds
a result twice.

Layout of ``study.sqlite`` (SI units; the Parquet exports add edge-unit columns):

- ``meta(key, value)``: JSON: ``spec`` (the study file, as read), ``station`` (the base
  station's content), ``config`` (engine, seed...), ``versions``, ``status`` (created, running,
  interrupted, failed, completed), ``created_at``/``updated_at``.
- ``point``: one row per design point: its parameters (JSON), the number of tasks it takes.
- ``task``: one row per finished task (point, block): when, on which engine, CPU seconds.
- ``estimate``: one row per estimate: point, pose, scans fused, group, status, the error and the
  reported sigma per axis (x, y, z m; roll, tilt, yaw rad) in the station frame, CPU seconds.
- ``bound``: one row per (point, pose, scans fused): the bound's std per axis, CPU seconds.
- ``event``: what happened (started, resumed, a lost worker's task run again, interrupted).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import sqlite3
import time
from pathlib import Path
from typing import Any

import numpy as np

from scenarios.store import dumps, file_problems, fsync_dir
from twin.core.errors import AimbenchError

STORE_NAME = "study.sqlite"
SCHEMA_VERSION = 1
STATUSES = ("created", "running", "interrupted", "failed", "completed")
AXES = ("x", "y", "z", "roll", "tilt", "yaw")
_ERR = tuple(f"err_{a}" for a in AXES)
_SIG = tuple(f"sigma_{a}" for a in AXES)
_STD = tuple(f"std_{a}" for a in AXES)
_TEMP_PREFIX = f".{STORE_NAME}.creating-"

_SCHEMA = f"""
CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE point (point INTEGER PRIMARY KEY, params TEXT NOT NULL, tasks INTEGER NOT NULL);
CREATE TABLE task (
    point INTEGER NOT NULL REFERENCES point(point),
    block INTEGER NOT NULL,
    finished_at REAL NOT NULL,
    engine TEXT NOT NULL,
    cpu_s REAL,
    PRIMARY KEY (point, block)
);
CREATE TABLE estimate (
    point INTEGER NOT NULL, pose INTEGER NOT NULL, fused INTEGER NOT NULL,
    grp INTEGER NOT NULL, status TEXT NOT NULL, success INTEGER NOT NULL,
    {", ".join(f"{c} REAL" for c in _ERR + _SIG)}, cpu_s REAL,
    UNIQUE (point, pose, fused, grp)
);
CREATE TABLE bound (
    point INTEGER NOT NULL, pose INTEGER NOT NULL, fused INTEGER NOT NULL,
    {", ".join(f"{c} REAL" for c in _STD)}, cpu_s REAL,
    UNIQUE (point, pose, fused)
);
CREATE TABLE event (id INTEGER PRIMARY KEY, at REAL NOT NULL, level TEXT NOT NULL,
                    message TEXT NOT NULL);
"""


class StudyStoreError(AimbenchError):
    """A study folder that cannot be created, opened or resumed."""


def _real(v: Any) -> float | None:
    f = float(v)
    return f if math.isfinite(f) else None


class StudyStore:
    """One study's store; `create` a new one, `open` an existing one; a context manager."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.conn = sqlite3.connect(path, isolation_level=None, timeout=30.0)
        self.conn.row_factory = sqlite3.Row
        self.conn.execute("PRAGMA journal_mode=WAL")
        self.conn.execute("PRAGMA synchronous=FULL")

    @classmethod
    def create(cls, folder: str | Path, points: list[dict[str, Any]], tasks_per_point: int,
               meta: dict[str, Any]) -> StudyStore:
        """A new store in `folder` for these design points; refuses a folder holding a study."""
        folder = Path(folder)
        path = folder / STORE_NAME
        if path.exists():
            raise StudyStoreError(f"{folder} already holds a study; continue it with --resume or "
                                  "choose another --out")
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise StudyStoreError(f"cannot create the study folder {folder}: "
                                  f"{exc.strerror}") from None
        for stale in folder.glob(f"{_TEMP_PREFIX}*"):
            stale.unlink(missing_ok=True)  # a creation that was killed: never a store
        tmp = folder / f"{_TEMP_PREFIX}{os.getpid()}"
        now = time.time()
        rows = [(k, dumps(v)) for k, v in {**meta, "schema_version": SCHEMA_VERSION,
                                           "status": "created", "created_at": now,
                                           "updated_at": now}.items()]
        try:
            conn = sqlite3.connect(tmp, isolation_level=None)
            try:
                conn.executescript(_SCHEMA)
                conn.execute("BEGIN")
                conn.executemany("INSERT INTO meta VALUES (?, ?)", rows)
                conn.executemany("INSERT INTO point VALUES (?, ?, ?)",
                                 [(i, dumps(p), tasks_per_point) for i, p in enumerate(points)])
                conn.execute("INSERT INTO event (at, level, message) VALUES (?, 'info', ?)",
                             (now, f"created: {len(points)} design points"))
                conn.execute("COMMIT")
            finally:
                conn.close()
            with tmp.open("rb+") as f:
                os.fsync(f.fileno())
            os.replace(tmp, path)  # atomic: study.sqlite appears whole or not at all
            fsync_dir(folder)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
        return cls(path)

    @classmethod
    def open(cls, folder: str | Path) -> StudyStore:
        """The store of an existing study, checked before it is trusted."""
        folder = Path(folder)
        path = folder / STORE_NAME if folder.is_dir() or not folder.suffix else folder
        if not path.is_file():
            raise StudyStoreError(f"no study in {folder} (no {STORE_NAME}); run aimbench study "
                                  f"FILE.toml --out {folder} first")
        problems = file_problems(path)
        if not problems:
            with contextlib.closing(sqlite3.connect(path, timeout=30.0)) as conn:
                try:
                    rows = [r[0] for r in conn.execute("PRAGMA integrity_check")]
                    version = conn.execute(
                        "SELECT value FROM meta WHERE key='schema_version'").fetchone()
                except sqlite3.DatabaseError as exc:
                    rows, version = [str(exc)], None
            if rows != ["ok"]:
                problems = ["SQLite's integrity check fails: " + " / ".join(rows[:3])]
            elif version is None or json.loads(version[0]) != SCHEMA_VERSION:
                problems = [f"unknown study store schema {version and version[0]}"]
        if problems:
            raise StudyStoreError(f"{path} is damaged: {'; '.join(problems)}; its results cannot "
                                  "be trusted: run the study again into another --out")
        return cls(path)

    def close(self) -> None:
        self.conn.close()

    def __enter__(self) -> StudyStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def folder(self) -> Path:
        return self.path.parent

    # -- metadata ----------------------------------------------------------------------------

    def get(self, key: str, default: Any = None) -> Any:
        row = self.conn.execute("SELECT value FROM meta WHERE key=?", (key,)).fetchone()
        return json.loads(row[0]) if row else default

    def put(self, **values: Any) -> None:
        with self._tx() as conn:
            conn.executemany("INSERT OR REPLACE INTO meta VALUES (?, ?)",
                             [(k, dumps(v)) for k, v in {**values,
                                                         "updated_at": time.time()}.items()])

    @property
    def status(self) -> str:
        return str(self.get("status"))

    def set_status(self, status: str, message: str = "") -> None:
        if status not in STATUSES:
            raise ValueError(f"unknown study status {status!r}")
        self.put(status=status)
        self.log(f"{status}: {message}".rstrip(": "), "error" if status == "failed" else "info")

    def log(self, message: str, level: str = "info") -> None:
        with self._tx() as conn:
            conn.execute("INSERT INTO event (at, level, message) VALUES (?, ?, ?)",
                         (time.time(), level, message))

    def events(self) -> list[dict]:
        return [dict(r) for r in self.conn.execute("SELECT * FROM event ORDER BY id")]

    @contextlib.contextmanager
    def _tx(self):
        if self.conn.in_transaction:
            self.conn.execute("ROLLBACK")  # never committed: the task runs again
        self.conn.execute("BEGIN IMMEDIATE")
        try:
            yield self.conn
        except BaseException:
            self.conn.execute("ROLLBACK")
            raise
        self.conn.execute("COMMIT")

    # -- points and tasks --------------------------------------------------------------------

    def points(self) -> list[dict[str, Any]]:
        """Every design point's parameters, in order."""
        return [json.loads(r[0]) for r in
                self.conn.execute("SELECT params FROM point ORDER BY point")]

    def done_tasks(self) -> set[tuple[int, int]]:
        return {(r[0], r[1]) for r in self.conn.execute("SELECT point, block FROM task")}

    def add_task(self, point: int, block: int, result: dict[str, Any], engine: str) -> bool:
        """Commit a task's rows and its task row in one transaction; False (nothing written)
        if the task is already stored (a lost worker's retry whose first run also arrived)."""
        try:
            with self._tx() as conn:
                conn.execute("INSERT INTO task VALUES (?, ?, ?, ?, ?)",
                             (point, block, time.time(), engine, result.get("cpu_s")))
                conn.executemany(
                    f"INSERT INTO estimate VALUES ({', '.join('?' * 19)})",
                    [(point, k, n, g, status, int(ok), *map(_real, err), *map(_real, sig), cpu)
                     for k, n, g, status, ok, err, sig, cpu in result["estimates"]])
                conn.executemany(
                    f"INSERT INTO bound VALUES ({', '.join('?' * 10)})",
                    [(point, k, n, *map(_real, std), cpu)
                     for k, n, std, cpu in result["bounds"]])
        except sqlite3.IntegrityError:
            return False
        return True

    # -- reading -----------------------------------------------------------------------------

    def estimates(self) -> dict[str, np.ndarray]:
        """The estimate table as numpy columns (NaN where a value is missing)."""
        return _columns(self.conn, "estimate", ("point", "pose", "fused", "grp", "status",
                                                "success", *_ERR, *_SIG, "cpu_s"))

    def bounds(self) -> dict[str, np.ndarray]:
        return _columns(self.conn, "bound", ("point", "pose", "fused", *_STD, "cpu_s"))

    def counts(self) -> tuple[int, int]:
        """(estimates, bounds) stored."""
        return (int(self.conn.execute("SELECT COUNT(*) FROM estimate").fetchone()[0]),
                int(self.conn.execute("SELECT COUNT(*) FROM bound").fetchone()[0]))


def _columns(conn: sqlite3.Connection, table: str, names: tuple[str, ...]
             ) -> dict[str, np.ndarray]:
    rows = conn.execute(f"SELECT {', '.join(names)} FROM {table} "
                        "ORDER BY point, pose, fused" + (", grp" if table == "estimate" else "")
                        ).fetchall()
    out: dict[str, np.ndarray] = {}
    for j, name in enumerate(names):
        values = [r[j] for r in rows]
        if name == "status":
            out[name] = np.array(values, dtype=object)
        elif name in ("point", "pose", "fused", "grp", "success"):
            out[name] = np.array(values, dtype=np.int64)
        else:
            out[name] = np.array([np.nan if v is None else v for v in values], dtype=float)
    return out
