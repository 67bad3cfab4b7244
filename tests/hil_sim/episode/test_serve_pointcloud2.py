"""`dct hil serve` publishes the lidar as the controller's config reads it: a PointCloud2 in
livox_ros_driver2's xfer_format 0 layout, or the Livox CustomMsg. What it sends, the controller's
receiver turns back into the same points at the same times."""
from __future__ import annotations

import time

import numpy as np
import pytest

from hil_sim.episode.serve import DdsSensorSink, lidar_pointcloud2_cdr
from runtime.common.sensor_data import LidarScan
from runtime.io.ros import convert as C
from runtime.io.ros.receiver import LidarTopic, RosInputConfig, RosSensorReceiver, decode_cdr
from runtime.io.sensor_inbox import SensorInbox

WALL0 = 1_760_000_000.125       # the simulated clock's 0 on the wall clock (ROS time)
PC2 = "sensor_msgs/msg/PointCloud2"


def sim_scan(k: int, n: int = 3000, stamp_s: float = 2.0) -> LidarScan:
    """A frame as the simulator's lidar makes it (points sorted by time within 0.1 s)."""
    rng = np.random.default_rng(k)
    return LidarScan(stamp_s=stamp_s + 0.1 * k, points_m=rng.uniform(-20, 20, (n, 3)).astype(np.float32),
                     point_time_offsets_s=np.sort(rng.uniform(0, 0.1, n)).astype(np.float32), frame_duration_s=0.1,
                     frame_id="livox_frame")


def test_serve_encoding_round_trips_through_the_receivers_decoder():
    scan = sim_scan(0)
    timebase = int(round((WALL0 + scan.stamp_s) * 1e9))
    back = C.pointcloud2_to_scan(decode_cdr(PC2, lidar_pointcloud2_cdr(scan, timebase)))
    np.testing.assert_array_equal(back.points_m, scan.points_m)
    assert back.frame_id == "livox_frame"
    # per-point times: float64 ns of a 2025 time resolve 256 ns
    np.testing.assert_allclose(back.point_stamps_s() - WALL0, scan.point_stamps_s(), rtol=0, atol=1e-6)
    assert back.frame_duration_s == pytest.approx(scan.frame_duration_s, abs=1e-6)


@pytest.mark.parametrize("lidar_type,domain_id", [(PC2, 161), ("livox_ros_driver2/msg/CustomMsg", 162)])
def test_dds_sensor_sink_publishes_what_the_controller_reads(lidar_type, domain_id):
    from runtime.io.ros.dds import CycloneTransport

    inputs = RosInputConfig(domain_id=domain_id, lidar=LidarTopic(topic="/livox/lidar", type=lidar_type))
    transport = CycloneTransport(domain_id)
    sink = DdsSensorSink(transport, inputs, lambda t: WALL0 + t)
    inbox = SensorInbox()
    rx = RosSensorReceiver(inputs, inbox, transport)
    sent, got = [], []
    end = time.monotonic() + 15.0
    while not got and time.monotonic() < end:   # best effort: send until the reader is matched
        sent.append(sim_scan(len(sent)))
        assert sink.put_scan(sent[-1])
        rx.poll(timeout_s=0.1)
        snap = inbox.take()
        if snap.scan is not None:
            got.append(snap.scan)
    assert got, f"nothing received ({rx.error_counts}, {rx.last_error})"
    assert rx.error_counts == {} and rx.lidar_time_notice is None
    back = got[-1]
    scan = min(sent, key=lambda s: abs(WALL0 + s.stamp_s - back.stamp_s))
    np.testing.assert_array_equal(back.points_m, scan.points_m)
    np.testing.assert_allclose(back.point_stamps_s() - WALL0, scan.point_stamps_s(), rtol=0, atol=1e-6)
    assert sink.published["lidar"] == len(sent)
