"""The host driver and `aimbench stage` against a stock grbl-Mega 1.1g, as it answers on the wire
(`stage_support.StockGrblMega`, a real pty): the driver finds the axes X, Y, Z, drives the
linear stage on X and the rotary stage on Y (the bench's wiring of a stock board,
bench_fw/PROTOCOL.md) and says so; letters it lacks are a clear error; the bench reference is the
middle of the travel; status in Alarm says the position is not known; settings have meanings.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterator

import pytest
from stage_support import StockGrblMega

from scenarios.cli import main
from twin.stage.controller import StageConnectionError, StageController


@pytest.fixture
def stock() -> Iterator[StockGrblMega]:
    peer = StockGrblMega()
    yield peer
    peer.close()


def test_driver_finds_the_stock_axes_and_chooses_x_and_y(stock: StockGrblMega) -> None:
    with StageController(stock.url) as stage:
        assert stage.banner == StockGrblMega.BANNER
        assert not stage.bench_firmware and stage.mpos_axes == "XYZ"
        assert stage.axis_letters == ("X", "Y")
        assert "stock Grbl" in stage.axis_note and "rotary stage on Y" in stage.axis_note
        # Stock Grbl's travel is [-$13x, 0]: the bench reference is its middle.
        assert (stage.x_ref_mm, stage.yaw_ref_deg) == (-50.0, -30.0)
        st = stage.status()
        assert st.state == "Alarm" and not st.position_known
        stage.unlock()
        stage.move_to(x_m=0.001, yaw_rad=math.radians(2.0))
        assert stock.received[-1] == "G90G0X-49Y-28"
        st = stage.status()
        assert (st.x_mm, st.yaw_deg) == (-49.0, -28.0) and st.position_known
        assert st.x_m == pytest.approx(0.001) and st.yaw_rad == pytest.approx(math.radians(2))


def test_letters_a_stock_board_lacks_are_a_clear_error(stock: StockGrblMega) -> None:
    with pytest.raises(StageConnectionError, match=r"axis A is not an axis .*\(it has XYZ\)"):
        StageController(stock.url, axis_letters=("X", "A")).connect()
    with StageController(stock.url, axis_letters=("X", "Z")) as stage:
        assert stage.axis_letters == ("X", "Z")


def test_cli_status_and_settings_on_a_stock_board(
    stock: StockGrblMega, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["stage", "--port", stock.url, "status"]) == 0
    out = capsys.readouterr().out
    assert "linear stage on X, rotary stage on Y" in out
    assert re.search(r"position\s+not known: the controller is in Alarm", out), out
    assert "from the bench centre" not in out  # no position printed as if it were known
    assert main(["stage", "--port", stock.url, "settings"]) == 0
    out = capsys.readouterr().out
    assert re.search(r"^\$0=10\s+step pulse time \(us\)$", out, re.M), out
    assert re.search(r"^\$101=800\s+Y steps per deg \(steps/deg\)$", out, re.M), out
    assert re.search(r"^\$131=60\s+Y maximum travel \(deg\)$", out, re.M), out
    assert re.search(r"^\$110=600\s+X maximum rate \(mm/min\)$", out, re.M), out
    assert re.search(r"^\$11=0.01\s+junction deviation \(mm\)$", out, re.M), out
