"""`aimbench hil`: build and run the stage firmware in simavr (hardware in the loop).

The first line printed is the pty to open, like a real board's /dev/ttyACM0:

    aimbench hil                       # prints e.g. /dev/pts/3, runs until Ctrl-C
    aimbench stage --port /dev/pts/3 home

With --watch it then prints the stage positions observed on the STEP/DIR pins twice a second.
"""

from __future__ import annotations

import argparse
import math
import sys
import time

from twin.stage.hil import SimavrHarness


def run(args: argparse.Namespace) -> int:
    with SimavrHarness(start_x_mm=args.x_start_mm, start_a_deg=args.a_start_deg,
                       pace=not args.no_pace) as hil:
        print(hil.pty_path, flush=True)
        print(f"simavr running bench_fw on {hil.pty_path} (log {hil.log_path}); Ctrl-C stops it",
              file=sys.stderr)
        while hil.running():
            time.sleep(0.5)
            if args.watch:
                p = hil.positions()
                print(f"t={p.sim_time_s:9.3f} s  x={p.x_steps:7d} steps ({p.x_m * 1000:+8.3f} mm)  "
                      f"a={p.a_steps:7d} steps ({math.degrees(p.yaw_rad):+8.3f} deg)  "
                      f"limits={'X' if p.limits[0] else '-'}{'A' if p.limits[1] else '-'}",
                      flush=True)
    print("aimbench hil: the harness stopped", file=sys.stderr)
    return 1


def register(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser("hil", help="run the stage firmware in simavr; prints the pty to open")
    p.add_argument("--x-start-mm", type=float, default=20.0,
                   help="where the linear stage stands at power-up, mm from home")
    p.add_argument("--a-start-deg", type=float, default=10.0,
                   help="where the rotary stage stands at power-up, deg from home")
    p.add_argument("--no-pace", action="store_true",
                   help="run simavr free (about 4x real time); host timeouts then mislead")
    p.add_argument("--watch", action="store_true",
                   help="print the observed positions every 0.5 s")
    p.set_defaults(func=run)
    return p
