"""Ground truth: the true LiDAR pose of a scan, and the ``CAPTURE.truth.json`` beside a capture.

The twin knows the pose of every scan (``Scan.meta["truth_pose"]``); `aimbench simulate` writes it
beside its capture, and `estimate`, `calibrate` and `replay` read it back to pair decoded scans
with their truth by sensor time. One writer, one reader, one lookup, for every command.

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
from pathlib import Path
from typing import Any

import numpy as np

from twin.core.errors import AimbenchError
from twin.core.pose import Pose
from twin.core.scan import Scan

#: Largest difference between a scan's first firing and a truth entry's time that pairs them, s
#: (a few firing sequences: far below a rotation's 0.1 s).
TIME_MATCH_S = 1e-3


class TruthFileError(AimbenchError):
    """A truth file that cannot be read."""


def truth_path(capture: str | Path) -> Path:
    """Where a capture's truth lives: ``CAPTURE.truth.json`` beside it."""
    capture = Path(capture)
    return capture.with_name(capture.stem + ".truth.json")


def pose_record(pose: Pose) -> dict[str, float]:
    """A truth entry's pose: metres and degrees, the unit in each key."""
    return {"x_m": pose.x, "y_m": pose.y, "z_m": pose.z, "roll_deg": math.degrees(pose.roll),
            "tilt_deg": math.degrees(pose.tilt), "yaw_deg": math.degrees(pose.yaw)}


def write_truth(capture: str | Path, scans: list[Scan], **extra: Any) -> Path:
    """Write the truth of the twin's scans (`twin.sim.bench.BenchSim.write_pcap` returns them)
    beside their capture: per scan its sensor time (s past the hour, first firing), rpm and true
    pose; ``extra`` (JSON-able) goes at the top (what the bench and the emulation were)."""
    entries = []
    for i, s in enumerate(scans):
        truth = s.meta.get("truth_pose")
        if truth is None or not len(s):
            continue
        entry: dict[str, Any] = {"index": i, "time_s": float(s.time[0])}
        if "rpm" in s.meta:
            entry["rpm"] = s.meta["rpm"]
        entries.append({**entry, **pose_record(truth)})
    path = truth_path(capture)
    record = {"capture": Path(capture).name,
              "frame": "board frame {O} of docs/DESIGN.md; pose at each scan's first firing",
              **extra, "scans": entries}
    path.write_text(json.dumps(record, indent=1), encoding="utf-8")
    return path


def load_truth(path: str | Path) -> list[tuple[float | None, Pose]]:
    """(sensor time or None, pose) entries of a truth file (module docstring)."""
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
    out: list[tuple[float | None, Pose]] = []
    for e in entries:
        pose = scan_truth(Scan.empty(meta={"truth": e})) if isinstance(e, dict) else None
        if pose is None:
            raise TruthFileError(f"{path}: an entry without a pose: {e}")
        # An earlier writer (the replay's) named it sensor_time_s.
        t = e.get("time_s", e.get("sensor_time_s"))
        out.append((None if t is None else float(t), pose))
    return out


def truth_for(scan: Scan, truths: list[tuple[float | None, Pose]]) -> Pose | None:
    """The truth entry of a decoded scan: the one whose sensor time is its first firing's (within
    `TIME_MATCH_S`), or the single static pose."""
    if not truths:
        return None
    if len(truths) == 1 and truths[0][0] is None:
        return truths[0][1]
    if not len(scan):
        return None
    t0 = float(scan.time[0])
    times = np.array([np.inf if t is None else t for t, _ in truths])
    j = int(np.argmin(np.abs(times - t0)))
    return truths[j][1] if abs(times[j] - t0) < TIME_MATCH_S else None


def scan_truth(scan: Scan) -> Pose | None:
    """The twin's true LiDAR pose for `scan` (``scan.meta['truth']``), or None on hardware.

    Accepts a `Pose`, a 6-array (SI), or a dict in SI or edge units, since the twin and a replay
    of a capture's ``.truth.json`` may give either.
    """
    if not scan.meta:
        return None
    truth = scan.meta.get("truth_pose", scan.meta.get("truth"))
    if truth is None:
        return None
    if isinstance(truth, Pose):
        return truth
    if isinstance(truth, dict):
        if "x_m" in truth:
            # The simulate command's truth.json: metres and degrees. (Tested before the edge
            # form: it has yaw_deg too, and reading it as edge units would drop x, y and z.)
            return Pose.from_edge(**{f"{a}_mm": truth[f"{a}_m"] * 1e3 for a in "xyz"},
                                  **{k: truth[k] for k in ("roll_deg", "tilt_deg", "yaw_deg")
                                     if k in truth})
        if "x_mm" in truth or "yaw_deg" in truth:
            return Pose.from_edge(**{k: v for k, v in truth.items() if k in
                                     ("x_mm", "y_mm", "z_mm", "roll_deg", "tilt_deg", "yaw_deg")})
        return Pose(**{k: float(truth.get(k, 0.0)) for k in
                       ("x", "y", "z", "roll", "tilt", "yaw")})
    return Pose.from_array(truth)



