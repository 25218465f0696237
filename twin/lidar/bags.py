"""ROS 1 and ROS 2 bags, read with rosbags: a LiDAR topic's raw packets or point clouds.

A bag names its LiDAR data in one of two ways:

- ``velodyne_msgs/VelodyneScan``: the sensor's own UDP payloads, a rotation's worth per message,
  each with its receive stamp. They go through our decoder byte for byte, as a pcap's would
  (`Bag.packets` yields the same `twin.lidar.capture.Packet`s a pcap gives).
- ``sensor_msgs/PointCloud2``: a driver's decoded points (`Bag.clouds` yields
  `twin.lidar.clouds.Cloud`s, turned into scans with their misses rebuilt).

rosbags (pure Python, no ROS install) reads ROS 1 ``.bag`` files and ROS 2 bags (a folder with
``metadata.yaml``, or a lone ``.db3`` / ``.mcap`` file). A bag need not carry its message
definitions (ROS 2 bags before Iron do not), and velodyne_msgs is in no distribution's standard
set, so `typestore` registers the velodyne_msgs definitions itself, beside the distribution's
standard messages.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from types import TracebackType

import numpy as np

from twin.core import vlp16
from twin.core.errors import AimbenchError
from twin.lidar.capture import Packet
from twin.lidar.clouds import Cloud
from twin.lidar.conventions import cloud_fields

#: velodyne_msgs (the ROS velodyne driver's package; ROS 1 and ROS 2 define them alike, ROS 1's
#: ``time`` being ROS 2's builtin_interfaces/Time): what a bag of raw packets holds.
VELODYNE_MSGS = {
    "velodyne_msgs/msg/VelodynePacket": "builtin_interfaces/Time stamp\nuint8[1206] data\n",
    "velodyne_msgs/msg/VelodyneScan": "std_msgs/Header header\nVelodynePacket[] packets\n",
}
PACKETS_TYPE = "velodyne_msgs/msg/VelodyneScan"
CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"
LIDAR_TYPES = (PACKETS_TYPE, CLOUD_TYPE)

#: sensor_msgs/PointField datatypes as numpy types.
POINT_FIELD_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


class BagError(AimbenchError):
    """A bag that cannot be read, or holds no LiDAR topic (or several, and none was named)."""


def typestore(ros2: bool = True):
    """A rosbags typestore: the distribution's standard messages plus velodyne_msgs."""
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE if ros2 else Stores.ROS1_NOETIC)
    _register_velodyne(store)
    return store


def _register_velodyne(store) -> None:
    from rosbags.typesys import get_types_from_msg

    types: dict = {}
    for name, text in VELODYNE_MSGS.items():
        if name not in store.fielddefs:
            types.update(get_types_from_msg(text, name))
    if types:
        store.register(types)


class Bag:
    """A bag opened on its LiDAR topic.

    ``topic``: the topic to read; None picks the bag's one LiDAR topic (raw packets preferred
    over point clouds, since they lose nothing). Raises `BagError` naming the topics the bag
    has when it has no LiDAR topic, or several of one kind.
    """

    def __init__(self, path: str | Path, topic: str | None = None) -> None:
        from rosbags.highlevel import AnyReader

        self.path = Path(path)
        if not self.path.exists():
            raise BagError(f"{self.path}: no such file or folder (check the path)")
        ros2 = self.path.suffix != ".bag"
        try:
            self._reader = AnyReader([self.path], default_typestore=typestore(ros2))
            self._reader.open()
        except Exception as exc:  # rosbags raises its own types, sqlite3's, OSError...
            detail = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise BagError(f"{self.path}: not a readable ROS {'2 ' if ros2 else '1 '}bag "
                           f"({detail}); check it with `ros2 bag info` or `rosbag info`") from None
        _register_velodyne(self._reader.typestore)
        self.topics = {name: info.msgtype for name, info in self._reader.topics.items()}
        self.topic, self.msgtype = self._choose(topic)
        self.messages = 0
        self.packet_count = 0

    @property
    def kind(self) -> str:
        """``packets`` (VelodyneScan) or ``cloud`` (PointCloud2)."""
        return "packets" if self.msgtype == PACKETS_TYPE else "cloud"

    def _listing(self) -> str:
        return ", ".join(f"{t} ({m})" for t, m in sorted(self.topics.items())) or "none"

    def _choose(self, topic: str | None) -> tuple[str, str]:
        if topic is not None:
            if topic not in self.topics:
                raise BagError(f"{self.path}: no topic {topic} in the bag (its topics: "
                               f"{self._listing()})")
            if self.topics[topic] not in LIDAR_TYPES:
                raise BagError(f"{self.path}: topic {topic} holds {self.topics[topic]}, not "
                               f"LiDAR data ({' or '.join(LIDAR_TYPES)})")
            return topic, self.topics[topic]
        for msgtype in LIDAR_TYPES:
            found = sorted(t for t, m in self.topics.items() if m == msgtype)
            if len(found) == 1:
                return found[0], msgtype
            if len(found) > 1:
                raise BagError(f"{self.path}: several {msgtype} topics ({', '.join(found)}); "
                               f"name one: {self.path}#{found[0]}")
        raise BagError(f"{self.path}: no LiDAR topic (velodyne_msgs/VelodyneScan or "
                       f"sensor_msgs/PointCloud2) in the bag; its topics: {self._listing()}")

    def _messages(self) -> Iterator[tuple[int, object]]:
        connections = [c for c in self._reader.connections if c.topic == self.topic]
        stream = self._reader.messages(connections=connections)
        while True:
            # Only opening was guarded: a .db3 damaged in its middle raised sqlite3's (or
            # rosbags') error from the reading, a traceback (issue 37).
            try:
                item = next(stream, None)
            except Exception as exc:  # sqlite3.DatabaseError, rosbags' ReaderError, ...
                detail = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
                raise BagError(f"{self.path}: damaged after message {self.messages} on "
                               f"{self.topic} ({detail}); what came before it was read; copy "
                               "the bag again or cut it (ros2 bag convert)") from None
            if item is None:
                return
            conn, stamp_ns, raw = item
            try:
                msg = self._reader.deserialize(raw, conn.msgtype)
            except Exception as exc:
                raise BagError(f"{self.path}: message {self.messages} on {self.topic} cannot be "
                               f"read ({exc}): a damaged bag") from None
            self.messages += 1
            yield stamp_ns, msg

    def packets(self) -> Iterator[Packet]:
        """Every VelodynePacket of the topic, in order, with its own stamp (s since the epoch)."""
        if self.kind != "packets":
            raise BagError(f"{self.path}: topic {self.topic} holds point clouds, not packets")
        for _, msg in self._messages():
            for pkt in msg.packets:
                self.packet_count += 1
                stamp = pkt.stamp.sec + pkt.stamp.nanosec * 1e-9
                yield Packet(stamp, vlp16.DATA_PORT, pkt.data.tobytes())

    def clouds(self) -> Iterator[Cloud]:
        """Every PointCloud2 of the topic as a `Cloud` (sensor frame, ROS convention)."""
        if self.kind != "cloud":
            raise BagError(f"{self.path}: topic {self.topic} holds packets, not point clouds")
        for stamp_ns, msg in self._messages():
            rec = cloud_records(msg, f"{self.path} {self.topic} message {self.messages - 1}")
            # The driver's fields (ring or channel, time in s or ns...): twin.lidar.conventions
            fields, told = cloud_fields(rec)
            meta = {"stamp_s": stamp_ns * 1e-9, "frame_id": msg.header.frame_id,
                    "cloud_fields": list(rec.dtype.names), "organized": msg.height > 1}
            if told:
                meta["convention_from"] = told
            yield Cloud.from_ros(rec["x"], rec["y"], rec["z"], **fields,
                                 name=f"{self.path} {self.topic} at {stamp_ns * 1e-9:.6f} s",
                                 meta=meta)

    def organised_clouds(self) -> Iterator[tuple[np.ndarray, str]]:
        """Every PointCloud2 of the topic as its (height, width) records and a name: an
        organised cloud's rows and columns kept (`twin.lidar.ouster_clouds`)."""
        for name, rec in self._clouds():
            yield rec, name

    def cloud_records(self) -> Iterator[tuple[str, np.ndarray]]:
        """Every PointCloud2 of the topic as its fields hold it (a name, a structured array):
        for readers of a driver's own fields (`twin.lidar.hesai_clouds`)."""
        for name, rec in self._clouds():
            yield name, rec.reshape(-1)

    def _clouds(self) -> Iterator[tuple[str, np.ndarray]]:
        """Every PointCloud2 of the topic: a name and its points, (height, width) records."""
        if self.kind != "cloud":
            raise BagError(f"{self.path}: topic {self.topic} holds packets, not point clouds")
        for stamp_ns, msg in self._messages():
            name = f"{self.path} {self.topic} at {stamp_ns * 1e-9:.6f} s"
            rec = cloud_records(msg, name)
            yield name, rec.reshape(int(msg.height), int(msg.width))

    def info(self) -> dict:
        """What the bag holds (for `aimbench info`)."""
        return {"path": str(self.path), "topic": self.topic, "type": self.msgtype,
                "messages": self.messages, "packets": self.packet_count,
                "topics": dict(sorted(self.topics.items()))}

    def close(self) -> None:
        if self._reader.stack is not None:
            self._reader.close()

    def __enter__(self) -> Bag:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()


def cloud_records(msg, name: str) -> np.ndarray:
    """A PointCloud2's points as a structured array (its fields at their offsets, any order and
    byte order; the padding between them skipped), x y z required."""
    fields = [f for f in msg.fields if f.count == 1 and f.datatype in POINT_FIELD_TYPES]
    if not {"x", "y", "z"} <= {f.name for f in fields}:
        raise BagError(f"{name}: the PointCloud2 has no x/y/z fields (fields: "
                       f"{' '.join(f.name for f in msg.fields)})")
    _check_layout(msg, fields, name)
    order = ">" if msg.is_bigendian else "<"
    dtype = np.dtype({"names": [f.name for f in fields],
                      "formats": [order + POINT_FIELD_TYPES[f.datatype] for f in fields],
                      "offsets": [f.offset for f in fields], "itemsize": msg.point_step})
    n = msg.width * msg.height
    data = np.asarray(msg.data, dtype=np.uint8)
    if msg.height > 1 and msg.row_step != msg.point_step * msg.width:
        rows = data[: msg.row_step * msg.height].reshape(msg.height, msg.row_step)
        data = rows[:, : msg.point_step * msg.width].copy()
    return np.frombuffer(data[: msg.point_step * n].tobytes(), dtype=dtype)


def _check_layout(msg, fields: list, name: str) -> None:
    """Refuse a PointCloud2 whose layout contradicts itself (each was a traceback, issue 37): a
    field named twice, a point_step of 0, a field reaching past its point, rows longer than
    the data or shorter than their points."""
    names = [f.name for f in fields]
    twice = sorted({n for n in names if names.count(n) > 1})
    damaged = f"{name}: a damaged PointCloud2"
    if twice:
        raise BagError(f"{damaged}: the field {', '.join(twice)} is declared twice")
    step, width, height = int(msg.point_step), int(msg.width), int(msg.height)
    if step <= 0:
        raise BagError(f"{damaged}: point_step {step} (a point takes at least its x, y, z)")
    for f in fields:
        size = np.dtype(POINT_FIELD_TYPES[f.datatype]).itemsize
        if f.offset + size > step:
            raise BagError(f"{damaged}: the field {f.name} ({size} bytes at offset {f.offset}) "
                           f"reaches past the point's {step} bytes (point_step)")
    size = len(msg.data)
    if height > 1 and msg.row_step != step * width:
        if msg.row_step < step * width or msg.row_step * height > size:
            raise BagError(f"{damaged}: {height} rows of {msg.row_step} bytes (row_step) for "
                           f"{width} points of {step} bytes, in {size} bytes of data")
    elif step * width * height > size:
        raise BagError(f"{damaged}: it says {width * height} points of {step} bytes but holds "
                       f"{size} bytes")
