"""What a record says about how it was made: software version and git commit, the station's
content hash, the calibration files' identity."""

from __future__ import annotations

import functools
import hashlib
import json
import subprocess
from importlib import metadata
from pathlib import Path
from typing import Any

from scenarios.inspection.acquire import sha256_of

#: The source tree this aimbench runs from (a git checkout when developing or on a bench PC).
_SOURCE = Path(__file__).resolve().parents[2]


def software_version() -> str:
    try:
        return metadata.version("aimbench")
    except metadata.PackageNotFoundError:
        return "unknown"


@functools.cache
def git_commit() -> str | None:
    """``git describe --always --dirty`` of the source tree (None outside a checkout): a result
    made with uncommitted changes says so."""
    try:
        out = subprocess.run(["git", "-C", str(_SOURCE), "describe", "--always", "--dirty",
                              "--abbrev=40"], capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() or None if out.returncode == 0 else None


def station_hash(station_json: dict[str, Any]) -> str:
    """SHA-256 of the station's canonical JSON: the same bench, the same hash."""
    text = json.dumps(station_json, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def calibration_identity(station: Any, calibration_file: str | None) -> dict[str, Any]:
    """Each calibration in use (the range calibration applied to the scans, the unit's factory
    calibration named by the station) with its path and SHA-256; empty: none."""
    out: dict[str, Any] = {}
    for key, path in (("range_calibration", calibration_file),
                      ("calibration_file", station.sensor.calibration_file)):
        if path:
            p = Path(path)
            out[key] = {"path": str(p.resolve()), "sha256": sha256_of(p) if p.is_file() else None}
    return out
