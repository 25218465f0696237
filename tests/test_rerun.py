"""Rerun recordings, read back with rerun's own reader: a real sweep on the twin with the real
estimator, replayed from its run folder (the twin re-simulated), a capture written by the twin and
replayed with its truth, and the command line. Nothing is rendered here (see docs/replay.md for
the screenshot)."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from rerun_reader import Recording, read_rrd

from scenarios.plans import Plan, Reference
from scenarios.recording import log as rl
from scenarios.runner import Runner, make_estimator
from scenarios.store import Store
from twin.core.pose import Pose

REPO = Path(__file__).resolve().parent.parent
PYTHON = sys.executable
SCANS = 3
YAWS_DEG = (-2.0, 0.0, 3.0)

#: Per-scan entities: exactly one row at every step of the scan timeline.
PER_SCAN = ("/world/truth", "/world/estimate", "/world/sensor", "/world/sensor/scan",
            "/world/sensor/board_points", "/world/sensor/features", "/world/sensor/plane")


def _rot(row_values: list) -> np.ndarray:
    """rerun's Mat3x3 is stored column-major."""
    return np.asarray(row_values, dtype=float).reshape(3, 3).T


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small yaw sweep on the twin with align's default method, run by the real runner."""
    from scenarios.bench import SimBench

    out = tmp_path_factory.mktemp("rerun") / "run"
    refs = tuple(Reference(math.radians(y), 0.0, label=f"yaw {y:+g} deg") for y in YAWS_DEG)
    plan = Plan("rerun test", "yaw", refs, SCANS)
    bench = SimBench(seed=3)
    store = Store.create(out, plan, {"bench": "sim", "seed": 3, "method": None}, bench.info())
    try:
        assert Runner(plan, bench, store, make_estimator(None)).run() == "completed"
    finally:
        store.close()
    return out


@pytest.fixture(scope="module")
def replayed(run_dir: Path) -> tuple[Recording, object, list[dict]]:
    from scenarios.recording.replay import replay_run

    path = run_dir / "replay.rrd"
    rec = rl.new_recording("test replay")
    rec.save(path, default_blueprint=rl.blueprint())
    summary = replay_run(run_dir, rec, points_every=1)  # the full clouds (--full-clouds)
    rec.flush()
    rec.disconnect()
    with Store.open(run_dir) as store:
        rows = list(store.iter_scans())
    return read_rrd(path), summary, rows


def test_replay_logs_every_entity_once_per_scan(replayed):
    recording, summary, _ = replayed
    n = len(YAWS_DEG) * SCANS
    assert summary.scans == n and summary.clouds == n
    assert recording.blueprints == 1
    assert {"scan", "sensor_time", "stage_time", "wall_time"} <= recording.timelines
    for entity in PER_SCAN:
        steps = {}
        for r in recording.rows(entity):
            steps[r.times["scan"]] = steps.get(r.times["scan"], 0) + 1
        assert steps == dict.fromkeys(range(n), 1), entity
    # Static scene: the board, its corners, the bench's bodies (the board plate left to
    # world/board).
    corners = recording.rows("/world/board/corners")[0].components["Points3D:positions"]
    np.testing.assert_allclose(corners, [[-0.45, 0, 0.27], [0.45, 0, 0.27], [-0.45, 0, -0.27],
                                         [0.45, 0, -0.27]], atol=1e-6)
    bodies = {e.split("/")[3] for e in recording.entities if e.startswith("/world/bench/")}
    assert {"carriage", "turntable", "vlp16", "linear_stage"} <= bodies
    assert "target_board" not in bodies


def test_replayed_scans_are_the_runs_own(replayed):
    """The twin, re-simulated, gives back the very scans the run estimated: the same number of
    returns as the runner stored, and the same estimates (no mismatch)."""
    recording, summary, rows = replayed
    assert summary.mismatches == 0
    for row in rows:
        step = row["reference"] * SCANS + row["scan"]
        (positions,) = recording.at("/world/sensor/scan", "scan", step, "Points3D:positions")
        assert len(positions) == row["points"]


def test_a_decimated_cloud_keeps_the_boards_neighbourhood_whole(tmp_path: Path):
    """A recording's default cloud (issue 38: a 2,100-scan sweep under 100 MB): every return
    around the board, where the estimator reads its edges, and every 32nd elsewhere."""
    import align
    from twin.sim.bench import BenchSim

    scan = BenchSim(seed=1).scan()
    used = align.estimate(scan).used
    keep = rl.board_neighbourhood(scan, used)
    assert keep is not None and keep[np.asarray(used["board"])].all()
    assert 0.01 < keep[scan.valid].mean() < 0.1  # the board's span, not the room
    path = tmp_path / "one.rrd"
    rec = rl.new_recording("decimated")
    rec.save(path)
    logged = rl.log_scan_points(rec, scan, every=32, keep=keep)
    rec.flush()
    rec.disconnect()
    row = read_rrd(path).rows("/world/sensor/scan", "Points3D:positions")[0]
    positions = row.components["Points3D:positions"]
    near, far = scan.valid & keep, scan.valid & ~keep
    assert len(positions) == logged == near.sum() + -(-far.sum() // 32)
    got = {tuple(p) for p in np.asarray(positions, dtype=np.float32).tolist()}
    whole = np.column_stack((scan.x, scan.y, scan.z))[near].astype(np.float32)
    assert {tuple(p) for p in whole.tolist()} <= got  # rerun keeps float32 as given


def test_true_and_estimated_pose_of_a_known_scan(replayed):
    recording, _, rows = replayed
    row = next(r for r in rows if r["reference"] == 2 and r["scan"] == 1)
    step = 2 * SCANS + 1
    truth = Pose(*(row[f"truth_{c}"] for c in ("x_m", "y_m", "z_m", "roll_rad", "tilt_rad",
                                                "yaw_rad")))
    # The twin's LiDAR sits 0.7 m right of and 2.5 m before the board, turned by the stage.
    assert math.degrees(truth.yaw) == pytest.approx(YAWS_DEG[2], abs=1e-6)
    (t,) = recording.at("/world/truth", "scan", step, "Transform3D:translation")
    (m,) = recording.at("/world/truth", "scan", step, "Transform3D:mat3x3")
    np.testing.assert_allclose(t[0], truth.translation, atol=1e-6)
    np.testing.assert_allclose(_rot(m[0]), truth.rotation(), atol=1e-6)
    # The plotted error is estimate - truth in mm/deg, with the report's tolerance band.
    errors = recording.at("/plots/error/yaw_deg", "scan", step, "Scalars:scalars")
    if row["success"]:
        (err,) = errors
        assert err[0] == pytest.approx(math.degrees(row["yaw_rad"] - row["truth_yaw_rad"]),
                                       abs=1e-9)
        assert err[1:] == [0.2, -0.2]
        (t_est,) = recording.at("/world/estimate", "scan", step, "Transform3D:translation")
        np.testing.assert_allclose(t_est[0], [row["x_m"], row["y_m"], row["z_m"]], atol=1e-6)
    else:
        assert errors == []


def test_failed_scans_are_annotated_and_clear_the_estimate(replayed):
    recording, _, rows = replayed
    texts = [(r.times.get("scan"), r.components["TextLog:level"][0], r.components[
        "TextLog:text"][0]) for r in recording.rows("/log", "TextLog:text")]
    for row in rows:
        step = row["reference"] * SCANS + row["scan"]
        warned = [t for s, lvl, t in texts if s == step and lvl == "WARN" and "no pose" in t]
        cleared = recording.at("/world/estimate", "scan", step, "Clear:is_recursive")
        errors = recording.at("/plots/error/x_mm", "scan", step, "Scalars:scalars")
        if row["success"]:
            assert not warned and not cleared and len(errors) == 1
        else:
            assert len(warned) == 1 and row["status"] in warned[0]
            assert cleared == [[False]] and errors == []
    # One annotation per reference, and the store's events (created, started, completed).
    assert sum(1 for _, _, t in texts if t.startswith("reference ")) == len(YAWS_DEG)
    assert any("completed" in t for _, _, t in texts)


def test_board_points_and_features_are_what_the_estimator_used(replayed, run_dir: Path):
    """The board points and the features at a scan are align's `used` for that very scan."""
    from scenarios.recording.replay import resimulate

    recording, _, rows = replayed
    with Store.open(run_dir) as store:
        wanted = {(r["reference"], r["scan"]) for r in rows if r["success"]}
        if not wanted:
            pytest.fail("no scan of the test sweep got a pose: the estimator or the twin broke")
        i, k, scan = next(resimulate(store, {min(wanted)}))
    est = make_estimator(None)(scan)  # the run's estimator: its (default) station's hints
    step = i * SCANS + k
    (board,) = recording.at("/world/sensor/board_points", "scan", step, "Points3D:positions")
    (feats,) = recording.at("/world/sensor/features", "scan", step, "Points3D:positions")
    assert len(board) == len(np.asarray(est.used["board"]).reshape(-1))
    assert len(feats) == len(np.asarray(est.used["features"]).reshape(-1))
    np.testing.assert_allclose(board, scan.xyz[np.asarray(est.used["board"])], atol=1e-5)


def test_store_only_replay_has_no_clouds(run_dir: Path, tmp_path: Path):
    from scenarios.recording.replay import replay_run

    path = tmp_path / "store.rrd"
    rec = rl.new_recording()
    rec.save(path)
    summary = replay_run(run_dir, rec, clouds=False)
    rec.flush()
    rec.disconnect()
    recording = read_rrd(path)
    assert summary.clouds == 0 and summary.source == "the result store only"
    assert "/world/sensor/scan" not in recording.entities
    assert len(recording.rows("/world/truth", "Transform3D:translation")) == len(YAWS_DEG) * SCANS


def test_capture_replay_pairs_scans_with_their_truth(tmp_path: Path):
    """A capture the twin wrote while the stages moved (so every scan has its own truth), with
    its truth file, replayed scan by scan: each decoded scan gets the truth of its own time."""
    from scenarios.recording.replay import replay_capture
    from scenarios.truth import write_truth
    from twin.sim.bench import BenchSim

    sim = BenchSim(seed=5)
    sim.move_to(x_m=0.0, yaw_rad=math.radians(-3.0))
    sim.start_move(x_m=0.02, yaw_rad=math.radians(3.0))
    pcap = tmp_path / "cap.pcap"
    scans = sim.write_pcap(pcap, 4)
    write_truth(pcap, scans)
    path = tmp_path / "cap.rrd"
    rec = rl.new_recording()
    rec.save(path)
    summary = replay_capture(pcap, rec)
    rec.flush()
    rec.disconnect()
    recording = read_rrd(path)
    assert 3 <= summary.scans <= 4  # the capture's first/last rotation may be partial
    truths = recording.rows("/world/truth", "Transform3D:translation")
    assert len(truths) == summary.scans
    assert len(recording.rows("/world/sensor/scan")) == summary.scans
    starts = np.array([s.time[0] for s in scans])
    yaws = []
    for r in truths:
        # The twin's scan that began at this sensor time (decoding quantises time to 1 us).
        j = int(np.argmin(np.abs(starts - r.times["sensor_time"] * 1e-9)))
        assert abs(starts[j] - r.times["sensor_time"] * 1e-9) < 1e-4
        truth = scans[j].meta["truth_pose"]
        np.testing.assert_allclose(r.components["Transform3D:translation"][0],
                                   truth.translation, atol=1e-6)
        yaws.append(truth.yaw)
    assert len(set(np.round(yaws, 9))) == len(yaws)  # the stages moved: no two truths alike
    # No stages for a bare capture.
    assert not any(e.startswith("/world/bench") for e in recording.entities)


@pytest.mark.slow
def test_cli_replay_saves_a_file_rerun_verifies(run_dir: Path, tmp_path: Path):
    out = tmp_path / "cli.rrd"
    cmd = [PYTHON, "-m", "scenarios.cli", "replay", str(run_dir), "--save", str(out),
           "--no-clouds", "--no-progress"]
    res = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=120,
                         env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"})
    assert res.returncode == 0, res.stderr
    assert f"recording saved to {out}" in res.stderr
    rerun = Path(PYTHON).with_name("rerun")
    res = subprocess.run([str(rerun), "rrd", "verify", str(out)], capture_output=True,
                         text=True, timeout=120)
    assert res.returncode == 0, res.stdout + res.stderr


def test_the_estimator_and_the_twin_never_import_rerun():
    code = ("import sys, align, twin.sim.bench, twin.core.scan, scenarios.runner, scenarios.cli, "
            "scenarios.commands.sweep, scenarios.commands.replay, scenarios.recording.observer, "
            "scenarios.recording.log; assert 'rerun' not in sys.modules, 'rerun imported'")
    res = subprocess.run([PYTHON, "-c", code], cwd=REPO, capture_output=True, text=True,
                         timeout=120)
    assert res.returncode == 0, res.stderr
    import re

    imports = re.compile(r"^\s*(import rerun|from rerun\b|from scenarios\.recording\.log|"
                         r"from scenarios\.recording import log)", re.MULTILINE)
    for path in [*(REPO / "align").rglob("*.py"), REPO / "twin" / "sim" / "bench.py",
                 REPO / "twin" / "core" / "scan.py", REPO / "scenarios" / "runner.py"]:
        assert not imports.search(path.read_text(encoding="utf-8")), path


def test_point_colours_by_intensity_and_ring():
    from twin.sim.bench import BenchSim

    scan = BenchSim(seed=2).scan()
    lut = rl.turbo_lut()
    assert lut.shape == (256, 3) and lut.dtype == np.uint8
    from matplotlib import colormaps

    ref = np.rint(colormaps["turbo"](np.linspace(0, 1, 256))[:, :3] * 255)
    assert np.abs(lut.astype(float) - ref).max() <= 4
    by_ring = rl.scan_colors(scan, scan.valid, "ring")
    assert len({tuple(c) for c in rl.ring_colors()}) == 16
    rgb = rl.ring_colors()[scan.ring[scan.valid]]
    np.testing.assert_array_equal(by_ring >> 24, rgb[:, 0])
    np.testing.assert_array_equal((by_ring >> 8) & 0xFF, rgb[:, 2])
    assert np.all(by_ring & 0xFF == 0xFF)
    by_intensity = rl.scan_colors(scan, scan.valid)
    assert by_intensity.shape == (int(scan.valid.sum()),) and by_intensity.dtype == np.uint32
    with pytest.raises(ValueError, match="intensity"):
        rl.scan_colors(scan, by="range")


def test_live_sweep_through_the_runner_logs_each_scan(tmp_path: Path):
    """The path of ``aimbench sweep --rerun``: the real runner drives an observed bench and the
    observed estimator; the recording has each scan once, with its truth and what align used."""
    from scenarios.bench import SimBench
    from scenarios.recording.observer import (
        ObservedBench,
        RerunObserver,
        SinkOptions,
        close_recording,
        observed_estimator,
        open_recording,
    )

    refs = (Reference(math.radians(1.0), 0.0), Reference(math.radians(1.0), 0.01))
    plan = Plan("live", "x", refs, 2)
    bench = SimBench(seed=4)
    store = Store.create(tmp_path / "run", plan, {"bench": "sim", "seed": 4}, bench.info())
    sinks = SinkOptions(save=tmp_path / "run" / "run.rrd")
    rec = open_recording("live", sinks)
    observer = RerunObserver(rec, scans_per_reference=plan.scans, points_every=1)  # full clouds
    observed = ObservedBench(bench, observer, plan)
    try:
        status = Runner(plan, observed, store, observed_estimator(observed)).run()
        observer.on_finish(status)
        rows = list(store.iter_scans())
    finally:
        close_recording(rec, sinks)
        store.close()
    assert status == "completed"
    recording = read_rrd(sinks.save)
    assert recording.per_step("/world/truth", "scan", "Transform3D:translation") == {
        0: 1, 1: 1, 2: 1, 3: 1}
    for row in rows:
        step = row["reference"] * plan.scans + row["scan"]
        (t,) = recording.at("/world/truth", "scan", step, "Transform3D:translation")
        np.testing.assert_allclose(t[0], [row[f"truth_{a}_m"] for a in "xyz"], atol=1e-6)
        (pts,) = recording.at("/world/sensor/scan", "scan", step, "Points3D:positions")
        assert len(pts) == row["points"]
        board = recording.at("/world/sensor/board_points", "scan", step, "Points3D:positions")
        assert (len(board) == 1 and len(board[0]) > 50) == bool(row["success"])
    # The carriage moved 10 mm between the references (the stages posed from the joints).
    xs = [r.components["Transform3D:translation"][0][0]
          for r in recording.rows("/world/bench/carriage", "Transform3D:translation")]
    assert max(xs) - min(xs) == pytest.approx(0.01, abs=1e-6)


def test_sweep_session_only_with_the_flag(tmp_path: Path):
    """``--rerun`` (or a sink flag) makes a session saving RUN/run.rrd; without, none."""
    import argparse

    from scenarios.recording.observer import add_rerun_arguments, session_from_args

    p = argparse.ArgumentParser()
    add_rerun_arguments(p)
    plan = Plan("s", "yaw", (Reference(),), 1)
    assert session_from_args(p.parse_args([]), tmp_path, plan, {"kind": "sim"}) is None
    session = session_from_args(p.parse_args(["--rerun"]), tmp_path, plan, {"kind": "sim"})
    assert session is not None and session.sinks.save == tmp_path / "run.rrd"
    session.finish("completed")
    session.close()
    texts = [r.components["TextLog:text"][0]
             for r in read_rrd(tmp_path / "run.rrd").rows("/log", "TextLog:text")]
    assert texts[-1] == "run completed"
    other = tmp_path / "other.rrd"
    session = session_from_args(p.parse_args(["--save", str(other)]), tmp_path, plan, None)
    assert session is not None and session.sinks.save == str(other)
    session.close()
    assert other.is_file()


def test_clouds_of_the_first_scans_only_are_still_the_runs_own(run_dir: Path, tmp_path: Path):
    """--clouds-per-reference 1: the twin must still take every scan of each reference, or the
    later references' scans would differ from the run's (the clock and spin carry over)."""
    from scenarios.recording.replay import replay_run

    path = tmp_path / "first.rrd"
    rec = rl.new_recording()
    rec.save(path)
    summary = replay_run(run_dir, rec, clouds_per_reference=1, points_every=1)
    rec.flush()
    rec.disconnect()
    assert summary.clouds == len(YAWS_DEG) and summary.mismatches == 0
    recording = read_rrd(path)
    with Store.open(run_dir) as store:
        points = {(r["reference"], r["scan"]): r["points"] for r in store.iter_scans()}
    steps = recording.per_step("/world/sensor/scan", "scan", "Points3D:positions")
    assert sorted(steps) == [i * SCANS for i in range(len(YAWS_DEG))]
    for i in range(len(YAWS_DEG)):
        (pos,) = recording.at("/world/sensor/scan", "scan", i * SCANS, "Points3D:positions")
        assert len(pos) == points[(i, 0)]


def test_a_real_capture_shorter_than_a_rotation_is_replayed_in_pieces(sample_pcap: Path,
                                                                      tmp_path: Path):
    """The real VLP-16 capture of tests/data holds no whole rotation: its pieces are replayed,
    flagged, with every return."""
    from scenarios.recording.replay import replay_capture
    from twin.lidar.sources import capture_scans

    pieces = [s for s in capture_scans(sample_pcap, whole_only=False) if len(s)]
    path = tmp_path / "real.rrd"
    rec = rl.new_recording()
    rec.save(path)
    summary = replay_capture(sample_pcap, rec, points_every=1)  # whole clouds: counted
    rec.flush()
    rec.disconnect()
    recording = read_rrd(path)
    assert summary.scans == len(pieces) > 0
    counts = [len(r.components["Points3D:positions"])
              for r in recording.rows("/world/sensor/scan", "Points3D:positions")]
    assert counts == [int(s.valid.sum()) for s in pieces]
    texts = [r.components["TextLog:text"][0] for r in recording.rows("/log", "TextLog:text")]
    assert any("no whole rotation" in t for t in texts)
    assert "/world/truth" not in recording.entities or not recording.rows(
        "/world/truth", "Transform3D:translation")


def _replay_points(run_dir: Path, tmp_path: Path) -> tuple[object, dict, dict]:
    """Replay `run_dir`; (summary, points per (reference, scan) in the recording, in the store)."""
    from scenarios.recording.replay import replay_run

    path = tmp_path / "replay.rrd"
    rec = rl.new_recording()
    rec.save(path)
    summary = replay_run(run_dir, rec, points_every=1)  # the full clouds (--full-clouds)
    rec.flush()
    rec.disconnect()
    recording = read_rrd(path)
    with Store.open(run_dir) as store:
        plan = store.plan
        stored = {(r["reference"], r["scan"]): r["points"] for r in store.iter_scans()}
    logged = {}
    for r in recording.rows("/world/sensor/scan", "Points3D:positions"):
        step = r.times["scan"]
        logged[divmod(step, plan.scans)] = len(r.components["Points3D:positions"])
    return summary, logged, stored


@pytest.mark.slow
def test_a_parallel_run_is_replayed_scan_by_scan(tmp_path: Path):
    """A run on two worker processes (--jobs 2): re-simulated on one twin, scan by scan, it
    gives back the very scans the run estimated."""
    from scenarios.bench import SimBench
    from scenarios.runner import ParallelSimRunner

    refs = tuple(Reference(math.radians(y), 0.0) for y in (-1.0, 0.0, 1.0))
    plan = Plan("parallel", "yaw", refs, 2)
    bench = SimBench(seed=6)
    store = Store.create(tmp_path / "run", plan, {"bench": "sim", "seed": 6, "jobs": 2},
                         bench.info())
    try:
        assert ParallelSimRunner(plan, bench, store, seed=6, jobs=2).run() == "completed"
    finally:
        store.close()
    summary, logged, stored = _replay_points(tmp_path / "run", tmp_path)
    assert logged == stored and summary.mismatches == 0


def test_a_run_that_replayed_a_capture_reads_it_again(tmp_path: Path):
    """--bench hw --port none --lidar CAPTURE.pcap: the replay re-reads the capture in the order
    the runner took its scans."""
    from scenarios.bench import HardwareBench
    from twin.sim.bench import BenchSim

    pcap = tmp_path / "cap.pcap"
    BenchSim(seed=7).write_pcap(pcap, 6)
    plan = Plan("capture", "yaw", (Reference(), Reference()), 2)
    bench = HardwareBench(None, lidar=str(pcap))
    store = Store.create(tmp_path / "run", plan, {"bench": "hw", "port": None,
                                                  "lidar": str(pcap)}, bench.info())
    try:
        assert Runner(plan, bench, store, make_estimator(None)).run() == "completed"
    finally:
        store.close()
    summary, logged, stored = _replay_points(tmp_path / "run", tmp_path)
    assert summary.source == f"the capture {pcap}"
    assert logged == stored and summary.mismatches == 0


def test_stage_moves_follow_the_firmware_profile(tmp_path: Path):
    """A move is drawn along the trapezoidal profile on stage_time, ending where it was told;
    a target beyond the twin's travel (a longer real stage) is drawn at its arrival only."""
    from twin.sim.physics import BenchPhysics
    from twin.stage.motion import X_AXIS, YAW_AXIS, StageMove

    path = tmp_path / "move.rrd"
    rec = rl.new_recording()
    rec.save(path)
    geometry = rl.BenchGeometry.from_physics(BenchPhysics())
    end = rl.log_stage_move(rec, geometry, (0.0, 0.0), (0.02, math.radians(5.0)), 1.0)
    duration = StageMove.plan((0.0, 0.0), (0.02, math.radians(5.0)), (X_AXIS, YAW_AXIS)).duration
    assert end == pytest.approx(1.0 + duration)
    assert rl.log_stage_move(rec, geometry, (0.02, 0.0), (0.5, 0.0), end) == end
    rec.flush()
    rec.disconnect()
    rows = read_rrd(path).rows("/world/bench/carriage", "Transform3D:translation")
    xs = [r.components["Transform3D:translation"][0][0] for r in rows]
    times = [r.times["stage_time"] * 1e-9 for r in rows]
    assert times == sorted(times) and times[0] == pytest.approx(1.0)
    assert xs[-2] - xs[0] == pytest.approx(0.02, abs=1e-6)  # the profiled move
    assert xs[-1] - xs[0] == pytest.approx(0.5, abs=1e-6)  # the arrival beyond travel
    assert len(rows) >= 2 + math.ceil(duration * 20)
