"""Ground truth: the true LiDAR pose of a scan, and the ``CAPTURE.truth.json`` beside a capture.

A scan's truth is one type, `ScanTruth` (a pose in SI units, and the sensor time that pairs it
with a decoded scan). The twin knows the pose of every scan it makes (``Scan.meta["truth_pose"]``,
read by `scan_truth`); `aimbench simulate` writes it beside its capture (`write_truth`), and
`estimate`, `calibrate` and `replay` read it back (`load_truth`) to pair decoded scans with their
truth by sensor time (`truth_for`). One writer, one reader, one lookup, for every command; units
and key names exist only in the file (`ScanTruth.to_record` / `from_record`).

The file (units in the key names, board frame {O} of docs/DESIGN.md)::

    {"capture": "cap.pcap", ...what the writer adds (bench, emulation, seed)...,
     "scans": [{"index": 0, "time_s": 12.3, "x_m": ..., "y_m": ..., "z_m": ...,
                "roll_deg": ..., "tilt_deg": ..., "yaw_deg": ...}, ...]}

The reader also takes entries in mm (``x_mm``...), a plain list of entries, or one pose for the
whole capture (a static bench whose pose was measured otherwise).
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from twin.core.errors import AimbenchError
from twin.core.pose import Pose
from twin.core.scan import Scan

#: Largest difference between a scan's first firing and a truth entry's time that pairs them, s
#: (a few firing sequences: far below a rotation's 0.1 s).
TIME_MATCH_S = 1e-3
#: The angles of a file entry, in degrees.
_ANGLES_DEG = ("roll_deg", "tilt_deg", "yaw_deg")
#: A file entry's pose keys in edge units.
_EDGE_KEYS = ("x_mm", "y_mm", "z_mm", *_ANGLES_DEG)


class TruthFileError(AimbenchError):
    """A truth file that cannot be read."""


@dataclass(frozen=True)
class ScanTruth:
    """The true LiDAR pose of a scan in the board frame {O} (SI), at the scan's first firing.

    time_s: that firing's sensor time (s past the hour), which pairs a decoded scan with its
    truth; None for the one static pose of a whole capture. index, rpm: what the twin's writer
    adds (the scan's number in its capture, its spin rate).
    """

    pose: Pose
    time_s: float | None = None
    index: int | None = None
    rpm: float | None = None

    @classmethod
    def of_scan(cls, scan: Scan, index: int | None = None) -> ScanTruth | None:
        """The twin's truth of `scan` with its first firing's time (None: no truth or no
        firing)."""
        pose = scan_truth(scan)
        if pose is None or not len(scan):
            return None
        rpm = scan.meta.get("rpm")
        return cls(pose, float(scan.time[0]), index, rpm)

    def to_record(self) -> dict[str, Any]:
        """The file's entry: metres and degrees, the unit in each key."""
        entry: dict[str, Any] = {}
        if self.index is not None:
            entry["index"] = self.index
        if self.time_s is not None:
            entry["time_s"] = self.time_s
        if self.rpm is not None:
            entry["rpm"] = self.rpm
        p = self.pose
        return {**entry, "x_m": p.x, "y_m": p.y, "z_m": p.z, "roll_deg": math.degrees(p.roll),
                "tilt_deg": math.degrees(p.tilt), "yaw_deg": math.degrees(p.yaw)}

    @classmethod
    def from_record(cls, entry: dict[str, Any]) -> ScanTruth:
        """From a file's entry in metres or millimetres, and degrees (ValueError: no pose)."""
        angles = {k: entry[k] for k in _ANGLES_DEG if k in entry}
        if "x_m" in entry:
            # The simulate command's file: metres and degrees. (Tested before the edge form: it
            # has yaw_deg too, and reading it as edge units would drop x, y and z.)
            pose = Pose.from_edge(**{f"{a}_mm": entry[f"{a}_m"] * 1e3 for a in "xyz"}, **angles)
        elif "x_mm" in entry or "yaw_deg" in entry:
            pose = Pose.from_edge(**{k: entry[k] for k in _EDGE_KEYS if k in entry})
        else:
            raise ValueError("no pose (x_m, y_m, z_m or x_mm, y_mm, z_mm, and roll_deg, "
                             "tilt_deg, yaw_deg)")
        # An earlier writer (the replay's) named the time sensor_time_s.
        t = entry.get("time_s", entry.get("sensor_time_s"))
        return cls(pose, None if t is None else float(t), entry.get("index"), entry.get("rpm"))


def truth_path(capture: str | Path) -> Path:
    """Where a capture's truth lives: ``CAPTURE.truth.json`` beside it."""
    capture = Path(capture)
    return capture.with_name(capture.stem + ".truth.json")


def write_truth(capture: str | Path, scans: list[Scan], **extra: Any) -> Path:
    """Write the truth of the twin's scans (`twin.sim.bench.BenchSim.write_pcap` returns them)
    beside their capture: per scan its sensor time (s past the hour, first firing), rpm and true
    pose; ``extra`` (JSON-able) goes at the top (what the bench and the emulation were)."""
    truths = (ScanTruth.of_scan(s, i) for i, s in enumerate(scans))
    path = truth_path(capture)
    record = {"capture": Path(capture).name,
              "frame": "board frame {O} of docs/DESIGN.md; pose at each scan's first firing",
              **extra, "scans": [t.to_record() for t in truths if t is not None]}
    path.write_text(json.dumps(record, indent=1), encoding="utf-8")
    return path


def load_truth(path: str | Path) -> list[ScanTruth]:
    """The entries of a truth file (module docstring)."""
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise TruthFileError(f"{path}: no such truth file (check the path)") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise TruthFileError(f"{path}: not a truth file (not JSON: {exc}); give the "
                             "CAPTURE.truth.json that aimbench simulate wrote") from None
    entries = data.get("scans", [data]) if isinstance(data, dict) else data
    if not isinstance(entries, list):
        raise TruthFileError(f"{path}: not a truth file (no list of scans)")
    out: list[ScanTruth] = []
    for e in entries:
        try:
            out.append(ScanTruth.from_record(e))
        except (ValueError, TypeError, AttributeError) as exc:
            raise TruthFileError(f"{path}: an entry without a pose ({exc}): {e}") from None
    return out


def truth_for(scan: Scan, truths: Sequence[ScanTruth]) -> Pose | None:
    """The true pose of a decoded scan: the entry whose sensor time is its first firing's
    (within `TIME_MATCH_S`), or the single static pose."""
    if not truths:
        return None
    if len(truths) == 1 and truths[0].time_s is None:
        return truths[0].pose
    if not len(scan):
        return None
    t0 = float(scan.time[0])
    times = np.array([np.inf if t.time_s is None else t.time_s for t in truths])
    j = int(np.argmin(np.abs(times - t0)))
    return truths[j].pose if abs(times[j] - t0) < TIME_MATCH_S else None


def scan_truth(scan: Scan) -> Pose | None:
    """The twin's true LiDAR pose of `scan` (``meta["truth_pose"]``, `twin.sim.bench`), or None
    for a real sensor's scan."""
    return scan.meta.get("truth_pose") if scan.meta else None
