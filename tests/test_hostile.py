"""Hostile input and the first hour of a new user (issue 37): each test is one symptom the
issue found, on the real part (the twin, real SQLite files, real sockets, real files), and
asserts the documented outcome: a result, or one clear line naming the problem."""

from __future__ import annotations

import os
import signal
import sqlite3
import time
from pathlib import Path

import pytest

from scenarios import station as stations
from scenarios.inspection.acquire import TwinAcquisition
from scenarios.inspection.procedure import inspect_unit
from scenarios.inspection.records import RecordError, Records, record_row


def test_a_locked_record_store_keeps_the_record_and_says_so(tmp_path: Path, capsys):
    """An inspection that met a store locked by another program lost the unit's record with a
    traceback after 30 s; now it waits, saying so, then keeps the record beside the store,
    and the next open commits it."""
    station = stations.default()
    with TwinAcquisition(station, {"tilt_deg": 0.3}, seed=1) as acq:
        insp = inspect_unit(acq, station, "LOCK-1", scans=2, max_scans=2)
    row = record_row(insp, station=station, operator=None, source="sim", capture=None,
                     capture_sha256=None, sensor=acq.sensor, calibration={},
                     started_at=time.time())
    db = tmp_path / "line.sqlite"
    with Records.open(db, create=True) as rec:
        rec.lock_wait_s, rec.lock_notice_s = 0.6, 0.2
        holder = sqlite3.connect(db, isolation_level=None)
        holder.execute("BEGIN IMMEDIATE")  # another program writing, and never finishing
        with pytest.raises(RecordError, match=r"stayed locked by another program .* kept in"):
            rec.add(row)
        assert "is locked by another program; waiting" in capsys.readouterr().err
        assert rec.count() == 0 and len(list(rec.pending.glob("*.json"))) == 1
        holder.execute("ROLLBACK")
        holder.close()
    with Records.open(db) as rec:  # the lock gone: the kept record goes in
        rows = rec.rows()
        assert [(r["unit"], r["trial"], r["verdict"]) for r in rows] == [
            ("LOCK-1", 1, row["verdict"])]
        assert rows[0]["err_tilt"] == row["err_tilt"] and not list(rec.pending.glob("*.json"))
        rid, trial = rec.add(row)
        assert trial == 2 and rec.count() == 2


def test_twin_units_named_apart_are_different_units():
    """`inspect sim --unit T1` and `--unit T2` were the same unit (one default seed)."""
    from scenarios.commands.inspect import unit_seed

    seeds = {unit_seed(f"T{i}") for i in range(100)}
    assert len(seeds) == 100 and unit_seed("T1") == unit_seed("T1")


def test_a_second_sigterm_stops_a_sweep_stuck_in_a_scan():
    """SIGTERM only set a flag checked between scans: a scan that never ended (a NaN station
    hung the twin) made a sweep deaf to it. The second SIGTERM now interrupts, as Ctrl-C's."""
    from scenarios.runner import _StopFlag

    said = []
    with _StopFlag(lambda: said.append(1)) as flag, pytest.raises(KeyboardInterrupt):
        os.kill(os.getpid(), signal.SIGTERM)
        assert flag.stop and flag.signal == "SIGTERM" and said == [1]
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(1.0)  # the handler runs here
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL
