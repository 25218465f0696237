"""A Hesai PandarXT32 on the twin (twin/sim/hesai_twin.py): its packets written from the
unit's angle corrections, read back by the decoder that reproduces nebula's real points
(tests/test_hesai.py), and estimated at the true pose. Over 8 random poses chi2/dof is 1.09
(docs/vlp16.md)."""

from __future__ import annotations

import json

import numpy as np

from twin.lidar.hesai import DEFAULT_ANGLES, XT32Angles, decode_xt32
from twin.sim.bench import BenchSim
from twin.sim.hesai_twin import emulate_xt32
from twin.sim.params import BenchParams


def test_the_twins_xt32_is_estimated_at_its_true_pose(tmp_path, capsys):
    angles = XT32Angles.from_csv(DEFAULT_ANGLES)
    sim = BenchSim(BenchParams.from_edge(roll_deg=1.0, tilt_deg=-0.5, yaw_deg=2.0), seed=5)
    packets, _ = emulate_xt32(sim, angles, 1, rng=np.random.default_rng(1), range_sigma=0.0)
    dec = decode_xt32(packets, angles)
    # one rotation: 2,000 blocks 0.18 deg apart (251 packets of 8), most firings returning
    hit = dec.distance > 0
    assert len(packets) == 251 and hit.mean() > 0.5
    assert np.all(dec.block_azimuth_cdeg[:, 1:] - dec.block_azimuth_cdeg[:, :-1] == 18)

    from scenarios.cli import main

    out = tmp_path / "xt32.pcap"
    assert main(["simulate", "--model", "PandarXT32", "--scans", "1", "--roll-deg", "1",
                 "--tilt-deg", "-0.5", "--quiet", "--out", str(out)]) == 0
    assert main(["estimate", str(out), "--model", "PandarXT32", "--json"]) == 0
    est = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    truth = json.loads((tmp_path / "xt32.truth.json").read_text())["scans"][0]
    assert est["status"] == "ok"
    for axis in ("roll_deg", "tilt_deg", "yaw_deg", "x_mm"):
        # (the truth file's pose in deg and m: x_m)
        want = truth[axis] if axis != "x_mm" else truth["x_m"] * 1e3
        assert abs(est[axis] - want) < 3 * est[f"{axis}_std"], axis
