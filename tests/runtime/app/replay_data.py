"""Synthetic drivers' bags for the `dct replay` tests: a lidar (sensor_msgs/PointCloud2 with Ouster's
per-point `t`) standing in a walled room with a box in one corner, an IMU at rest and, on request, a
camera driver's CameraInfo, written as a rosbag2 folder (rosbags' writer) or a single MCAP file
(mcap's writer, as `ros2 bag` records)."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

T0_S = 1_760_000_000.0
LIDAR_HZ, IMU_HZ, CAMERA_INFO_HZ = 10.0, 200.0, 5.0
LIDAR_TOPIC, IMU_TOPIC = "/livox/lidar", "/livox/imu"


def _room_ranges(angles: np.ndarray) -> np.ndarray:
    """Horizontal range from (0.3, -0.2) to the walls of an 8 x 6 m room with a 1 m box at (2.5, 1.8)."""
    ox, oy = 0.3, -0.2
    c, s = np.cos(angles), np.sin(angles)
    with np.errstate(divide="ignore", invalid="ignore"):
        tx = np.where(c > 0, (4.0 - ox) / c, np.where(c < 0, (-4.0 - ox) / c, np.inf))
        ty = np.where(s > 0, (3.0 - oy) / s, np.where(s < 0, (-3.0 - oy) / s, np.inf))
    r = np.minimum(tx, ty)
    # the box: x in [2.0, 3.0], y in [1.3, 2.3] (slab test)
    with np.errstate(divide="ignore", invalid="ignore"):
        t1x, t2x = (2.0 - ox) / c, (3.0 - ox) / c
        t1y, t2y = (1.3 - oy) / s, (2.3 - oy) / s
    tmin = np.maximum(np.minimum(t1x, t2x), np.minimum(t1y, t2y))
    tmax = np.minimum(np.maximum(t1x, t2x), np.maximum(t1y, t2y))
    hit = (tmax >= tmin) & (tmin > 0)
    return np.where(hit, np.minimum(r, tmin), r)


def lidar_cdr(k: int, rng: np.random.Generator) -> tuple[float, bytes]:
    """Frame k: (its stamp, PointCloud2 CDR) of 16 rings x 720 azimuths swept over 0.1 s."""
    from runtime.io.ros.messages import Header, PointCloud2, PointField, stamp_to_time, to_cdr

    stamp = T0_S + k / LIDAR_HZ
    az = np.linspace(0.0, 2 * math.pi, 720, endpoint=False)
    el = np.radians(np.linspace(-15.0, 15.0, 16))
    d = _room_ranges(az)[None, :] + rng.normal(0.0, 0.005, (16, 720))
    x, y = d * np.cos(az), d * np.sin(az)
    z = d * np.tan(el)[:, None]
    t_ns = np.broadcast_to((az / (2 * math.pi) * 0.1e9).astype(np.uint32), (16, 720))
    rec = np.zeros((16 * 720,), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("t", "<u4")])
    rec["x"], rec["y"], rec["z"], rec["t"] = x.ravel(), y.ravel(), z.ravel(), t_ns.ravel()
    fields = [PointField("x", 0, 7, 1), PointField("y", 4, 7, 1), PointField("z", 8, 7, 1), PointField("t", 12, 6, 1)]
    msg = PointCloud2(Header(stamp_to_time(stamp), "livox_frame"), 1, len(rec), fields, False, 16, 16 * len(rec),
                      rec.tobytes(), True)
    return stamp, to_cdr(msg)


def imu_cdr(j: int) -> tuple[float, bytes]:
    from runtime.io.ros.fast_imu import encode_imu

    stamp = T0_S + j / IMU_HZ
    return stamp, encode_imu(stamp, "livox_frame", [0.0, 0.0, 0.0], [0.0, 0.0, 9.81])


def camera_info_cdr(i: int, fx: float) -> tuple[float, bytes]:
    """The i-th CameraInfo of a 640 x 480 camera with focal length fx (px), no distortion."""
    from runtime.io.ros.messages import CameraInfo, Header, stamp_to_time, to_cdr

    stamp = T0_S + i / CAMERA_INFO_HZ
    return stamp, to_cdr(CameraInfo(Header(stamp_to_time(stamp), "camera_color_optical_frame"), 480, 640, "plumb_bob",
                                    [0.0] * 5, [fx, 0.0, 319.5, 0.0, fx, 239.5, 0.0, 0.0, 1.0]))


def messages(duration_s: float, seed: int = 0, camera_info: tuple[str, float] | None = None,
             ) -> list[tuple[float, str, str, bytes]]:
    """(receive time, topic, type, CDR) in time order; each message received 2 ms after its stamp
    (a lidar frame after its sweep). camera_info: (topic, fx) of a CameraInfo at CAMERA_INFO_HZ."""
    rng = np.random.default_rng(seed)
    out = []
    if camera_info is not None:
        for i in range(int(duration_s * CAMERA_INFO_HZ)):
            stamp, data = camera_info_cdr(i, camera_info[1])
            out.append((stamp + 0.003, camera_info[0], "sensor_msgs/msg/CameraInfo", data))
    for k in range(int(duration_s * LIDAR_HZ)):
        stamp, data = lidar_cdr(k, rng)
        out.append((stamp + 0.102, LIDAR_TOPIC, "sensor_msgs/msg/PointCloud2", data))
    for j in range(int(duration_s * IMU_HZ)):
        stamp, data = imu_cdr(j)
        out.append((stamp + 0.002, IMU_TOPIC, "sensor_msgs/msg/Imu", data))
    out.sort(key=lambda m: m[0])
    return out


def write_rosbag2(path: Path, duration_s: float = 3.0, camera_info: tuple[str, float] | None = None) -> Path:
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    with Writer(path, version=8) as w:
        conns = {}
        for t, topic, type_name, data in messages(duration_s, camera_info=camera_info):
            if topic not in conns:
                conns[topic] = w.add_connection(topic, type_name, typestore=store)
            w.write(conns[topic], int(round(t * 1e9)), data)
    return path


def write_mcap_bag(path: Path, duration_s: float = 3.0, camera_info: tuple[str, float] | None = None) -> Path:
    from mcap.writer import Writer

    from runtime.io.ros.msg_definitions import schema_text

    with open(path, "wb") as f:
        w = Writer(f)
        w.start(profile="ros2", library="test")
        channels = {}
        for t, topic, type_name, data in messages(duration_s, camera_info=camera_info):
            if topic not in channels:
                sid = w.register_schema(type_name, "ros2msg", schema_text(type_name).encode())
                channels[topic] = w.register_channel(topic, "cdr", sid)
            ns = int(round(t * 1e9))
            w.add_message(channels[topic], log_time=ns, data=data, publish_time=ns)
        w.finish()
    return path
