"""A unit's factory calibration file as a `LaserTable`: VeloView's XML or the ROS driver's YAML.

Velodyne ships each sensor with a calibration of its own lasers (VeloView's ``db.xml`` format);
the ROS velodyne driver's ``gen_calibration.py`` converts it to YAML, and both are common. Either
overrides the model's nominal table (`twin.core.sensors`) when decoding that unit's packets.

Not to be confused with aimbench's own per-laser *range* calibration (`align.calibration`,
``--calibration``), which it measures on the bench.

The two formats (as gen_calibration.py converts one into the other):

- XML: ``DB/points_/item/px`` per laser with ``id_``, ``rotCorrection_`` and ``vertCorrection_``
  in degrees, ``vertOffsetCorrection_``, ``horizOffsetCorrection_``, ``distCorrection_`` in cm;
  ``DB/enabled_`` flags; ``DB/distLSB_`` the distance unit in cm.
- YAML: ``lasers`` with ``laser_id``, ``rot_correction``, ``vert_correction`` (rad),
  ``vert_offset_correction``, ``horiz_offset_correction``, ``dist_correction`` (m);
  ``distance_resolution`` (m); ``num_lasers``.

Signs: ``rot_correction`` is subtracted from the azimuth (the driver's rawdata.cc: cos(a - rc)),
so a beam's azimuth offset in aimbench's clockwise convention is ``-rot_correction``. Per-laser
distance corrections (the HDL-64E's two-point calibration) are not modelled: a file with any is
refused rather than decoded wrongly.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ElementTree
from pathlib import Path

import numpy as np
import yaml

from twin.core.errors import AimbenchError
from twin.core.lasers import LaserTable

CM = 0.01  # m per cm (VeloView's unit)
#: Largest vertical or horizontal offset of a laser's origin a file may give, m: Velodyne's are
#: a few cm; 1e300 (issue 37) made every point infinite downstream.
MAX_OFFSET_M = 0.5
#: Largest distance unit, in the file's unit (m in the YAML, cm in the XML): theirs is 0.002 m.
MAX_LSB = 1.0


class CalibrationFileError(AimbenchError):
    """A sensor calibration file that cannot be read as a laser table."""


def read_calibration_file(path: str | Path) -> tuple[LaserTable, float | None]:
    """The laser table of a VeloView XML or ROS YAML calibration file, and its distance unit
    (m, None if the file gives none). Raises `CalibrationFileError` naming what is wrong."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise CalibrationFileError(f"cannot read the sensor calibration file {path} "
                                   f"({exc.strerror})") from None
    if text.lstrip().startswith("<"):
        return parse_veloview_xml(text, path.name)
    return parse_ros_yaml(text, path.name)


def parse_ros_yaml(text: str, name: str = "calibration") -> tuple[LaserTable, float | None]:
    """The ROS velodyne driver's calibration YAML as a laser table and distance unit."""
    try:
        doc = yaml.safe_load(text)
    except RecursionError:
        raise CalibrationFileError(f"{name}: lists or mappings nested too deep: not a ROS "
                                   "velodyne calibration") from None
    except yaml.YAMLError as exc:
        raise CalibrationFileError(
            f"{name}: not a YAML file ({exc.__class__.__name__}); a sensor calibration is "
            "VeloView XML or ROS driver YAML") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("lasers"), list):
        raise CalibrationFileError(f"{name}: no 'lasers' list: not a ROS velodyne calibration")
    rows = []
    for entry in doc["lasers"]:
        if not isinstance(entry, dict):
            raise CalibrationFileError(f"{name}: a 'lasers' entry is not a mapping")
        rows.append({
            "id": entry.get("laser_id"),
            "rot": entry.get("rot_correction", 0.0),
            "vert": entry.get("vert_correction"),
            "vert_offset": entry.get("vert_offset_correction", 0.0),
            "horiz_offset": entry.get("horiz_offset_correction", 0.0),
            "dist": [entry.get(k, 0.0) for k in ("dist_correction", "dist_correction_x",
                                                  "dist_correction_y")],
        })
    unit = doc.get("distance_resolution")
    table = _table(rows, name, _count(doc.get("num_lasers", len(rows)), "num_lasers", name))
    return table, None if unit is None else _resolution(unit, "distance_resolution", name)


def parse_veloview_xml(text: str, name: str = "calibration") -> tuple[LaserTable, float | None]:
    """VeloView's calibration XML (``db.xml`` layout) as a laser table and distance unit."""
    try:
        root = ElementTree.fromstring(text)
    except ElementTree.ParseError as exc:
        raise CalibrationFileError(f"{name}: not well-formed XML ({exc})") from None
    db = root if root.tag == "DB" else root.find("DB")
    points = None if db is None else db.find("points_")
    if points is None:
        raise CalibrationFileError(f"{name}: no DB/points_ element: not a VeloView calibration")
    enabled = None
    if db.find("enabled_") is not None:
        enabled = [_count(e.text or 0, "enabled_", name) != 0 for e in db.find("enabled_")
                   if e.tag == "item"]

    def field(px: ElementTree.Element, tag: str, default: float | None = 0.0) -> float | None:
        el = px.find(tag)
        return default if el is None or el.text is None else el.text

    rows = []
    for item in points.iter("item"):
        px = item.find("px")
        if px is None:
            continue
        vert = field(px, "vertCorrection_", None)
        rows.append({
            "id": field(px, "id_", None),
            "rot": math.radians(_number(field(px, "rotCorrection_"), "rotCorrection_", name)),
            "vert": None if vert is None else math.radians(_number(vert, "vertCorrection_", name)),
            "vert_offset": CM * _number(field(px, "vertOffsetCorrection_"), "offset", name),
            "horiz_offset": CM * _number(field(px, "horizOffsetCorrection_"), "offset", name),
            "dist": [CM * _number(field(px, t), t, name)
                     for t in ("distCorrection_", "distCorrectionX_", "distCorrectionY_")],
        })
    if enabled is not None:
        rows = [r for r in rows if _laser_id(r, name) < len(enabled)
                and enabled[_laser_id(r, name)]]
    lsb = db.find("distLSB_")
    unit = None if lsb is None or lsb.text is None else CM * _resolution(lsb.text, "distLSB_",
                                                                         name)
    return _table(rows, name, len(rows)), unit


def _number(value, what: str, name: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise CalibrationFileError(f"{name}: {what} is {value!r}, not a number") from None
    if not math.isfinite(v):
        raise CalibrationFileError(f"{name}: {what} is {v}, not a finite number")
    return v


def _count(value, what: str, name: str) -> int:
    """A whole number >= 0 of the file (a count, a flag)."""
    v = _number(value, what, name)
    if v != int(v) or v < 0:
        raise CalibrationFileError(f"{name}: {what} is {value!r}, not a whole number >= 0")
    return int(v)


def _resolution(value, what: str, name: str) -> float:
    """The distance unit: a positive number of metres or centimetres, not above `MAX_LSB`."""
    v = _number(value, what, name)
    if not 0.0 < v <= MAX_LSB:
        raise CalibrationFileError(f"{name}: {what} is {value!r}; a distance resolution is a "
                                   f"positive number (0.002 m, 0.2 cm on Velodyne sensors)")
    return v


def _laser_id(row: dict, name: str) -> int:
    v = _number(row["id"], "laser_id", name)
    if v != int(v) or v < 0:
        raise CalibrationFileError(f"{name}: laser id {row['id']!r} is not a laser index")
    return int(v)


def _table(rows: list[dict], name: str, num_lasers: int) -> LaserTable:
    """Rows by laser id (every id 0..n-1 once) as a `LaserTable`, checked."""
    if not rows:
        raise CalibrationFileError(f"{name}: no lasers in the calibration file")
    ids = [_laser_id(r, name) for r in rows]
    n = len(rows)
    if sorted(ids) != list(range(n)) or num_lasers != n:
        raise CalibrationFileError(
            f"{name}: laser ids {sorted(ids)[:4]}... are not 0..{n - 1} once each (or "
            f"num_lasers {num_lasers} differs): a damaged calibration file")
    by_id = sorted(zip(ids, rows, strict=True), key=lambda p: p[0])
    for i, r in by_id:
        if r["vert"] is None:
            raise CalibrationFileError(f"{name}: laser {i} has no vertical correction")
        if any(_number(d, "dist_correction", name) != 0.0 for d in r["dist"]):
            raise CalibrationFileError(
                f"{name}: laser {i} has a distance correction (an HDL-64E style two-point "
                "calibration), which aimbench does not model")
    col = {k: np.array([_number(r[k], k, name) for _, r in by_id])
           for k in ("rot", "vert", "vert_offset", "horiz_offset")}
    if (np.abs(col["vert"]) >= math.pi / 2).any() or (np.abs(col["rot"]) >= math.pi).any():
        raise CalibrationFileError(f"{name}: an angle is out of range (radians expected in the "
                                   "YAML, degrees in the XML)")
    for k in ("vert_offset", "horiz_offset"):
        worst = float(np.max(np.abs(col[k])))
        if worst > MAX_OFFSET_M:
            raise CalibrationFileError(
                f"{name}: a laser's {k.replace('_', ' ')} correction is {worst:g} m; a laser's "
                f"origin is within {MAX_OFFSET_M:g} m of the optical centre (metres expected in "
                "the YAML, centimetres in the XML)")
    return LaserTable(f"calibration {name}", col["vert"], col["vert_offset"], -col["rot"],
                      col["horiz_offset"])
