"""`aimbench info SOURCE`: what a source holds (model: VLP-16, Puck Hi-Res, VLP-32C or
HDL-32E; return mode, rpm, packets, scans, gaps), as text or as one JSON object (``--json``).
SOURCE is any name `twin.lidar.sources` reads: a capture, a live sensor (udp://HOST:PORT), a ROS
bag or a PCD file."""

from __future__ import annotations

import argparse
import json
import math
import sys
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

from twin.core.errors import AimbenchError
from twin.core.sensor_names import HESAI_NAMES, VELODYNE_NAMES
from twin.lidar.format_names import CLOUD_CONVENTIONS, HESAI_CLOUD_CONVENTIONS

# The readers, the decoders and the progress bar (numpy, tqdm) are imported where a source is
# read: the parsers of every command that reads one are built from this module (issue 38).
if TYPE_CHECKING:
    from scenarios.progress import Bar
    from twin.core.scan import Scan
    from twin.lidar.sources import ScanSource

SOURCE_HELP = ("a capture (.pcap/.pcapng), the live sensor (udp://HOST:PORT, e.g. "
               "udp://0.0.0.0:2368; Ctrl-C ends it), a ROS 1 .bag, a ROS 2 bag (its folder, "
               ".db3 or .mcap; BAG#TOPIC names the LiDAR topic) or a .pcd file")


def add_source_arguments(p: argparse.ArgumentParser) -> None:
    """The source every capture-taking command reads, and how much of it."""
    p.add_argument("capture", metavar="SOURCE", help=SOURCE_HELP)
    p.add_argument("--scans", type=int, default=None, metavar="N",
                   help="stop after N whole scans (a live sensor is read until Ctrl-C "
                        "without it)")


def open_source(args: argparse.Namespace, station: Any = None) -> ScanSource:
    """The `ScanSource` the command line names, decoded as its options say (and, for what they
    leave unsaid, as ``station``'s sensor: `decode_options`)."""
    from twin.lidar.sources import open_scans

    if getattr(args, "scans", None) is not None and args.scans < 1:
        raise AimbenchError(f"--scans {args.scans}: give at least 1")
    return open_scans(args.capture, max_scans=getattr(args, "scans", None),
                      **decode_options(args, station))


def quiet_scans(source: ScanSource) -> Iterator[Scan]:
    """The source's scans with its warnings held back: they are in its summary, and
    `warn_lines` prints each once (the commands' own code keeps its warnings)."""
    scans = iter(source)
    while True:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            scan = next(scans, None)
        if scan is None:
            return
        yield scan


#: Files at least this big show their progress (a minute of VLP-16 data is ~56 MB in a pcap);
#: smaller ones read in a second or two, and a bar would only flash. A live sensor always does.
PROGRESS_BYTES = 50_000_000
#: Bytes one VLP-16 rotation at 600 rpm takes in a pcap (75.4 packets of 16 + 42 + 1206 bytes):
#: a pcap's estimated scan count is its size over this.
PCAP_SCAN_BYTES = 95_300


def progress_bar(name: str, command: str, min_bytes: int = PROGRESS_BYTES) -> Bar:
    """The `scenarios.progress.Bar` of reading source ``name``: over the estimated scans of a
    big pcap, counting scans of another big file or of a live sensor, off for small files."""
    from scenarios.progress import Bar

    path = Path(name)
    live = name.startswith("udp://")
    size = path.stat().st_size if path.is_file() else 0
    pcap = path.suffix.lower() in (".pcap", ".pcapng")
    total = max(1, size // PCAP_SCAN_BYTES) if pcap else None
    return Bar(total, command, "scans", enabled=live or size >= min_bytes,
               every=None if live else 0, estimated=True)


def read_source(args: argparse.Namespace, keep_scans: bool) -> tuple[list[Scan], dict]:
    """Every scan of the named source (or until --scans or Ctrl-C) and its summary."""
    scans = []
    with open_source(args) as source, progress_bar(str(args.capture),
                                                   getattr(args, "command", "read")) as bar:
        try:
            for scan in quiet_scans(source):
                bar.update(1)
                if keep_scans:
                    scans.append(scan)
        except KeyboardInterrupt:  # a live source: Ctrl-C ends the reading, not the command
            pass
    return scans, {"capture": str(args.capture), **source.summary()}


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
    p.add_argument("--cloud-convention", choices=CLOUD_CONVENTIONS + HESAI_CLOUD_CONVENTIONS,
                   default=None,
                   help="the driver that wrote a point cloud (how it turned each laser's "
                        "point; hesai-ros: Hesai's own ROS driver, in Hesai's frame or turned "
                        "to the ROS frame; docs/vlp16.md): default, told from the cloud's "
                        "fields, else from its points")
    p.add_argument("--metadata", "--ouster-metadata", dest="metadata", metavar="FILE.json",
                   default=None,
                   help="an Ouster sensor's metadata JSON, which its packets or its driver's "
                        "organised cloud are read with (default: the NAME.json recorded "
                        "beside a NAME.pcap or NAME.pcd)")
    add_sensor_arguments(p)


def add_sensor_arguments(p: argparse.ArgumentParser) -> None:
    """Which sensor the packets come from: ``--model`` and ``--sensor-calibration``, on every
    command that reads a source (a ``--station`` file's [sensor] gives both otherwise)."""
    p.add_argument("--model", choices=(*VELODYNE_NAMES, *HESAI_NAMES), default=None,
                   help="decode as this model whatever the product id byte says (default: "
                        "the --station file's sensor.model if one is given, else from the "
                        "product id); point clouds are rebuilt on its grid (default VLP-16)")
    p.add_argument("--angles", metavar="FILE.csv", default=None,
                   help="a Hesai PandarXT32's or PandarQT128's angle-correction file (Channel,"
                        "Elevation,Azimuth; default: the nominal one nebula ships)")
    p.add_argument("--sensor-calibration", metavar="FILE", default=None,
                   help="the unit's factory laser table (VeloView .xml or ROS driver .yaml) "
                        "instead of the model's nominal one (default: the --station file's "
                        "sensor.calibration_file, if any; not aimbench's own per-laser range "
                        "calibration, --calibration of estimate)")


def sensor_options(args: argparse.Namespace, station: Any = None) -> dict:
    """``model`` and ``lasers`` for `twin.lidar.sources.open_scans`: ``--model`` and
    ``--sensor-calibration``, else the sensor of ``station`` (a `scenarios.station.Station` the
    command was given, None: none): its model and its factory calibration file's table. A
    ``--model`` other than the station's drops the station's file (another model's table)."""
    from twin.lidar.calibration_file import read_calibration_file

    model = getattr(args, "model", None)
    cal = getattr(args, "sensor_calibration", None)
    lasers = None if cal is None else read_calibration_file(cal)[0]
    if station is not None:
        same = model is None or _model_key(model) == _model_key(station.sensor.model)
        if model is None:
            model = station.sensor.model
        if lasers is None and same:
            lasers = station.factory_lasers()
    return {"model": model, "lasers": lasers}


def _model_key(name: str) -> str:
    return "".join(ch for ch in name.upper() if ch.isalnum())


def decode_options(args: argparse.Namespace, station: Any = None) -> dict:
    """How the command line (and ``station``, `sensor_options`) says packets become scans."""
    return {
        "cut_azimuth": None if args.cut_at_start else math.radians(args.cut_azimuth_deg),
        "split": args.split,
        "vertical_offsets": not args.no_vertical_offsets,
        "cloud_convention": getattr(args, "cloud_convention", None),
        "ouster_metadata": getattr(args, "metadata", None),
        "hesai_angles": getattr(args, "angles", None),
        **sensor_options(args, station),
    }


def warn_lines(command: str, summary: dict) -> None:
    """Print the capture's warnings as one line each on stderr."""
    for message in summary.get("warnings", []):
        print(f"aimbench {command}: warning: {message}", file=sys.stderr)
    if summary.get("file", {}).get("truncated_file"):
        print(f"aimbench {command}: warning: the capture ends mid-record (cut off while "
              "recording); everything before the cut was read", file=sys.stderr)


def run(args: argparse.Namespace) -> int:
    _, summary = read_source(args, keep_scans=False)
    warn_lines("info", summary)
    if args.json:
        print(json.dumps(summary))
    else:
        print(format_summary(summary))
    return 0


#: How a cloud's driver convention was told, as `info` says it.
_TOLD = {"fields": "told by the cloud's fields", "points": "told from the points",
         "option": "given by --cloud-convention"}


def _told(how: str | None) -> str:
    """How a convention was told, in words: a reader's own words pass through."""
    return _TOLD.get(how, how or "given")


def format_summary(s: dict) -> str:
    """The summary as aligned lines of text, for whichever kind of source it came from."""
    kind = s.get("kind", "pcap")
    rpm = "-" if s["rpm"] is None else f"{s['rpm']:.1f}"
    lines = [("source", _describe(s))]
    if "ouster_cloud" in s:  # an Ouster driver's organised cloud
        return _ouster_cloud_summary(s, lines)
    if kind in ("pcd",) or "clouds" in s:
        lines += [
            ("model", f"{s['model']} "
                      f"({s.get('model_from', 'from the rings and elevations of the points')})"),
            ("rpm", f"{rpm} ({s.get('rpm_from', 'from the azimuth step of the firings')})"),
            ("clouds", s["clouds"]),
            ("scans", f"{s['scans']} ({s['complete_scans']} whole rotations, "
                      f"{s['partial_scans']} partial)"),
            ("points", f"{s['points']} firings: {s['returns']} returns from the cloud, "
                       f"{s['rebuilt_misses']} misses rebuilt from the firing grid"),
            ("vertical offsets", "in the points' z" if s["vertical_offsets"] else
             "not applied (as the ROS driver writes)"),
            ("convention", f"{s.get('cloud_convention') or '-'} "
                           f"({_told(s.get('cloud_convention_from'))})"),
        ]
        return "\n".join(f"{k:17s} {v}" for k, v in lines)
    if s.get("model") in HESAI_NAMES:  # a Hesai's packets
        lines += [
            ("model", f"{s['model']} (angles {s['laser_table']})"),
            ("return mode", s["return_mode"] if s["return_mode"] is not None else "-"),
            ("rpm", rpm),
            ("data packets", f"{s['data_packets']} ({s['other_datagrams']} other datagrams)"),
            ("scans", f"{s['scans']} whole rotations"),
            ("points", f"{s['points']} firings, {s['returns']} returns"),
        ]
        return "\n".join(f"{k:17s} {v}" for k, v in lines)
    if "osf" in s:  # an Ouster's OSF file, read by ouster-sdk
        lines += [
            ("model", f"{s['model']} ({s['prod_line']}, serial {s['serial'] or '-'}, "
                      f"firmware {s['firmware'] or '-'}; metadata in the file)"),
            ("lidar mode", f"{s['lidar_mode']} ({s['profile']} packets, as recorded)"),
            ("rpm", rpm),
            ("sensors", f"{s['osf']['sensors']} (the first read)"),
            ("scans", f"{s['scans']} ({s['complete_scans']} complete, {s['partial_scans']} "
                      f"partial: {s['missing_columns']} columns missing)"),
            ("points", f"{s['points']} firings, {s['returns']} returns"),
        ]
        return "\n".join(f"{k:17s} {v}" for k, v in lines)
    if "lidar_mode" in s:  # an Ouster sensor's packets
        lines += [
            ("model", f"{s['model']} ({s['prod_line']}, serial {s['serial'] or '-'}, "
                      f"firmware {s['firmware'] or '-'}; metadata {s['metadata']})"),
            ("lidar mode", f"{s['lidar_mode']} ({s['profile']} packets{_dual(s)})"),
            ("rpm", rpm),
            ("data packets", f"{s['data_packets']} ({s['other_datagrams']} other datagrams)"),
            ("scans", f"{s['scans']} ({s['complete_scans']} complete, {s['partial_scans']} "
                      f"partial: {s['missing_columns']} columns missing)"),
            ("points", f"{s['points']} firings, {s['returns']} returns"),
        ]
        return "\n".join(f"{k:17s} {v}" for k, v in lines)
    lines += [
        ("model", f"{s['model'] or '-'} (product id {s['product_id'] or '-'})"),
        ("return mode", s["return_mode"] or "-"),
        ("rpm", rpm),
        ("data packets", s["data_packets"]),
        ("position packets", s["position_packets"]),
        ("scans", f"{s['scans']} ({s['complete_scans']} complete, {s['partial_scans']} partial "
                  f"at the ends, {s['scans_with_missing_packets']} with missing packets)"),
        ("points", _points(s)),
        ("gaps", f"{s['gaps']} ({s['missing_packets']} packets missing)"),
        ("time breaks", s["time_breaks"]),
        ("duplicates", s["duplicates"]),
        ("out of order", f"{s['out_of_order']} ({s['late']} too late, dropped)"),
        ("rejected", ", ".join(f"{k} {v}" for k, v in s["rejected"].items()) or "none"),
    ]
    f = s.get("file")
    if f is not None:
        skipped = ", ".join(f"{k} {v}" for k, v in f.get("skipped", {}).items()) or "none"
        lines.append(("skipped", f"{skipped} (of {f.get('records', 0)} records)"))
    if "udp" in s:
        u = s["udp"]
        lines.append(("received", f"{u['data']} data packets, {u['malformed']} malformed "
                                  f"datagrams, {u['kernel_drops']} dropped by the kernel"))
    lines.append(("duration", "-" if s["duration_s"] is None else f"{s['duration_s']:.3f} s"))
    if s.get("interrupted"):
        lines.append(("interrupted", "yes (Ctrl-C): the figures cover what was received"))
    return "\n".join(f"{k:17s} {v}" for k, v in lines)


def _ouster_cloud_summary(s: dict, lines: list[tuple[str, Any]]) -> str:
    """An Ouster organised cloud's summary (`twin.lidar.ouster_clouds`): every pixel is a
    firing, nothing rebuilt."""
    lines += [
        ("model", f"{s['model']} ({s['prod_line']}, serial {s['serial'] or '-'}, "
                  f"firmware {s['firmware'] or '-'}; metadata {s['metadata']})"),
        ("lidar mode", s["lidar_mode"]),
        ("rpm", f"{s['rpm']:.1f}"),
        ("clouds", f"{s['clouds']} organised (rows = beams; {s['ouster_cloud'] or '-'})"),
        ("points", f"{s['points']} firings (every pixel), {s['returns']} returns"),
    ]
    return "\n".join(f"{k:17s} {v}" for k, v in lines)


def _describe(s: dict) -> str:
    if "ouster_cloud" in s:
        return f"{s['capture']} (Ouster organised point cloud)"
    if "osf" in s:
        return f"{s['capture']} (Ouster OSF, read by ouster-sdk {s['osf']['ouster_sdk']})"
    kind = s.get("kind", "pcap")
    if kind == "udp" and "lidar_mode" not in s and s.get("model") not in HESAI_NAMES:
        return f"{s['capture']} (live)"
    if "bag" in s:
        b = s["bag"]
        return (f"{s['capture']} (ROS bag, topic {b['topic']}, {b['type']}, "
                f"{b['messages']} messages)")
    if "clouds" in s and s.get("model") in HESAI_NAMES:
        driver = s.get("cloud_driver", "nebula's Hesai")
        return f"{s['capture']} ({driver} {s['model']} point cloud, {kind})"
    if "lidar_mode" in s or s.get("model") in HESAI_NAMES:
        maker = "Ouster lidar" if "lidar_mode" in s else f"Hesai {s['model']}"
        return f"{s['capture']} ({maker} packets, {'live' if kind == 'udp' else kind})"
    f = s.get("file")
    if f is not None:
        return (f"{s['capture']} ({f.get('format', '?')}, "
                f"{'ns' if f.get('nanosecond') else 'us'} timestamps, "
                f"{f.get('byte_order', '?')}-endian)")
    return f"{s['capture']} (point cloud file)"


def _dual(s: dict) -> str:
    """What an Ouster's dual-return profile gives the scans (`twin.lidar.ouster`)."""
    if s.get("return_mode") != "dual":
        return ""
    return "; two returns a pixel: the first, strongest, read, the second where it has none"


def _points(s: dict) -> str:
    """Fired and returned points; in dual-return mode also the distinct points, which is what
    velodyne_decoder and the ROS driver count (an echo that is both the strongest and the last
    comes twice in the packets and is counted once)."""
    text = f"{s['points']} fired, {s['returns']} returns"
    distinct = s.get("distinct_returns", s["returns"])
    if distinct != s["returns"] or s.get("return_mode") == "dual":
        text += (f" (every echo of both blocks of each pair), {distinct} distinct points (an "
                 "echo both strongest and last counted once, as velodyne_decoder counts)")
    return text


def register(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser("info", help="summarise a lidar source (capture, live sensor, ROS bag, "
                                    "PCD file)")
    add_source_arguments(p)
    p.add_argument("--json", action="store_true", help="one JSON object")
    add_decode_options(p)
    p.set_defaults(func=run)
    return p
