"""`aimbench stage`: drive the stage controller by hand (a real board or the simavr harness).

    aimbench stage --port /dev/ttyACM0 status
    aimbench stage --port /dev/ttyACM0 home
    aimbench stage --port /dev/ttyACM0 move --x-mm 5 --yaw-deg -10
    aimbench stage --port /dev/ttyACM0 settings

--x-mm and --yaw-deg are relative to the bench reference (x = 0 at the bench centre, yaw = 0
facing the board), like StageController.move_to; status prints both those and the machine
position. The driver finds the controller's axes itself (bench_fw: X and A; a stock grbl-Mega:
X and Y, where the bench wires the rotary stage) and says which it drives; --axes overrides.
`settings` prints each `$N=value` with its meaning and unit.
"""

from __future__ import annotations

import argparse
import math
from typing import TYPE_CHECKING

from scenarios import cliargs

# The driver (pyserial, numpy through its poses) and the progress display (tqdm) are imported
# by the functions that talk to the controller, not for the parser (issue 38).
if TYPE_CHECKING:
    from twin.stage.controller import StageController, StageStatus

#: The axis letters a Grbl controller may name (bench_fw drives X and A).
AXIS_LETTERS = "XYZABC"


def _print_status(st: StageStatus) -> None:
    print(f"state     {st.state}" + (f":{st.substate}" if st.substate is not None else ""))
    if st.position_known:
        print(f"x         {st.x_m * 1000.0:+.3f} mm from the bench centre "
              f"(machine {st.x_mm:.3f} mm)")
        yaw = math.degrees(st.yaw_rad)
        print(f"yaw       {yaw:+.4f} deg from the reference (machine {st.yaw_deg:.4f} deg)")
    else:
        print("position  not known: the controller is in Alarm (after power-up, a hard limit or a "
              "reset in motion); home it (aimbench stage --port P home)")
    print(f"limits    {st.limits or 'none hit'}")


def _print_settings(stage: StageController) -> None:
    from twin.stage import grbl

    letters = stage.mpos_axes
    rotary = stage.slot(1)  # the rotary stage's slot: its settings are in degrees
    units = ",".join("deg" if i == rotary else "mm" for i in range(len(letters)))
    for number, value in sorted(stage.settings().items()):
        meaning, unit = grbl.setting_meaning(number, letters, units)
        setting = f"${number}={value:g}"
        print(f"{setting:<14} {meaning}" + (f" ({unit})" if unit else ""))


def axes(text: str) -> tuple[str, str]:
    """``--axes``: two different Grbl axis letters (linear, rotary), e.g. XA."""
    letters = text.upper()
    if len(letters) != 2 or not set(letters) <= set(AXIS_LETTERS):
        raise argparse.ArgumentTypeError(f"{text!r}: give two Grbl axis letters of "
                                         f"{AXIS_LETTERS}, linear then rotary, e.g. XA or XY")
    if letters[0] == letters[1]:
        raise argparse.ArgumentTypeError(f"{text!r} names one axis twice; the linear and the "
                                         "rotary stage are two axes, e.g. XA or XY")
    return (letters[0], letters[1])


def run(args: argparse.Namespace) -> int:
    from scenarios.progress import StageMotion
    from twin.stage.controller import StageController

    letters = args.axes
    with StageController(args.port, axis_letters=letters) as stage:
        print(f"axes      {stage.axis_note}")
        if args.action == "status":
            _print_status(stage.status())
        elif args.action == "home":
            with StageMotion("homing") as shown:
                st = stage.home(timeout=args.timeout, on_status=shown)
            _print_status(st)
        elif args.action == "move":
            st = stage.status()
            x_m = st.x_m if args.x_mm is None else args.x_mm / 1000.0
            yaw = st.yaw_rad if args.yaw_deg is None else math.radians(args.yaw_deg)
            with StageMotion("moving") as shown:
                stage.move_to(x_m=x_m, yaw_rad=yaw, wait=True, timeout=args.timeout,
                              on_status=shown)
            _print_status(stage.status())
        elif args.action == "settings":
            _print_settings(stage)
    return 0


def register(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser("stage", help="status, home, move or settings of the stage controller")
    p.add_argument("--port", required=True,
                   help="serial port or pyserial URL (/dev/ttyACM0, the pty of `aimbench hil`)")
    p.add_argument("--axes", type=axes, default=None,
                   help="letters of the linear and rotary axes (default: found from the "
                        "controller, XA on bench_fw, XY on a stock grbl-Mega)")
    p.add_argument("--timeout", type=cliargs.positive_float, default=120.0,
                   help="seconds to wait for arrival")
    actions = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    actions.add_parser("status", help="state and position")
    actions.add_parser("home", help="run the homing cycle ($H)")
    mv = actions.add_parser("move", help="move to a position relative to the bench reference")
    mv.add_argument("--x-mm", type=cliargs.finite_float, default=None,
                   help="x from the bench centre, mm")
    mv.add_argument("--yaw-deg", type=cliargs.finite_float, default=None,
                   help="yaw from the reference, deg")
    actions.add_parser("settings", help="list the controller's settings ($$)")
    p.set_defaults(func=run)
    return p
