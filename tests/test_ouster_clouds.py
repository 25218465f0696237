"""Ouster drivers' organised clouds (twin/lidar/ouster_clouds.py) against the packet path.

The real OS1-32 frame of tests/data/ouster-os1-32/ (ouster-sdk's test capture) is decoded from
its packets, written as ouster-ros writes its cloud (destaggered, os_sensor or os_lidar, its
``original`` fields; or stripped to ouster-sdk's XYZLut image: staggered x y z, misses at 0)
and read back: the `Scan` is the packets' own. An OS1-64 twin frame of the board, written as a
cloud, estimates the pose its packets do.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import numpy.lib.recfunctions as rfn
import pytest

import align
from tests.bag_support import write_records_bag
from tests.conftest import DATA_DIR
from twin.core.scan import Scan
from twin.lidar.ouster import (
    OusterInfo,
    decode_packets,
    frames,
    info_json,
    nominal_info,
    scan_from_frame,
)
from twin.lidar.ouster_clouds import (
    OusterCloudError,
    ouster_ros_cloud,
    scan_from_ouster_cloud,
    write_ouster_pcd,
)
from twin.lidar.pcap import read_pcap
from twin.lidar.sources import open_scans
from twin.sim.bench import BenchSim
from twin.sim.ouster_twin import emulate_frames
from twin.sim.params import BenchParams

OS1 = DATA_DIR / "ouster-os1-32"
PCAP = OS1 / "OS-1-32-G_v2.1.1_1024x10.pcap"
META = OS1 / "OS-1-32-G_v2.1.1_1024x10.json"


@pytest.fixture(scope="module")
def info() -> OusterInfo:
    return OusterInfo.from_json(META)


@pytest.fixture(scope="module")
def frame(info):
    payloads = [r.payload for r in read_pcap(PCAP, ports=None)]
    (f,) = list(frames(decode_packets(payloads, info), info))
    return f


def assert_same_scan(ours: Scan, packets: Scan, time_atol: float = 1e-9,
                     reflectivity: bool = True) -> None:
    """The cloud's scan is the packets': the same firings, rays, ranges, hits and misses (and
    reflectivities, when the cloud has them)."""
    assert np.array_equal(ours.valid, packets.valid)
    assert np.array_equal(ours.laser_id, packets.laser_id)
    assert np.array_equal(ours.azimuth, packets.azimuth)
    assert np.array_equal(ours.distance, packets.distance)
    assert np.array_equal(ours.xyz, packets.xyz)
    assert np.array_equal(ours.directions(), packets.directions())
    assert np.array_equal(ours.intensity, packets.intensity) or not reflectivity
    # times: the cloud's t is after the scan's stamp (its header's), so up to a constant
    dt = (ours.time - ours.time[0]) - (packets.time - packets.time[0])
    assert np.abs(dt).max() <= time_atol


def xyzlut_image(cloud: np.ndarray) -> np.ndarray:
    """ouster-sdk's XYZLut output saved as an organised cloud: x y z only, misses at 0."""
    xyz = rfn.repack_fields(cloud[["x", "y", "z"]])
    for f in "xyz":
        xyz[f] = np.nan_to_num(xyz[f], nan=0.0)
    return xyz


@pytest.mark.parametrize("cloud_frame", ["os_sensor", "os_lidar"])
@pytest.mark.parametrize("destagger", [True, False])
def test_ouster_ros_cloud_reads_back_as_the_packets_scan(info, frame, cloud_frame, destagger):
    packets = scan_from_frame(frame, info)
    cloud = ouster_ros_cloud(frame, info, cloud_frame=cloud_frame, destagger=destagger)
    assert cloud.shape == (32, 1024) and np.isnan(cloud["x"]).sum() == 32 * 1024 - 27310
    assert cloud.dtype.names == ("x", "y", "z", "intensity", "t", "reflectivity", "ring",
                                 "ambient", "range")
    scan = scan_from_ouster_cloud(cloud, info)
    assert scan.meta["ouster_cloud"] == {"destaggered": destagger, "cloud_frame": cloud_frame,
                                         "range_from": "range field"}
    assert_same_scan(scan, packets)
    # without range and t: the ranges from the float32 points (exact to the mm), the times
    # the columns' nominal ones (this unit's clock within 14 us of them)
    bare = xyzlut_image(cloud)
    scan = scan_from_ouster_cloud(bare, info)
    assert scan.meta["ouster_cloud"]["range_from"] == "points"
    assert scan.meta["ouster_cloud"]["destaggered"] == destagger
    assert_same_scan(scan, packets, time_atol=2e-5, reflectivity=False)


def test_the_destagger_is_ouster_ros_s(info, frame):
    """point_cloud_compose.h: cloud pixel (u, v) holds staggered (u, (v - shift[u]) mod W)."""
    cloud = ouster_ros_cloud(frame, info)
    shift = info.pixel_shift_by_row
    u = 5
    assert np.array_equal(cloud["range"][u], np.roll(frame.range_mm[u], shift[u]))
    assert (cloud["ring"] == np.arange(32)[:, None]).all()


def test_a_pcd_file_reads_with_its_metadata_and_without_it_is_one_line(info, frame, tmp_path):
    packets = scan_from_frame(frame, info)
    path = tmp_path / "os1.pcd"
    write_ouster_pcd(path, ouster_ros_cloud(frame, info))
    header = path.read_bytes()[:400].decode("ascii", "replace")
    assert "WIDTH 1024" in header and "HEIGHT 32" in header
    with open_scans(path, ouster_metadata=META) as source:
        (scan,) = list(source)
        summary = source.summary()
    assert_same_scan(scan, packets)
    assert summary["model"] == "OS1-32" and summary["returns"] == 27310
    assert summary["ouster_cloud"].startswith("destaggered, os_sensor frame")
    # no metadata: told an Ouster cloud by its shape, refused in one line
    with pytest.raises(OusterCloudError, match="--ouster-metadata"):
        open_scans(path)
    # NAME.json beside it, as a pcap's
    shutil.copy(META, tmp_path / "os1.json")
    with open_scans(path) as source:
        (scan,) = list(source)
    assert_same_scan(scan, packets)


@pytest.mark.parametrize("ros2", [True, False])
def test_a_bag_of_ouster_ros_clouds_gives_the_packets_scans(info, frame, tmp_path, ros2):
    packets = scan_from_frame(frame, info)
    cloud = ouster_ros_cloud(frame, info)
    path = write_records_bag(tmp_path / ("os1" if ros2 else "os1.bag"), [cloud, cloud],
                             ros2=ros2)
    with pytest.raises(OusterCloudError, match="--ouster-metadata"):
        open_scans(path)
    with open_scans(path, ouster_metadata=META) as source:
        scans = list(source)
        summary = source.summary()
    assert len(scans) == 2 and summary["bag"]["messages"] == 2
    for scan in scans:
        assert_same_scan(scan, packets)
    # a Velodyne's cloud in a bag still goes the rebuilding way (tests/test_sources.py); an
    # unorganised cloud with metadata given is refused in one line
    flat = write_records_bag(tmp_path / ("flat" if ros2 else "flat.bag"), [cloud.ravel()],
                             ros2=ros2)
    with pytest.raises(OusterCloudError, match="an unorganised cloud of 32768 points"):
        list(open_scans(flat, ouster_metadata=META))
    # ouster-ros's unorganised cloud (organized:=false, the misses dropped) is told by its
    # fields: refused in one line, not rebuilt as a Velodyne's
    dropped = cloud.ravel()[np.isfinite(cloud.ravel()["x"])]
    flat = write_records_bag(tmp_path / ("drop" if ros2 else "drop.bag"), [dropped], ros2=ros2)
    with pytest.raises(OusterCloudError, match="organized:=false"):
        list(open_scans(flat, ouster_metadata=META))
    with pytest.raises(OusterCloudError, match="--ouster-metadata"):
        open_scans(flat)


def test_another_sensors_metadata_is_refused(frame, info):
    cloud = ouster_ros_cloud(frame, info)
    with pytest.raises(OusterCloudError, match="32 x 1024 cloud"):
        scan_from_ouster_cloud(cloud, nominal_info("OS1-64"))
    # the same shape, another line's beams: its points lie 0.7 m off the OS2-32's rays
    with pytest.raises(OusterCloudError, match="off the rays of the OS2-32 metadata"):
        scan_from_ouster_cloud(cloud, nominal_info("OS2-32"))


def test_info_says_ouster_cloud(info, frame, tmp_path, capsys):
    from scenarios.cli import main

    path = tmp_path / "os1.pcd"
    write_ouster_pcd(path, ouster_ros_cloud(frame, info))
    assert main(["info", str(path), "--ouster-metadata", str(META)]) == 0
    out = capsys.readouterr().out
    assert "Ouster organised point cloud" in out and "27310 returns" in out
    assert main(["info", str(path)]) == 2
    assert "--ouster-metadata" in capsys.readouterr().err


def test_an_os1_64_twin_cloud_estimates_its_packets_pose(tmp_path, capsys):
    info = nominal_info("OS1-64")
    sim = BenchSim(BenchParams.from_edge(roll_deg=1.0, tilt_deg=-0.5, yaw_deg=2.0), seed=5)
    (frame,), _ = emulate_frames(sim, info, 1, rng=np.random.default_rng(1))
    packets = scan_from_frame(frame, info)
    # the hardest layout: staggered x y z in the lidar frame, ranges from the points
    cloud = xyzlut_image(ouster_ros_cloud(frame, info, cloud_frame="os_lidar",
                                          destagger=False))
    scan = scan_from_ouster_cloud(cloud, info)
    hints = align.Hints(edge_tolerance=(0.0, 0.0))
    a, b = align.estimate(packets, hints=hints), align.estimate(scan, hints=hints)
    assert a.success and b.success
    z = (b.pose.as_array() - a.pose.as_array()) / np.sqrt(np.diag(a.covariance))
    assert np.abs(z).max() < 0.05, np.round(z, 3)
    # and `aimbench estimate` reads the cloud saved as ouster-ros's PCD, its metadata beside it
    from scenarios.cli import main

    write_ouster_pcd(tmp_path / "os1-64.pcd", ouster_ros_cloud(frame, info))
    (tmp_path / "os1-64.json").write_text(info_json(info))
    assert main(["estimate", str(tmp_path / "os1-64.pcd"), "--json"]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert out["status"] == "ok" and out["hits"] > 500
