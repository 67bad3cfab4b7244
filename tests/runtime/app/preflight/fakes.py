"""Stand-ins for the robot that `dct preflight` talks to, for the preflight and deploy tests:
the emulated base firmware on a CAN bus (stepped by a thread at wall-clock time, wheels still),
a publisher of the sensor topics (Livox CustomMsg, IMU, camera image) over DDS, and a stock
rclpy node's publisher (the graph shows its type and QoS as ROS 2 reports them)."""
from __future__ import annotations

import os
import threading
import time

import numpy as np

from calibration.robot_description import load_robot_description
from firmware_bridge.buses import BusConfig, open_bus
from firmware_bridge.firmware_emulator import EmulatedBaseFirmware


def unique_port() -> int:
    """A udp_multicast port of this test process (parallel runs on one machine never share one)."""
    return 20000 + os.getpid() % 20000


def unique_domain() -> int:
    return 1 + (os.getpid() + 101) % 200


class EmulatedBase:
    """The base firmware answering on `bus_config`, stepped every 2 ms in a thread."""

    def __init__(self, bus_config: BusConfig, *, estop: bool = False) -> None:
        self.bus = open_bus(bus_config)
        self.firmware = EmulatedBaseFirmware(self.bus, load_robot_description())
        self.firmware.emergency_stop = estop
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="emulated-base", daemon=True)

    def _run(self) -> None:
        t0 = time.monotonic()
        still = np.zeros(4)
        while not self._stop.is_set():
            self.firmware.step(time.monotonic() - t0, still, still)
            time.sleep(0.002)

    def __enter__(self) -> "EmulatedBase":
        self._thread.start()
        end = time.monotonic() + 10.0       # a real base is already running when preflight starts
        while self.firmware.frames_sent == 0 and time.monotonic() < end:
            time.sleep(0.01)
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.bus.shutdown()


class SensorPublisher:
    """Publishes the shipped controller config's sensor topics (ros.inputs) at `rates_hz` (stream -> Hz) on
    `domain_id`, stamped with this computer's clock plus `clock_offset_s` (a driver on another clock)."""

    def __init__(self, domain_id: int, rates_hz: dict[str, float], *, clock_offset_s: float = 0.0) -> None:
        from cyclonedds.domain import DomainParticipant

        from runtime.io.ros import messages as M
        from runtime.io.ros.dds import RosWriter, ros_qos

        from runtime.config import load_controller_config

        self.M = M
        topics = load_controller_config(None).ros.inputs  # what preflight reads from the shipped config
        dp = DomainParticipant(domain_id)
        self.writers = {}
        if "lidar" in rates_hz:
            self.writers["lidar"] = RosWriter(dp, topics.lidar.topic, M.CustomMsg, ros_qos())
        if "imu" in rates_hz:
            self.writers["imu"] = RosWriter(dp, topics.imu.topic, M.Imu, ros_qos(depth=50))
        if "camera" in rates_hz:
            self.writers["camera"] = RosWriter(dp, topics.camera.topic, M.Image, ros_qos())
        self.rates_hz = rates_hz
        self.clock_offset_s = clock_offset_s
        self.sent = {s: 0 for s in rates_hz}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="sensor-publisher", daemon=True)

    def _message(self, stream: str, k: int):
        M = self.M
        now = time.time() + self.clock_offset_s
        stamp = M.stamp_to_time(now)
        if stream == "lidar":  # a frame whose sweep (90 ms) has just ended, as a Livox driver sends it
            pts = np.zeros(100, M.CUSTOM_POINT_DTYPE)
            pts["offset_time"] = np.arange(100) * 900_000
            pts["x"] = 2.0
            timebase = int((now - 0.0891) * 1e9)
            return M.encode_custom_msg(M.Header(M.Time(timebase // 10**9, timebase % 10**9), "livox"), timebase, pts)
        if stream == "imu":
            return M.Imu(header=M.Header(stamp, "imu"), linear_acceleration=M.Vector3(0.0, 0.0, 9.81))
        return M.Image(M.Header(stamp, "camera"), 4, 6, "bgr8", 0, 18, bytes(72))

    def _run(self) -> None:
        t0 = time.monotonic()
        due = {s: t0 for s in self.rates_hz}
        while not self._stop.is_set():
            now = time.monotonic()
            for s, rate in self.rates_hz.items():
                if now >= due[s]:
                    msg = self._message(s, self.sent[s])
                    if isinstance(msg, bytes):
                        self.writers[s].write_cdr(msg)
                    else:
                        self.writers[s].write(msg)
                    self.sent[s] += 1
                    due[s] += 1.0 / rate
                    if due[s] < now:        # fell far behind (a loaded machine): do not burst
                        due[s] = now + 1.0 / rate
            time.sleep(0.001)

    def __enter__(self) -> "SensorPublisher":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(2.0)


class RclpyPublisher:
    """A stock rclpy node publishing `msg_cls` (an rclpy message class) on `topic` with a QoS."""

    def __init__(self, domain_id: int, topic: str, msg_cls, *, reliability: str = "reliable",
                 durability: str = "volatile") -> None:
        import rclpy
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node = rclpy.create_node("stock_publisher", context=self.context)
        qos = QoSProfile(depth=1, reliability=getattr(ReliabilityPolicy, reliability.upper()),
                         durability=getattr(DurabilityPolicy, durability.upper()))
        self.publisher = self.node.create_publisher(msg_cls, topic, qos)
        self.msg_cls = msg_cls

    def __enter__(self) -> "RclpyPublisher":
        return self

    def __exit__(self, *exc) -> None:
        self.node.destroy_node()
        self.context.try_shutdown()
