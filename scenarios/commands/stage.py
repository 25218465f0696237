"""`aimbench stage`: drive the stage controller by hand (a real board or the simavr harness).

    aimbench stage --port /dev/ttyACM0 status
    aimbench stage --port /dev/ttyACM0 home
    aimbench stage --port /dev/ttyACM0 move --x-mm 5 --yaw-deg -10
    aimbench stage --port /dev/ttyACM0 settings

--x-mm and --yaw-deg are relative to the bench reference (x = 0 at the bench centre, yaw = 0
facing the board), like StageController.move_to; status prints both those and the machine
position. For a stock grbl-Mega board pass --axes XY (or XZ).
"""

from __future__ import annotations

import argparse
import math

from twin.stage.controller import StageController, StageStatus


def _print_status(st: StageStatus) -> None:
    print(f"state     {st.state}" + (f":{st.substate}" if st.substate is not None else ""))
    print(f"x         {st.x_m * 1000.0:+.3f} mm from the bench centre (machine {st.x_mm:.3f} mm)")
    yaw = math.degrees(st.yaw_rad)
    print(f"yaw       {yaw:+.4f} deg from the reference (machine {st.yaw_deg:.4f} deg)")
    print(f"limits    {st.limits or 'none hit'}")


def run(args: argparse.Namespace) -> int:
    axes = args.axes.upper()
    if len(axes) != 2:
        raise SystemExit("aimbench stage: error: --axes takes two letters, e.g. XA or XY")
    with StageController(args.port, axis_letters=(axes[0], axes[1])) as stage:
        if args.action == "status":
            _print_status(stage.status())
        elif args.action == "home":
            _print_status(stage.home(timeout=args.timeout))
        elif args.action == "move":
            st = stage.status()
            x_m = st.x_m if args.x_mm is None else args.x_mm / 1000.0
            yaw = st.yaw_rad if args.yaw_deg is None else math.radians(args.yaw_deg)
            stage.move_to(x_m=x_m, yaw_rad=yaw, wait=True, timeout=args.timeout)
            _print_status(stage.status())
        elif args.action == "settings":
            for number, value in sorted(stage.settings().items()):
                print(f"${number}={value:g}")
    return 0


def register(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser("stage", help="status, home, move or settings of the stage controller")
    p.add_argument("--port", required=True,
                   help="serial port or pyserial URL (/dev/ttyACM0, the pty of `aimbench hil`)")
    p.add_argument("--axes", default="XA",
                   help="letters of the linear and rotary axes (XA; XY for a stock grbl-Mega)")
    p.add_argument("--timeout", type=float, default=120.0, help="seconds to wait for arrival")
    actions = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    actions.add_parser("status", help="state and position")
    actions.add_parser("home", help="run the homing cycle ($H)")
    mv = actions.add_parser("move", help="move to a position relative to the bench reference")
    mv.add_argument("--x-mm", type=float, default=None, help="x from the bench centre, mm")
    mv.add_argument("--yaw-deg", type=float, default=None, help="yaw from the reference, deg")
    actions.add_parser("settings", help="list the controller's settings ($$)")
    p.set_defaults(func=run)
    return p
