"""What the controller publishes for an operator, from a thread fed by the tick.

The tick never touches DDS: `RosPublisher.offer()` (called from the loop's after_tick hook,
outside the tick's timings) puts a few references into a bounded deque and returns; a thread
turns them into ROS 2 messages (runtime.io.ros.convert) and writes them. When the thread is
behind, the oldest queued tick is dropped and counted: an operator's view may skip a frame, the
loop may not wait for it.

References, not copies: P_fix, the plan's states and the lidar scan are arrays the controller
replaces (never mutates in place) from one tick to the next, so handing them over is safe.

Published (RosOutputConfig): /tf (odom -> base_link), nav_msgs/Odometry and
diagnostic_msgs/DiagnosticArray (state, hold or stop reason, the partition's fall-back to all-fixed
and why, stage timings) every tick;
nav_msgs/Path (the MPC's predicted states), P_fix (odom frame) and P_mov (lidar frame, the vpp
partition) as PointCloud2 and the safety supervisor's footprint and stop zone as a
visualization_msgs/MarkerArray every `clouds_every_ticks` ticks; /tf_static (base_link -> lidar
and camera) once, at start. QoS: reliable for what tools subscribe to reliably by default,
best effort for the clouds, tf2's profiles for /tf and /tf_static (docs/ros.md).
"""
from __future__ import annotations

import logging
import threading
import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from runtime.common.geometry import Pose2D
from runtime.io.ros import convert
from runtime.io.ros.messages import (
    DIAG_ERROR, DIAG_OK, DIAG_WARN, DiagnosticArray, MarkerArray, Odometry, Path, PointCloud2, TFMessage,
    stamp_to_time,
)
from runtime.io.ros.settings import RosOutputConfig
from runtime.io.ros.transport import TF, TF_STATIC, QosSpec, Transport

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TickView:
    """What one tick hands to the publisher (references; see the module docstring)."""

    stamp_s: float
    pose: Pose2D
    v_mps: float
    omega_radps: float
    state: str
    stage_ms: dict
    tick_ms: float
    extra: dict
    points_fix: np.ndarray | None = None  # (N, 2) odom frame
    plan_states: np.ndarray | None = None  # (H+1, 3) odom frame
    points_mov: np.ndarray | None = None  # (M, 3) lidar frame
    #: This tick also publishes the plan, the clouds and the markers (every clouds_every_ticks).
    clouds: bool = True


#: Reliable for what an operator's tools subscribe to reliably by default (RViz, Nav2's
#: conventions; a reliable writer also serves best-effort readers), best effort for the clouds
#: (sensor data: a lost cloud is replaced by the next).
STATE_QOS = QosSpec("reliable", 10)
CLOUD_QOS = QosSpec("best_effort", 1)


class RosPublisher:
    """static_transforms: (parent, child, 4x4) mounts for /tf_static, published once at start
    (transient local: a viewer that starts later gets them); zones: (footprint, stop zone)
    polygons in the base frame for the safety markers (None: no markers)."""

    def __init__(self, transport: Transport, config: RosOutputConfig, *, static_transforms=None,
                 zones: tuple | None = None) -> None:
        self.config = config

        def writer(topic: str | None, cls, qos: QosSpec):
            return transport.writer(topic, cls, qos) if topic else None

        self._tf = writer("/tf" if config.publish_tf else None, TFMessage, TF)
        if config.publish_tf and static_transforms:
            # Built now (a bad mount is an error at start-up), written by the thread's first turn.
            self._static = convert.static_transforms(0.0, static_transforms)
            self._tf_static = writer("/tf_static", TFMessage, TF_STATIC)
        else:
            self._static = self._tf_static = None
        self._zones = zones
        self._markers = writer(config.safety_markers if zones is not None else None, MarkerArray, STATE_QOS)

        self._odom = writer(config.odometry, Odometry, STATE_QOS)
        self._diag = writer(config.diagnostics, DiagnosticArray, STATE_QOS)
        self._plan = writer(config.plan, Path, STATE_QOS)
        self._fix = writer(config.p_fix, PointCloud2, CLOUD_QOS)
        self._mov = writer(config.p_mov, PointCloud2, CLOUD_QOS)
        self._queue: deque[TickView] = deque()
        self._cond = threading.Condition()
        self._stop = False
        self.offered = 0
        self.published = 0
        self.dropped = 0
        self.errors = 0
        self.last_error: str | None = None
        self._thread = threading.Thread(target=self._run, name="ros_io-publisher", daemon=True)
        self._thread.start()

    def offer(self, view: TickView) -> None:
        """From the loop thread: O(1), never blocks on DDS."""
        with self._cond:
            self.offered += 1
            if len(self._queue) >= self.config.queue_depth:
                self._queue.popleft()
                self.dropped += 1
            self._queue.append(view)
            self._cond.notify()

    def _run(self) -> None:
        if self._tf_static is not None:
            try:
                stamp = time.time()
                for t in self._static.transforms:
                    t.header.stamp = stamp_to_time(stamp)
                self._tf_static.write(self._static)
            except Exception as exc:  # noqa: BLE001 - counted and said like any other failed write
                self.errors += 1
                self.last_error = f"/tf_static: {type(exc).__name__}: {exc}".splitlines()[0][:200]
        while True:
            with self._cond:
                while not self._queue and not self._stop:
                    self._cond.wait(0.5)
                if not self._queue and self._stop:
                    return
                view = self._queue.popleft()
            try:
                self._publish(view)
                self.published += 1
            except Exception as exc:  # noqa: BLE001 - a bad message must not end the thread
                self.errors += 1
                self.last_error = f"{type(exc).__name__}: {exc}".splitlines()[0][:200]
                log.warning("ros_io publisher: %s", self.last_error)

    def _publish(self, v: TickView) -> None:
        c = self.config
        if self._tf is not None:
            self._tf.write(convert.tf_message(v.stamp_s, [(c.odom_frame, c.base_frame, v.pose)]))
        if self._odom is not None:
            self._odom.write(convert.odometry_msg(v.stamp_s, v.pose, v.v_mps, v.omega_radps, frame_id=c.odom_frame,
                                                  child_frame_id=c.base_frame))
        if self._diag is not None:
            level = {"STOPPED": DIAG_ERROR, "HOLDING": DIAG_WARN}.get(v.state, DIAG_OK)
            timings = {**v.stage_ms, "tick": v.tick_ms}
            # The status line an operator reads first: the state, and why when it is not driving;
            # while driving on the all-fixed fallback, why it fell back (a warning).
            why = v.extra.get("stop_reason") if v.state == "STOPPED" else v.extra.get("hold_reason")
            fallback = v.extra.get("partition_fallback")
            if why and v.state in ("STOPPED", "HOLDING"):
                message = f"{v.state}: {why}"
            elif fallback:
                message, level = f"{v.state}: partition all-fixed: {fallback}", max(level, DIAG_WARN)
            else:
                message = v.state
            self._diag.write(convert.diagnostics_msg(v.stamp_s, v.state, timings, level=level, message=message,
                                                     extra=v.extra))
        if self._plan is not None and v.plan_states is not None and len(v.plan_states):
            self._plan.write(convert.path_msg(v.stamp_s, np.asarray(v.plan_states)[:, :3], frame_id=c.odom_frame))
        if self._fix is not None and v.points_fix is not None:
            p = np.asarray(v.points_fix, dtype=np.float32)
            xyz = np.zeros((len(p), 3), np.float32)
            xyz[:, :2] = p[:, :2]
            self._fix.write(convert.pointcloud2_msg(v.stamp_s, xyz, frame_id=c.odom_frame))
        if self._mov is not None and v.points_mov is not None:
            self._mov.write(convert.pointcloud2_msg(v.stamp_s, v.points_mov, frame_id=c.lidar_frame))
        if self._markers is not None and v.clouds:
            self._markers.write(convert.footprint_markers(v.stamp_s, c.base_frame, *self._zones, v.state))

    def close(self, timeout_s: float = 2.0) -> None:
        """Publish what is queued (flush), then end the thread."""
        with self._cond:
            self._stop = True
            self._cond.notify()
        self._thread.join(timeout_s)

    def stats(self) -> dict:
        return {"offered": self.offered, "published": self.published, "dropped": self.dropped,
                "errors": self.errors, "last_error": self.last_error}


__all__ = ["RosPublisher", "TickView"]
