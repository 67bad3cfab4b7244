"""The one-line, named rejections every ROS 2 converter raises, and the checks they share.

A rejection is a RosMessageError whose text names the ROS type and field and whose `.name` is a
short reason: `[bad_size] sensor_msgs/msg/Image.data: 100 bytes, expected step 30 x height 4 = 120`.
convert.py (images, IMU, goals, the Livox CustomMsg) and pointcloud.py (PointCloud2) use these.
"""
from __future__ import annotations

from runtime.common.sensor_data import SensorDataError
from runtime.io.ros.messages import Header, RosMessageError, time_to_s

DEFAULT_FRAME_DURATION_S = 0.1      # a 10 Hz lidar (Livox Mid-360's default publish rate)


def fail(type_name: str, field_name: str, what: str, name: str = "bad_message"):
    raise RosMessageError(what, name=name, field_name=f"{type_name}.{field_name}")


def rewrap(type_name: str, field_name: str, exc: SensorDataError):
    """A check of the controller's own type failed: name the ROS field the value came from."""
    inner = f"{exc.field_name}: " if exc.field_name else ""
    msg = str(exc).split("] ", 1)[-1]
    if inner and msg.startswith(inner):
        msg = msg[len(inner):]
    raise RosMessageError(f"{msg} ({exc.field_name or 'value'})", name=exc.name,
                          field_name=f"{type_name}.{field_name}") from exc


def stamp_of(type_name: str, header: Header) -> float:
    t = header.stamp
    if not 0 <= t.nanosec < 1_000_000_000:
        fail(type_name, "header.stamp.nanosec", f"{t.nanosec} not in [0, 1e9)", "bad_stamp")
    if t.sec < 0:
        fail(type_name, "header.stamp.sec", f"negative stamp {t.sec} s", "bad_stamp")
    return time_to_s(t)


def frame_id_of(type_name: str, header: Header, default: str) -> str:  # noqa: ARG001 - the converters' call shape
    return header.frame_id.strip() or default
