"""Bags written in the tests with rosbags, as the ROS drivers write them: VelodyneScan messages
of raw packets (velodyne_driver), or PointCloud2 messages with x y z intensity ring time
(velodyne_pointcloud's PointXYZIRT)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from twin.core.scan import Scan
from twin.lidar.bags import CLOUD_TYPE, PACKETS_TYPE, typestore
from twin.lidar.capture import Packet

#: The ROS driver's rotation at 600 rpm: one VelodyneScan message per ~76 packets.
PACKETS_PER_MESSAGE = 76
#: Clouds carry the sensor clock (s past the hour); their bag stamps start at this epoch time.
EPOCH_S = 1_700_000_000


def _writer(path: Path, ros2: bool, storage: str = "sqlite3"):
    if ros2:
        from rosbags.rosbag2 import StoragePlugin, Writer

        plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        return Writer(path, version=9, storage_plugin=plugin)
    from rosbags.rosbag1 import Writer

    return Writer(path)


def _serialize(store, msg, msgtype: str, ros2: bool) -> bytes:
    return store.serialize_cdr(msg, msgtype) if ros2 else store.serialize_ros1(msg, msgtype)


def _stamp(store, t: float):
    Time = store.types["builtin_interfaces/msg/Time"]
    sec = int(np.floor(t))
    return Time(sec=sec, nanosec=round((t - sec) * 1e9) % 1_000_000_000)


def _header(store, t: float, frame_id: str = "velodyne"):
    Header = store.types["std_msgs/msg/Header"]
    kwargs = {"stamp": _stamp(store, t), "frame_id": frame_id}
    if "seq" in [name for name, _ in store.fielddefs["std_msgs/msg/Header"][1]]:
        kwargs["seq"] = 0  # ROS 1's Header
    return Header(**kwargs)


def write_packet_bag(path: Path, packets: Sequence[Packet], *, ros2: bool,
                     topic: str = "/velodyne_packets", storage: str = "sqlite3",
                     extra_topics: Sequence[str] = ()) -> Path:
    """A bag of VelodyneScan messages holding ``packets`` (data packets only), each packet with
    its own stamp; ``extra_topics``: more topics of the same packets (to test the choice)."""
    store = typestore(ros2)
    Scan_, Packet_ = (store.types[n] for n in (PACKETS_TYPE, "velodyne_msgs/msg/VelodynePacket"))
    data = [p for p in packets if len(p.payload) == 1206]
    with _writer(path, ros2, storage) as w:
        conns = [w.add_connection(t, PACKETS_TYPE, typestore=store)
                 for t in (topic, *extra_topics)]
        for i in range(0, len(data), PACKETS_PER_MESSAGE):
            group = data[i:i + PACKETS_PER_MESSAGE]
            msg = Scan_(header=_header(store, group[-1].timestamp), packets=[
                Packet_(stamp=_stamp(store, p.timestamp),
                        data=np.frombuffer(p.payload, np.uint8)) for p in group])
            raw = _serialize(store, msg, PACKETS_TYPE, ros2)
            for conn in conns:
                w.write(conn, int(group[-1].timestamp * 1e9), raw)
    return path


def write_cloud_bag(path: Path, scans: Sequence[Scan], *, ros2: bool,
                    topic: str = "/velodyne_points", ring: bool = True) -> Path:
    """A bag of PointCloud2 messages, one per scan: its returns in the ROS frame (x forward,
    y left), fields x y z intensity ring time as velodyne_pointcloud writes them."""
    store = typestore(ros2)
    Cloud, Field = store.types[CLOUD_TYPE], store.types["sensor_msgs/msg/PointField"]
    layout = [("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 16, 7), ("ring", 20, 4),
              ("time", 24, 7)]
    if not ring:
        layout = [f for f in layout if f[0] != "ring"]
    dtype = np.dtype({"names": [n for n, _, _ in layout],
                      "formats": ["<f4" if t == 7 else "<u2" for _, _, t in layout],
                      "offsets": [o for _, o, _ in layout], "itemsize": 32})
    with _writer(path, ros2) as w:
        conn = w.add_connection(topic, CLOUD_TYPE, typestore=store)
        for s in scans:
            h = s.hits()
            rec = np.zeros(len(h), dtype=dtype)
            rec["x"], rec["y"], rec["z"] = h.y, -h.x, h.z
            rec["intensity"] = h.intensity
            rec["time"] = h.time - s.time[0]
            if ring:
                rec["ring"] = h.ring
            msg = Cloud(header=_header(store, EPOCH_S + float(s.time[0])), height=1, width=len(h),
                        fields=[Field(name=n, offset=o, datatype=t, count=1)
                                for n, o, t in layout],
                        is_bigendian=False, point_step=32, row_step=32 * len(h),
                        data=rec.view(np.uint8).reshape(-1), is_dense=True)
            w.write(conn, int((EPOCH_S + float(s.time[0])) * 1e9),
                    _serialize(store, msg, CLOUD_TYPE, ros2))
    return path


#: sensor_msgs/PointField datatypes of numpy's kinds.
_FIELD_TYPES = {"i1": 1, "u1": 2, "i2": 3, "u2": 4, "i4": 5, "u4": 6, "f4": 7, "f8": 8}


def write_records_bag(path: Path, clouds: Sequence[np.ndarray], *, ros2: bool,
                      topic: str = "/ouster/points", frame_id: str = "os_sensor") -> Path:
    """A bag of PointCloud2 messages holding structured arrays field for field, as a driver
    writing its own point type does (ouster-ros's, nebula's PointXYZIRCAEDT): an (H, W) one as
    an organised cloud (height H, width W), as ouster-ros publishes its cloud."""
    store = typestore(ros2)
    Cloud, Field = store.types[CLOUD_TYPE], store.types["sensor_msgs/msg/PointField"]
    with _writer(path, ros2) as w:
        conn = w.add_connection(topic, CLOUD_TYPE, typestore=store)
        for i, rec in enumerate(clouds):
            dt = rec.dtype
            t = EPOCH_S + 0.1 * i
            fields = [Field(name=n, offset=dt.fields[n][1], count=1,
                            datatype=_FIELD_TYPES[dt[n].str.lstrip("<>|=")])
                      for n in dt.names]
            height, width = rec.shape if rec.ndim == 2 else (1, len(rec))
            msg = Cloud(header=_header(store, t, frame_id), height=height, width=width,
                        fields=fields, is_bigendian=False, point_step=dt.itemsize,
                        row_step=dt.itemsize * width,
                        data=np.ascontiguousarray(rec).view(np.uint8).reshape(-1),
                        is_dense=False)
            w.write(conn, int(t * 1e9), _serialize(store, msg, CLOUD_TYPE, ros2))
    return path


def write_other_bag(path: Path, *, ros2: bool) -> Path:
    """A bag without LiDAR data: an IMU topic and a string topic."""
    store = typestore(ros2)
    String = store.types["std_msgs/msg/String"]
    with _writer(path, ros2) as w:
        conn = w.add_connection("/chatter", "std_msgs/msg/String", typestore=store)
        w.add_connection("/imu", "sensor_msgs/msg/Imu", typestore=store)
        w.write(conn, 1_000_000_000, _serialize(store, String(data="hello"),
                                                "std_msgs/msg/String", ros2))
    return path
