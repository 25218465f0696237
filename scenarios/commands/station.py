"""`aimbench station --station FILE --db line.sqlite`: the line station, one process serving the
operator's and the engineer's web pages, an OPC UA server for the line's PLC and an HTTP/JSON
endpoint for MES, all inspecting through `aimbench inspect`'s pipeline, one unit at a time
(docs/station-line.md).

    aimbench station --station my-line.toml --db line.sqlite             # the twin (sim)
    aimbench station --station my-line.toml --db line.sqlite --source udp://0.0.0.0:2368
    aimbench station --hash-password          # a password's hash for [[line.users]]

It listens on the station file's ``[line] address`` (default 127.0.0.1: this machine only)
and ``port`` (web and JSON; ``--port`` overrides), OPC UA on ``[line.opcua] port``. Source
``sim``: each unit id is a twin unit of its own (its misalignment and sensor drawn from the
id); ``serve``: the wire-level twin of `aimbench serve` on the station's sensor network;
``udp://HOST:PORT``: the live sensor.
"""

from __future__ import annotations

import argparse
import getpass
import os
from pathlib import Path

from scenarios import station_options
from scenarios.cliargs import int_at_least
from scenarios.defaults import INSPECTION_SCANS as DEFAULT_SCANS
from scenarios.extras import require
from twin.core.errors import AimbenchError


def run(args: argparse.Namespace) -> int:
    # here, not at the top: the station model (pydantic) is the run's, not the parser's
    # (issue 38); the line's web and OPC UA servers load only once the station file is read
    from scenarios import station as stations
    from scenarios.line import auth

    if args.hash_password:
        pw = os.environ.get("AIMBENCH_PASSWORD") or getpass.getpass("password: ")
        print(auth.hash_password(pw))
        return 0
    if not args.db:
        raise AimbenchError("give --db FILE: the station's record store (SQLite)")
    station, _ = stations.from_args(args, twin=args.source in ("sim", "serve"))
    source = args.source
    if source == "serve":
        source = f"udp://{station.sensor.network.host}:{station.sensor.network.port}"
    elif source != "sim" and not source.startswith("udp://"):
        raise AimbenchError(f"--source {source}: give sim, serve or udp://HOST:PORT")
    if args.scans < 1:
        raise AimbenchError(f"--scans {args.scans}: give at least 1")
    db = Path(args.db)
    folder = db.resolve().parent / (db.stem + ".station")
    folder.mkdir(parents=True, exist_ok=True)
    # NiceGUI keeps its sessions in files: beside the store, not in the working directory
    os.environ.setdefault("NICEGUI_STORAGE_PATH", str(folder / "sessions"))
    require("nicegui", "aimbench station (its pages)")
    require("asyncua", "aimbench station (its OPC UA server)")
    from scenarios.line.engine import StationEngine
    from scenarios.line.opcua import StationOpcUa
    from scenarios.line.web import run as serve

    host = args.address or station.line.address
    port = args.port or station.line.port
    opc_port = args.opcua_port or station.line.opcua.port
    engine = StationEngine(station, db, source, scans=args.scans, max_scans=args.max_scans,
                           calibration=args.calibration, batch=args.batch,
                           board_view=None if args.no_board_view else folder / "views")
    engine.warm_up()  # the worker process's imports now, not at the first unit
    opcua = None if args.no_opcua else StationOpcUa(engine, host, opc_port, folder)
    serve(engine, host, port, opcua, None if args.no_board_view else folder / "views",
          args.type1_reference)
    return 0


def register(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser("station", help="the line station: operator and engineer web pages, "
                                       "OPC UA for the PLC, HTTP/JSON for MES",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    station_options.add_arguments(p)
    p.add_argument("--db", metavar="FILE", help="the record store (SQLite, created if missing)")
    p.add_argument("--source", default="sim",
                   help="sim (default), serve, or udp://HOST:PORT (the live sensor)")
    p.add_argument("--address", default=None,
                   help="listen on this address (default: the station file's [line] address, "
                        "127.0.0.1)")
    p.add_argument("--port", type=int_at_least(1), default=None,
                   help="web and JSON port (default: the station file's, 8080)")
    p.add_argument("--opcua-port", type=int_at_least(1), default=None,
                   help="OPC UA port (default: the station file's, 4840)")
    p.add_argument("--no-opcua", action="store_true", help="no OPC UA server")
    p.add_argument("--scans", type=int_at_least(1), default=DEFAULT_SCANS,
                   help=f"scans per measurement (default {DEFAULT_SCANS})")
    p.add_argument("--max-scans", type=int_at_least(1), default=None,
                   help="most scans a re-measure may reach (default 3 x --scans)")
    p.add_argument("--calibration", default=None, metavar="FILE",
                   help="per-laser range calibration (default: the station's)")
    p.add_argument("--batch", default=None, help="the batch new records are filed under")
    p.add_argument("--type1-reference", default=None, metavar="FILE",
                   help="the Type-1 reference part's file, for the engineer's page")
    p.add_argument("--no-board-view", action="store_true",
                   help="do not draw the board as the sensor saw it after each unit")
    p.add_argument("--hash-password", action="store_true",
                   help="print a password's scrypt hash for the station file's [[line.users]] "
                        "(reads it from the terminal, or AIMBENCH_PASSWORD)")
    p.set_defaults(func=run)
    return p
