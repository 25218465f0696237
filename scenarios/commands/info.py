"""`aimbench info CAPTURE`: what a VLP-16 capture holds (model, return mode, rpm, packets, scans,
gaps), as text or as one JSON object (``--json``)."""

from __future__ import annotations

import argparse
import json
import math
import sys
import warnings

from twin.lidar.capture import PcapSource, read_capture


def add_decode_options(p: argparse.ArgumentParser) -> None:
    """Options shared by `info` and `decode`: how packets become scans."""
    p.add_argument("--cut-azimuth-deg", type=float, default=180.0,
                   help="azimuth where one scan ends and the next begins, deg "
                        "(default 180: behind the sensor, away from the board)")
    p.add_argument("--cut-at-start", action="store_true",
                   help="cut at the first firing's azimuth instead (the first scan is whole)")
    p.add_argument("--split", choices=("firing", "packet"), default="firing",
                   help="cut between firings (exact rotations) or between packets (as ROS and "
                        "velodyne_decoder do)")
    p.add_argument("--no-vertical-offsets", action="store_true",
                   help="do not add the lasers' vertical offsets to z")
    p.add_argument("--model", choices=("VLP-16",), default=None,
                   help="decode as VLP-16 whatever the product id byte says")


def decode_options(args: argparse.Namespace) -> dict:
    return {
        "cut_azimuth": None if args.cut_at_start else math.radians(args.cut_azimuth_deg),
        "split": args.split,
        "vertical_offsets": not args.no_vertical_offsets,
        "model": args.model,
    }


def warn_lines(command: str, summary: dict) -> None:
    """Print the capture's warnings as one line each on stderr."""
    for message in summary.get("warnings", []):
        print(f"aimbench {command}: warning: {message}", file=sys.stderr)
    if summary.get("file", {}).get("truncated_file"):
        print(f"aimbench {command}: warning: the capture ends mid-record (cut off while "
              "recording); everything before the cut was read", file=sys.stderr)


def run(args: argparse.Namespace) -> int:
    source = PcapSource(args.capture)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # collected in the summary, printed once below
        result = read_capture(source, keep_scans=False, **decode_options(args))
    summary = {"capture": str(args.capture), **result.summary}
    warn_lines("info", summary)
    if args.json:
        print(json.dumps(summary))
    else:
        print(format_summary(summary))
    return 0


def format_summary(s: dict) -> str:
    f = s.get("file", {})
    rpm = "-" if s["rpm"] is None else f"{s['rpm']:.1f}"
    skipped = ", ".join(f"{k} {v}" for k, v in f.get("skipped", {}).items()) or "none"
    rejected = ", ".join(f"{k} {v}" for k, v in s["rejected"].items()) or "none"
    lines = [
        ("capture", f"{s['capture']} ({f.get('format', '?')}, "
                    f"{'ns' if f.get('nanosecond') else 'us'} timestamps, "
                    f"{f.get('byte_order', '?')}-endian)"),
        ("model", f"{s['model'] or '-'} (product id {s['product_id'] or '-'})"),
        ("return mode", s["return_mode"] or "-"),
        ("rpm", rpm),
        ("data packets", s["data_packets"]),
        ("position packets", s["position_packets"]),
        ("scans", f"{s['scans']} ({s['complete_scans']} complete, {s['partial_scans']} partial "
                  f"at the ends, {s['scans_with_missing_packets']} with missing packets)"),
        ("points", f"{s['points']} fired, {s['returns']} returns"),
        ("gaps", f"{s['gaps']} ({s['missing_packets']} packets missing)"),
        ("time breaks", s["time_breaks"]),
        ("duplicates", s["duplicates"]),
        ("out of order", f"{s['out_of_order']} ({s['late']} too late, dropped)"),
        ("rejected", rejected),
        ("skipped", f"{skipped} (of {f.get('records', 0)} records)"),
        ("duration", "-" if s["duration_s"] is None else f"{s['duration_s']:.3f} s"),
    ]
    return "\n".join(f"{k:17s} {v}" for k, v in lines)


def register(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser("info", help="summarise a VLP-16 capture (pcap or pcapng)")
    p.add_argument("capture", help="capture file (.pcap or .pcapng)")
    p.add_argument("--json", action="store_true", help="one JSON object")
    add_decode_options(p)
    p.set_defaults(func=run)
    return p
