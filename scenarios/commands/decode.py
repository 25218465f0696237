"""`aimbench decode CAPTURE --out scans.npz`: every firing of every scan as flat arrays.

Per point: x, y, z (m, LiDAR frame {L}), distance (m, 0 = no return), intensity, laser_id,
ring, azimuth_deg, time_s (sensor clock, s past the hour), scan (index), return_type (flags of
`twin.core.scan.ReturnType`). Per scan: scan_index, scan_start (first point), scan_points,
scan_complete, scan_partial, scan_missing_packets, scan_packets, scan_rpm. ``summary``: the
`aimbench info --json` object as a JSON string.
"""

from __future__ import annotations

import argparse
import json
import warnings
from pathlib import Path

import numpy as np

from scenarios.commands.info import add_decode_options, decode_options, warn_lines
from twin.core.errors import AimbenchError
from twin.core.scan import Scan
from twin.lidar.capture import PcapSource, read_capture


def scans_to_arrays(scans: list[Scan], returns_only: bool = False) -> dict[str, np.ndarray]:
    """Flat per-point and per-scan arrays of a list of scans (what `decode` writes)."""
    if returns_only:
        scans = [s.hits() for s in scans]
    n = np.array([len(s) for s in scans], dtype=np.int64)
    scan_of_point = np.repeat(np.array([s.index for s in scans], dtype=np.int32), n)
    whole = Scan.concatenate(scans) if scans else Scan.empty()
    return {
        "x": whole.x, "y": whole.y, "z": whole.z, "distance": whole.distance,
        "intensity": whole.intensity, "laser_id": whole.laser_id, "ring": whole.ring,
        "azimuth_deg": np.degrees(whole.azimuth), "time_s": whole.time,
        "scan": scan_of_point, "return_type": whole.return_type,
        "scan_index": np.array([s.index for s in scans], dtype=np.int32),
        "scan_start": np.concatenate(([0], np.cumsum(n)[:-1])).astype(np.int64),
        "scan_points": n,
        "scan_complete": np.array([s.complete for s in scans], dtype=bool),
        "scan_partial": np.array([s.meta.get("partial", False) for s in scans], dtype=bool),
        "scan_missing_packets": np.array([s.missing_packets for s in scans], dtype=np.int64),
        "scan_packets": np.array([s.packets for s in scans], dtype=np.int64),
        "scan_rpm": np.array([s.meta.get("rpm", np.nan) for s in scans], dtype=np.float64),
    }


def run(args: argparse.Namespace) -> int:
    out = Path(args.out)
    if not out.parent.is_dir():
        raise AimbenchError(f"cannot write {out}: the folder {out.parent} does not exist")
    source = PcapSource(args.capture)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # collected in the summary, printed once below
        result = read_capture(source, keep_scans=True, **decode_options(args))
    summary = {"capture": str(args.capture), **result.summary}
    warn_lines("decode", summary)
    if not result.scans:
        raise AimbenchError(
            f"{args.capture}: no VLP-16 data packets (1206-byte UDP payloads on port 2368) "
            "in this capture; `aimbench info` shows what it holds")
    arrays = scans_to_arrays(result.scans, returns_only=args.returns_only)
    save = np.savez_compressed if args.compress else np.savez
    try:
        with out.open("wb") as f:
            save(f, summary=np.array(json.dumps(summary)), **arrays)
    except OSError as exc:
        raise AimbenchError(f"cannot write {out} ({exc.strerror})") from None
    print(f"{out}: {len(result.scans)} scans, {len(arrays['x'])} points "
          f"({summary['complete_scans']} complete scans)")
    return 0


def register(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser("decode", help="decode a VLP-16 capture into per-point arrays (.npz)")
    p.add_argument("capture", help="capture file (.pcap or .pcapng)")
    p.add_argument("--out", required=True, help="output .npz file")
    p.add_argument("--returns-only", action="store_true",
                   help="leave out firings without a return (distance 0)")
    p.add_argument("--compress", action="store_true", help="write a compressed .npz")
    add_decode_options(p)
    p.set_defaults(func=run)
    return p
