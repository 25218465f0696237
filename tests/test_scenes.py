"""The scenes a user picks (models.SCENES): by BenchParams, by a station's [twin] scene and by
`aimbench simulate --scene`; the lab keeps the bench's board returns and adds its clutter."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from twin_analytic import board_intersections

from models import SCENES
from scenarios import station as stations
from scenarios.cli import main as cli_main
from twin.sim.bench import BenchSim
from twin.sim.emulation import EmulationConfig
from twin.sim.params import BenchParams


def test_the_lab_is_the_bench_in_a_cluttered_room() -> None:
    bench = BenchSim(seed=0, noise=EmulationConfig.ideal())
    lab = BenchSim(BenchParams(scene="lab"), seed=0, noise=EmulationConfig.ideal())
    m = lab.physics.model
    assert m.ngeom - bench.physics.model.ngeom >= 50
    s_b, s_l = bench.scan(), lab.scan()
    # The board's returns are the bench's (nothing stands between the sensor and the board).
    _, on = board_intersections(s_b.meta["truth_pose"], s_b.azimuth, s_b.laser_id, 0.9, 0.54)
    np.testing.assert_array_equal(s_l.distance[on], s_b.distance[on])
    # A closed room: almost every firing returns, and the clutter is seen.
    assert s_l.valid.mean() > 0.85 > s_b.valid.mean()
    with pytest.raises(ValueError, match="scene"):
        BenchParams(scene="garage")


def test_a_station_and_simulate_pick_the_scene(tmp_path: Path) -> None:
    (tmp_path / "lab.toml").write_text('name = "lab bench"\n[twin]\nscene = "lab"\n')
    station = stations.load(tmp_path / "lab.toml")
    assert station.bench_params().scene == "lab" and set(SCENES) == {"bench", "lab"}
    assert stations.load(None).bench_params().scene == "bench"
    (tmp_path / "bad.toml").write_text('[twin]\nscene = "garage"\n')
    with pytest.raises(stations.StationError, match="scene"):
        stations.load(tmp_path / "bad.toml")
    out = tmp_path / "cap.pcap"
    assert cli_main(["simulate", "--scans", "1", "--ideal", "--scene", "lab", "--quiet",
                     "--out", str(out)]) == 0
    truth = json.loads((tmp_path / "cap.truth.json").read_text())
    assert truth["params"]["scene"] == "lab"
    assert cli_main(["simulate", "--scans", "1", "--ideal", "--station",
                     str(tmp_path / "lab.toml"), "--quiet", "--out", str(out)]) == 0
    assert json.loads((tmp_path / "cap.truth.json").read_text())["params"]["scene"] == "lab"
