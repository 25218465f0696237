"""Bad command lines (issue 19), each through the real `aimbench` entry point: one line naming
the problem, exit code 2, no traceback, and nothing made (no run folder, no file)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from scenarios.cli import main

CAPTURE = Path(__file__).resolve().parent / "data" / "vlp16-strongest-10hz.pcap"


def bad(capsys: pytest.CaptureFixture, *argv: str) -> str:
    """Run `aimbench argv`; it must refuse with exit code 2 and one error line: that line."""
    try:
        code = main(list(argv))
    except SystemExit as exc:  # argparse refuses a bad option value this way
        code = exc.code
    err = capsys.readouterr().err
    assert code == 2, err
    lines = [ln for ln in err.splitlines() if ": error: " in ln]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


@pytest.mark.parametrize(("argv", "expected"), [
    (("sweep", "yaw", "--out", "r", "--jobs", "0"), "--jobs: must be a whole number >= 1, got 0"),
    (("sweep", "yaw", "--out", "r", "--jobs", "-3"), "--jobs: must be a whole number >= 1"),
    (("sweep", "yaw", "--out", "r", "--max-consecutive-failures", "-1"),
     "--max-consecutive-failures: must be a whole number >= 1, got -1"),
    (("sweep", "yaw", "--out", "r", "--seed", "-1"), "--seed: a seed is a whole number 0.."),
    (("sweep", "yaw", "--out", "r", "--scans", "0"), "--scans: must be a whole number >= 1"),
    (("sweep", "yaw", "--out", "r", "--tolerance-deg", "-1"),
     "--tolerance-deg: must be within 0..inf, got -1"),
    (("sweep", "yaw", "--out", "r", "--tolerance-mm", "nan"), "--tolerance-mm: 'nan' is not a "
                                                              "finite number"),
    (("sweep", "yaw", "--out", "r", "--max-failed-percent", "150"),
     "--max-failed-percent: must be within 0..100"),
    (("report", "r", "--tolerance-deg", "-1"), "--tolerance-deg: must be within 0..inf"),
    (("estimate", str(CAPTURE), "--expected-distance-m", "-5"),
     "--expected-distance-m: must be > 0, got -5"),
    (("estimate", str(CAPTURE), "--fuse", "0"), "--fuse: must be a whole number >= 1"),
    (("simulate", "--out", "."), "--out: . is a folder; give a file name in it"),
    (("simulate", "--out", "missing/dir/x.pcap", "--scans", "1"),
     "--out: the folder missing/dir does not exist"),
    (("simulate", "--out", "x.pcap", "--yaw-deg", "inf"), "--yaw-deg: 'inf' is not a finite"),
    (("export", "r", "--csv", "missing/dir/x.csv"), "--csv: the folder missing/dir does not "
                                                    "exist"),
    (("export", "r", "--parquet", "."), "--parquet: . is a folder"),
    (("calibrate", "--bench", "sim", "--out", "."), "--out: . is a folder"),
    (("demo", "--jobs", "0"), "--jobs: must be a whole number >= 1"),
    # issue 37: refused up front, not after the whole study or on the serial line
    (("grr", "--twin", "--confidence", "1.5"), "--confidence: must be between 0 and 1"),
    (("grr", "--twin", "--confidence", "95"), "(did you mean 0.95?)"),
    (("stage", "--port", "loop://", "move", "--x-mm", "nan"), "--x-mm: 'nan' is not a finite"),
    (("stage", "--port", "loop://", "--axes", "XX", "status"), "--axes: 'XX' names one axis "
                                                               "twice"),
    (("inspect", "sim", "--units", "0", "--db", "x.sqlite"), "--units: must be a whole number "
                                                             ">= 1, got 0"),
    (("inspect", "sim", "--unit", "VIN1\nVIN2", "--db", "x.sqlite"), "is not a unit id: give "
                                                                     "printable characters"),
    (("inspect", "sim", "--unit", "A", "--tilt-deg", "nan", "--db", "x.sqlite"),
     "--tilt-deg: 'nan' is not a finite number"),
    (("simluate", "--scans", "2"), "unknown command 'simluate'; did you mean 'simulate'?"),
    (("estimate", str(CAPTURE), "--board-mm", "0.9x0.54"), "is 0.9 x 0.54 mm, smaller than any "
                                                           "target board; did you mean 900x540"),
])
def test_a_bad_option_is_one_line(capsys, monkeypatch, tmp_path: Path, argv, expected):
    monkeypatch.chdir(tmp_path)
    line = bad(capsys, *argv)
    assert expected in line, line
    assert list(tmp_path.iterdir()) == [], "a refused command made something"


@pytest.mark.parametrize(("toml", "expected"), [
    ("scans = 1\nyaw_deg = { start = -10, stop = 10, step = 1e-9 }\n",
     "yaw_deg: -10..10 by 1e-09 is 20000000001 values, more than the 100000 references"),
    ("scans = 1\nyaw_deg = nan\n", "yaw_deg must be a finite number, got nan"),
    ("scans = 1\nx_mm = [0, inf]\n", "x_mm must be a finite number, got inf"),
    ("scans = 1\n[mount]\ntilt_deg = nan\n", "mount tilt_deg must be a finite number"),
    ("scans = 1\n[mount]\ntilt_deg = 'up'\n", "mount values must be numbers"),
    ("scans = 1\nyaw_deg = { start = 0, stop = nan, step = 1 }\n", "must be a finite number"),
    ("scans = 1\nyaw_deg = { start = 0, stop = 1, step = '1' }\n", "must be numbers"),
    ("scans = 1\nseed = -4\n", "seed must be a whole number 0..2**63-1, got -4"),
    ("scans = 1\nmethod = 3\n", "method must be a non-empty string, got 3"),
    ("scans = 10000000000\n", "scans must be a whole number 1..1000000"),
    ("scans = 1\nyaw_deg = [1, 2]\nx_mm = { start = 0, stop = 60000, step = 1 }\n",
     "is 120002 references, more than the 100000"),
    ("scans = 1\nreference = [1, 2]\n", "reference 1 must be a table"),
])
def test_a_bad_plan_file_is_one_line_and_leaves_no_run(capsys, monkeypatch, tmp_path: Path,
                                                      toml, expected):
    monkeypatch.chdir(tmp_path)
    Path("plan.toml").write_text(toml)
    line = bad(capsys, "sweep", "plan.toml", "--out", "run")
    assert line.startswith("aimbench sweep: error: plan.toml: ") and expected in line, line
    assert not Path("run").exists()


@pytest.mark.parametrize(("text", "expected"), [
    ("surveyed poses: see the lab book\n", "notes.txt: not a truth file (not JSON"),
    # an entry with a time but no pose (read as the zero pose once)
    ('{"scans": [{"time_s": 12.5}]}', "notes.txt: an entry without a pose"),
])
def test_a_calibration_truth_that_is_not_one_is_one_line(capsys, tmp_path: Path, text: str,
                                                         expected: str):
    notes = tmp_path / "notes.txt"
    notes.write_text(text)
    line = bad(capsys, "calibrate", str(CAPTURE), "--truth", str(notes), "--out",
               str(tmp_path / "cal.json"))
    assert expected in line
    assert not (tmp_path / "cal.json").exists()


@pytest.mark.slow
def test_estimate_with_the_board_out_of_view_prints_no_pose(capsys, tmp_path: Path):
    """Tilted 30 deg up, the beams pass above the board: a scan the estimator calls
    partial_board once came with a tilt of 130 deg and sigma x 0.0. No row may carry a pose
    without success, and the JSON is JSON (no NaN)."""
    cap = tmp_path / "up.pcap"
    assert main(["simulate", "--tilt-deg", "30", "--scans", "3", "--seed", "0", "--out",
                 str(cap), "--quiet"]) == 0
    assert main(["estimate", str(cap), "--json"]) == 1  # no scan gave a pose
    rows = [json.loads(ln) for ln in capsys.readouterr().out.splitlines()]
    assert len(rows) >= 2 and {r["status"] for r in rows} <= {"partial_board", "no_board"}
    for r in rows:
        assert all(r[k] is None for k in ("x_mm", "tilt_deg", "yaw_deg", "x_mm_std"))
        assert r["reason"]
        assert all(not (isinstance(v, float) and math.isnan(v)) for v in r.values())
    assert main(["estimate", str(cap)]) == 1
    table = capsys.readouterr().out
    assert "129." not in table and "(0.0 mm" not in table


def test_the_command_line_imports_only_the_command_that_runs(capsys):
    # Issue 38: --help lists every command with its help line without importing any command
    # module (nor numpy); a command's own parser is the full one. The lines read from source
    # are those the modules register.
    import subprocess
    import sys

    from scenarios.cli import ALL, build_parser, command_help, command_names

    probe = ("import sys; from scenarios.cli import main\n"
             "try:\n    main(['--help'])\nexcept SystemExit:\n    pass\n"
             "print(sorted(m for m in sys.modules if m.startswith('scenarios.commands.') or "
             "m == 'numpy'), file=sys.stderr)")
    res = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                         timeout=60, cwd=Path(__file__).resolve().parents[1], check=True)
    assert res.stderr.strip().splitlines()[-1] == "[]", res.stderr
    full = build_parser(ALL)._subparsers._group_actions[0]
    helps = {a.dest: a.help for a in full._choices_actions}
    assert set(helps) == set(command_names())
    assert all(helps[name] and command_help(name) == helps[name] for name in helps)
    for name in command_names():
        assert name in res.stdout and (helps[name].split()[0] in res.stdout)


@pytest.mark.parametrize(("hidden", "argv", "extra"), [
    ("open3d", ["estimate", str(CAPTURE), "--method", "icp"], "open3d"),
    ("rerun", ["replay", str(CAPTURE), "--save", "x.rrd"], "rerun"),
    ("statsmodels", ["grr", "--db", "g.sqlite"], "grr"),
])
def test_a_missing_extra_is_one_line_naming_it(capsys, monkeypatch, tmp_path: Path, hidden,
                                               argv, extra):
    # `make demo` installs no extras (issue 38): a command needing one says which, before it
    # runs (the library hidden as if it were not installed: None in sys.modules).
    import sys

    monkeypatch.setitem(sys.modules, hidden, None)
    monkeypatch.chdir(tmp_path)
    assert f"pip install 'aimbench[{extra}]'" in bad(capsys, *argv)
    assert list(tmp_path.iterdir()) == []  # nothing made
