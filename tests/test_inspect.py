"""The inspection station (`aimbench inspect`, scenarios/inspection/): the decision rules, the
mounting error, verdicts on the twin against its truth, the records, the report and the live
view, all on the real twin and real SQLite files."""

from __future__ import annotations

import csv
import hashlib
import json
import math
import os
import sqlite3
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from scenarios import station as stations
from scenarios.inspection import mounting
from scenarios.inspection.acquire import TwinAcquisition
from scenarios.inspection.line import line_units
from scenarios.inspection.procedure import inspect_unit
from scenarios.inspection.records import RecordError, Records
from scenarios.inspection.verdict import Verdict, judge, limits_si, overall
from twin.core.pose import Pose

REPO = Path(__file__).resolve().parents[1]


def cli(*args: str, cwd: Path, timeout: float = 600) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run([sys.executable, "-m", "scenarios.cli", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=timeout)


# -- the decision rules ------------------------------------------------------------------------

@pytest.mark.parametrize(("error", "u", "expected"), [
    (0.0, 0.1, Verdict.PASS), (0.8, 0.1, Verdict.PASS), (-0.8, 0.1, Verdict.PASS),
    (0.81, 0.1, Verdict.INCONCLUSIVE), (1.0, 0.1, Verdict.INCONCLUSIVE),
    (1.2, 0.1, Verdict.INCONCLUSIVE), (-1.2, 0.1, Verdict.INCONCLUSIVE),
    (1.21, 0.1, Verdict.FAIL), (-1.5, 0.1, Verdict.FAIL), (0.0, 0.6, Verdict.INCONCLUSIVE),
    (0.5, math.inf, Verdict.INCONCLUSIVE),
])
def test_iso14253_guard_bands(error, u, expected):
    # limit 1, k = 2: the acceptance zone is |e| <= 0.8, the rejection zone |e| > 1.2.
    assert judge(error, u, 1.0, "iso14253-1", 2.0) == expected


def test_simple_rule_and_the_units_verdict():
    assert judge(0.99, 0.5, 1.0, "simple") == Verdict.PASS
    assert judge(1.01, 0.0, 1.0, "simple") == Verdict.FAIL
    assert overall([Verdict.PASS, Verdict.PASS]) == Verdict.PASS
    assert overall([Verdict.PASS, Verdict.INCONCLUSIVE]) == Verdict.INCONCLUSIVE
    assert overall([Verdict.INCONCLUSIVE, Verdict.FAIL]) == Verdict.FAIL
    assert overall([]) == Verdict.INCONCLUSIVE
    with pytest.raises(ValueError, match="unknown decision rule"):
        judge(0.0, 0.1, 1.0, "guess")


# -- the mounting error ------------------------------------------------------------------------

def test_mounting_error_is_the_misalignment_and_carries_the_covariance():
    """A station whose frame and board are turned and shifted: the error of a pose made from the
    nominal and a known misalignment is that misalignment, and a covariance comes through J C
    J^T (compared with the error's spread over poses drawn from it)."""
    st = stations.from_dict({"board": {"position_mm": [100.0, 50.0, 480.0], "yaw_deg": 3.0,
                                       "tilt_deg": -1.0},
                             "frame": {"name": "vehicle", "pose": {"x_mm": 700.0, "y_mm": -2500.0,
                                                                   "yaw_deg": 90.0}},
                             "mount": {"nominal": {"z_mm": 500.0, "yaw_deg": -90.0}}})
    nominal, source = mounting.nominal_pose(st)
    assert source == "station"
    mis = Pose.from_edge(x_mm=3.0, y_mm=-2.0, z_mm=1.0, roll_deg=0.4, tilt_deg=-0.7, yaw_deg=1.1)
    in_station = nominal.matrix() @ mis.matrix()
    in_station = Pose.from_matrix(in_station[:3, :3], nominal.translation + mis.translation)
    # the same pose in the board frame: {O} <- {W} <- {S}
    m = (np.linalg.inv(st.board_in_bench()) @ st.frame.pose.to_pose().matrix()
         @ in_station.matrix())
    in_board = Pose.from_matrix(m[:3, :3], m[:3, 3])
    cov = np.diag(np.array([2e-3, 1e-3, 5e-3, 2e-3, 1e-3, 1.5e-3]) ** 2)
    err, c, back = mounting.mounting_error(in_board, cov, st, nominal)
    assert np.allclose(err, mis.as_array(), atol=1e-9)
    assert np.allclose(back.as_array(), in_station.as_array(), atol=1e-9)
    rng = np.random.default_rng(1)
    draws = rng.multivariate_normal(in_board.as_array(), cov, 4000)
    errs = np.array([mounting.error_of(st.lidar_in_station(Pose.from_array(d)), nominal)
                     for d in draws])
    sample = np.cov(errs.T)
    sd, sd_c = np.sqrt(np.diag(sample)), np.sqrt(np.diag(c))
    assert np.allclose(sd, sd_c, rtol=0.05)
    # correlations: 4000 draws give them to about 0.016 (1-sigma)
    assert np.allclose(sample / np.outer(sd, sd), c / np.outer(sd_c, sd_c), atol=0.06)


def test_the_nominal_without_mount_nominal_is_the_twins_perfect_mount():
    nominal, source = mounting.nominal_pose(stations.default())
    assert source == "twin"
    assert np.allclose(nominal.as_array(), [0.7, -2.5, 0.5, 0, 0, 0], atol=1e-6)


# -- verdicts on the twin ----------------------------------------------------------------------

@pytest.mark.slow
def test_a_small_line_has_no_wrong_verdict_and_doubt_only_near_the_limits():
    """12 twin units of a line (misalignments within +-1.3 x each limit), sensors without range
    offsets: every PASS is truly inside on every axis, every FAIL truly outside on one, and an
    inconclusive axis lies within U of its limit by its true error. The benchmark runs 200,
    with the sensor errors on and off."""
    # the twin's sensors here have no range offsets: a station that says so
    shipped = stations.default()
    st = shipped.model_copy(update={"sensor": shipped.sensor.model_copy(update={
        "laser_offset_std_mm": 0.0})})
    limits = limits_si(st.tolerances)
    z2 = []
    for u in line_units(st, 12, seed=11):
        with TwinAcquisition(st, u.misalignment, seed=u.seed, sensor_errors=False) as acq:
            insp = inspect_unit(acq, st, u.name)
        truth = insp.true_verdict(limits)
        assert insp.status == "ok", insp.message
        if insp.verdict != Verdict.INCONCLUSIVE:
            assert insp.verdict == truth, (u, insp.message, insp.truth_error)
        for j in insp.axes:
            t = insp.truth_error[("x", "y", "z", "roll", "tilt", "yaw").index(j.axis)]
            if j.verdict == Verdict.INCONCLUSIVE:
                # doubt only where the truth is within about U (a little more: U is estimated)
                assert abs(abs(t) - j.limit) <= 1.5 * j.expanded, (u.name, j)
            z2.append(((j.error - t) / j.u) ** 2)
    # The estimator's sigma, pooled over the judged axes: a chi-square test at 0.1 %.
    n = len(z2)
    lo, hi = stats.chi2.ppf([0.0005, 0.9995], n) / n
    assert lo < np.mean(z2) < hi * 1.25, f"chi2/n {np.mean(z2):.2f} over {n} axes"


@pytest.mark.slow
def test_a_units_own_range_errors_stated_by_the_station_keep_the_sigma_honest():
    """12 twin units, each with its own per-laser and common range offsets (2.5 mm sigma): a
    station that states their spread (`[sensor] range_offset_std_mm`, `laser_offset_std_mm`)
    has the estimator estimate the common offset with the pose and carry the per-laser ones,
    so that its sigma alone is a promise again, with no system term (without the spread the
    chi2 is 7-36: docs/inspection.md). The benchmark runs 200 (setting D)."""
    from scenarios.inspection.acquire import unit_sensor

    base = stations.default()
    st = base.model_copy(update={"sensor": base.sensor.model_copy(update={
        "range_offset_std_mm": 2.5, "laser_offset_std_mm": 2.5})})
    z2, b_err = [], []
    for u in line_units(st, 12, seed=12):
        with TwinAcquisition(st, u.misalignment, seed=u.seed) as acq:
            insp = inspect_unit(acq, st, u.name)
        assert insp.status == "ok", insp.message
        diag = insp.estimate.diagnostics
        b_err.append((diag["range_offset_m"] - unit_sensor(u.seed).range_bias)
                     / diag["range_offset_std_m"])
        for j in insp.axes:
            t = insp.truth_error[("x", "y", "z", "roll", "tilt", "yaw").index(j.axis)]
            z2.append(((j.error - t) / j.u) ** 2)
    n = len(z2)
    lo, hi = stats.chi2.ppf([0.0005, 0.9995], n) / n
    assert lo < np.mean(z2) < hi, f"chi2/n {np.mean(z2):.2f} over {n} axes"
    # the common offset is reported with a sigma that covers its error
    assert np.mean(np.square(b_err)) < stats.chi2.ppf(0.9995, len(b_err)) / len(b_err)


# -- the command, the records, the report -------------------------------------------------------

@pytest.mark.slow
def test_inspect_sim_records_reports_and_exports(tmp_path: Path):
    db = tmp_path / "line.sqlite"
    r = cli("inspect", "sim", "--unit", "VIN-1", "--tilt-deg", "2.5", "--seed", "3", "--db",
            str(db), "--operator", "ann", "--report", "rep", "--json", "--batch", "lot-7",
            cwd=tmp_path)
    assert r.returncode == 1, r.stderr  # FAIL
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out["verdict"] == "fail" and out["record"] == 1 and out["scans"] == 10
    assert abs(out["tilt_deg_true"] - 2.5) < 1e-9
    r2 = cli("inspect", "sim", "--unit", "VIN-1", "--seed", "3", "--db", str(db),
             "--no-captures", cwd=tmp_path)
    assert r2.returncode in (0, 3), r2.stderr
    assert "VIN-1" in r2.stdout and "trial 2" in r2.stdout
    assert "captures:" not in r2.stderr  # said when kept (2 MB a unit), not when not
    with Records.open(db) as rec:
        rows = rec.rows()
        assert [(x["unit"], x["trial"]) for x in rows] == [("VIN-1", 1), ("VIN-1", 2)]
        first = rows[0]
        assert first["operator"] == "ann" and first["verdict"] == "fail"
        assert first["verdict_tilt"] in ("fail", "inconclusive") and first["verdict_y"] is None
        assert first["git_commit"] and first["software_version"]
        cap = Path(first["capture_path"])
        assert cap.is_file() and hashlib.sha256(cap.read_bytes()).hexdigest() == \
            first["capture_sha256"]
        assert first["sensor_serial"] == "twin-3" and first["board_found"] == 1
        assert rows[1]["capture_path"] is None and rows[1]["capture_sha256"] is None
    assert len(list((tmp_path / "line.captures").glob("*.pcap"))) == 1
    # The kept capture is the sensor's data: it estimates as the record says.
    est = cli("estimate", str(cap), "--fuse", "10", "--json", cwd=tmp_path)
    assert est.returncode == 0, est.stderr
    page = tmp_path / "rep" / "VIN-1-1.html"
    assert page.is_file() and (tmp_path / "rep" / "VIN-1-1.png").stat().st_size > 10_000
    # why the board was found (scenarios.explain), beneath the figure
    assert (tmp_path / "rep" / "VIN-1-1-explain.png").stat().st_size > 10_000
    assert "How the board was found" in page.read_text()
    assert "FAIL" in page.read_text() and "data:image/png;base64" in page.read_text()
    for name in ("line.csv", "line.parquet"):
        r = cli("inspect", "--db", str(db), "--export", name, cwd=tmp_path)
        assert r.returncode == 0, r.stderr
    with (tmp_path / "line.csv").open() as f:
        table = list(csv.DictReader(f))
    assert [t["unit"] for t in table] == ["VIN-1", "VIN-1"]
    assert abs(float(table[0]["true_tilt_deg"]) - 2.5) < 1e-9
    import pyarrow.parquet as pq

    pt = pq.read_table(tmp_path / "line.parquet")
    assert pt.num_rows == 2 and str(pt.schema.field("started_at").type).startswith("timestamp")
    listing = cli("inspect", "--db", str(db), "--list", cwd=tmp_path)
    assert listing.returncode == 0 and listing.stdout.count("VIN-1") == 2
    show = cli("inspect", "--db", str(db), "--show", "1", cwd=tmp_path)
    assert "tilt_deg" in show.stdout and "(true +2.500)" in show.stdout
    summary = cli("inspect", "--db", str(db), "--summary", "--report", "rep", cwd=tmp_path)
    assert summary.returncode == 0, summary.stderr
    assert "pass rate" in (tmp_path / "rep" / "summary.html").read_text()
    # --summary prints without --report: the tally and each axis's capability
    summary = cli("inspect", "--db", str(db), "--summary", "--batch", "lot-7", cwd=tmp_path)
    assert summary.returncode == 0, summary.stderr
    assert summary.stdout.startswith("1 inspections of 1 units: 0 PASS (0.0 %), 1 FAIL")
    assert first["batch"] == "lot-7" and rows[1]["batch"] is None
    # a batch that is not there is refused with the batches there are
    grr = cli("grr", "--db", str(db), "--batch", "lot-8", cwd=tmp_path)
    assert grr.returncode == 2 and "'lot-7' (1 records)" in grr.stderr, grr.stderr


def test_bad_input_is_one_line_and_loses_nothing(tmp_path: Path):
    (tmp_path / "folder").mkdir()
    r = cli("inspect", "sim", "--unit", "A", "--db", "folder", cwd=tmp_path)
    assert r.returncode == 2 and "is a folder" in r.stderr and len(r.stderr.splitlines()) <= 2
    r = cli("inspect", "--db", "none.sqlite", "--list", cwd=tmp_path)
    assert r.returncode == 2 and "no inspection records" in r.stderr
    r = cli("inspect", "sim", "--db", "x.sqlite", cwd=tmp_path)
    assert r.returncode == 2 and "--unit" in r.stderr
    assert not (tmp_path / "x.sqlite").exists()
    r = cli("inspect", "sim", "--unit", "A", "--scans", "10", "--max-scans", "5", "--db",
            "x.sqlite", cwd=tmp_path)
    assert r.returncode == 2 and "--max-scans" in r.stderr
    (tmp_path / "cap.pcap").write_bytes(b"\xd4\xc3\xb2\xa1" + bytes(20))
    r = cli("inspect", "cap.pcap", "--unit", "A", "--tilt-deg", "1", "--db", "x.sqlite",
            cwd=tmp_path)
    assert r.returncode == 2 and "misalignment" in r.stderr
    # A damaged store is refused, and left as it was.
    with Records.open(tmp_path / "ok.sqlite", create=True):
        pass
    data = (tmp_path / "ok.sqlite").read_bytes()
    (tmp_path / "cut.sqlite").write_bytes(data[: len(data) - 100])
    with pytest.raises(RecordError, match="damaged"):
        Records.open(tmp_path / "cut.sqlite")
    assert (tmp_path / "cut.sqlite").read_bytes() == data[: len(data) - 100]
    other = sqlite3.connect(tmp_path / "other.sqlite")
    other.execute("CREATE TABLE t (a)")
    other.close()
    with pytest.raises(RecordError, match="not an inspection"):
        Records.open(tmp_path / "other.sqlite")


@pytest.mark.slow
def test_the_live_view_shows_board_frames_points_and_verdict(tmp_path: Path):
    from rerun_reader import read_rrd

    r = cli("inspect", "sim", "--unit", "R1", "--yaw-deg", "2", "--db", "r.sqlite", "--rerun",
            "--save", "live.rrd", "--max-scans", "10", cwd=tmp_path)
    assert r.returncode == 1, r.stderr
    rec = read_rrd(tmp_path / "live.rrd")
    for entity in ("/world/board", "/world/nominal", "/world/estimate", "/world/sensor/scan",
                   "/world/sensor/board_points", "/plots/estimate/yaw_deg"):
        assert rec.rows(entity), f"{entity} missing from the recording"
    texts = [row.components["TextLog:text"][0] for row in rec.rows("/log", "TextLog:text")]
    assert any("R1: FAIL" in t for t in texts), texts
    yaw = rec.rows("/plots/estimate/yaw_deg", "Scalars:scalars")[-1].components[
        "Scalars:scalars"][0]
    assert abs(yaw - 2.0) < 0.3


@pytest.mark.slow
def test_a_recording_is_read_on_by_a_re_measure(tmp_path: Path):
    """take() twice from a capture gives the next scans, not the same ones and not none (a
    re-measure reads on from the same stream); the recording is its own capture."""
    from scenarios.inspection.acquire import RecordedAcquisition, sha256_of

    r = cli("simulate", "--scans", "8", "--seed", "2", "--out", "cap.pcap", "--quiet",
            cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    with RecordedAcquisition(str(tmp_path / "cap.pcap")) as acq:
        first, second = acq.take(3), acq.take(3)
        rest = acq.take(10)
    stamps = [s.time[0] for s in first + second + rest]
    assert len(first) == len(second) == 3 and len(rest) >= 1
    assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps)
    assert acq.capture_sha256() == sha256_of(tmp_path / "cap.pcap")
