"""The recording's ROS 2 channels: /tf and /tf_static as tf2_msgs/msg/TFMessage in ROS 2 CDR.

JSON (schemas.py) is what the recording's own channels are; these two are ROS 2 messages, written
as rosbag2 writes them into MCAP (message encoding `cdr`, schema encoding `ros2msg`, the schema the
type's `.msg` text with its dependencies: runtime.io.ros.msg_definitions), so that Foxglove draws the
robot's frames, and `ros2 bag`, mcap_ros2 and Foxglove's readers decode them without our code:

  /tf         odom -> base_link, the controller's pose at each tick (planar: z = 0, yaw about z)
  /tf_static  the sensor mounts (base_link -> lidar, base_link -> camera), once, at the first tick

Frame names are the `ros.outputs` ones (odom_frame, base_frame) the published odometry uses. The
messages are built and serialised on the recorder's writer thread; the tick only queues a tuple.
"""
from __future__ import annotations

from collections.abc import Iterable

import numpy as np

TOPIC_TF = "/tf"
TOPIC_TF_STATIC = "/tf_static"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
#: topic -> ROS 2 type of every ROS 2 channel.
CHANNELS = {TOPIC_TF: TF_MESSAGE, TOPIC_TF_STATIC: TF_MESSAGE}
#: MCAP encodings of a ROS 2 channel (rosbag2's MCAP plug-in writes the same).
SCHEMA_ENCODING = "ros2msg"
MESSAGE_ENCODING = "cdr"


def channel_schemas() -> dict[str, tuple[str, bytes]]:
    """topic -> (schema name, ros2msg schema text)."""
    from runtime.io.ros.msg_definitions import schema_text

    return {topic: (type_name, schema_text(type_name).encode()) for topic, type_name in CHANNELS.items()}


def checked_mounts(mounts: Iterable) -> tuple[tuple[str, str, np.ndarray], ...]:
    """The static transforms as (parent, child, 4x4 float64 copy), each checked as /tf_static will
    need it (frames, a rigid matrix; runtime.io.ros.outbound.static_transforms). ValueError otherwise."""
    from runtime.io.ros.outbound import static_transforms

    out = []
    for k, m in enumerate(mounts):
        if not isinstance(m, (tuple, list)) or len(m) != 3:
            raise ValueError(f"[bad_shape] static_transforms[{k}]: expected (parent, child, 4x4 matrix), got {m!r}")
        out.append((m[0], m[1], np.array(m[2], dtype=np.float64, copy=True)))
    static_transforms(0.0, out)
    return tuple(out)


def tf_static_cdr(t_s: float, mounts: Iterable) -> bytes:
    from runtime.io.ros.messages import to_cdr
    from runtime.io.ros.outbound import static_transforms

    return to_cdr(static_transforms(max(0.0, t_s), mounts))


def tf_cdr(t_s: float, xyyaw: tuple[float, float, float], frames: tuple[str, str]) -> bytes:
    """odom -> base_link at the tick's time, from the pose the tick recorded."""
    from runtime.common.geometry import Pose2D
    from runtime.io.ros.messages import to_cdr
    from runtime.io.ros.outbound import tf_message

    return to_cdr(tf_message(max(0.0, t_s), [(frames[0], frames[1], Pose2D(*xyyaw))]))
