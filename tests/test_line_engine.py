"""The line station's parts that need no browser or PLC (tests/test_line_station.py has those):
passwords, the station file's [line] section, one inspection at a time, recovery after a kill,
and the command line's refusals. Real stores, the real engine; no twin scans."""

from __future__ import annotations

import asyncio

import pytest

from scenarios import station as stations
from scenarios.cli import main
from scenarios.inspection.records import Records
from scenarios.line import auth
from scenarios.line.engine import Busy, StationEngine, check_unit, twin_unit
from twin.core.errors import AimbenchError


def test_passwords_are_scrypt_hashes_and_roles_say_who_may_what():
    h = auth.hash_password("s3cret")
    assert h.startswith("scrypt$16384$8$1$") and "s3cret" not in h
    assert auth.verify_password("s3cret", h) and not auth.verify_password("s3creT", h)
    assert auth.hash_password("s3cret") != h  # salted
    assert not auth.verify_password("x", "scrypt$broken") and not auth.verify_password("x", "")
    st = stations.from_dict({"line": {"users": [
        {"name": "eng", "role": "engineer", "password_scrypt": h}]}})
    u = auth.authenticate(st, "eng", "s3cret")
    assert u == auth.User("eng", "engineer") and u.may("engineer") and u.may("set_batch")
    assert auth.authenticate(st, "eng", "wrong") is None
    assert auth.authenticate(st, "nobody", "s3cret") is None
    assert not auth.User("op", "operator").may("engineer")
    with pytest.raises(stations.StationError, match="users named twice"):
        stations.from_dict({"line": {"users": [
            {"name": "a", "role": "plc", "password_scrypt": h},
            {"name": "a", "role": "engineer", "password_scrypt": h}]}})
    with pytest.raises(stations.StationError, match=r"line\.users\.0\.password_scrypt"):
        stations.from_dict({"line": {"users": [
            {"name": "a", "role": "plc", "password_scrypt": "plain-text"}]}})
    assert stations.load("paper").line.address == "127.0.0.1"  # this machine unless named
    assert "users" not in st.to_dict()["line"]  # no password hash in records or on pages


def test_unit_ids_and_twin_units():
    assert check_unit("  VIN-1\n") == "VIN-1"
    for bad in ("", "   ", "x" * 65, "A\x00B", 12):
        with pytest.raises(AimbenchError):
            check_unit(bad)
    st = stations.load("paper")
    assert twin_unit(st, "VIN-1") == twin_unit(st, "VIN-1") != twin_unit(st, "VIN-2")
    mis, _ = twin_unit(st, "VIN-1")
    assert set(mis) == {"roll_deg", "tilt_deg", "yaw_deg", "x_mm"}
    assert all(abs(v) <= 1.3 * 10 for v in mis.values())


def test_one_inspection_at_a_time_and_recovery_after_a_kill(tmp_path):
    """A held lock stands for an inspection in progress: a second trigger is refused at once
    and logged; a start in the audit trail without its record (a kill) comes back as an
    error naming the unit."""
    st = stations.load("paper")
    db = tmp_path / "line.sqlite"
    eng = StationEngine(st, db, "sim")
    try:
        assert eng.snapshot.state == "idle"
        eng._lock.acquire()
        eng.snapshot.unit, eng.snapshot.origin = "A-1", "opcua"

        async def second() -> None:
            with pytest.raises(Busy, match=r"busy: inspecting unit A-1 .*B-2 was not started"):
                await eng.trigger("B-2", "web", who="op", role="operator")
            with pytest.raises(AimbenchError, match="no unit id"):
                await eng.trigger("  ", "http")

        asyncio.run(second())
        eng._lock.release()
        acts = [(a["action"], a["detail"].get("unit")) for a in eng.audit_rows()]
        assert ("refused", "B-2") in acts
        eng.audit("plc", None, "start", {"unit": "K-1", "origin": "opcua", "last_record": 0})
    finally:
        eng.close()
    again = StationEngine(st, db, "sim")  # as after a kill -9 during K-1
    try:
        assert again.snapshot.state == "error" and "K-1" in again.snapshot.message
        assert again.audit_rows(1)[0]["action"] == "recovered"
    finally:
        again.close()
    third = StationEngine(st, db, "sim")  # recovered once: not an error again
    try:
        assert third.snapshot.state == "idle"
    finally:
        third.close()
    with Records.open(db) as r:
        assert r.count() == 0


def test_the_command_line_refuses_bad_input_in_one_line(capsys, monkeypatch, tmp_path):
    monkeypatch.chdir(tmp_path)
    for argv, expected in (
            (["station"], "give --db FILE"),
            (["station", "--db", "x.sqlite", "--source", "ftp://x"], "--source ftp://x: give"),
            (["station", "--db", "x.sqlite", "--scans", "0"], "--scans: must be a whole number"),
    ):
        try:
            code = main(argv)
        except SystemExit as exc:
            code = exc.code
        err = capsys.readouterr().err
        assert code == 2 and expected in err and "Traceback" not in err, err
    monkeypatch.setenv("AIMBENCH_PASSWORD", "pw-1")
    assert main(["station", "--hash-password"]) == 0
    assert auth.verify_password("pw-1", capsys.readouterr().out.strip())
