"""ouster-sdk itself (1.0.1, BSD-3), run in the suite: the project's Ouster decoder
(twin/lidar/ouster.py) against ouster-sdk's on ouster-sdk's own capture and on the twin's pcaps,
and OSF files in and out through ouster-sdk (twin/lidar/ouster_sdk.py).

CI installs ouster-sdk (`tools/setup.sh test`, without its pins: pyproject.toml's extra
``ouster``), so these run there; without it the module is skipped, saying so.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("ouster.sdk.osf", reason="ouster-sdk is not installed: tools/setup.sh ouster "
                                             "(CI's tools/setup.sh test installs it)")

from scenarios.cli import main
from tests.conftest import DATA_DIR
from twin.lidar import ouster_sdk
from twin.lidar.ouster import (
    OusterInfo,
    decode_packets,
    frames,
    nominal_info,
    scan_from_frame,
    xyz_lidar,
)
from twin.lidar.pcap import read_pcap
from twin.lidar.sources import open_scans
from twin.sim.bench import BenchSim
from twin.sim.ouster_twin import write_ouster_osf, write_ouster_pcap
from twin.sim.params import BenchParams

OS1 = DATA_DIR / "ouster-os1-32"
PCAP = OS1 / "OS-1-32-G_v2.1.1_1024x10.pcap"
META = OS1 / "OS-1-32-G_v2.1.1_1024x10.json"
#: Every field of a `Frame` (ouster-sdk's channels and column headers).
FIELDS = ("range_mm", "reflectivity", "signal", "near_ir", "timestamp_ns", "measurement_id",
          "status", "received")
#: Every array of a Scan (the estimator's input); the OSF's must be the pcap's, bit for bit.
SCAN_ARRAYS = ("distance", "azimuth", "laser_id", "intensity", "time", "return_type", "x", "y",
               "z")
#: The twin's bench for the twin's captures here: a pose off every axis.
POSE = {"roll_deg": 1.0, "tilt_deg": -0.5, "yaw_deg": 2.0}


def our_frames(pcap: Path, info: OusterInfo) -> list:
    return list(frames(decode_packets([r.payload for r in read_pcap(pcap, ports=None)], info),
                       info))


def assert_same_frames(ours: list, theirs: list) -> None:
    """Every field of every frame equal, bit for bit and type for type."""
    assert len(ours) == len(theirs) >= 1
    for k, (a, b) in enumerate(zip(ours, theirs, strict=True)):
        assert a.frame_id == b.frame_id, k
        for name in FIELDS:
            x, y = getattr(a, name), getattr(b, name)
            assert x.dtype == y.dtype and np.array_equal(x, y), (k, name)


def assert_points_equal(lidar_frames: list, ours: list, info: OusterInfo, sensor_info) -> float:
    """ouster-sdk's XYZLut points of every frame are ours (`xyz_lidar` plus the transform's
    translation, m) within 1e-8 m; the largest difference."""
    worst = 0.0
    for lf, f in zip(lidar_frames, ours, strict=True):
        theirs = ouster_sdk.sdk_xyz(lf, sensor_info)
        mine = xyz_lidar(f.range_mm, info) * 1e-3 + info.lidar_to_sensor[:3, 3] * 1e-3
        hit = f.range_mm > 0
        assert hit.sum() > 1000
        worst = max(worst, float(np.abs(theirs[hit] - mine[hit]).max()))
        assert not np.any(theirs[~hit])  # a miss: (0, 0, 0) both
    assert worst < 1e-8, worst
    return worst


# ----------------------------------------------------------------------------------------------
# ouster-sdk's own capture


def test_ouster_sdks_real_os1_capture_decodes_as_ours_field_for_field():
    info = OusterInfo.from_json(META)
    sdk_info, theirs, lidar_frames = ouster_sdk.pcap_frames(PCAP, META)
    ours = our_frames(PCAP, info)
    assert_same_frames(ours, theirs)
    # the metadata as ouster-sdk reads it (its own JSON of it) is the metadata as we read it
    for name in ("beam_altitude_deg", "beam_azimuth_deg", "pixel_shift_by_row", "lidar_to_sensor"):
        assert np.array_equal(getattr(sdk_info, name), getattr(info, name)), name
    assert (sdk_info.beam_to_lidar_mm, sdk_info.lidar_mode, sdk_info.column_window) == (
        info.beam_to_lidar_mm, info.lidar_mode, info.column_window)
    sensor_info = ouster_sdk.sdk()[0].SensorInfo(META.read_text())
    assert_points_equal(lidar_frames, ours, info, sensor_info)


METADATA = sorted((Path(ouster_sdk.__file__).parent / "ouster_metadata").glob("*.json"))


@pytest.mark.parametrize("path", METADATA, ids=[p.stem for p in METADATA])
def test_every_shipped_units_metadata_reads_and_projects_as_ouster_sdks(path):
    """The real units' metadata the twin is built from (ouster-sdk's test captures, firmware
    2.0-2.3, flat and nested): ouster-sdk's reading of each is ours, and its XYZLut puts a
    random range image's pixels where `xyz_lidar` does."""
    core, _, _ = ouster_sdk.sdk()
    info = OusterInfo.from_json(path)
    sensor_info = core.SensorInfo(path.read_text())
    theirs = ouster_sdk.info_of(sensor_info, path.name)
    for name in ("beam_altitude_deg", "beam_azimuth_deg", "pixel_shift_by_row", "lidar_to_sensor"):
        assert np.array_equal(getattr(theirs, name), getattr(info, name)), name
    assert theirs.beam_to_lidar_mm == info.beam_to_lidar_mm
    rng = np.random.default_rng(0)
    h, w = info.pixels_per_column, info.columns_per_frame
    range_mm = np.where(rng.random((h, w)) < 0.9, rng.integers(300, 120_000, (h, w)), 0)
    lidar_frame = core.LidarFrame(sensor_info)
    lidar_frame.field("RANGE")[:] = range_mm
    mine = xyz_lidar(range_mm, info) * 1e-3 + info.lidar_to_sensor[:3, 3] * 1e-3
    hit = range_mm > 0  # (a miss is (0, 0, 0) in both, before the translation)
    assert np.abs(ouster_sdk.sdk_xyz(lidar_frame, sensor_info)[hit] - mine[hit]).max() < 1e-8


# ----------------------------------------------------------------------------------------------
# The twin's captures


@pytest.fixture(scope="module")
def sim() -> BenchSim:
    return BenchSim(BenchParams.from_edge(**POSE), seed=5)


@pytest.mark.parametrize(("model", "mode"), [("OS0-32", "512x20"), ("OS1-64", "1024x10")])
def test_ouster_sdk_reads_the_twins_pcap_to_our_frames_and_points(sim, tmp_path, model, mode):
    info = nominal_info(model, mode)
    pcap = tmp_path / "twin.pcap"
    write_ouster_pcap(sim, info, pcap, 2, rng=np.random.default_rng(3))
    sdk_info, theirs, lidar_frames = ouster_sdk.pcap_frames(pcap, pcap.with_suffix(".json"))
    ours = our_frames(pcap, info)
    assert_same_frames(ours, theirs)
    sensor_info = ouster_sdk.sensor_info_of(info)
    assert_points_equal(lidar_frames, ours, info, sensor_info)
    # and the scans of ouster-sdk's frames, with ouster-sdk's reading of the metadata, are ours
    for k, (a, b) in enumerate(zip(ours, theirs, strict=True)):
        s, t = scan_from_frame(a, info, index=k), scan_from_frame(b, sdk_info, index=k)
        for name in SCAN_ARRAYS:
            assert np.array_equal(getattr(s, name), getattr(t, name)), name


# ----------------------------------------------------------------------------------------------
# OSF in and out


@pytest.fixture(scope="module")
def osf_and_pcap(sim, tmp_path_factory) -> tuple[Path, Path]:
    """The same two OS1-64 frames of the twin (the same draws) as an OSF and as a pcap."""
    d = tmp_path_factory.mktemp("osf")
    info = nominal_info("OS1-64")
    write_ouster_osf(sim, info, d / "twin.osf", 2, rng=np.random.default_rng(7))
    write_ouster_pcap(sim, info, d / "twin.pcap", 2, rng=np.random.default_rng(7))
    return d / "twin.osf", d / "twin.pcap"


def test_an_osf_of_the_twin_reads_to_the_scans_of_its_pcap(osf_and_pcap):
    osf, pcap = osf_and_pcap
    with open_scans(osf) as source:  # the metadata from the file itself
        from_osf = list(source)
        summary = source.summary()
    with open_scans(pcap) as source:  # the metadata JSON beside it
        from_pcap = list(source)
    assert len(from_osf) == len(from_pcap) == 2
    for a, b in zip(from_osf, from_pcap, strict=True):
        for name in SCAN_ARRAYS:
            assert np.array_equal(getattr(a, name), getattr(b, name)), name
        assert a.complete and b.complete and a.meta == b.meta
        assert np.array_equal(a.lasers.vertical_offset, b.lasers.vertical_offset)
    assert summary["kind"] == "osf" and summary["model"] == "OS1-64"
    assert summary["osf"] == {"sensors": 1, "ouster_sdk": ouster_sdk.SDK_VERSION,
                              "profile": "LEGACY"}
    assert summary["complete_scans"] == 2 and summary["points"] == 2 * 64 * 1024


def test_an_osf_of_ouster_sdks_own_capture_reads_as_its_pcap(tmp_path):
    """The real OS1-32 frame, written to OSF by ouster-sdk's writer and read back: the scan of
    its pcap (a real unit's metadata through ouster-sdk's JSON, its 36.18 mm transform kept)."""
    info = OusterInfo.from_json(META)
    (frame,) = our_frames(PCAP, info)
    assert ouster_sdk.write_osf(tmp_path / "os1.osf", [frame], info) == 1
    with open_scans(tmp_path / "os1.osf") as source:
        (a,) = list(source)
    with open_scans(PCAP) as source:
        (b,) = list(source)
    for name in SCAN_ARRAYS:
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert int(a.valid.sum()) == 27310


def test_an_osf_of_a_profile_our_packet_decoder_refuses_reads_all_the_same(tmp_path):
    """An OSF holds frames ouster-sdk decoded: one recorded in RNG19_RFL8_SIG16_NIR16 (whose
    packets `twin.lidar.ouster` refuses, saying to set LEGACY) reads to the scan of the same
    frame's LEGACY pcap."""
    core, osf, _ = ouster_sdk.sdk()
    info = OusterInfo.from_json(META)
    (frame,) = our_frames(PCAP, info)
    meta = json.loads(META.read_text())
    meta["data_format"]["udp_profile_lidar"] = "RNG19_RFL8_SIG16_NIR16"
    sensor_info = core.SensorInfo(json.dumps(meta))
    lidar_frame = ouster_sdk.lidar_frame_of(frame, sensor_info)
    lidar_frame.status[:] = 1  # a valid column in the newer profiles: bit 0
    writer = osf.Writer(str(tmp_path / "rng19.osf"), sensor_info)
    writer.save(0, lidar_frame)
    writer.close()
    with open_scans(tmp_path / "rng19.osf") as source:
        (a,) = list(source)
        assert source.summary()["profile"] == "RNG19_RFL8_SIG16_NIR16"
    with open_scans(PCAP) as source:
        (b,) = list(source)
    assert a.complete
    for name in SCAN_ARRAYS:
        assert np.array_equal(getattr(a, name), getattr(b, name)), name


def test_simulate_writes_an_osf_that_info_and_estimate_read(tmp_path, capsys):
    out = tmp_path / "os1.osf"
    assert main(["simulate", "--model", "OS1-64", "--scans", "2", "--roll-deg", "1",
                 "--tilt-deg", "-0.5", "--yaw-deg", "2", "--seed", "4", "--quiet",
                 "--out", str(out)]) == 0
    assert not out.with_suffix(".json").exists()  # the metadata is in the OSF
    capsys.readouterr()
    assert main(["info", str(out)]) == 0
    text = capsys.readouterr().out
    assert "Ouster OSF, read by ouster-sdk 1.0.1" in text and "OS1-64 (OS-1-64" in text
    assert "2 (2 complete, 0 partial" in text
    assert main(["estimate", str(out), "--json", "--edge-tolerance-mrad", "0,0"]) == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [r["status"] for r in rows] == ["ok", "ok"]
    for r in rows:  # the truth file beside it: the twin's pose, within 3 sigma on every axis
        z = [r[f"{k}_error"] / r[f"{k}_std"] for k in ("x_mm", "y_mm", "z_mm", "roll_deg",
                                                          "tilt_deg", "yaw_deg")]
        assert np.abs(z).max() < 3.0, np.round(z, 2)


# ----------------------------------------------------------------------------------------------
# Bad input, one line each


def refused(capsys, *argv: str) -> str:
    """`aimbench argv` refuses with one error line and no traceback: that line."""
    assert main(list(argv)) == 2
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ": error: " in ln]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def test_a_damaged_or_foreign_osf_is_one_line(tmp_path, capsys, osf_and_pcap):
    junk = tmp_path / "junk.osf"
    junk.write_bytes(b"\0" * 8 + b"OSF$" + bytes(range(200)))
    assert "not a readable OSF file" in refused(capsys, "info", str(junk))
    cut = tmp_path / "cut.osf"
    cut.write_bytes(osf_and_pcap[0].read_bytes()[:3000])  # cut off before its first frame
    line = refused(capsys, "estimate", str(cut))
    assert "OSF" in line and "give" in line
    text = tmp_path / "notes.osf"
    text.write_text("not an osf\n")
    assert "not a readable OSF file" in refused(capsys, "info", str(text))


def test_simulate_refuses_an_osf_of_a_velodyne(tmp_path, capsys):
    line = refused(capsys, "simulate", "--model", "VLP-16", "--scans", "1",
                   "--out", str(tmp_path / "v.osf"))
    assert "writes an Ouster's frames, not a VLP-16's" in line
    assert list(tmp_path.iterdir()) == []


def test_without_ouster_sdk_an_osf_names_the_set_up_to_run(tmp_path, capsys, monkeypatch,
                                                           osf_and_pcap):
    monkeypatch.setitem(sys.modules, "ouster.sdk", None)
    ouster_sdk._load.cache_clear()
    try:
        assert "tools/setup.sh ouster" in refused(capsys, "info", str(osf_and_pcap[0]))
        line = refused(capsys, "simulate", "--model", "OS1-64", "--out", str(tmp_path / "x.osf"))
        assert "--out FILE.osf needs ouster-sdk" in line and "tools/setup.sh ouster" in line
    finally:
        ouster_sdk._load.cache_clear()
