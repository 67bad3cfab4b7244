"""Write scans as the recordings users have: a PCD folder, a KITTI .bin folder, an MCAP of
PointCloud2 (mcap_ros2's encoder), a rosbag2 folder (rosbags' writer, sqlite3 or mcap storage)
and an MCAP of Livox CustomMsg, each by another library than the readers under test.

`frames`: a list of dicts of point fields (x, y, z float32, optionally intensity), one per scan;
`stamps_ns`: the header stamp of each.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from calibration.pointcloud_write import write_pcd
from tests.runtime.io.test_ros_messages import LIVOX_MSGS
from tests.runtime.odometry.synthetic_sequence import write_kitti_bin

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
CUSTOM_MSG = "livox_ros_driver2/msg/CustomMsg"
IMU = "sensor_msgs/msg/Imu"
FLOAT32 = 7


def typestore():
    """rosbags' ROS 2 Jazzy types plus the Livox driver's."""
    ts = get_typestore(Stores.ROS2_JAZZY)
    types = {}
    for name, text in LIVOX_MSGS.items():
        types.update(get_types_from_msg(text, name))
    ts.register(types)
    return ts


def _xyzi(fields: dict) -> np.ndarray:
    rec = np.zeros((len(fields["x"]), 4), dtype="<f4")
    for i, k in enumerate(("x", "y", "z")):
        rec[:, i] = fields[k]
    rec[:, 3] = fields.get("intensity", 0.0)
    return rec


def write_pcd_folder(folder: Path, frames: list[dict]) -> Path:
    folder.mkdir(parents=True)
    for i, f in enumerate(frames):
        write_pcd(folder / f"scan_{i}.pcd", f)
    return folder


def write_bin_folder(folder: Path, frames: list[dict]) -> Path:
    folder.mkdir(parents=True)
    for i, f in enumerate(frames):
        rec = _xyzi(f)
        write_kitti_bin(folder / f"{i:06d}.bin", rec[:, :3], rec[:, 3])
    return folder


def pointcloud2_dict(fields: dict, stamp_ns: int, frame_id: str = "velodyne") -> dict:
    """A PointCloud2 as mcap_ros2 encodes it: x, y, z, intensity float32, 16-byte points."""
    rec = _xyzi(fields)
    sec, nanosec = divmod(stamp_ns, 1_000_000_000)
    return {"header": {"stamp": {"sec": sec, "nanosec": nanosec}, "frame_id": frame_id},
            "height": 1, "width": len(rec),
            "fields": [{"name": n, "offset": 4 * i, "datatype": FLOAT32, "count": 1}
                       for i, n in enumerate(("x", "y", "z", "intensity"))],
            "is_bigendian": False, "point_step": 16, "row_step": 16 * len(rec), "data": rec.tobytes(),
            "is_dense": True}


def custom_msg_dict(fields: dict, stamp_ns: int, sweep_ns: int = 99_000_000) -> dict:
    """A Livox CustomMsg of the same points, offset_time spread over the sweep in point order."""
    rec = _xyzi(fields)
    offsets = (np.arange(len(rec)) * (sweep_ns / max(len(rec) - 1, 1))).astype(np.uint32)
    sec, nanosec = divmod(stamp_ns, 1_000_000_000)
    points = [{"offset_time": int(o), "x": float(p[0]), "y": float(p[1]), "z": float(p[2]), "reflectivity": 10,
               "tag": 0, "line": 0} for o, p in zip(offsets, rec)]
    return {"header": {"stamp": {"sec": sec, "nanosec": nanosec}, "frame_id": "livox_frame"}, "timebase": stamp_ns,
            "point_num": len(points), "lidar_id": 0, "rsvd": [0, 0, 0], "points": points}


def imu_dict(stamp_ns: int, gyro=(0.0, 0.0, 0.1), accel=(0.0, 0.0, 9.81), cov0: float = 0.0) -> dict:
    sec, nanosec = divmod(stamp_ns, 1_000_000_000)
    vec = lambda v: {"x": float(v[0]), "y": float(v[1]), "z": float(v[2])}  # noqa: E731
    return {"header": {"stamp": {"sec": sec, "nanosec": nanosec}, "frame_id": "imu"},
            "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}, "orientation_covariance": [-1.0] + [0.0] * 8,
            "angular_velocity": vec(gyro), "angular_velocity_covariance": [cov0] + [0.0] * 8,
            "linear_acceleration": vec(accel), "linear_acceleration_covariance": [0.0] * 9}


def write_mcap(path: Path, messages: list[tuple[str, str, dict, int]]) -> Path:
    """(topic, type, message dict, log time ns) -> an MCAP file, encoded by mcap_ros2."""
    from mcap_ros2.writer import Writer

    ts = typestore()
    with open(path, "wb") as f:
        w = Writer(f)
        schemas = {}
        for topic, msgtype, msg, log_ns in messages:
            if msgtype not in schemas:
                schemas[msgtype] = w.register_msgdef(msgtype, ts.generate_msgdef(msgtype, ros_version=2)[0])
            w.write_message(topic, schemas[msgtype], msg, log_time=log_ns, publish_time=log_ns)
        w.finish()
    return path


def _rosbags_message(ts, msgtype: str, d):
    """A message dict (as above) as rosbags' message object."""
    cls = ts.types[msgtype]
    if msgtype == POINTCLOUD2:
        hdr = _header(ts, d["header"])
        fields = [ts.types["sensor_msgs/msg/PointField"](name=f["name"], offset=f["offset"], datatype=f["datatype"],
                                                         count=f["count"]) for f in d["fields"]]
        return cls(header=hdr, height=d["height"], width=d["width"], fields=fields, is_bigendian=d["is_bigendian"],
                   point_step=d["point_step"], row_step=d["row_step"],
                   data=np.frombuffer(d["data"], dtype=np.uint8), is_dense=d["is_dense"])
    if msgtype == IMU:
        V, Q = ts.types["geometry_msgs/msg/Vector3"], ts.types["geometry_msgs/msg/Quaternion"]
        arr = lambda v: np.array(v, dtype=np.float64)  # noqa: E731
        return cls(header=_header(ts, d["header"]), orientation=Q(**d["orientation"]),
                   orientation_covariance=arr(d["orientation_covariance"]), angular_velocity=V(**d["angular_velocity"]),
                   angular_velocity_covariance=arr(d["angular_velocity_covariance"]),
                   linear_acceleration=V(**d["linear_acceleration"]),
                   linear_acceleration_covariance=arr(d["linear_acceleration_covariance"]))
    raise ValueError(msgtype)


def _header(ts, h):
    T, H = ts.types["builtin_interfaces/msg/Time"], ts.types["std_msgs/msg/Header"]
    return H(stamp=T(sec=h["stamp"]["sec"], nanosec=h["stamp"]["nanosec"]), frame_id=h["frame_id"])


def write_rosbag2(folder: Path, messages: list[tuple[str, str, dict, int]], storage: str = "sqlite3") -> Path:
    """(topic, type, message dict, log time ns) -> a rosbag2 folder written by rosbags."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    ts = typestore()
    plugin = {"sqlite3": StoragePlugin.SQLITE3, "mcap": StoragePlugin.MCAP}[storage]
    with Writer(folder, version=9, storage_plugin=plugin) as w:
        conns = {}
        for topic, msgtype, d, log_ns in messages:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, msgtype, typestore=ts)
            w.write(conns[topic], log_ns, ts.serialize_cdr(_rosbags_message(ts, msgtype, d), msgtype))
    return folder


__all__ = ["CUSTOM_MSG", "IMU", "POINTCLOUD2", "custom_msg_dict", "imu_dict", "pointcloud2_dict", "typestore",
           "write_bin_folder", "write_mcap", "write_pcd_folder", "write_rosbag2"]
