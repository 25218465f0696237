"""`aimbench station` end to end: the real process on the twin, a real headless browser
(Debian's chromium and chromedriver, driven by Selenium; nothing downloaded), a real OPC UA
client as the line's PLC (asyncua, username over Basic256Sha256 SignAndEncrypt, its certificate
in the station's trust list), the JSON
endpoint, and a kill -9 mid-inspection. One scan per unit keeps the twin's share of CPU down.
"""

from __future__ import annotations

import asyncio
import json
import os
import select
import shutil
import signal
import socket
import sqlite3
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from scenarios.line import auth

REPO = Path(__file__).resolve().parents[1]
CHROMIUM, DRIVER = "/usr/bin/chromium", "/usr/bin/chromedriver"
PASSWORDS = {"eng": "eng-secret-1", "plc1": "plc-secret-1", "op": "op-secret-1"}
PARTS = 50

pytestmark = pytest.mark.slow


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def station_file(folder: Path) -> Path:
    role = {"eng": "engineer", "plc1": "plc", "op": "operator"}
    users = "".join(f'[[line.users]]\nname = "{n}"\nrole = "{role[n]}"\n'
                    f'password_scrypt = "{auth.hash_password(p)}"\n\n'
                    for n, p in PASSWORDS.items())
    path = folder / "line.toml"
    # A unit calibrated on the range bench (its common offset known, as the twin's is: 0): the
    # tests here are about the station's handshakes, and an uncalibrated unit's offset integral
    # (0.3 s a scan; tests/test_align_offsets.py and test_inspect.py hold it) would be most of
    # their time.
    path.write_text('name = "line-ci"\n\n[sensor]\nrange_offset_std_mm = 0\n\n'
                    '[line]\naddress = "127.0.0.1"\n\n'
                    '[line.opcua]\nanonymous = false\n\n' + users, encoding="utf-8")
    return path


class Station:
    """The station process, started and restarted on the same store and ports."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.toml = station_file(folder)
        self.db = folder / "line.sqlite"
        self.port, self.opc = free_port(), free_port()
        self.proc: subprocess.Popen | None = None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    @property
    def opc_url(self) -> str:
        return f"opc.tcp://127.0.0.1:{self.opc}/aimbench/station"

    def start(self, scans: int = 1) -> None:
        # NiceGUI takes a process with PYTEST_CURRENT_TEST for its own screen tests
        env = {k: v for k, v in os.environ.items() if k != "PYTEST_CURRENT_TEST"}
        env["PYTHONPATH"] = str(REPO)
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "scenarios.cli", "station", "--station", str(self.toml),
             "--db", str(self.db), "--port", str(self.port), "--opcua-port", str(self.opc),
             "--scans", str(scans), "--max-scans", str(scans), "--no-board-view"],
            cwd=self.folder, env=env, stdout=subprocess.PIPE,
            stderr=(self.folder / "station.err").open("a"), text=True)  # a pipe would fill up
        ready, _, _ = select.select([self.proc.stdout], [], [], 240)
        line = self.proc.stdout.readline() if ready else ""
        assert line.startswith("station line-ci: http://"), (
            line, (self.folder / "station.err").read_text()[-3000:])

    def kill9(self) -> None:
        """SIGKILL the station; its worker process must not outlive it."""
        children = [int(p.name) for p in Path("/proc").iterdir() if p.name.isdigit()
                    and _ppid(p) == self.proc.pid]
        assert children, "the station has no worker process"
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(timeout=30)
        wait(lambda: not any(Path(f"/proc/{c}").exists() and _ppid(Path(f"/proc/{c}")) != 0
                             and Path(f"/proc/{c}/stat").read_text().split()[2] != "Z"
                             for c in children), timeout=20)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()

    def rows(self, sql: str, params: tuple = ()) -> list[tuple]:
        conn = sqlite3.connect(f"file:{self.db}?mode=ro", uri=True, timeout=30)
        try:
            return conn.execute(sql, params).fetchall()
        finally:
            conn.close()

    def post(self, unit: str, user: str = "plc1") -> tuple[int, dict]:
        import base64

        req = urllib.request.Request(
            f"{self.url}/api/inspect", data=json.dumps({"unit": unit}).encode(),
            headers={"Content-Type": "application/json", "Authorization": "Basic " +
                     base64.b64encode(f"{user}:{PASSWORDS[user]}".encode()).decode()})
        try:
            with urllib.request.urlopen(req, timeout=120) as r:
                return r.status, json.loads(r.read())
        except urllib.error.HTTPError as e:
            return e.code, json.loads(e.read())


def _ppid(proc: Path) -> int:
    try:
        return int((proc / "stat").read_text().rsplit(")", 1)[1].split()[1])
    except (OSError, IndexError, ValueError):
        return 0


@pytest.fixture(scope="module")
def station(tmp_path_factory):
    st = Station(tmp_path_factory.mktemp("station"))
    st.start()
    yield st
    st.stop()


@pytest.fixture(scope="module")
def browser():
    if not (Path(CHROMIUM).exists() and Path(DRIVER).exists()):
        pytest.fail("Debian's chromium and chromium-driver are needed (tools/setup.sh test)")
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    os.environ["SE_OFFLINE"] = "true"  # Selenium Manager must not fetch a driver or browser
    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for flag in ("--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                 "--disable-background-networking", "--disable-component-update",
                 "--disable-sync", "--window-size=1400,1000"):
        opts.add_argument(flag)
    drv = webdriver.Chrome(service=Service(DRIVER), options=opts)
    drv.set_page_load_timeout(60)
    yield drv
    drv.quit()


def wait(cond, timeout: float = 60.0, every: float = 0.1):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        got = cond()
        if got:
            return got
        time.sleep(every)
    raise AssertionError(f"not within {timeout} s: {cond}")


def type_unit(browser, unit: str) -> None:
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys

    box = browser.find_element(By.CSS_SELECTOR, "input[aria-label^='unit id']")
    box.clear()
    box.send_keys(unit + Keys.ENTER)  # what a barcode scanner does


def verdict_of(browser) -> tuple[str, str, str]:
    from selenium.webdriver.common.by import By

    el = browser.find_element(By.ID, "verdict")
    return el.get_attribute("data-state"), el.get_attribute("data-unit"), el.text


# -- the operator's page and the engineer's ------------------------------------------------------

def test_the_page_inspects_a_scanned_unit_and_the_engineer_sees_the_charts(station, browser,
                                                                           tmp_path):
    from selenium.webdriver.common.by import By

    browser.get(station.url + "/")
    wait(lambda: browser.find_elements(By.ID, "verdict"))
    # everything the page loads comes from the station itself (no CDN: offline lines)
    srcs = browser.execute_script(
        "return [...document.querySelectorAll('script[src],link[href]')]"
        ".map(e => e.src || e.href).concat(performance.getEntriesByType('resource')"
        ".map(e => e.name))")
    assert srcs and all(s.startswith((station.url, "data:", "ws://127.0.0.1"))
                        for s in srcs), srcs
    for i in range(3):  # three units, so the engineer's charts have lines
        type_unit(browser, f"WEB-{i}")
        _, _, text = wait(lambda i=i: (v := verdict_of(browser))[0] == "done"
                          and v[1] == f"WEB-{i}" and v[2] in ("PASS", "FAIL", "INCONCLUSIVE")
                          and v)
        rec = station.rows("SELECT verdict, operator, software_version FROM inspection "
                           "WHERE unit = ?", (f"WEB-{i}",))
        assert len(rec) == 1 and rec[0][0].upper() == text and rec[0][2]
    axes = browser.find_element(By.ID, "axes").get_attribute("innerHTML")
    assert "<svg" in axes and "tilt_deg" in axes and "limit 1" in axes
    # the engineer's page wants a login; a wrong password is refused and logged
    browser.get(station.url + "/engineer")
    wait(lambda: browser.find_elements(By.CSS_SELECTOR, "input[aria-label='name']"))

    def login(name: str, pw: str) -> None:
        for label, val in (("name", name), ("password", pw)):
            el = browser.find_element(By.CSS_SELECTOR, f"input[aria-label='{label}']")
            el.clear()
            el.send_keys(val)
        browser.find_element(By.ID, "login-button").click()

    login("eng", "wrong")
    time.sleep(1.0)
    assert "/engineer" not in browser.current_url or browser.find_elements(By.ID,
                                                                           "login-button")
    login("op", PASSWORDS["op"])  # an operator is not an engineer
    time.sleep(1.5)
    browser.get(station.url + "/engineer")
    wait(lambda: browser.find_elements(By.ID, "login-button"))
    login("eng", PASSWORDS["eng"])
    wait(lambda: browser.find_elements(By.ID, "imr-tilt_deg"), timeout=60)
    wait(lambda: browser.find_elements(By.CSS_SELECTOR, "#imr-tilt_deg canvas"))
    assert browser.find_elements(By.ID, "capability")
    assert "sha256" in browser.find_element(By.ID, "station-hash").text
    audit = browser.find_element(By.ID, "audit").text
    assert "login refused" in audit and "login" in audit and "end" in audit
    shot = tmp_path / "engineer.png"
    browser.save_screenshot(str(shot))
    assert shot.stat().st_size > 20_000
    keep = os.environ.get("AIMBENCH_SCREENSHOTS")  # docs/: regenerate the kept pictures
    if keep:
        shutil.copy(shot, Path(keep) / "station-engineer.png")
        browser.get(station.url + "/")
        wait(lambda: verdict_of(browser)[0] == "done")
        time.sleep(1.0)
        browser.save_screenshot(str(Path(keep) / "station-operator.png"))
    acts = [r[0] for r in station.rows("SELECT action FROM audit")]
    assert "login refused" in acts and acts.count("start") == acts.count("end")


# -- the PLC over OPC UA, with the page triggering too ------------------------------------------

async def plc_client(station: Station, tmp: Path, user: str = "plc1",
                     password: str | None = None):
    from asyncua import Client
    from asyncua.crypto.cert_gen import setup_self_signed_certificate
    from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
    from cryptography.x509.oid import ExtendedKeyUsageOID

    cert, key = tmp / "plc-cert.der", tmp / "plc-key.pem"
    await setup_self_signed_certificate(key, cert, "urn:aimbench:test-plc", "localhost",
                                        [ExtendedKeyUsageOID.CLIENT_AUTH],
                                        {"commonName": "test plc"})
    # the engineer trusts this PLC: its certificate in the station's trust list
    # (tests/test_line_opcua.py shows an untrusted one refused)
    trust = station.db.parent / (station.db.stem + ".station") / "opcua-trusted"
    trust.mkdir(parents=True, exist_ok=True)
    shutil.copy(cert, trust)
    client = Client(station.opc_url, timeout=30)
    client.application_uri = "urn:aimbench:test-plc"
    client.set_user(user)
    client.set_password(PASSWORDS.get(user, "") if password is None else password)
    await client.set_security(SecurityPolicyBasic256Sha256, str(cert), str(key),
                              mode=__import__("asyncua").ua.MessageSecurityMode.SignAndEncrypt)
    await client.connect()
    return client


async def nodes(client) -> dict:
    idx = await client.get_namespace_index("urn:aimbench:line-station")
    names = ("PartId", "Start", "State", "Busy", "Done", "Error", "Refused", "Message",
             "ResultPartId", "Verdict", "RecordId", "ResultCounter")
    out = {n: client.get_node(f"ns={idx};s=Station.{n}") for n in names}
    out["tilt"] = client.get_node(f"ns={idx};s=Station.Axes.tilt_deg.Value")
    out["tiltU"] = client.get_node(f"ns={idx};s=Station.Axes.tilt_deg.Uncertainty")
    out["tiltV"] = client.get_node(f"ns={idx};s=Station.Axes.tilt_deg.Verdict")
    return out


async def plc_inspect(n: dict, part: str, timeout: float = 120) -> dict:
    """The PLC's handshake for one part: PartId, Start; retried while the station is busy
    with someone else's unit; returns what the PLC read back."""
    from asyncua import ua

    end = time.monotonic() + timeout
    while time.monotonic() < end:
        while await n["Busy"].read_value():
            await asyncio.sleep(0.05)
        await n["PartId"].write_value(ua.Variant(part, ua.VariantType.String))
        await n["Start"].write_value(ua.Variant(True, ua.VariantType.Boolean))
        ours = False  # seen Busy with our part: an Error from now on is this part's
        while time.monotonic() < end:
            await asyncio.sleep(0.02)
            if await n["Start"].read_value():
                continue  # not taken yet
            ours = ours or await n["Busy"].read_value()
            if await n["Refused"].read_value():
                break  # the station was busy with the page's unit: try again
            if await n["Done"].read_value() and await n["ResultPartId"].read_value() == part:
                return {"verdict": await n["Verdict"].read_value(),
                        "record": await n["RecordId"].read_value(),
                        "tilt": await n["tilt"].read_value(),
                        "tiltU": await n["tiltU"].read_value(),
                        "tiltV": await n["tiltV"].read_value()}
            if ours and await n["Error"].read_value() and not await n["Busy"].read_value():
                raise AssertionError(await n["Message"].read_value())
    raise AssertionError(f"{part}: no result within {timeout} s")


def test_fifty_parts_over_opc_ua_while_the_page_triggers_too(station, browser, tmp_path):
    from selenium.webdriver.common.by import By

    browser.get(station.url + "/")
    wait(lambda: browser.find_elements(By.ID, "verdict"))
    stop = threading.Event()
    typed: list[str] = []

    def operator() -> None:  # the page, typing units while the PLC runs its parts
        i = 0
        while not stop.is_set():
            unit = f"PAGE-{i:03d}"
            type_unit(browser, unit)
            typed.append(unit)
            # done with it once it has a record or its refusal is logged
            wait(lambda u=unit: station.rows("SELECT 1 FROM inspection WHERE unit = ?", (u,))
                 or station.rows("SELECT 1 FROM audit WHERE action = 'refused' AND "
                                 "json_extract(detail, '$.unit') = ?", (u,)), timeout=120)
            i += 1
            time.sleep(0.3)

    async def plc() -> dict[str, dict]:
        from asyncua import Client

        # no anonymous session, no wrong password

        anon = Client(station.opc_url, timeout=10)
        with pytest.raises(Exception):  # noqa: B017 (asyncua raises its own several kinds)
            await anon.connect()
            await (await nodes(anon))["Start"].write_value(True)
        with pytest.raises(Exception):  # noqa: B017
            await plc_client(station, tmp_path, "plc1", "not-the-password")
        client = await plc_client(station, tmp_path)
        try:
            n = await nodes(client)
            got = {}
            for i in range(PARTS):
                part = f"PLC-{i:03d}"
                got[part] = await plc_inspect(n, part)
            return got
        finally:
            await client.disconnect()

    t = threading.Thread(target=operator, daemon=True)
    t.start()
    try:
        got = asyncio.run(plc())
    finally:
        stop.set()
        t.join(timeout=180)
    rows = station.rows("SELECT unit, id, verdict, err_tilt, u_tilt, coverage_k, verdict_tilt "
                        "FROM inspection")
    by_unit: dict[str, list] = {}
    for r in rows:
        by_unit.setdefault(r[0], []).append(r)
    # one record per PLC part, none lost or doubled, and what the PLC read is the record
    for part, seen in got.items():
        assert len(by_unit.get(part, [])) == 1, part
        unit, rid, verdict, err, u, k, vt = by_unit[part][0]
        assert seen["record"] == rid and seen["verdict"] == verdict and seen["tiltV"] == vt
        assert seen["tilt"] == pytest.approx(err * 57.29577951308232, rel=1e-9)
        assert seen["tiltU"] == pytest.approx(u * k * 57.29577951308232, rel=1e-9)
    # the page's units: each has one record, or was refused (busy) and has none
    assert typed
    for unit in typed:
        refused = station.rows("SELECT 1 FROM audit WHERE action='refused' AND "
                               "json_extract(detail, '$.unit') = ?", (unit,))
        assert len(by_unit.get(unit, [])) == (0 if refused else 1), unit
    assert all(len(v) == 1 for v in by_unit.values())


def test_busy_refusal_then_kill_9_mid_inspection_the_plc_sees_the_error_and_goes_on(
        station, tmp_path):
    """Ten scans a unit here, so that an inspection lasts long enough to be interrupted."""
    from asyncua import ua

    station.stop()
    station.start(scans=10)

    async def trigger_and_wait_busy(part: str, client=None):
        client = client or await plc_client(station, tmp_path)
        n = await nodes(client)
        while await n["Busy"].read_value():
            await asyncio.sleep(0.05)
        await n["PartId"].write_value(ua.Variant(part, ua.VariantType.String))
        await n["Start"].write_value(ua.Variant(True, ua.VariantType.Boolean))
        while not await n["Busy"].read_value():
            await asyncio.sleep(0.005)
        return client, n

    async def busy() -> None:
        client, n = await trigger_and_wait_busy("BUSY-1")
        try:
            # the MES and the PLC itself, while BUSY-1 is scanned: both refused, clearly
            code, body = await asyncio.to_thread(station.post, "MES-1")
            assert code == 409 and body["error"] == "busy"
            assert body["message"].startswith("busy: inspecting unit BUSY-1")
            await n["PartId"].write_value(ua.Variant("PLC-2", ua.VariantType.String))
            await n["Start"].write_value(ua.Variant(True, ua.VariantType.Boolean))
            await asyncio.to_thread(wait, lambda: station.rows(
                "SELECT 1 FROM audit WHERE action='refused' AND json_extract(detail, '$.unit')"
                " = 'PLC-2'"), 30, 0.02)
            assert "BUSY-1" in await n["Message"].read_value()
            assert await n["Refused"].read_value() is True
            seen = await plc_inspect(n, "BUSY-1")  # already running: its result arrives
            assert seen["verdict"] in ("pass", "fail", "inconclusive")
        finally:
            await client.disconnect()

    asyncio.run(busy())
    assert station.rows("SELECT COUNT(*) FROM inspection WHERE unit IN ('MES-1', 'PLC-2')"
                        ) == [(0,)]
    before = station.rows("SELECT COUNT(*) FROM inspection")[0][0]
    asyncio.run(trigger_and_wait_busy("KILLED-1"))
    station.kill9()  # mid-scan: the PLC's session is cut with the station
    assert station.rows("PRAGMA integrity_check") == [("ok",)]
    assert station.rows("SELECT COUNT(*) FROM inspection WHERE unit='KILLED-1'")[0][0] == 0
    station.start(scans=1)

    async def after() -> None:
        client = await plc_client(station, tmp_path)
        try:
            n = await nodes(client)
            assert await n["Error"].read_value() is True
            assert await n["State"].read_value() == "error"
            assert "KILLED-1" in await n["Message"].read_value()
            seen = await plc_inspect(n, "KILLED-1")
            assert await n["Error"].read_value() is False
            rec = station.rows("SELECT id, verdict FROM inspection WHERE unit='KILLED-1'")
            assert rec == [(seen["record"], seen["verdict"])]
        finally:
            await client.disconnect()

    asyncio.run(after())
    assert station.rows("SELECT COUNT(*) FROM inspection")[0][0] == before + 1
    assert station.rows("SELECT COUNT(*) FROM audit WHERE action = 'recovered'")[0][0] == 1
