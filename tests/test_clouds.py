"""Point clouds as scans (twin/lidar/clouds.py, pcd.py): the misses rebuilt from the returns.

The proof is a real capture: its decoded scan, stripped to the returns as a driver's cloud holds
them, must come back firing for firing (laser order, ranges, the misses' azimuths); and the five
real ACFR PCD scans must load as whole rotations on the sensor's grid.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from pypcd4 import PointCloud

from tests.conftest import DATA_DIR
from twin.core import vlp16
from twin.core.lasers import LaserTable
from twin.core.scan import Scan
from twin.lidar.capture import open_pcap, read_capture
from twin.lidar.clouds import (
    Cloud,
    CloudError,
    RingsFromElevationWarning,
    UnsupportedCloudError,
    scan_from_cloud,
)
from twin.lidar.pcd import PcdFormatError, read_pcd, read_pcd_scans

ACFR = sorted((DATA_DIR / "acfr-vlp16").glob("pose*_full.pcd"))


@pytest.fixture(scope="module")
def decoded(sample_pcap: Path) -> Scan:
    """The sample capture's one whole rotation, as the decoder gives it (misses included)."""
    scans = read_capture(open_pcap(sample_pcap), cut_azimuth=None).scans
    assert scans[0].complete
    return scans[0]


def cloud_of(scan: Scan, *, time: bool = False, ring: bool = True) -> Cloud:
    """What a driver's cloud keeps of a scan: the returns only."""
    h = scan.select(scan.valid)
    return Cloud(h.x, h.y, h.z, intensity=h.intensity.astype(np.float64),
                 ring=h.ring if ring else None, time=h.time if time else None, name="test cloud")


def assert_same_firings(rebuilt: Scan, scan: Scan, az_tol_deg: float = 1e-3) -> None:
    assert len(rebuilt) == len(scan)
    assert np.array_equal(rebuilt.laser_id, scan.laser_id)
    assert np.array_equal(rebuilt.distance > 0, scan.distance > 0)
    assert np.allclose(rebuilt.distance, scan.distance, atol=1e-9)
    v = scan.valid  # a miss's reflectivity byte is not in a cloud: rebuilt as 0
    assert np.array_equal(rebuilt.intensity[v], scan.intensity[v])
    d = np.abs((rebuilt.azimuth - scan.azimuth + math.pi) % (2 * math.pi) - math.pi)
    assert math.degrees(float(d.max())) < az_tol_deg


@pytest.mark.parametrize("time", [False, True])
def test_a_capture_stripped_to_its_returns_comes_back_firing_for_firing(decoded, time):
    rebuilt = scan_from_cloud(cloud_of(decoded, time=time))
    assert_same_firings(rebuilt, decoded)
    assert rebuilt.complete and rebuilt.vertical_offsets_applied
    assert rebuilt.meta["rebuilt_misses"] == int((decoded.distance == 0).sum())
    assert abs(rebuilt.meta["rpm"] - decoded.meta["rpm"]) < 1.0
    if time:  # the cloud's own times for the returns, the grid's (on its clock) for the misses
        assert np.abs(rebuilt.time - decoded.time).max() < 50e-6
        v = decoded.valid
        assert np.array_equal(rebuilt.time[v], decoded.time[v])


def test_any_point_order_with_time_and_no_time_order_without(decoded):
    cloud = cloud_of(decoded, time=True)
    perm = np.random.default_rng(7).permutation(len(cloud))
    shuffled = Cloud(*(getattr(cloud, f)[perm] for f in ("x", "y", "z", "intensity", "ring",
                                                        "time")), name="shuffled")
    assert_same_firings(scan_from_cloud(shuffled), decoded)
    # Without time a shuffled cloud is ordered by azimuth alone: the same grid, a rotated start.
    untimed = Cloud(shuffled.x, shuffled.y, shuffled.z, shuffled.intensity, shuffled.ring)
    rebuilt = scan_from_cloud(untimed)
    assert len(rebuilt) == len(decoded) and rebuilt.valid.sum() == decoded.valid.sum()


def test_vertical_offsets_are_recognised_either_way(sample_pcap):
    plain = read_capture(open_pcap(sample_pcap), cut_azimuth=None, vertical_offsets=False).scans[0]
    rebuilt = scan_from_cloud(cloud_of(plain))
    assert not rebuilt.vertical_offsets_applied
    assert_same_firings(rebuilt, plain)


def test_rings_recovered_from_elevation_with_a_warning(decoded):
    with pytest.warns(RingsFromElevationWarning, match="no ring field"):
        rebuilt = scan_from_cloud(cloud_of(decoded, ring=False))
    assert_same_firings(rebuilt, decoded)
    assert rebuilt.meta["rings_from_elevation"]


def test_sequences_where_every_laser_missed_are_put_back(decoded):
    # Every return of 40 consecutive firing sequences (8 deg) gone: a patch of sky.
    seq = np.arange(len(decoded)) // vlp16.N_LASERS
    sky = replace(decoded, distance=np.where((seq >= 500) & (seq < 540), 0.0, decoded.distance))
    rebuilt = scan_from_cloud(cloud_of(sky))
    assert rebuilt.meta["rebuilt_sequences"] >= 40 and rebuilt.complete
    # The sequences put back lie between their neighbours, on a rotation that is not quite
    # uniform: within a quarter of the 0.2 deg step of the sensor's own azimuths.
    assert_same_firings(rebuilt, sky, az_tol_deg=0.05)
    outside = (seq < 499) | (seq > 541)
    assert_same_firings(rebuilt.select(outside), sky.select(outside))


def test_a_cropped_cloud_is_partial_and_no_miss_is_invented_in_the_crop(decoded):
    # A driver's field-of-view filter: only the front half (|azimuth| < 90 deg) is kept.
    az = decoded.azimuth
    front = decoded.select((az < math.pi / 2) | (az > 3 * math.pi / 2))
    rebuilt = scan_from_cloud(cloud_of(front))
    assert not rebuilt.complete and rebuilt.meta["partial"]
    assert max(rebuilt.meta["unfilled_gaps_deg"]) > 170
    back = (rebuilt.azimuth > math.pi / 2 + 0.02) & (rebuilt.azimuth < 3 * math.pi / 2 - 0.02)
    assert not back.any()


def test_the_acfr_scans_load_as_whole_rotations_on_the_sensors_grid():
    for path in ACFR:
        (cloud,) = read_pcd(path)
        scan = read_pcd_scans(path)[0]
        # 76 packets of 24 firing sequences of 16 lasers: the driver's scan, misses included.
        assert len(scan) == 76 * 24 * 16, path.name
        assert np.array_equal(scan.laser_id.reshape(-1, 16),
                              np.broadcast_to(np.arange(16), (76 * 24, 16)))
        assert scan.complete and scan.valid.sum() == len(cloud)
        assert scan.meta["rebuilt_misses"] == len(scan) - len(cloud) > 4000
        assert 595 < scan.meta["rpm"] < 605
        # The ROS driver applied no vertical offsets; each return is where the file put it, and
        # on its laser's ray.
        assert not scan.vertical_offsets_applied
        v = scan.valid
        on_ray = scan.origins()[v] + scan.directions()[v] * scan.distance[v, None]
        assert np.abs(on_ray - scan.xyz[v]).max() < 1e-5
        file_xyz = np.column_stack((-cloud.x, cloud.y, cloud.z))  # {L} back to x fwd, y left
        assert np.allclose(np.sort(scan.y[v]), np.sort(file_xyz[:, 1]))


def write(path: Path, fields: tuple[str, ...], arrays: list[np.ndarray], types) -> Path:
    PointCloud.from_points(arrays, fields, types).save(path)
    return path


def test_our_clouds_through_a_binary_pcd_file(decoded, tmp_path):
    h = decoded.hits()
    path = write(tmp_path / "scan.pcd", ("x", "y", "z", "intensity", "ring"),
                 [h.y, -h.x, h.z, h.intensity.astype(np.float32), h.ring.astype(np.uint16)],
                 (np.float64, np.float64, np.float64, np.float32, np.uint16))
    assert_same_firings(read_pcd_scans(path)[0], decoded)


def test_other_sensors_and_bad_files_get_one_clear_line(decoded, tmp_path):
    h = decoded.hits()
    ros = [h.y, -h.x, h.z]
    f32 = (np.float32,) * 3
    cases = {
        "32 rings": (write(tmp_path / "vlp32.pcd", ("x", "y", "z", "ring"),
                           [*ros, (h.ring * 2).astype(np.uint16)], (*f32, np.uint16)),
                     UnsupportedCloudError, "rings 0..30"),
        "elevations": (write(tmp_path / "puck.pcd", ("x", "y", "z", "ring"),
                             [h.y, -h.x, h.z * 0.66, h.ring.astype(np.uint16)],
                             (*f32, np.uint16)), UnsupportedCloudError, "another sensor"),
        "no z": (write(tmp_path / "xy.pcd", ("x", "y"), [h.y, -h.x], f32[:2]),
                 PcdFormatError, "no z field"),
        "few": (write(tmp_path / "few.pcd", ("x", "y", "z"), [a[:5] for a in ros], f32),
                CloudError, "too few"),
    }
    text = (tmp_path / "scan.pcd").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(200))
    assert text
    cases["png"] = (tmp_path / "scan.pcd", PcdFormatError, "not a PCD file")
    whole = (tmp_path / "vlp32.pcd").read_bytes()
    (tmp_path / "cut.pcd").write_bytes(whole[: len(whole) // 2])
    cases["cut"] = (tmp_path / "cut.pcd", PcdFormatError, "cut off")
    cases["missing"] = (tmp_path / "nope.pcd", PcdFormatError, "no such file")
    for name, (path, error, words) in cases.items():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RingsFromElevationWarning)
            with pytest.raises(error, match=words) as info:
                read_pcd_scans(path)
        message = str(info.value)
        assert "\n" not in message and str(path) in message, name


@pytest.mark.parametrize("model", ["Puck Hi-Res", "VLP-32C", "HDL-32E"])
def test_every_models_cloud_is_rebuilt_on_its_own_firing_grid(model, tmp_path):
    """The grid is rebuilt with the model's own firing timing (`twin.core.sensors`: the
    VLP-32C's lasers in pairs, the HDL-32E's 32 in 46.08 us): a twin capture of each model,
    decoded and stripped to its returns, comes back firing for firing (the first and last
    sequences, cut mid-sequence, come back whole), from a scan and through a PCD file."""
    from twin.core.sensors import model_named
    from twin.lidar.export import export_scans
    from twin.lidar.sources import open_scans
    from twin.sim.bench import BenchSim
    from twin.sim.emulation import EmulationConfig

    sensor = model_named(model)
    sim = BenchSim(seed=3, noise=EmulationConfig(model=model))
    path = tmp_path / "twin.pcap"
    sim.write_pcap(path, 2)
    scan = next(s for s in read_capture(open_pcap(path), cut_azimuth=None).scans if s.complete)
    assert scan.lasers is sensor.lasers
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RingsFromElevationWarning)
        for ring in (True, False):
            rebuilt = scan_from_cloud(cloud_of(scan, ring=ring), sensor.lasers, model=sensor)
            assert rebuilt.complete and rebuilt.lasers is sensor.lasers
            assert 0 <= len(rebuilt) - len(scan) < sensor.n_lasers
            assert_same_firings(rebuilt.select(np.arange(len(scan))), scan, az_tol_deg=0.005)
            assert abs(rebuilt.meta["rpm"] - scan.meta["rpm"]) < 1.0
        # Through a PCD file and the source layer, named by its model (a cloud has no product
        # id): its lasers and grid; as a VLP-16 it is another sensor's cloud.
        export_scans([scan], tmp_path / "scan.pcd")
        with open_scans(tmp_path / "scan.pcd", model=model) as source:
            (back,) = list(source)
            assert source.summary()["model"] == model
        assert back.lasers is sensor.lasers and back.valid.sum() == scan.valid.sum()
        with pytest.raises(UnsupportedCloudError, match="another sensor"):
            list(open_scans(tmp_path / "scan.pcd"))
    # A table of no known model (a unit's calibration, say) needs the model named.
    table = LaserTable("calibration unit.xml", sensor.lasers.elevation,
                       sensor.lasers.vertical_offset, sensor.lasers.azimuth_offset)
    with pytest.raises(UnsupportedCloudError, match="name the model"):
        scan_from_cloud(cloud_of(scan), table)
    assert_same_firings(scan_from_cloud(cloud_of(scan), table, model=sensor).select(
        np.arange(len(scan))), scan, az_tol_deg=0.005)
