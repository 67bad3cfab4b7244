"""What the publisher thread puts on the wire for an operator: /tf every tick, /tf_static once and
latched (a viewer that starts later still gets it), the safety markers, and a diagnostics status
line that says why the robot holds."""
from __future__ import annotations

import os
import time

import numpy as np

from runtime.common.geometry import Pose2D
from runtime.io.ros import messages as M
from runtime.io.ros.dds import CycloneTransport
from runtime.io.ros.publisher import RosPublisher, TickView
from runtime.io.ros.settings import RosOutputConfig
from runtime.io.ros.transport import TF, TF_STATIC, QosSpec

T_LIDAR = np.eye(4)
T_LIDAR[:3, 3] = [0.1, 0.0, 0.2]
FOOTPRINT = np.array([[0.16, 0.11], [-0.16, 0.11], [-0.16, -0.11], [0.16, -0.11]])


def _view(state="HOLDING", hold="IMU stale (no sample for 0.06 s)"):
    return TickView(stamp_s=time.time(), pose=Pose2D(1.0, 2.0, 0.5), v_mps=0.0, omega_radps=0.0, state=state,
                    stage_ms={"read": 0.1}, tick_ms=1.0, extra={"hold_reason": hold, "stop_reason": ""},
                    points_fix=np.zeros((5, 2)), plan_states=np.zeros((3, 3)), clouds=True)


def _first(reader, offer, timeout_s=15.0):
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        offer()
        got = reader.take_raw()
        if got:
            return got[-1]
        time.sleep(0.05)
    raise AssertionError(f"nothing on {reader.topic}")


def test_tf_static_markers_and_diagnostics_on_the_wire():
    domain = 221 + os.getpid() % 10  # (test_ros_transport: 205-220; test_ros_dds: 1-140)
    with CycloneTransport(domain, "localhost") as ours, CycloneTransport(domain, "localhost") as viewer:
        pub = RosPublisher(ours, RosOutputConfig(lidar_frame="livox_frame"),
                           static_transforms=[("base_link", "livox_frame", T_LIDAR)],
                           zones=(FOOTPRINT, FOOTPRINT * 1.1))
        time.sleep(0.5)  # /tf_static is written before this viewer exists: it must still get it
        tf = viewer.reader("/tf", M.TFMessage, TF)
        static = viewer.reader("/tf_static", M.TFMessage, TF_STATIC)
        markers = viewer.reader("/dct/safety_markers", M.MarkerArray, QosSpec("reliable", 10))
        diag = viewer.reader("/diagnostics", M.DiagnosticArray, QosSpec("reliable", 10))
        try:
            st = M.from_cdr(M.TFMessage, _first(static, lambda: None))
            (t,) = st.transforms
            assert (t.header.frame_id, t.child_frame_id) == ("base_link", "livox_frame")
            assert (t.transform.translation.x, t.transform.translation.z) == (0.1, 0.2)
            assert abs(time.time() - M.time_to_s(t.header.stamp)) < 60
            dyn = M.from_cdr(M.TFMessage, _first(tf, lambda: pub.offer(_view())))
            (t,) = dyn.transforms
            assert (t.header.frame_id, t.child_frame_id) == ("odom", "base_link")
            assert (t.transform.translation.x, t.transform.translation.y) == (1.0, 2.0)
            assert abs(t.transform.rotation.z - np.sin(0.25)) < 1e-12
            ma = M.from_cdr(M.MarkerArray, _first(markers, lambda: pub.offer(_view())))
            assert [m.ns for m in ma.markers] == ["dct/footprint", "dct/stop_zone"]
            assert all(m.header.frame_id == "base_link" for m in ma.markers)
            assert ma.markers[1].color.r > ma.markers[1].color.g  # red while holding
            status = M.from_cdr(M.DiagnosticArray, _first(diag, lambda: pub.offer(_view()))).status[0]
            assert status.message == "HOLDING: IMU stale (no sample for 0.06 s)" and status.level == M.DIAG_WARN
        finally:
            pub.close()
    assert pub.stats()["errors"] == 0, pub.stats()


class _Writer:
    def __init__(self, topic):
        self.topic, self.sent = topic, []

    def write(self, msg):
        self.sent.append(msg)


class _Transport:
    """Keeps what each writer was given (no DDS)."""

    def __init__(self):
        self.writers = {}

    def writer(self, topic, cls, qos):
        return self.writers.setdefault(topic, _Writer(topic))


def test_the_status_line_says_the_partition_fell_back_and_why():
    transport = _Transport()
    pub = RosPublisher(transport, RosOutputConfig())
    reason = "camera intrinsics: my_robot.yaml camera.fx: 336.0, the camera reports 346.1 (+3.0%, tolerance 1%)"
    view = TickView(stamp_s=time.time(), pose=Pose2D(0.0, 0.0, 0.0), v_mps=0.3, omega_radps=0.0, state="ACTIVE",
                    stage_ms={"read": 0.1}, tick_ms=1.0,
                    extra={"hold_reason": "", "stop_reason": "", "partition_fallback": reason,
                           "calibration_mismatch": reason})
    pub.offer(view)
    pub.offer(TickView(**{**view.__dict__, "extra": {**view.extra, "partition_fallback": "",
                                                     "calibration_mismatch": ""}}))
    pub.close()
    fell_back, normal = (a.status[0] for a in transport.writers["/diagnostics"].sent)
    assert fell_back.message == f"ACTIVE: partition all-fixed: {reason}" and fell_back.level == M.DIAG_WARN
    assert {kv.key: kv.value for kv in fell_back.values}["partition_fallback"] == reason
    assert normal.message == "ACTIVE" and normal.level == M.DIAG_OK
