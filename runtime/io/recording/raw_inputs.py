"""The sensor messages as the controller received them, recorded as ROS 2 channels.

`dct run --record` taps the ROS receiver (runtime.io.ros.receiver, its `tap`): on the receiver's
thread, never the tick's, each sample's raw CDR bytes go into the recorder's bounded queue with
the loop clock's time and the sample's number; the writer thread writes them as rosbag2 does
(message encoding `cdr`, schema encoding `ros2msg`, the type's `.msg` text: mcap_ros2, Foxglove
and `ros2 bag` read them), on the topic they came on:

  log time      when the receiver took the sample (the loop's clock: ROS time)
  publish time  the message's header stamp (the log time where the bytes hold none)
  sequence      the sample's number: the n-th sensor sample is the n-th piece of data the
                controller's inbox counted (goals have their own numbering)

and the channel's metadata names the stream (`dct_stream`: lidar, camera, camera_info, imu, goal).
With the per-tick `/dct/inputs` channel (how many samples each tick had taken in) a replay hands
the controller exactly what it had at each tick (runtime.app.replay).

Bounded twice: by the queue's record count, and by the bytes of raw samples waiting for the
writer (`max_pending_bytes`: a lidar frame is hundreds of kB); beyond either the sample is dropped
and counted under its kind (`raw_lidar`, ...), as every other record is.
"""
from __future__ import annotations

import struct

#: Recorder record kinds of the raw samples, by stream.
KIND_OF_STREAM = {"lidar": "raw_lidar", "camera": "raw_camera", "camera_info": "raw_camera_info", "imu": "raw_imu",
                  "goal": "raw_goal"}
KINDS = tuple(KIND_OF_STREAM.values())
#: Channel metadata key that names the stream a raw channel carries.
STREAM_KEY = "dct_stream"


def header_stamp_ns(data: bytes) -> int | None:
    """The `header.stamp` of a ROS 2 message whose first field is a std_msgs/Header (every sensor
    message and PoseStamped), in ns, read from its CDR bytes (4-byte encapsulation header, then
    int32 sec and uint32 nanosec in the encapsulation's byte order); None where the bytes are too
    short, the encapsulation is not plain CDR, or the stamp is negative or out of range."""
    if len(data) < 12 or data[0] != 0 or data[1] not in (0, 1):
        return None
    sec, nsec = struct.unpack_from("<iI" if data[1] == 1 else ">iI", data, 4)
    if sec < 0 or nsec >= 1_000_000_000:
        return None
    return sec * 1_000_000_000 + nsec


class RawInputWriter:
    """The writer thread's side: registers a channel per topic at its first sample, then writes
    each sample (module docstring). `writer` is the recorder's mcap Writer."""

    def __init__(self, writer) -> None:
        self._writer = writer
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self.goal_seq = 0

    def _channel(self, stream: str, topic: str, type_name: str) -> int:
        ch = self._channels.get(topic)
        if ch is None:
            from runtime.io.recording.ros_channels import MESSAGE_ENCODING, SCHEMA_ENCODING
            from runtime.io.ros.msg_definitions import schema_text

            sid = self._schemas.get(type_name)
            if sid is None:
                sid = self._writer.register_schema(name=type_name, encoding=SCHEMA_ENCODING,
                                                   data=schema_text(type_name).encode())
                self._schemas[type_name] = sid
            ch = self._writer.register_channel(topic=topic, message_encoding=MESSAGE_ENCODING, schema_id=sid,
                                               metadata={STREAM_KEY: stream})
            self._channels[topic] = ch
        return ch

    def write(self, item: tuple) -> None:
        """One ("raw", t_s, stream, topic, type_name, data, seq) record."""
        _, t_s, stream, topic, type_name, data, seq = item
        ch = self._channel(stream, topic, type_name)
        log_ns = max(0, int(round(t_s * 1e9)))
        stamp = header_stamp_ns(data)
        if seq is None:  # a goal: numbered among the goals
            self.goal_seq += 1
            seq = self.goal_seq
        self._writer.add_message(ch, log_time=log_ns, data=data, publish_time=log_ns if stamp is None else stamp,
                                 sequence=int(seq) & 0xFFFFFFFF)
