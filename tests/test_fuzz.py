"""Property-based bad input beyond the packet decoder (tests/test_decode_fuzz.py): pcapng files,
the data path from a capture to scans, the serial line of the stage controller (its parser, and
the driver on a real pty answered with fuzzed bytes), and TOML plan files.

Each property feeds what a hostile user, a damaged file or a noisy cable could give and accepts
only the documented outcome: a result, or the component's own `AimbenchError` (one clear line
at the command line). Anything else is a crash. Budgets: tests/fuzzing.py (bounded and
derandomized in CI; tools/fuzz.py runs the long, seeded one).
"""

from __future__ import annotations

import math
import os
import tempfile
import threading
import tomllib
import warnings
from pathlib import Path

import numpy as np
import tomli_w
from conftest import DATA_DIR
from fuzzing import fuzz, fuzz_input
from hypothesis import assume, given
from hypothesis import strategies as st

from scenarios import plans
from scenarios.store import Store
from twin.core.errors import AimbenchError
from twin.lidar.capture import PcapSource, read_capture
from twin.lidar.packets import ProductIdWarning
from twin.lidar.pcap import CaptureFormatError, PcapWriter, ipv4_udp_frame, read_pcap
from twin.lidar.scans import ScanAssembler
from twin.stage import grbl
from twin.stage.controller import StageController

REAL = [r.payload for r in read_pcap(DATA_DIR / "vlp16-strongest-10hz.pcap")]
#: Block azimuth of block b of a data packet: bytes 2..3 of its 100-byte block (little endian).
AZIMUTH_AT = [b * 100 + 2 for b in range(12)]


def _flip(data: bytes, flips: list[tuple[int, int]], keep: int | None = None) -> bytes:
    out = bytearray(data)
    for pos, value in flips:
        out[pos % len(out)] = value
    return bytes(out[:keep] if keep is not None else out)


# -- pcapng files ------------------------------------------------------------------------------

def _small_pcapng() -> bytes:
    from pcapng import FileWriter, blocks

    with tempfile.TemporaryDirectory() as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # python-pcapng writing options
        path = Path(tmp) / "small.pcapng"
        shb = blocks.SectionHeader(options={"shb_userappl": "aimbench fuzz"})
        shb.new_member(blocks.InterfaceDescription, link_type=1,
                       options={"if_tsresol": b"\x06"})
        with path.open("wb") as f:
            w = FileWriter(f, shb)
            for i, p in enumerate(REAL[:4]):
                epb = shb.new_member(blocks.EnhancedPacket)
                epb.interface_id = 0
                epb.timestamp_high, epb.timestamp_low = divmod(1_000_000 + 1000 * i, 2**32)
                epb.packet_data = ipv4_udp_frame(p)
                w.write_block(epb)
        return path.read_bytes()


SMALL_PCAPNG = _small_pcapng()


@fuzz(80)
@given(st.lists(st.tuples(st.integers(0, len(SMALL_PCAPNG) - 1), st.integers(0, 255)),
                max_size=12),
       st.integers(0, len(SMALL_PCAPNG)))
def test_mutated_pcapng_files(flips, keep):
    data = _flip(SMALL_PCAPNG, flips, keep)
    with fuzz_input("pcapng file"), tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "fuzzed.pcapng"
        path.write_bytes(data)
        try:
            reader = read_pcap(path)
            records = list(reader)
        except CaptureFormatError:
            return
    assert reader.stats.udp == len(records)
    assert reader.stats.records == reader.stats.udp + reader.stats.n_skipped


# -- the data path: a capture to scans ----------------------------------------------------------

def _capture(payloads: list[bytes], path: Path) -> None:
    with PcapWriter(path) as w:
        for i, p in enumerate(payloads):
            w.write_udp(p, 1.0 + i * 1.327e-3)


def _scans_of(payloads: list[bytes]) -> list:
    """What `aimbench info`/`decode`/`estimate` do with a capture: read it, decode, assemble."""
    with tempfile.TemporaryDirectory() as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore", ProductIdWarning)
        path = Path(tmp) / "fuzzed.pcap"
        _capture(payloads, path)
        try:
            return read_capture(PcapSource(path), keep_scans=True).scans
        except AimbenchError:
            return []


azimuth_hits = st.lists(st.tuples(st.integers(0, len(REAL) - 1), st.sampled_from(AZIMUTH_AT),
                                  st.integers(0, 65535)), max_size=4)
byte_flips = st.lists(st.tuples(st.integers(0, len(REAL) - 1), st.integers(0, 1205),
                                st.integers(0, 255)), max_size=6)


@fuzz(40)
@given(azimuth_hits, byte_flips, st.integers(10, len(REAL)))
def test_mutated_captures_through_the_data_path(azimuths, flips, n):
    payloads = [bytearray(p) for p in REAL[:n]]
    for j, at, value in azimuths:
        if j < n:
            payloads[j][at:at + 2] = value.to_bytes(2, "little")
    for j, pos, value in flips:
        if j < n:
            payloads[j][pos] = value
    with fuzz_input("capture through the data path"):
        scans = _scans_of([bytes(p) for p in payloads])
    for scan in scans:
        assert np.isfinite(scan.xyz).all()
        assert ((scan.azimuth >= 0) & (scan.azimuth < 2 * np.pi)).all()


def test_two_corrupted_block_azimuths_do_not_crash_the_assembler():
    """Found by the fuzz suite: two block azimuths overwritten (107.17 deg in packet 41's
    block 0, 233.99 deg in packet 21's block 8) in the first 50 packets of the real capture
    made `ScanAssembler._make_scan` raise IndexError ('index 0 is out of bounds'); fixed with
    issue 19 (twin/lidar/scans.py)."""
    payloads = [bytearray(p) for p in REAL[:50]]
    for j, block, value in ((41, 0, 10717), (21, 8, 23399)):
        payloads[j][AZIMUTH_AT[block]:AZIMUTH_AT[block] + 2] = value.to_bytes(2, "little")
    asm = ScanAssembler(model="VLP-16")
    for p in payloads:
        asm.push(bytes(p))
    asm.finish()


# -- the serial line of the stage controller ----------------------------------------------------

GRBL_LINES = [b"Grbl 1.1h ['$' for help]", b"<Idle|MPos:55.000,32.000|FS:0,0>",
              b"<Run|MPos:1.000,2.000,0.000|FS:100,0|Pn:XA>", b"$110=4400.000", b"$130=100.000",
              b"ok", b"error:3", b"ALARM:1", b"[MSG:Reset to continue]",
              b"<Alarm|WPos:1,2|WCO:0,0>"]
serial_line = st.one_of(
    st.binary(max_size=80),
    st.tuples(st.sampled_from(GRBL_LINES),
              st.lists(st.tuples(st.integers(0, 79), st.integers(0, 255)), max_size=4)
              ).map(lambda t: _flip(t[0], t[1])),
    st.sampled_from(GRBL_LINES))


@fuzz(300)
@given(serial_line)
def test_grbl_parser_on_any_line(raw):
    line = raw.decode("ascii", "replace")
    with fuzz_input("Grbl line parser"):
        for parse in (grbl.banner_version, grbl.error_code, grbl.alarm_code, grbl.parse_setting):
            parse(line)  # these answer None for what is not theirs, never raise
        try:
            st_ = grbl.parse_status(line)
        except ValueError:
            return
    assert st_.mpos and all(isinstance(v, float) for v in st_.mpos)


class _FuzzedGrbl:
    """The far end of a real pty: answers every write of the driver with the next fuzzed
    chunk. (Nothing before the first write: opening the port flushes what is waiting.)"""

    def __init__(self, chunks: list[bytes]) -> None:
        self.master, slave = os.openpty()
        self.path = os.ttyname(slave)
        self._slave = slave
        self.chunks = list(chunks)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        import select

        while not self._stop.is_set():
            ready, _, _ = select.select([self.master], [], [], 0.02)
            if not ready:
                continue
            try:
                os.read(self.master, 4096)
            except OSError:
                return
            if self.chunks:
                os.write(self.master, self.chunks.pop(0))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        os.close(self.master)
        os.close(self._slave)


chunk = st.lists(serial_line, max_size=4).map(lambda lines: b"".join(x + b"\r\n" for x in lines))


#: A handshake the driver accepts (a status report for its first "?", then a $$ listing), so
#: that the fuzzed bytes after it reach status reports, settings and positions.
HANDSHAKE = [b"<Idle|MPos:1.000,2.000|FS:0,0>\r\n", b"$110=4400.000\r\n$130=100.000\r\nok\r\n"]


@fuzz(15)
@given(st.booleans(), st.lists(chunk, max_size=6))
def test_stage_driver_on_a_pty_answered_with_fuzzed_bytes(handshake, chunks):
    if handshake:
        chunks = [*HANDSHAKE, *chunks]
    far = _FuzzedGrbl(chunks)
    ctl = StageController(far.path, reply_timeout_s=0.1, boot_timeout_s=0.1, hold_dtr=False)
    try:
        with fuzz_input("stage driver on a pty"):
            try:
                ctl.connect()
                ctl.status()
                ctl.settings()
                ctl.position()
            except AimbenchError:
                pass
    finally:
        ctl.close()
        far.close()


# -- TOML plan files ---------------------------------------------------------------------------

numbers = st.one_of(st.integers(-10**20, 10**20), st.floats(allow_nan=True, allow_infinity=True),
                    st.sampled_from([0, 1, -1, 1e-9, 1e9, 2**63, -2**63]))
scalars = st.one_of(numbers, st.text(max_size=8), st.booleans())
axis = st.one_of(scalars, st.lists(numbers, max_size=5),
                 st.fixed_dictionaries({}, optional={k: scalars for k in ("start", "stop",
                                                                            "step", "extra")}))
mount = st.dictionaries(st.sampled_from([*plans.MOUNT_KEYS, "pitch"]), scalars, max_size=5)
reference = st.fixed_dictionaries({}, optional={"yaw_deg": axis, "x_mm": axis, "mount": mount,
                                                "label": scalars, "speed": scalars})
plan_doc = st.fixed_dictionaries({}, optional={
    "name": scalars, "scans": st.one_of(st.integers(-5, 10**12), scalars), "method": scalars,
    "seed": scalars, "yaw_deg": axis, "x_mm": axis, "mount": st.one_of(mount, scalars),
    "reference": st.one_of(st.lists(reference, max_size=4), scalars), "colour": scalars})


def _plan_or_error(text: str) -> plans.Plan | None:
    """`plans.from_toml` on `text` in a file: the plan, or None after its own error."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "plan.toml"
        path.write_bytes(text.encode("utf-8", "surrogatepass"))
        try:
            return plans.from_toml(path)
        except plans.PlanError:
            return None


def _accepted_plan_is_sound(plan: plans.Plan) -> None:
    """A plan that was accepted can be run: bounded, finite, and the store takes it."""
    assert 1 <= len(plan) <= plans.MAX_REFERENCES and 1 <= plan.scans <= plans.MAX_SCANS
    for r in plan.references:
        assert math.isfinite(r.yaw_rad) and math.isfinite(r.x_m)
        assert all(math.isfinite(v) for v in (r.mount or {}).values())
    with tempfile.TemporaryDirectory() as tmp:
        Store.create(Path(tmp) / "run", plan).close()


@fuzz(120)
@given(plan_doc)
def test_random_plan_files(doc):
    try:
        text = tomli_w.dumps(doc)
    except (TypeError, ValueError):
        assume(False)  # not a document TOML can hold
    with fuzz_input("TOML plan file"):
        plan = _plan_or_error(text)
        if plan is not None:
            _accepted_plan_is_sound(plan)


VALID_PLANS = [
    'name = "fine"\nscans = 2\nmethod = "paper"\nseed = 3\n'
    'yaw_deg = { start = -2, stop = 2, step = 0.5 }\nx_mm = 0\n[mount]\ntilt_deg = 0.5\n',
    'scans = 1\n[[reference]]\nyaw_deg = 2\nx_mm = -5\nlabel = "left"\n'
    '[[reference]]\nyaw_deg = -2\n[reference.mount]\nroll_deg = 1.0\n',
]


@fuzz(150)
@given(st.sampled_from(VALID_PLANS),
       st.lists(st.tuples(st.integers(0, 200), st.integers(0, 127)), max_size=6),
       st.integers(0, 200))
def test_mutated_plan_files(text, flips, keep):
    data = _flip(text.encode(), flips, keep if keep < len(text) else None)
    with fuzz_input("TOML plan file (mutated text)"):
        plan = _plan_or_error(data.decode("ascii", "replace"))
        if plan is not None:
            _accepted_plan_is_sound(plan)


def test_the_valid_plans_parse():
    """The seeds of the mutations are themselves accepted (else the property tests nothing)."""
    for text in VALID_PLANS:
        assert tomllib.loads(text)
        plan = _plan_or_error(text)
        assert plan is not None and len(plan) >= 2
