"""Grbl protocol parsing and the driver's errors, without a controller (fast)."""

from __future__ import annotations

import math

import pytest

from twin.core.errors import AimbenchError
from twin.stage import grbl
from twin.stage.controller import (
    GrblAlarm,
    GrblError,
    StageConnectionError,
    StageController,
    trapezoid_time,
)


def test_parse_status_bench_firmware() -> None:
    st = grbl.parse_status("<Run|MPos:12.345,-0.500|FS:0,0|Pn:XA>")
    assert st.state == "Run" and st.substate is None
    assert st.mpos == (12.345, -0.5) and st.feed == 0.0 and st.pins == "XA"


def test_parse_status_three_values_of_bench_firmware() -> None:
    # bench_fw now reports X, Y, Z like every Grbl 1.1: the rotary stage in Y, Z unused.
    st = grbl.parse_status("<Jog|MPos:12.345,-0.500,0.000|FS:0,0|Pn:XY>")
    assert st.state == "Jog" and st.mpos == (12.345, -0.5, 0.0) and st.pins == "XY"


def test_build_info_lines() -> None:
    assert grbl.parse_axes("[AXS:2:XA]") == "XA"
    assert grbl.parse_axes("[AXS:3:XA]") is None  # the count must match the letters
    assert grbl.parse_axes("[OPT:VNM+,35,255]") is None
    assert grbl.parse_version("[VER:1.1h.aimbench-0.1.0:]") == "1.1h.aimbench-0.1.0"
    assert grbl.parse_version("[VER:1.1g.20180813.Mega:my bench]") == "1.1g.20180813.Mega"


def test_setting_meanings_and_units() -> None:
    assert grbl.setting_meaning(0) == ("step pulse time", "us")
    assert grbl.setting_meaning(101, "XA", "mm,deg") == ("A steps per deg", "steps/deg")
    assert grbl.setting_meaning(120, "XA", "mm,deg") == ("X acceleration", "mm/s^2")
    assert grbl.setting_meaning(132, "XYZ") == ("Z maximum travel", "mm")
    assert grbl.setting_meaning(7)[0] == "not a Grbl 1.1 setting"


def test_parse_status_stock_grbl_variants() -> None:
    line = "<Hold:1|MPos:1.000,2.000,3.000|Bf:15,128|FS:500,0|WCO:0.000,0.000,0.000>"
    st = grbl.parse_status(line)
    assert st.state == "Hold" and st.substate == 1 and st.mpos == (1.0, 2.0, 3.0)
    assert st.fields["Bf"] == "15,128" and st.feed == 500.0
    st = grbl.parse_status("<Idle|WPos:1.000,2.000,3.000|F:0|WCO:1.000,1.000,1.000>")
    assert st.mpos == (2.0, 3.0, 4.0)
    with pytest.raises(ValueError, match="without MPos"):
        grbl.parse_status("<Idle|WPos:1.000,2.000,3.000>")
    with pytest.raises(ValueError, match="not a Grbl status"):
        grbl.parse_status("ok")


def test_line_classifiers() -> None:
    assert grbl.banner_version("Grbl 1.1h ['$' for help]") == "1.1h"
    assert grbl.banner_version("Grbl 1.1h [aimbench 0.1.0 '$' for help]") == "1.1h"
    assert grbl.banner_version("ok") is None
    assert grbl.error_code("error:15") == 15 and grbl.error_code("ok") is None
    assert grbl.alarm_code("ALARM:1") == 1 and grbl.alarm_code("error:1") is None
    assert grbl.parse_setting("$110=600.000") == (110, 600.0)
    assert grbl.parse_setting("[MSG:x]") is None


def test_format_number() -> None:
    assert grbl.format_number(50.0) == "50"
    assert grbl.format_number(-0.0000001) == "0"
    assert grbl.format_number(12.3456789) == "12.345679"
    assert grbl.format_number(0.00125) == "0.00125"
    assert grbl.format_number(1e-7) == "0"


def test_every_emitted_code_has_a_meaning() -> None:
    for code in (1, 2, 3, 4, 5, 6, 8, 9, 10, 11, 12, 15, 16, 20, 21, 22, 25, 26, 27, 28, 31, 36):
        assert code in grbl.ERRORS
    for code in (1, 3, 6, 8, 9):
        assert code in grbl.ALARMS


def test_errors_carry_code_and_meaning() -> None:
    e = GrblError(15, "G0X200")
    assert isinstance(e, AimbenchError) and e.code == 15
    assert "error:15" in str(e) and "G0X200" in str(e) and e.meaning in str(e)
    a = GrblAlarm(1)
    assert a.code == 1 and "ALARM:1" in str(a) and "hard limit" in str(a)
    assert "home it ($H)" in str(GrblAlarm(0))


def test_trapezoid_time() -> None:
    assert trapezoid_time(20.0, 20.0, 40.0) == pytest.approx(1.5)
    assert trapezoid_time(1.0, 20.0, 40.0) == pytest.approx(2 * math.sqrt(1 / 40))
    assert trapezoid_time(0.0, 20.0, 40.0) == 0.0


def test_unreachable_port_is_a_clear_error() -> None:
    with pytest.raises(StageConnectionError, match="cannot open the stage controller port"):
        StageController("/dev/does-not-exist-aimbench").connect()


def test_silent_port_is_a_clear_error() -> None:
    # loop:// echoes our own bytes and never sends a banner.
    s = StageController("loop://", boot_timeout_s=0.2, reply_timeout_s=0.2)
    with pytest.raises(StageConnectionError, match="no Grbl controller answers"):
        s.connect()


def test_bad_axis_letters() -> None:
    with pytest.raises(ValueError, match="axis_letters"):
        StageController("loop://", axis_letters=("X", "X"))
    with pytest.raises(ValueError, match="axis_letters"):
        StageController("loop://", axis_letters=("X", "Q"))


def test_not_connected_is_a_clear_error() -> None:
    with pytest.raises(StageConnectionError, match="not connected"):
        StageController("loop://").status()
