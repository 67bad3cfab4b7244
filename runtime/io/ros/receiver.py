"""Sensor topics over DDS -> SensorInbox, decoded and validated off the tick.

`RosSensorReceiver` owns readers for the configured lidar, camera (and its CameraInfo), IMU and
goal topics (on the
middleware's transport: rclpy or cyclonedds, runtime.io.ros.transport) and one thread that
waits on them, takes each sample's raw CDR bytes, decodes and converts it
(convert.py) and puts the result into a SensorInbox. The tick only calls `inbox.take()`: it
never decodes, and a slow or malformed sample costs the receiver thread, not the tick.

Raw bytes, not the middleware's decoded objects: a generic decoder builds a Python object per
Livox point (0.13 s for a 20k-point frame with cyclonedds', longer than the frame period) and
raises whatever its parser hits on malformed bytes. Taking the bytes (`take_raw`) lets the Livox
frame use the numpy decoder and turns every undecodable sample into a named rejection.

A sample that fails is counted by `<stream>.<reason>` in `error_counts`, remembered in
`last_error`, and handed to the tick through the inbox's rejections, as SensorInbox does for the
data it refuses itself (non-monotonic stamps, frozen frames).

A recording taps the samples here (`tap`, on this thread, never the tick's): each one's raw bytes
as received, numbered in the order they are processed (sensor samples only: lidar, camera,
camera info, IMU; the n-th one is the n-th piece of data the inbox counts, SensorInbox.delivered,
so each one, accepted or refused here or by the inbox, is counted there exactly once), so that a
replay can hand the controller the same data at the same tick (runtime.app.replay).

Topic names are ROS names (`/livox/lidar`); on the DDS wire they are `rt/livox/lidar`. QoS:
sensor data best effort, keep last (the ROS 2 sensor-data profile), the goal reliable.
"""
from __future__ import annotations

import logging
import re
import threading
from collections.abc import Callable
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from runtime.io.ros import convert
from runtime.io.ros.messages import ROS_TYPES, RosMessageError, decode_custom_msg, from_cdr
from runtime.io.ros.transport import QosSpec, TopicReader, Transport
from runtime.io.ros.workspace import GoalWorkspace
from runtime.common.sensor_data import SensorDataError
from runtime.io.sensor_inbox import SensorInbox

log = logging.getLogger(__name__)

_ROS_NAME = re.compile(r"^/?[A-Za-z_~{][A-Za-z0-9_/{}]*$")


# ----------------------------------------------------------------------------- config


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class TopicQos(_Strict):
    reliability: Literal["best_effort", "reliable"] = "best_effort"
    depth: int = Field(default=1, ge=1, le=1000)

    def spec(self) -> QosSpec:
        return QosSpec(self.reliability, self.depth)


class _Topic(_Strict):
    topic: str
    qos: TopicQos = TopicQos()

    @field_validator("topic")
    @classmethod
    def _ros_name(cls, v: str) -> str:
        if not _ROS_NAME.match(v) or "//" in v or v.endswith("/"):
            raise ValueError(f"{v!r} is not a ROS 2 topic name (e.g. /livox/lidar)")
        return v


class LidarTopic(_Topic):
    type: Literal["livox_ros_driver2/msg/CustomMsg", "sensor_msgs/msg/PointCloud2"]
    #: PointCloud2 only: where each point's time comes from (runtime.io.ros.pointcloud): "auto" (found
    #: from the message's fields by the drivers' conventions), "none" (every point at the header
    #: stamp: deskewing off), or a field name, in units of time_unit_s, absolute when
    #: time_is_absolute. null is "none" (what it meant before "auto" existed).
    time_field: str = convert.TIME_FIELD_AUTO
    time_unit_s: float = Field(default=1.0, gt=0.0)
    time_is_absolute: bool = False
    nominal_frame_duration_s: float = Field(default=convert.DEFAULT_FRAME_DURATION_S, gt=0.0, le=1.0)

    @field_validator("time_field", mode="before")
    @classmethod
    def _null_is_none(cls, v):
        return convert.TIME_FIELD_NONE if v is None else v

    @field_validator("time_field")
    @classmethod
    def _field_name(cls, v: str) -> str:
        if not v or v != v.strip() or any(c.isspace() for c in v):
            raise ValueError(f"{v!r} is not a field name (or auto, none)")
        return v

    @model_validator(mode="after")
    def _time_settings(self) -> "LidarTopic":
        # A setting given at its default (a dumped config writes every field) says nothing.
        defaults = {"time_field": convert.TIME_FIELD_AUTO, "time_unit_s": 1.0, "time_is_absolute": False}
        given = sorted(k for k in defaults if k in self.model_fields_set and getattr(self, k) != defaults[k])
        if self.type != "sensor_msgs/msg/PointCloud2" and given:
            raise ValueError(f"{', '.join(given)}: PointCloud2 only (CustomMsg has offset_time)")
        named = self.time_field not in (convert.TIME_FIELD_AUTO, convert.TIME_FIELD_NONE)
        if not named and (self.time_unit_s != 1.0 or self.time_is_absolute):
            raise ValueError(f"time_unit_s / time_is_absolute go with a named time_field, not {self.time_field!r} "
                             "(auto finds the unit from the field)")
        return self


class CameraTopic(_Topic):
    type: Literal["sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"]


class CameraInfoTopic(_Topic):
    """The camera driver's intrinsics (beside its image topic): held against the calibration."""

    type: Literal["sensor_msgs/msg/CameraInfo"] = "sensor_msgs/msg/CameraInfo"


class ImuTopic(_Topic):
    type: Literal["sensor_msgs/msg/Imu"] = "sensor_msgs/msg/Imu"
    qos: TopicQos = TopicQos(depth=50)     # 200 Hz and more: keep what arrives between two wake-ups


class GoalTopic(_Topic):
    topic: str = "/goal_pose"               # the Nav2 / RViz "2D Goal Pose" convention
    type: Literal["geometry_msgs/msg/PoseStamped"] = "geometry_msgs/msg/PoseStamped"
    qos: TopicQos = TopicQos(reliability="reliable", depth=1)
    #: Where goals may be: a goal outside (or in another frame) is refused (workspace.py).
    workspace: GoalWorkspace | None = None


class RosInputConfig(_Strict):
    """Which ROS 2 topics the controller reads, with their types and QoS."""

    domain_id: int = Field(default=0, ge=0, le=232)
    lidar: LidarTopic | None = None
    camera: CameraTopic | None = None
    #: What the camera's driver says its intrinsics are (calibration check; never projected with).
    camera_info: CameraInfoTopic | None = None
    imu: ImuTopic | None = None
    goal: GoalTopic | None = None


# ----------------------------------------------------------------------------- decoding


def decode_cdr(type_name: str, data: bytes):
    """CDR bytes -> our IDL struct (CustomMsg: the numpy CustomMsgArrays); every failure a RosMessageError."""
    if type_name == "livox_ros_driver2/msg/CustomMsg":
        return decode_custom_msg(data)
    if type_name == "sensor_msgs/msg/Imu":  # 200 Hz: struct, not the generic decoder (fast_imu.py)
        from runtime.io.ros.fast_imu import decode_imu

        try:
            return decode_imu(data)
        except RosMessageError as exc:  # named as the generic decoder's failures are
            raise RosMessageError(f"undecodable CDR ({exc})"[:200], name="undecodable",
                                  field_name=exc.field_name) from exc
    try:
        return from_cdr(ROS_TYPES[type_name], data)
    except Exception as exc:    # cyclonedds' parser on untrusted bytes: struct.error, UnicodeDecodeError, ...
        raise RosMessageError(f"undecodable CDR ({type(exc).__name__}: {exc})".splitlines()[0][:200],
                              name="undecodable", field_name=f"{type_name}.(bytes)") from exc


# ----------------------------------------------------------------------------- the receiver


class RosSensorReceiver:
    """Reads the configured topics on its own thread and feeds `inbox` (and the newest goal).

    camera_K / camera_distortion: the camera's intrinsics from the calibration (ROS images
    carry none); required when a camera topic is configured.
    transport: the middleware's node on config.domain_id (runtime.io.ros.transport), which the
    caller opens and closes.
    tap: called on the receiver's thread with (stream, topic, ROS type, raw CDR bytes, sample
    number) for every sample before it is decoded; the number counts the sensor samples (lidar,
    camera, camera info, IMU) from 1 and is None for a goal (module docstring). It must be O(1) and
    never block; one that raises is counted (`<stream>.tap_failed` in error_counts), not propagated.

    lidar_time_notice: set once, and logged as a warning, when a PointCloud2 lidar with time_field
    auto has no per-point time field (deskewing is off; convert.no_point_time_notice).
    """

    lidar_time_notice: str | None = None
    GOAL_REJECTIONS_KEPT = 16
    _goal_rejections: tuple[str, ...] = ()

    def __init__(self, config: RosInputConfig, inbox: SensorInbox, transport: Transport, *,
                 camera_K: np.ndarray | None = None, camera_distortion: np.ndarray | None = None,
                 tap: Callable[[str, str, str, bytes, int | None], None] | None = None) -> None:
        if config.camera is not None and camera_K is None:
            raise ValueError("RosSensorReceiver: a camera topic is configured but no camera_K was given")
        self.config = config
        self.inbox = inbox
        self.transport = transport
        self._K, self._dist = camera_K, camera_distortion
        self._lock = threading.Lock()
        self._goal: convert.GoalPose | None = None
        self.received: dict[str, int] = {}
        self.tap = tap
        self.samples = 0  # sensor samples taken so far (the tap's numbering)
        self.error_counts: dict[str, int] = {}
        self.last_error: str | None = None
        self._readers: list[tuple[str, str, TopicReader, Callable[[object], None]]] = []
        self._topics: dict[str, str] = {}  # stream -> topic name
        for stream, topic in (("lidar", config.lidar), ("camera", config.camera),
                              ("camera_info", config.camera_info), ("imu", config.imu), ("goal", config.goal)):
            if topic is None:
                continue
            reader = transport.reader(topic.topic, ROS_TYPES[topic.type], topic.qos.spec())
            self._readers.append((stream, topic.type, reader, self._handler(stream, topic)))
            self._topics[stream] = topic.topic
            self.received[stream] = 0
        self._stop = threading.Event()
        self.thread_errors = 0  # exceptions the receiver thread survived (last_thread_error names the last)
        self.last_thread_error: str | None = None
        self._thread: threading.Thread | None = None

    # -- conversion per stream

    def _handler(self, stream: str, topic: _Topic) -> Callable[[object], None]:
        inbox = self.inbox
        if stream == "lidar":
            assert isinstance(topic, LidarTopic)
            if topic.type == "livox_ros_driver2/msg/CustomMsg":
                def lidar(msg):
                    inbox.put_scan(convert.custom_msg_to_scan(
                        msg, nominal_frame_duration_s=topic.nominal_frame_duration_s))
            else:
                def lidar(msg):
                    scan, source = convert.pointcloud2_decode(
                        msg, time_field=topic.time_field, time_unit_s=topic.time_unit_s,
                        time_is_absolute=topic.time_is_absolute,
                        nominal_frame_duration_s=topic.nominal_frame_duration_s)
                    said = self.lidar_time_notice is not None
                    if source is None and topic.time_field == convert.TIME_FIELD_AUTO and not said:
                        # said once (the first such frame), not per frame; the scans are still used
                        self.lidar_time_notice = convert.no_point_time_notice(topic.topic, msg)
                        log.warning("%s", self.lidar_time_notice)
                    inbox.put_scan(scan)
            return lidar
        if stream == "camera":
            to_camera = (convert.image_to_camera if topic.type == "sensor_msgs/msg/Image"
                         else convert.compressed_image_to_camera)
            return lambda msg: inbox.put_image(to_camera(msg, self._K, self._dist))
        if stream == "camera_info":
            return lambda msg: inbox.put_camera_info(convert.camera_info_to_intrinsics(msg))
        if stream == "imu":
            return lambda msg: inbox.put_imu(convert.imu_to_sample(msg))

        workspace = topic.workspace

        def goal(msg):
            g = convert.pose_stamped_to_goal(msg)
            if workspace is not None:  # refused here: a goal outside never reaches the controller
                workspace.check_goal(g)
            with self._lock:
                self._goal = g
        return goal

    def _reject(self, stream: str, exc: SensorDataError) -> None:
        key = f"{stream}.{exc.name}"
        with self._lock:
            self.error_counts[key] = self.error_counts.get(key, 0) + 1
            self.last_error = f"{stream}: {exc}"
            if stream == "goal":  # for the operator's console (take_goal_rejections); the newest few
                self._goal_rejections = (*self._goal_rejections, str(exc))[-self.GOAL_REJECTIONS_KEPT:]
        if stream != "goal":
            # Hand the rejection to the tick with the inbox's own (SensorInbox has no public
            # method for data refused before it became a LidarScan / CameraImage / ImuSample).
            self.inbox._reject(stream, exc, None)

    def process(self, stream: str, type_name: str, data: bytes, handle: Callable[[object], None]) -> bool:
        """Decode, convert and deliver one sample; False when it was rejected (and counted)."""
        with self._lock:
            self.received[stream] = self.received.get(stream, 0) + 1
        try:
            handle(decode_cdr(type_name, data))
            return True
        except SensorDataError as exc:          # RosMessageError included
            self._reject(stream, exc)
        except Exception as exc:                # a bug in a converter must not end the thread
            log.exception("ros_io: %s sample crashed its converter", stream)
            self._reject(stream, SensorDataError(f"{type(exc).__name__}: {exc}".splitlines()[0][:200],
                                                 name="internal_error", field_name=type_name))
        return False

    def _tap(self, tap, stream: str, type_name: str, data: bytes, seq: int | None) -> None:
        """Hand the sample to the recording; a tap that raises costs the recording the sample (counted
        as `<stream>.tap_failed`), never the controller: the sample is still processed and counted."""
        try:
            tap(stream, self._topics[stream], type_name, data, seq)
        except Exception as exc:  # noqa: BLE001 - a recording's fault must not stop the sensor data
            key = f"{stream}.tap_failed"
            with self._lock:
                first = key not in self.error_counts
                self.error_counts[key] = self.error_counts.get(key, 0) + 1
            if first:
                log.warning("ros_io: the recording's tap failed on a %s sample (%s: %s); counted as %s from now on",
                            stream, type(exc).__name__, exc, key)

    def poll(self, timeout_s: float = 0.0) -> int:
        """Wait up to timeout_s for samples, then process everything pending; returns how many."""
        self.transport.wait(timeout_s)
        n = 0
        tap = self.tap
        for stream, type_name, reader, handle in self._readers:
            for data in reader.take_raw():
                seq = None
                if stream != "goal":
                    self.samples += 1
                    seq = self.samples
                if tap is not None:
                    self._tap(tap, stream, type_name, data, seq)
                self.process(stream, type_name, data, handle)
                n += 1
        return n

    # -- thread

    def start(self) -> "RosSensorReceiver":
        if self._thread is not None:
            raise RuntimeError("RosSensorReceiver already started")
        self._thread = threading.Thread(target=self._run, name="ros_io-receiver", daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self.poll(timeout_s=0.1)
            except Exception as exc:  # noqa: BLE001 - a DDS take that fails must not end the thread silently
                self.thread_errors += 1
                self.last_thread_error = f"{type(exc).__name__}: {exc}"
                self._stop.wait(0.1)  # back off; the inbox goes stale meanwhile and the monitor holds the robot

    def stop(self, timeout_s: float = 2.0) -> None:
        self._stop.set()
        self.transport.wake()
        if self._thread is not None:
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                raise RuntimeError(f"RosSensorReceiver: the receiver thread did not stop within {timeout_s} s")
            self._thread = None
        self._stop.clear()

    def __enter__(self) -> "RosSensorReceiver":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def take_goal(self) -> convert.GoalPose | None:
        """The newest goal received since the last call (None if none)."""
        with self._lock:
            g, self._goal = self._goal, None
        return g

    def take_goal_rejections(self) -> tuple[str, ...]:
        """The goals refused since the last call (each its one-line error; the newest
        GOAL_REJECTIONS_KEPT), for the operator's console; every one is counted in error_counts."""
        with self._lock:
            r, self._goal_rejections = self._goal_rejections, ()
        return r


__all__ = ["RosInputConfig", "LidarTopic", "CameraTopic", "CameraInfoTopic", "ImuTopic", "GoalTopic", "TopicQos", "RosSensorReceiver",
           "decode_cdr"]
