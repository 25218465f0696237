"""A scan's truth file (`scenarios.truth`): the forms a surveyed file may take read into the one
type, `ScanTruth`, and paired with decoded scans (the twin's own files: tests/test_rerun.py)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from scenarios.truth import ScanTruth, load_truth, truth_for
from twin.core.pose import Pose
from twin.lidar.sources import capture_scans

CAPTURE = Path(__file__).resolve().parent / "data" / "vlp16-strongest-10hz.pcap"


def test_a_surveyed_static_pose_in_mm_is_every_scans_truth(tmp_path: Path):
    """One pose for the whole capture, in mm and degrees: every scan of it gets that pose."""
    path = tmp_path / "survey.json"
    path.write_text(json.dumps({"x_mm": 700.0, "y_mm": -2500.0, "yaw_deg": 5.0}))
    (truth,) = load_truth(path)
    assert truth.time_s is None
    assert truth.pose.as_array() == pytest.approx([0.7, -2.5, 0.0, 0.0, 0.0, math.radians(5)])
    scans = capture_scans(CAPTURE, whole_only=False)
    assert scans and all(truth_for(s, [truth]) == truth.pose for s in scans)


def test_an_entry_reads_back_as_written():
    t = ScanTruth(Pose(0.71, -2.5, 0.02, 0.01, -0.02, 0.1), time_s=12.25, index=3, rpm=600.0)
    back = ScanTruth.from_record(json.loads(json.dumps(t.to_record())))
    assert (back.time_s, back.index, back.rpm) == (12.25, 3, 600.0)
    assert back.pose.as_array() == pytest.approx(t.pose.as_array(), abs=1e-12)
