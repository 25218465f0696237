"""Screenshot of rerun's web viewer in headless Chromium (for docs/replay.png).

    .venv/bin/python tools/rerun_screenshot.py RECORDING.rrd docs/replay.png
    .venv/bin/python tools/rerun_screenshot.py "http://127.0.0.1:9090/?url=..." shot.png

Given an .rrd file, the tool hosts rerun's web viewer from the installed rerun-sdk
(`rerun.serve_web_viewer`, no internet needed) and the file itself over HTTP (with the CORS
header the viewer's fetch needs), and points the viewer at the file: the viewer downloads it
whole, which is much faster than streaming it over gRPC on a busy machine.

Chromium's own ``--screenshot`` fires at the page's load event, long before the viewer has
fetched its wasm, streamed the recording and drawn a frame. So this drives Chromium over the
DevTools protocol (a websocket; the `websockets` package is already in the venv): open the page,
wait until the canvas has been drawn and the page has been quiet for a while, then capture.
Chromium runs with SwiftShader (software WebGL) because a headless server has no GPU.

Reproduce the README's screenshot: see docs/replay.md.
"""

from __future__ import annotations

import argparse
import asyncio
import base64
import json
import shutil
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path

CHROMIUM_FLAGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    # Software WebGL: no GPU here. Without these the viewer reports "no WebGL".
    "--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
    "--hide-scrollbars", "--mute-audio",
]


async def _capture(ws_url: str, url: str, width: int, height: int, wait_s: float,
                   out: Path, quality: int | None, seek_end: bool = True,
                   settle_s: float = 20.0) -> None:
    import websockets

    # No keepalive pings: a busy software renderer can leave them unanswered for a minute.
    async with websockets.connect(ws_url, max_size=64 * 2**20, ping_interval=None) as ws:
        ids = iter(range(1, 10**6))

        async def call(method: str, **params: object) -> dict:
            i = next(ids)
            await ws.send(json.dumps({"id": i, "method": method, "params": params}))
            while True:
                msg = json.loads(await ws.recv())
                if msg.get("id") == i:
                    if "error" in msg:
                        raise RuntimeError(f"{method}: {msg['error']}")
                    return msg.get("result", {})

        await call("Emulation.setDeviceMetricsOverride", width=width, height=height,
                   deviceScaleFactor=1, mobile=False)
        await call("Page.enable")
        await call("Runtime.enable")
        await call("Page.navigate", url=url)
        t0 = time.monotonic()
        # Wait for the viewer's canvas, then give it time to stream and draw the recording.
        while time.monotonic() - t0 < 120:
            r = await call("Runtime.evaluate",
                           expression="document.querySelectorAll('canvas').length")
            if r.get("result", {}).get("value", 0):
                break
            await asyncio.sleep(0.5)
        else:
            raise RuntimeError("the viewer never created its canvas (no WebGL/WebGPU?)")
        await asyncio.sleep(wait_s)
        if seek_end:
            # A file plays from its first scan, and a software renderer plays slowly: click the
            # right end of the time panel's ruler (the bottom bar) to show the last scan.
            for kind in ("mousePressed", "mouseReleased"):
                await call("Input.dispatchMouseEvent", type=kind, x=int(width * 0.905),
                           y=height - 14, button="left", clickCount=1)
            await asyncio.sleep(settle_s)
        params: dict[str, object] = {"format": "jpeg" if quality else "png"}
        if quality:
            params["quality"] = quality
        shot = await call("Page.captureScreenshot", **params)
        out.write_bytes(base64.b64decode(shot["data"]))


def serve_file(path: Path, port: int) -> str:
    """Serve `path`'s folder over HTTP on 127.0.0.1:`port` (a daemon thread); its URL."""
    import functools
    import http.server
    import threading

    class Handler(http.server.SimpleHTTPRequestHandler):
        def end_headers(self) -> None:
            # The viewer runs on another port, i.e. another origin: it may fetch only with this.
            self.send_header("Access-Control-Allow-Origin", "*")
            super().end_headers()

        def log_message(self, *args: object) -> None:
            pass

    handler = functools.partial(Handler, directory=str(path.resolve().parent))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", port), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return f"http://127.0.0.1:{port}/{path.name}"


def viewer_url(rrd: Path, web_port: int = 9090, file_port: int = 9091) -> str:
    """Host the web viewer and `rrd`; the URL that opens the one on the other."""
    import urllib.parse

    import rerun as rr

    rr.serve_web_viewer(web_port=web_port, open_browser=False)
    file_url = serve_file(rrd, file_port)
    return f"http://127.0.0.1:{web_port}/?url={urllib.parse.quote(file_url, safe='')}"


def screenshot(url: str, out: Path, width: int = 1600, height: int = 900, wait_s: float = 25.0,
               port: int = 9333, quality: int | None = None, seek_end: bool = True) -> Path:
    """Open `url` in headless Chromium and save a screenshot of the page to `out`."""
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        raise SystemExit("no chromium: apt-get install -y chromium")
    with tempfile.TemporaryDirectory() as profile:
        proc = subprocess.Popen(
            [chromium, *CHROMIUM_FLAGS, f"--user-data-dir={profile}",
             f"--remote-debugging-port={port}", f"--window-size={width},{height}",
             "about:blank"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            ws_url = None
            for _ in range(100):
                try:
                    with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list") as r:
                        pages = [p for p in json.load(r) if p.get("type") == "page"]
                    if pages:
                        ws_url = pages[0]["webSocketDebuggerUrl"]
                        break
                except OSError:
                    pass
                time.sleep(0.2)
            if ws_url is None:
                raise SystemExit("chromium did not open its DevTools port")
            asyncio.run(_capture(ws_url, url, width, height, wait_s, out, quality, seek_end))
        finally:
            proc.terminate()
            proc.wait(timeout=20)
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("source", help="an .rrd file, or a web viewer URL (with ?url=...)")
    p.add_argument("out", type=Path, help="image to write (.png, or .jpg with --quality)")
    p.add_argument("--width", type=int, default=1600)
    p.add_argument("--height", type=int, default=900)
    p.add_argument("--wait", type=float, default=25.0,
                   help="seconds to let the viewer load and draw after its canvas appears")
    p.add_argument("--quality", type=int, help="JPEG quality (smaller file than PNG)")
    p.add_argument("--palette", type=int, metavar="N",
                   help="quantise the PNG to N colours (Pillow), a third of the size")
    p.add_argument("--no-seek-end", action="store_true",
                   help="leave the time cursor where the viewer put it (default: click the end "
                        "of the time panel, to show the last scan)")
    args = p.parse_args()
    url = args.source
    if not url.startswith("http"):
        url = viewer_url(Path(url))
    path = screenshot(url, args.out, args.width, args.height, args.wait,
                      quality=args.quality, seek_end=not args.no_seek_end)
    if args.palette:
        from PIL import Image

        Image.open(path).convert("RGB").quantize(colors=args.palette, dither=0).save(
            path, optimize=True)
    print(f"{path}: {path.stat().st_size // 1024} KiB")


if __name__ == "__main__":
    main()
