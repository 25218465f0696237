"""The line station (`aimbench station`): trigger to verdict over OPC UA, over the operator's
page and over the HTTP/JSON endpoint, against `aimbench inspect`'s 2 s goal.

    .venv/bin/python benchmarks/bench_station.py [--units 8] [--scans 10] [--work DIR]

Starts the station on the twin (source ``sim``, ``--scans`` scans a unit, no re-measure) on
free local ports and inspects ``--units`` units each way, one after the other:

- OPC UA: an asyncua client as the PLC (anonymous, as the station file allows here) writes
  PartId and Start; the time runs until it reads Done with its part's result;
- the page: Debian's chromium, headless, driven by Selenium: the unit id typed and Enter
  (as a barcode scanner does); the time runs until the page shows the unit's verdict;
- HTTP: POST /api/inspect, until the answer arrives.

Printed per path: the median and the worst wall time from the trigger to the verdict, the
station's own time for the inspection (scans, estimate, record: the record's total_s), the
path's overhead (the difference), the goal (2 s) and the ratio.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import select
import signal
import socket
import sqlite3
import statistics
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
GOAL_S = 2.0


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start(work: Path, scans: int) -> tuple[subprocess.Popen, int, int]:
    (work / "line.toml").write_text('name = "bench"\n[line.opcua]\nanonymous = true\n')
    web, opc = free_port(), free_port()
    env = {k: v for k, v in os.environ.items() if k != "PYTEST_CURRENT_TEST"}
    env["PYTHONPATH"] = str(REPO)
    proc = subprocess.Popen(
        [sys.executable, "-m", "scenarios.cli", "station", "--station", "line.toml", "--db",
         "line.sqlite", "--port", str(web), "--opcua-port", str(opc), "--scans", str(scans),
         "--max-scans", str(scans), "--no-board-view"], cwd=work, env=env,
        stdout=subprocess.PIPE, stderr=(work / "station.err").open("w"), text=True)
    ready, _, _ = select.select([proc.stdout], [], [], 300)
    if not ready or not proc.stdout.readline().startswith("station"):
        raise SystemExit("the station did not start: " + (work / "station.err").read_text())
    return proc, web, opc


def station_time(db: Path, unit: str) -> float:
    conn = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
    try:
        t = conn.execute("SELECT timings FROM inspection WHERE unit = ?", (unit,)).fetchone()[0]
    finally:
        conn.close()
    return float(json.loads(t)["total_s"])


async def over_opcua(port: int, units: list[str]) -> list[float]:
    from asyncua import Client, ua

    out = []
    async with Client(f"opc.tcp://127.0.0.1:{port}/aimbench/station", timeout=30) as client:
        idx = await client.get_namespace_index("urn:aimbench:line-station")
        n = {k: client.get_node(f"ns={idx};s=Station.{k}") for k in (
            "PartId", "Start", "Done", "ResultPartId", "Refused")}
        for unit in units:
            t0 = time.perf_counter()
            await n["PartId"].write_value(ua.Variant(unit, ua.VariantType.String))
            await n["Start"].write_value(ua.Variant(True, ua.VariantType.Boolean))
            while not (await n["Done"].read_value() and not await n["Start"].read_value()
                       and await n["ResultPartId"].read_value() == unit):
                await asyncio.sleep(0.005)
            out.append(time.perf_counter() - t0)
    return out


def over_page(web: int, units: list[str]) -> list[float]:
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys

    os.environ["SE_OFFLINE"] = "true"
    opts = webdriver.ChromeOptions()
    opts.binary_location = "/usr/bin/chromium"
    for flag in ("--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                 "--disable-background-networking", "--disable-component-update",
                 "--disable-sync"):
        opts.add_argument(flag)
    drv = webdriver.Chrome(service=Service("/usr/bin/chromedriver"), options=opts)
    out = []
    try:
        drv.get(f"http://127.0.0.1:{web}/")
        time.sleep(2.0)
        for unit in units:
            box = drv.find_element(By.CSS_SELECTOR, "input[aria-label^='unit id']")
            t0 = time.perf_counter()
            box.send_keys(unit + Keys.ENTER)
            while True:
                el = drv.find_element(By.ID, "verdict")
                if (el.get_attribute("data-unit") == unit and el.text in (
                        "PASS", "FAIL", "INCONCLUSIVE")):
                    break
                time.sleep(0.005)
            out.append(time.perf_counter() - t0)
    finally:
        drv.quit()
    return out


def over_http(web: int, units: list[str]) -> list[float]:
    out = []
    for unit in units:
        req = urllib.request.Request(f"http://127.0.0.1:{web}/api/inspect",
                                     data=json.dumps({"unit": unit}).encode(),
                                     headers={"Content-Type": "application/json"})
        t0 = time.perf_counter()
        with urllib.request.urlopen(req, timeout=120) as r:
            json.loads(r.read())
        out.append(time.perf_counter() - t0)
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--units", type=int, default=8, help="units per path (default 8)")
    p.add_argument("--scans", type=int, default=10, help="scans per unit (default 10)")
    p.add_argument("--work", type=Path, default=None, help="the station's folder (default: "
                                                           "a temporary one)")
    args = p.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="bench-station-"))
    work.mkdir(parents=True, exist_ok=True)
    proc, web, opc = start(work, args.scans)
    try:
        over_http(web, ["WARM-1"])  # the worker's first unit compiles and caches
        res = {}
        for name, fn in (("OPC UA (PLC)", lambda u: asyncio.run(over_opcua(opc, u))),
                         ("page (browser)", lambda u: over_page(web, u)),
                         ("HTTP/JSON (MES)", lambda u: over_http(web, u))):
            tag = name.split()[0].replace("/", "")
            units = [f"{tag}-{i:03d}" for i in range(args.units)]
            walls = fn(units)
            own = [station_time(work / "line.sqlite", u) for u in units]
            res[name] = (walls, own)
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=60)
    print(f"# trigger to verdict, {args.units} twin units per path, {args.scans} scans each "
          "(no re-measure)")
    print(f"{'path':<18}{'median s':>10}{'worst s':>9}{'station s':>11}{'overhead s':>12}"
          f"{'goal s':>8}{'ratio':>7}")
    for name, (walls, own) in res.items():
        med = statistics.median(walls)
        over = statistics.median(w - o for w, o in zip(walls, own, strict=True))
        print(f"{name:<18}{med:>10.2f}{max(walls):>9.2f}{statistics.median(own):>11.2f}"
              f"{over:>12.3f}{GOAL_S:>8.1f}{med / GOAL_S:>7.2f}")


if __name__ == "__main__":
    main()
