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
import time
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


# -- the station file: any float NaN or infinite (issue 37) -------------------------------------

def _float_leaves(value: object, path: tuple = ()) -> list[tuple]:
    """The paths of the floats of a station's dict (a tuple's element by its index)."""
    if isinstance(value, dict):
        return [p for k, v in value.items() for p in _float_leaves(v, (*path, k))]
    if isinstance(value, list | tuple):
        return [p for i, v in enumerate(value) for p in _float_leaves(v, (*path, i))]
    return [path] if isinstance(value, float) else []


def _station_doc() -> dict:
    from scenarios import station as stations

    doc = stations.Station().model_dump()
    doc["mount"]["nominal"] = stations.PoseMmDeg().model_dump()
    doc["board"]["pattern"] = {"squares": [4, 3], "square_mm": 100.0}
    for key in ("calibration_file", "range_calibration", "range_offset_std_mm"):
        doc["sensor"].pop(key)
    doc["stages"].pop("port")
    return stations.from_dict(doc).model_dump(exclude_none=True)


STATION_DOC = _station_doc()
STATION_FLOATS = _float_leaves(STATION_DOC)


def _set(doc: dict, path: tuple, value: float) -> None:
    *head, last = path
    node = doc
    for k in head:
        node = node[k]
    if isinstance(node, tuple):
        raise AssertionError("tuples are lists after the copy")
    node[last] = value


def _lists(value: object) -> object:
    if isinstance(value, dict):
        return {k: _lists(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_lists(v) for v in value]
    return value


@fuzz(100)
@given(st.lists(st.tuples(st.sampled_from(STATION_FLOATS),
                          st.one_of(st.sampled_from([math.nan, math.inf, -math.inf, 1e300,
                                                     -1e300, 0.0, -0.0]),
                                    st.floats(allow_nan=True, allow_infinity=True))),
                min_size=1, max_size=4))
def test_station_files_with_any_float(changes):
    """A station with a NaN or an infinity anywhere is refused naming the key; one accepted
    has only finite floats (a NaN mount angle hung the twin; an inspection stored x NaN)."""
    from scenarios import station as stations

    doc = _lists(STATION_DOC)
    for path, value in changes:
        _set(doc, path, value)
    with fuzz_input("station file floats"), tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "station.toml"
        path.write_text(tomli_w.dumps(doc), encoding="utf-8")
        try:
            station = stations.load(path)
        except stations.StationError as exc:
            text = str(exc)
            assert "\n" not in text and len(text) < 2000
            return
    assert all(math.isfinite(v) for v in _floats(station.model_dump()))
    assert np.isfinite(station.board_in_bench()).all()


def _floats(value: object) -> list[float]:
    if isinstance(value, dict):
        return [f for v in value.values() for f in _floats(v)]
    if isinstance(value, list | tuple):
        return [f for v in value for f in _floats(v)]
    return [value] if isinstance(value, float) else []


# -- ROS PointCloud2 layouts (issue 37) ----------------------------------------------------------

def _cloud_message(fields, point_step, width, height, row_step, n_bytes, bigendian):
    from twin.lidar.bags import CLOUD_TYPE, typestore

    store = typestore(True)
    Cloud2, Field = store.types[CLOUD_TYPE], store.types["sensor_msgs/msg/PointField"]
    Header, Time = store.types["std_msgs/msg/Header"], store.types["builtin_interfaces/msg/Time"]
    return Cloud2(header=Header(stamp=Time(sec=0, nanosec=0), frame_id="velodyne"),
                  height=height, width=width,
                  fields=[Field(name=n, offset=o, datatype=t, count=c) for n, o, t, c in fields],
                  is_bigendian=bigendian, point_step=point_step, row_step=row_step,
                  data=np.arange(n_bytes, dtype=np.uint64).astype(np.uint8), is_dense=True)


cloud_fields = st.lists(st.tuples(st.sampled_from(["x", "y", "z", "intensity", "ring", "time"]),
                                  st.integers(0, 40), st.integers(0, 9), st.integers(0, 2)),
                        max_size=8).map(lambda f: [("x", 0, 7, 1), ("y", 4, 7, 1),
                                                   ("z", 8, 7, 1), *f])


@fuzz(200)
@given(cloud_fields, st.integers(0, 48), st.integers(0, 6), st.integers(0, 4),
       st.integers(0, 400), st.integers(0, 600), st.booleans())
def test_point_cloud2_messages_of_any_layout(fields, point_step, width, height, row_step,
                                             n_bytes, bigendian):
    """A field past the point, a field twice, point_step 0, rows past the data: a `BagError`
    naming it (each was a traceback); a layout that holds together: every point read."""
    from twin.lidar.bags import BagError, cloud_records

    msg = _cloud_message(fields, point_step, width, height, row_step, n_bytes, bigendian)
    with fuzz_input("PointCloud2 layout"):
        try:
            rec = cloud_records(msg, "fuzzed")
        except BagError as exc:
            assert "\n" not in str(exc)
            return
    assert len(rec) == width * height and {"x", "y", "z"} <= set(rec.dtype.names)


# -- PCD headers (issue 37) ------------------------------------------------------------------------

def _small_pcd() -> bytes:
    from pypcd4 import PointCloud

    rng = np.random.default_rng(0)
    arrays = [rng.normal(size=50).astype(np.float32) for _ in range(3)]
    arrays.append(np.arange(50, dtype=np.uint16) % 16)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "small.pcd"
        PointCloud.from_points(arrays, ("x", "y", "z", "ring"),
                               (np.float32, np.float32, np.float32, np.uint16)).save(path)
        return path.read_bytes()


SMALL_PCD = _small_pcd()
PCD_HEADER, _, PCD_BODY = SMALL_PCD.partition(b"DATA binary\n")
PCD_KEYS = ("SIZE", "COUNT", "WIDTH", "HEIGHT", "POINTS", "TYPE", "FIELDS")


@fuzz(150)
@given(st.lists(st.tuples(st.sampled_from(PCD_KEYS),
                          st.lists(st.one_of(st.integers(-2, 2**40).map(str),
                                             st.sampled_from(["F", "U", "I", "x", "nan", ""])),
                                   max_size=5)), max_size=3),
       st.sampled_from(["binary", "ascii", "binary_compressed"]), st.integers(0, len(PCD_BODY)))
def test_pcd_files_with_hostile_headers(changes, data, keep):
    """Any header claim (COUNT 99999999, POINTS 2**40...) is checked against the file before
    anything is allocated: clouds, or a `CloudError`, quickly."""
    from twin.lidar.clouds import CloudError
    from twin.lidar.pcd import read_pcd

    lines = PCD_HEADER.decode().splitlines()
    for key, values in changes:
        lines = [f"{key} {' '.join(values)}" if ln.startswith(key + " ") else ln for ln in lines]
    text = "\n".join(lines).encode() + f"\nDATA {data}\n".encode() + PCD_BODY[:keep]
    with fuzz_input("PCD header"), tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "fuzzed.pcd"
        path.write_bytes(text)
        t0 = time.monotonic()
        try:
            clouds = read_pcd(path)
        except CloudError as exc:
            assert "\n" not in str(exc)
            clouds = []
        assert time.monotonic() - t0 < 5.0
    assert sum(len(c) for c in clouds) <= 50 * 200


# -- factory calibration files (issue 37) ----------------------------------------------------------

CAL_KEYS = ("laser_id", "rot_correction", "vert_correction", "vert_offset_correction",
            "horiz_offset_correction", "dist_correction")
hostile_values = st.one_of(
    st.sampled_from([math.nan, math.inf, 1e300, -1e300, -1, 0, 1.5, True, None, "", "abc",
                     [], [1], {}, {"a": 1}, 2**70]),
    st.floats(allow_nan=True, allow_infinity=True), st.integers(-2**40, 2**40), st.text(max_size=5))


def _cal_doc(n: int = 4) -> dict:
    return {"num_lasers": n, "distance_resolution": 0.002,
            "lasers": [{"laser_id": i, "rot_correction": 0.0,
                        "vert_correction": math.radians(-15 + 2 * i),
                        "vert_offset_correction": 0.01, "horiz_offset_correction": 0.0,
                        "dist_correction": 0.0} for i in range(n)]}


@fuzz(60)
@given(st.lists(st.tuples(st.integers(0, 3), st.sampled_from((*CAL_KEYS, "num_lasers",
                                                             "distance_resolution")),
                          hostile_values), min_size=1, max_size=4))
def test_calibration_files_with_wrong_types(changes):
    """A ROS calibration YAML with any value of any type, and the same as VeloView XML: a
    laser table with finite, bounded geometry, or one `CalibrationFileError` line."""
    import yaml

    from twin.lidar.calibration_file import (
        MAX_OFFSET_M,
        CalibrationFileError,
        parse_ros_yaml,
        parse_veloview_xml,
    )

    doc = _cal_doc()
    for i, key, value in changes:
        (doc if key in ("num_lasers", "distance_resolution") else doc["lasers"][i])[key] = value
    xml = ("<boost_serialization><DB><distLSB_>{}</distLSB_><points_>".format(
        doc["distance_resolution"] * 100 if isinstance(doc["distance_resolution"], float)
        else doc["distance_resolution"])
        + "".join(f"<item><px><id_>{e['laser_id']}</id_><rotCorrection_>{e['rot_correction']}"
                  f"</rotCorrection_><vertCorrection_>{e['vert_correction']}</vertCorrection_>"
                  f"<vertOffsetCorrection_>{e['vert_offset_correction']}"
                  "</vertOffsetCorrection_></px></item>" for e in doc["lasers"])
        + "</points_></DB></boost_serialization>")
    with fuzz_input("sensor calibration file"):
        for parse, text in ((parse_ros_yaml, yaml.safe_dump(doc)), (parse_veloview_xml, xml)):
            try:
                table, unit = parse(text, "fuzzed")
            except CalibrationFileError as exc:
                assert "\n" not in str(exc)
                continue
            for k in ("elevation", "vertical_offset", "azimuth_offset", "horizontal_offset"):
                assert np.isfinite(getattr(table, k)).all()
            assert np.abs(table.vertical_offset).max() <= MAX_OFFSET_M
            assert unit is None or 0 < unit <= 1.0
