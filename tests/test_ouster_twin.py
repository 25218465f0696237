"""Ouster sensors on the twin (twin/sim/ouster_twin.py): emulated from a real unit's metadata,
written as LEGACY packets in a pcap with the metadata beside it, read back through the source
layer and estimated at the true pose.

ouster-sdk 1.0.1 itself reads such pcaps to the same frames and points, and writes and reads
the twin's OSF files: tests/test_ouster_sdk.py, run in the suite.
"""

from __future__ import annotations

import numpy as np
import pytest

import align
from twin.lidar.ouster import (
    columns_from_frame,
    decode_packets,
    encode_packets,
    frames,
    nominal_info,
)
from twin.lidar.sources import open_scans
from twin.sim.bench import BenchSim
from twin.sim.ouster_twin import emulate_frames, write_ouster_pcap
from twin.sim.params import BenchParams

SHARP_BEAM = align.Hints(edge_tolerance=(0.0, 0.0))


def test_a_frame_goes_through_its_packets_unchanged():
    info = nominal_info("OS2-32", "512x20")
    sim = BenchSim(BenchParams.from_edge(tilt_deg=0.5), seed=1)
    (frame,), _ = emulate_frames(sim, info, 1, rng=np.random.default_rng(0))
    packets = encode_packets(columns_from_frame(frame, info), info)
    assert len(packets) == 512 // 16 and len(packets[0]) == 16 * (16 + 12 * 32 + 4)
    (back,) = list(frames(decode_packets(packets, info), info))
    for name in ("range_mm", "reflectivity", "signal", "timestamp_ns", "measurement_id"):
        assert np.array_equal(getattr(back, name), getattr(frame, name)), name
    # 20 Hz, 512 columns: the columns 1 / 10240 s apart
    assert np.allclose(np.diff(back.timestamp_ns.astype(float)), 1e9 / 10240, atol=1)


@pytest.mark.parametrize("model", ["OS0-32", "OS1-64", "OS2-128"])
def test_every_line_is_estimated_at_its_true_pose(model, tmp_path):
    info = nominal_info(model)
    sim = BenchSim(BenchParams.from_edge(roll_deg=1.0, tilt_deg=-0.5, yaw_deg=2.0), seed=5)
    truth = write_ouster_pcap(sim, info, tmp_path / "os.pcap", 1, rng=np.random.default_rng(1))
    with open_scans(tmp_path / "os.pcap") as source:  # its metadata found beside it
        (scan,) = list(source)
        assert source.summary()["model"] == model
    assert scan.complete and len(scan) == 1024 * info.pixels_per_column
    res = align.estimate(scan, hints=SHARP_BEAM)
    assert res.success, res.status
    z = (res.pose.as_array() - truth.as_array()) / np.sqrt(np.diag(res.covariance))
    # (within 3 sigma each; over 12 poses of an OS1-64 chi2/dof is 3.4, not 1: the estimator's
    # rays leave the beams' 1.2 mm horizontal origin offsets out, docs/vlp16.md)
    assert np.abs(z).max() < 3.0, np.round(z, 2)


def test_simulate_writes_what_info_and_estimate_read(tmp_path, capsys):
    from scenarios.cli import main

    out = tmp_path / "os1.pcap"
    assert main(["simulate", "--model", "OS1-64", "--lidar-mode", "1024x20", "--scans", "1",
                 "--tilt-deg", "0.5", "--quiet", "--out", str(out)]) == 0
    assert out.with_suffix(".json").is_file() and (tmp_path / "os1.truth.json").is_file()
    assert main(["info", str(out)]) == 0
    info = capsys.readouterr().out
    assert "OS1-64 (OS-1-64" in info and "1024x20 (LEGACY packets)" in info
    assert main(["estimate", str(out), "--truth", str(tmp_path / "os1.truth.json")]) == 0
    est = capsys.readouterr().out
    assert " ok " in est and "error" in est


def test_a_station_of_an_ouster_decodes_its_captures_and_the_sim_bench_takes_it(tmp_path,
                                                                                   capsys):
    """``sensor.model = "os1-64"`` in a station file: the model's name as aimbench writes it,
    its captures read (a capture without its metadata JSON: the model's nominal beams, said in a
    warning), and the simulated bench takes it (its own twin's scans)."""
    from scenarios import station as stations
    from scenarios.bench import SimBench
    from scenarios.cli import main

    path = tmp_path / "ouster.toml"
    path.write_text('[sensor]\nmodel = "os1-64"\n')
    st = stations.load(path)
    assert st.sensor.model == "OS1-64" and st.decoding() == {"model": "OS1-64", "lasers": None}
    out = tmp_path / "os1.pcap"
    sim = BenchSim(BenchParams.from_edge(tilt_deg=0.5), seed=3)
    write_ouster_pcap(sim, nominal_info("OS1-64"), out, 1, rng=np.random.default_rng(3))
    out.with_suffix(".json").unlink()  # the metadata lost: the model's nominal beams stand in
    assert main(["estimate", str(out), "--station", str(path)]) == 0
    captured = capsys.readouterr()
    assert "nominal beams" in captured.err and " ok " in captured.out
    # the simulated bench scans it with the Ouster's own twin (tests/test_own_twin_benches.py)
    assert SimBench(station=st).own_model == "OS1-64"
