"""The station file: the paper's bench as the shipped default, one clear line for a bad file, and
the twin built from a non-default file with its board, mount and stand where the file says (the
compiled model's bodies, geoms and sites, and a scan's returns), on every command that takes
``--station``."""

from __future__ import annotations

import json
import math
import os
import sqlite3
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import ConvexHull

from align.board import BoardSpec
from scenarios import plans
from scenarios import station as stations
from scenarios.bench import HardwareBench, SimBench, open_bench
from scenarios.config import RunConfig

REPO = Path(__file__).resolve().parents[1]

#: A bench unlike the paper's: a bigger, thicker board, moved, turned, tipped and hung at 30 deg
#: in its plane, brighter; the LiDAR higher and off the axis; the stand elsewhere.
ODD = """
name = "odd"
[board]
width_mm = 1200
height_mm = 700
thickness_mm = 10
position_mm = [100, 200, 750]
yaw_deg = 5
tilt_deg = -3
in_plane_deg = 30
reflectivity = 0.8
[mount]
lever_arm_mm = [10, 20, 80]
[stages]
base_position_mm = [600, -2300, 0]
"""

#: A level board of another size and height, which today's estimator handles (a board hung at
#: an in-plane rotation is the estimator's issue, not the station file's).
BIG = """
name = "big"
[board]
width_mm = 1200
height_mm = 700
thickness_mm = 5
position_mm = [0, 0, 560]
reflectivity = 0.7
"""


def aimbench(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run([sys.executable, "-m", "scenarios.cli", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=600)


def write(tmp_path: Path, text: str, name: str = "station.toml") -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def test_the_paper_station_is_the_default_and_ships_installed():
    from twin.sim.params import BenchParams

    assert "paper" in stations.shipped()
    paper = stations.load("paper")
    assert paper.model_copy(update={"description": ""}) == stations.Station()
    assert stations.load(None) == paper
    # The twin's and the estimator's defaults are the paper's bench, and so is the file.
    assert paper.bench_params() == BenchParams()
    assert paper.board_spec() == BoardSpec()
    assert paper.axis_letters == ("X", "A") and paper.lidar_url() == "udp://0.0.0.0:2368"
    assert RunConfig().station == paper


@pytest.mark.parametrize(("text", "message"), [
    ("[board]\nwidht_mm = 900\n", "board.widht_mm: unknown key; allowed here: width_mm,"),
    ("[board]\nwidth_mm = -900\n", "board.width_mm: Input should be greater than 0"),
    ("[board]\nwidth_mm = '900'\n", "board.width_mm: Input should be a valid number"),
    ("[board]\nposition_mm = [0, 2500]\n", "board.position_mm: expects a list of 3 numbers"),
    ("[board]\nreflectivity = 1.5\n", "board.reflectivity: Input should be less than or equal"),
    ("[board.pattern]\nsquares = [7, 5]\nsquare_mm = 200\n", "do not fit on the 900 x 540 mm"),
    ("[sensor]\nmodel = 'HDL-64E'\n", "sensor.model: unknown sensor model 'HDL-64E'"),
    ("[sensor]\nrange_calibration = 'cal.json'\n", "sensor.range_calibration: no such file"),
    ("[sensor.network]\nport = 70000\n", "sensor.network.port: Input should be less than"),
    ("[stages]\nyaw_axis = 'X'\n", "x_axis and yaw_axis are both 'X'"),
    ("[stages]\nx_travel_mm = [10, 50]\n", "stages.x_travel_mm: [10, 50] must hold the bench"),
    ("[tolerances]\nrule = 'loose'\n", "tolerances.rule: Input should be 'iso14253-1', 'vda5' or"),
    ("board = 3\n", "board: must be a table"),
    ("[board\n", "is not valid TOML"),
    # issue 37: NaN and inf are refused in every float (a NaN mount angle hung the twin)
    ("[mount]\nroll_deg = nan\n", "mount.roll_deg: Input should be a finite number (got nan)"),
    ("[mount]\nlever_arm_mm = [0, inf, 60]\n", "mount.lever_arm_mm: Input should be a finite"),
    ("[mount.nominal]\nx_mm = -inf\n", "mount.nominal.x_mm: Input should be a finite"),
    ("[frame.pose]\nyaw_deg = nan\n", "frame.pose.yaw_deg: Input should be a finite"),
    ("[board]\nposition_mm = [nan, 0, 500]\n", "board.position_mm: Input should be a finite"),
    ("[board]\nwidth_mm = inf\n", "board.width_mm: Input should be a finite"),
    ("[sensor]\nrange_offset_mm = nan\n", "sensor.range_offset_mm: Input should be a finite"),
    # an absurdly fine chessboard took minutes and gigabytes to build
    ("[board.pattern]\nsquares = [100, 60]\nsquare_mm = 5.0\n", "6000 squares; the twin draws"),
    ("[board.pattern]\nsquares = [7, 5]\nsquare_mm = 0.001\n", "board.pattern.square_mm: Input "
                                                               "should be greater than or equal"),
])
def test_a_bad_station_file_names_the_key(tmp_path: Path, text: str, message: str):
    path = write(tmp_path, text)
    with pytest.raises(stations.StationError, match="^" + str(path)) as err:
        stations.load(path)
    assert message in str(err.value) and "\n" not in str(err.value)


def test_hostile_station_files_are_short_lines(tmp_path: Path):
    """Issue 37: 1,000 unknown keys made a 143,000-character line; TOML nested deep a
    RecursionError. Both are one short line now, the first problems named."""
    many = write(tmp_path, "".join(f"key{i:04d} = 1\n" for i in range(1000)), "many.toml")
    with pytest.raises(stations.StationError) as err:
        stations.load(many)
    text = str(err.value)
    assert len(text) < 1000 and "key0000: unknown key" in text and "and 995 more problems" in text
    for deep in ("a = " + "[" * 5000 + "]" * 5000, "a = " + "{b = " * 5000 + "1" + "}" * 5000):
        with pytest.raises(stations.StationError, match="nested too deep"):
            stations.load(write(tmp_path, deep + "\n", "deep.toml"))
    with pytest.raises(plans.PlanError, match="nested too deep"):
        plans.from_toml(write(tmp_path, "yaw_deg = " + "[" * 5000 + "]" * 5000, "deep.toml"))


def test_a_bad_station_is_one_line_on_the_command_line(tmp_path: Path, sample_pcap: Path):
    write(tmp_path, "[board]\nheight_mm = 0\n", "bad.toml")
    for args in (("estimate", str(sample_pcap), "--station", "bad.toml"),
                 ("estimate", str(sample_pcap), "--station", "missing.toml"),
                 ("sweep", "yaw", "--station", "bad.toml", "--out", "r")):
        res = aimbench(*args, cwd=tmp_path)
        lines = res.stderr.strip().splitlines()
        assert res.returncode == 2 and len(lines) == 1, res.stderr
        assert ("board.height_mm" in lines[0]
                or "no such station file missing.toml" in lines[0]), lines[0]
    assert not (tmp_path / "r").exists()  # refused before a run folder is made


def test_what_is_not_applied_yet_is_said(tmp_path: Path):
    (tmp_path / "db.xml").write_text("<DB/>")
    st = stations.load(write(tmp_path, "[sensor]\ncalibration_file = 'db.xml'\n"
                                       "[board.pattern]\nsquares = [7, 5]\nsquare_mm = 95\n"))
    assert st.sensor.calibration_file == str(tmp_path / "db.xml")  # beside the station file
    assert st.board.pattern is not None and st.board.pattern.dark_reflectivity == 0.03
    # The factory calibration decodes the real sensor's packets; only the twin, which emulates
    # the model's nominal lasers, does not apply it.
    notes = st.notes(twin=True)
    assert len(notes) == 1 and "calibration_file" in notes[0]
    assert st.notes(twin=False) == []
    # Read when a command decodes with it: an unreadable file is one error naming the key.
    with pytest.raises(stations.StationError, match=r"sensor\.calibration_file"):
        st.decoding()


NEBULA = REPO / "tests" / "data" / "nebula-vlp32c"
#: A VLP-32C bench with the unit's factory calibration (nebula's ROS driver YAML).
VLP32C_STATION = f"""
name = "vlp32c"
[sensor]
model = "vlp32c"
calibration_file = "{NEBULA / 'VLP32.yaml'}"
"""


def test_the_stations_sensor_decodes_its_packets(tmp_path: Path):
    """sensor.model and sensor.calibration_file are --model and --sensor-calibration for the
    commands that read a source with a station file, which the command line overrides."""
    from scenarios.cli import build_parser
    from scenarios.commands.info import open_source, sensor_options
    from twin.core.sensors import MODELS, VLP16, VLP32C
    from twin.lidar.calibration_file import read_calibration_file

    assert tuple(MODELS) == stations.SENSOR_MODELS
    st = stations.load(write(tmp_path, VLP32C_STATION))
    assert st.sensor.model == "VLP-32C"  # as the user wrote it, kept by its name
    table, _ = read_calibration_file(NEBULA / "VLP32.yaml")
    dec = st.decoding()
    assert dec["model"] == "VLP-32C" and dec["lasers"].same_geometry(table)
    parser = build_parser()
    bag = str(NEBULA / "1713492677464078412")
    args = parser.parse_args(["estimate", bag, "--station", str(tmp_path / "station.toml")])
    with open_source(args, st) as source:
        scans = list(source)
        summary = source.summary()
    assert scans and all(s.lasers.same_geometry(table) for s in scans)
    assert not any(s.lasers.vertical_offset.any() for s in scans)  # nebula's table has none
    assert summary["model"] == "VLP-32C" and summary["laser_table"] == "calibration VLP32.yaml"
    # The command line wins: --model of another sensor drops the station's (VLP-32C) table.
    args = parser.parse_args(["estimate", bag, "--model", "VLP-16"])
    assert sensor_options(args, st) == {"model": "VLP-16", "lasers": None}
    args = parser.parse_args(["estimate", bag])
    assert sensor_options(args) == {"model": None, "lasers": None}  # no station: product id
    # A table of another model's lasers is refused by the station, naming the key.
    text = VLP32C_STATION.replace('model = "vlp32c"', 'model = "VLP-16"')
    wrong = stations.load(write(tmp_path, text, "wrong.toml"))
    with pytest.raises(stations.StationError, match="32 lasers, but a VLP-16"):
        wrong.decoding()
    assert VLP16.n_lasers == 16 and VLP32C.n_lasers == 32


@pytest.mark.slow
def test_a_vlp32c_station_simulates_and_decodes_its_sensor(tmp_path: Path):
    """The twin emulates the station's model; a hardware bench, a run's replayed capture and
    estimate decode its packets as the station's sensor, with its factory calibration."""
    from scenarios.recording.replay import recapture

    write(tmp_path, VLP32C_STATION)
    sim = aimbench("simulate", "--station", "station.toml", "--scans", "2", "--ideal",
                   "--out", "cap.pcap", cwd=tmp_path)
    assert sim.returncode == 0, sim.stderr
    assert "sensor.calibration_file" in sim.stderr  # the twin's nominal lasers, said
    truth = json.loads((tmp_path / "cap.truth.json").read_text())
    assert truth["emulation"]["model"] == "VLP-32C"
    info = json.loads(aimbench("info", "cap.pcap", "--json", cwd=tmp_path).stdout)
    assert info["model"] == "VLP-32C" and info["laser_table"] == "VLP-32C"  # by its product id
    st = stations.load(tmp_path / "station.toml")
    config = RunConfig(bench="hw", port="none", lidar=str(tmp_path / "cap.pcap"), station=st,
                       station_file=str(tmp_path / "station.toml"))
    with open_bench(config) as bench:
        (scan,) = list(bench.scans(1))
    assert scan.lasers.model == "calibration VLP32.yaml" and scan.lasers.n_lasers == 32
    # Without a station file named, the run decodes by the product id.
    assert config.with_(station_file=None).lidar_decoding() == {}

    class _Store:  # what recapture reads of a run's store
        def get(self, key: str):
            return config.as_dict() if key == "config" else None

    (_, _, again), = list(recapture(_Store(), tmp_path / "cap.pcap", {(0, 0)}))
    assert again.lasers.model == "calibration VLP32.yaml"
    assert np.array_equal(again.distance, scan.distance)


@pytest.fixture(scope="module")
def odd(tmp_path_factory: pytest.TempPathFactory) -> stations.Station:
    return stations.load(write(tmp_path_factory.mktemp("odd"), ODD))


def test_the_twin_puts_the_board_where_the_file_says(odd: stations.Station):
    import mujoco

    from twin.sim.params import (
        BOARD_BODY,
        BOARD_GEOM,
        BOARD_STAND_BODY,
        SENSOR_BODY,
        SENSOR_MODULE_BODY,
    )
    from twin.sim.physics import BenchPhysics

    params = odd.bench_params()
    phys = BenchPhysics(params)
    m, d = phys.model, phys.data
    b = odd.board
    w, h, t = b.width_mm / 1e3, b.height_mm / 1e3, b.thickness_mm / 1e3
    # The board frame {O} in the bench frame, from the file alone (not from the model).
    o = odd.board_in_bench()
    np.testing.assert_allclose(d.xpos[m.body(BOARD_BODY).id], [0.1, 0.2, 0.75], atol=1e-12)
    np.testing.assert_allclose(d.xmat[m.body(BOARD_BODY).id].reshape(3, 3), o[:3, :3],
                               atol=1e-9)
    geom = m.geom(BOARD_GEOM)
    np.testing.assert_allclose(geom.size, [w / 2, t / 2, h / 2], atol=1e-12)
    # The plate's front face is Y_O = 0: its centre sits half a thickness behind it.
    np.testing.assert_allclose(d.geom_xpos[geom.id], (o @ [0, t / 2, 0, 1])[:3], atol=1e-9)
    for name, (sx, sz) in {"tl": (-1, 1), "tr": (1, 1), "bl": (-1, -1), "br": (1, -1)}.items():
        np.testing.assert_allclose(d.site_xpos[m.site(f"board_corner_{name}").id],
                                   (o @ [sx * w / 2, 0, sz * h / 2, 1])[:3], atol=1e-9)
    # 30 deg in its plane, clockwise seen from the LiDAR: the right edge runs down to the right.
    right = d.site_xpos[m.site("board_corner_tr").id] - d.site_xpos[m.site("board_corner_tl").id]
    assert math.degrees(math.atan2(-right[2], math.hypot(right[0], right[1]))) == \
        pytest.approx(30.0, abs=0.2)
    # The stand where the file puts it, the optical centre at the lever arm from the axis.
    np.testing.assert_allclose(d.xpos[m.body(SENSOR_MODULE_BODY).id], [0.6, -2.3, 0.0],
                               atol=1e-12)
    axis = d.site_xpos[m.site("rotation_axis").id]
    np.testing.assert_allclose(d.xpos[m.body(SENSOR_BODY).id] - axis, [0.01, 0.02, 0.08],
                               atol=1e-9)
    assert params.geom_reflectivity(m)[geom.id] == 0.8
    # Its stand came along: on the floor, behind the board's centre, turned with it.
    stand = d.xpos[m.body(BOARD_STAND_BODY).id]
    assert stand[2] == 0.0 and (o[:3, :3].T @ (stand - o[:3, 3]))[1] > 0.1
    assert mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, BOARD_GEOM) == geom.id


def test_a_scan_of_the_twin_sees_the_board_where_the_file_says(odd: stations.Station):
    from twin.sim.bench import BenchSim
    from twin.sim.emulation import EmulationConfig

    sim = BenchSim(odd.bench_params(), seed=0, noise=EmulationConfig.ideal())
    scan = sim.scan()
    p_l, r_l = sim.physics.lidar_pose_world()  # where the sensor is: no board in it
    ok = scan.valid
    pts_l = np.column_stack((scan.x, scan.y, scan.z))[ok]
    world = pts_l @ r_l.T + p_l
    o = odd.board_in_bench()
    # Every return, in the file's board frame.
    u, v, z = ((world - o[:3, 3]) @ o[:3, :3]).T
    b = odd.board
    w2, h2 = b.width_mm / 2e3, b.height_mm / 2e3
    face = np.abs(v) < 3e-3  # on the front face's plane (2 mm range quantum)
    near = face & (np.abs(u) < w2 + 0.05) & (np.abs(z) < h2 + 0.05)
    assert near.sum() > 500
    # The face's returns lie on the rectangle the file gives and fill it: the board is this
    # size, at this pose and in-plane rotation, and nowhere else.
    assert np.abs(u[near]).max() <= w2 + 2e-3 and np.abs(z[near]).max() <= h2 + 2e-3
    hull = ConvexHull(np.column_stack((u[near], z[near])))
    assert hull.volume > 0.75 * (2 * w2) * (2 * h2)
    # Its brighter face (0.8 against the background's 0.3) returns more light than the wall.
    wall = ~face & (np.linalg.norm(pts_l, axis=1) > 3.0)
    assert np.median(scan.intensity[ok][near]) > np.median(scan.intensity[ok][wall])
    # The truth in the board frame, taken to the station (here the bench) frame, is the sensor.
    station_pose = odd.lidar_in_station(scan.meta["truth_pose"])
    np.testing.assert_allclose(station_pose.translation, sim.physics.lidar_pose_world()[0],
                               atol=1e-6)
    np.testing.assert_allclose(station_pose.rotation(), r_l, atol=1e-6)


def test_the_station_frame_moves_the_reported_pose(odd: stations.Station):
    from twin.core.pose import Pose

    moved = odd.model_copy(update={"frame": stations.StationFrame(
        name="vehicle", pose=stations.PoseMmDeg(x_mm=500, y_mm=-3000, yaw_deg=90))})
    in_board = Pose(0.1, -2.4, -0.1, 0.01, 0.02, 0.03)
    bench, vehicle = odd.lidar_in_station(in_board), moved.lidar_in_station(in_board)
    # {S} turned 90 deg left at (0.5, -3.0): a bench point (X, Y) is (Y + 3.0, 0.5 - X) in it.
    np.testing.assert_allclose(vehicle.translation,
                               [bench.y + 3.0, 0.5 - bench.x, bench.z], atol=1e-9)
    assert math.degrees(vehicle.yaw - bench.yaw) == pytest.approx(-90.0)


def test_benches_are_built_from_the_station(odd: stations.Station, tmp_path: Path,
                                            sample_pcap: Path):
    narrow = odd.model_copy(update={"stages": odd.stages.model_copy(update={
        "yaw_travel_deg": (-5.0, 8.0), "x_travel_mm": (-20.0, 10.0)})})
    config = RunConfig(station=narrow)
    with open_bench(config) as bench:
        assert isinstance(bench, SimBench)
        assert bench.base_params == narrow.bench_params()
        (y0, y1), (x0, x1) = bench.travel()
        assert (math.degrees(y0), math.degrees(y1)) == pytest.approx((-5.0, 8.0))
        assert (x0, x1) == pytest.approx((-0.02, 0.01))
        assert bench.info()["lever_arm_m"] == [0.01, 0.02, 0.08]
    # A hardware bench: the LiDAR source from the sensor's network, the travel from the file.
    net = narrow.model_copy(update={"sensor": narrow.sensor.model_copy(update={
        "network": stations.Network(host="127.0.0.1", port=2401)})})
    with HardwareBench(None, station=net) as hw:
        assert hw.source.info()["lidar"] == "udp://127.0.0.1:2401"
        assert hw.travel() == net.travel()
    with HardwareBench("none", str(sample_pcap), station=net) as hw:
        assert hw.info()["station"] == "odd" and hw.info()["lever_arm_m"] == [0.01, 0.02, 0.08]


@pytest.mark.slow
@pytest.mark.simavr
def test_stage_axis_letters_and_travel_reach_the_stage_driver(odd: stations.Station):
    from scenarios.bench import BenchError
    from twin.stage.hil import SimavrHarness

    narrow = odd.model_copy(update={"stages": odd.stages.model_copy(update={
        "yaw_travel_deg": (-5.0, 8.0)})})
    # Z: bench_fw has no Z (Y is its rotary stage's report slot, an alias of A).
    wrong = odd.model_copy(update={"stages": odd.stages.model_copy(update={"yaw_axis": "Z"})})
    with SimavrHarness(start_x_mm=1.0, start_a_deg=1.0) as hil:
        with HardwareBench(hil.url, "udp://127.0.0.1:2402", station=narrow) as hw:
            assert hw.controller.axis_letters == ("X", "A")
            (y0, y1), (x0, x1) = hw.travel()
            # yaw from the station (narrower than the firmware's), x from the firmware's $13x.
            assert (math.degrees(y0), math.degrees(y1)) == pytest.approx((-5.0, 8.0))
            assert x1 - x0 > 0
        with pytest.raises(BenchError, match="axis Z is not an axis"):
            HardwareBench(hil.url, "udp://127.0.0.1:2402", station=wrong)


@pytest.mark.slow
def test_simulate_and_estimate_with_a_station(tmp_path: Path):
    write(tmp_path, BIG, "big.toml")
    sim = aimbench("simulate", "--station", "big.toml", "--scans", "2", "--yaw-deg", "3",
                   "--seed", "5", "--out", "cap.pcap", cwd=tmp_path)
    assert sim.returncode == 0, sim.stderr
    truth = json.loads((tmp_path / "cap.truth.json").read_text())
    assert truth["station"]["board"]["width_mm"] == 1200 and truth["station_file"]
    res = aimbench("estimate", "cap.pcap", "--station", "big.toml", "--fuse", "2", "--json",
                   cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    (row,) = [json.loads(line) for line in res.stdout.splitlines()]
    assert row["status"] == "ok"
    # Every quantity with its 1-sigma, and its error against the truth found beside the capture
    # (within what an uncalibrated twin sensor gives on two scans: its range offsets bias roll).
    for k, most in (("x_mm", 15), ("y_mm", 10), ("z_mm", 30), ("roll_deg", 1.5),
                    ("tilt_deg", 1.0), ("yaw_deg", 0.5)):
        assert row[f"{k}_std"] > 0 and abs(row[f"{k}_error"]) < most, (k, row)
    assert row["truth"]["z_mm"] == pytest.approx(truth["scans"][0]["z_m"] * 1e3)
    # The human table: a 1-sigma beside each quantity, the errors below, the mean and RMS.
    table = aimbench("estimate", "cap.pcap", "--station", "big.toml", "--truth",
                     "cap.truth.json", cwd=tmp_path)
    lines = table.stdout.splitlines()
    assert table.returncode == 0 and lines[1].count("+-") == 6, table.stdout
    assert lines[2].split()[0] == "error" and any(li.split()[:2] == ["rms", "error"]
                                                  for li in lines)
    # --board-mm overrides the station's board: the paper's size on this board misplaces it.
    wrong = aimbench("estimate", "cap.pcap", "--station", "big.toml", "--board-mm", "900x540",
                     "--fuse", "2", "--json", cwd=tmp_path)
    (bad,) = [json.loads(line) for line in wrong.stdout.splitlines()]
    assert bad["status"] != "ok" or abs(bad["z_mm_error"]) > 3 * abs(row["z_mm_error"]) + 10 \
        or abs(bad["x_mm_error"]) > 3 * abs(row["x_mm_error"]) + 10, (bad, row)


@pytest.mark.slow
def test_a_sweep_keeps_its_station(tmp_path: Path):
    write(tmp_path, BIG.replace("width_mm = 1200\nheight_mm = 700\n", ""), "level.toml")
    # The TOML sweep sets the board's size (board_mm), the station the rest.
    (tmp_path / "plan.toml").write_text("scans = 3\nyaw_deg = [-2, 2]\nboard_mm = '1200x700'\n")
    res = aimbench("sweep", "plan.toml", "--station", "level.toml", "--out", "r", "--jobs", "2",
                   "--no-progress", "--no-report", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    with sqlite3.connect(tmp_path / "r" / "run.sqlite") as db:
        config = json.loads(db.execute("select value from meta where key = 'config'")
                            .fetchone()[0])
        rows = db.execute("select success, x_m - truth_x_m from scan").fetchall()
    stored = RunConfig.from_dict(config).station
    assert stored.board.width_mm == 1200 and stored.board.height_mm == 700
    assert stored.board.position_mm == (0.0, 0.0, 560.0) and stored.name == "big"
    assert config["station_file"] == str((tmp_path / "level.toml").resolve())
    # Both workers' twins and estimators used the station's 1200 x 700 board.
    assert len(rows) == 6 and all(s for s, _ in rows)
    assert max(abs(e) for _, e in rows) < 0.03
    again = aimbench("sweep", "--resume", "--out", "r", "--station", "level.toml", cwd=tmp_path)
    assert again.returncode == 2 and "keeps the station it was started with" in again.stderr


def test_the_twin_draws_the_stations_pattern(tmp_path: Path):
    from twin.sim.bench import BenchSim
    from twin.sim.params import BoardPattern

    st = stations.load(write(tmp_path, "[board.pattern]\nsquares = [9, 4]\nsquare_mm = 90\n"
                                       "offset_mm = [10.0, -20.0]\ndark_reflectivity = 0.0\n"))
    params = st.bench_params()
    assert params.board_pattern == BoardPattern(rows=4, cols=9, square=0.09,
                                                dark_reflectivity=0.0, offset=(0.01, -0.02))
    sim = BenchSim(params, seed=1)
    names = [sim.physics.model.geom(i).name for i in range(sim.physics.model.ngeom)]
    assert sum(n.startswith("board_square_") for n in names) == 36


def test_a_diamond_station_gives_the_estimator_its_rotation(tmp_path: Path):
    # A board hung turned 45 deg clockwise (as the LiDAR sees it) puts a level LiDAR's roll at
    # -45 deg; a unit bolted rolled by 2 deg sits at -43. A level board gives no prior.
    st = stations.load(write(tmp_path, "[board]\nin_plane_deg = 45.0\n[mount]\nroll_deg = 2.0\n"))
    centre, sd = st.roll_prior()
    assert math.degrees(centre) == pytest.approx(-43.0, abs=1e-9)
    assert math.degrees(sd) == stations.ROLL_PRIOR_SD_DEG
    assert stations.default().roll_prior() is None


@pytest.mark.slow
def test_simulate_and_estimate_a_diamond_station(tmp_path: Path):
    write(tmp_path, "[board]\nwidth_mm = 610\nheight_mm = 850\nin_plane_deg = 45.0\n"
                    "position_mm = [0.0, 0.0, 700.0]\n", "diamond.toml")
    sim = aimbench("simulate", "--station", "diamond.toml", "--scans", "3", "--seed", "3",
                   "--out", "cap.pcap", cwd=tmp_path)
    assert sim.returncode == 0, sim.stderr
    for extra in ((), ("--roll-hint-deg=-45:5",)):
        res = aimbench("estimate", "cap.pcap", "--station", "diamond.toml", "--fuse", "3",
                       "--json", *extra, cwd=tmp_path)
        assert res.returncode == 0, res.stderr
        (row,) = [json.loads(line) for line in res.stdout.splitlines()]
        assert row["status"] == "ok", row
        assert abs(row["roll_deg_error"]) < 4 * row["roll_deg_std"] + 0.3, row
    bad = aimbench("estimate", "cap.pcap", "--roll-hint-deg", "x", cwd=tmp_path)
    assert bad.returncode != 0 and "--roll-hint-deg takes CENTRE" in bad.stderr


def test_a_printed_sheet_is_a_board_of_thickness_zero(tmp_path: Path):
    """A chessboard printed on paper has no side face: thickness 0 is accepted (issue 34: it
    was refused, "Input should be greater than 0"), the twin builds it and the board is found."""
    import align
    from twin.sim.bench import BenchSim

    path = tmp_path / "sheet.toml"
    path.write_text('name = "sheet"\n[board]\nthickness_mm = 0\n', encoding="utf-8")
    station = stations.load(path)
    assert station.board.thickness_mm == 0 and station.board_spec().thickness == 0
    scan = BenchSim(station.bench_params(), seed=2).scan()
    est = align.estimate(scan, station.board_spec())
    assert est.success, est.diagnostics.get("reason")
    err = est.pose.as_array() - scan.meta["truth_pose"].as_array()
    assert np.all(np.abs(err[3:]) < np.deg2rad(1.0)) and np.all(np.abs(err[:3]) < 0.03)
