"""The rclpy transport: ROS 2 topics through rclpy, raw CDR in and out (runtime.io.ros.transport).

- Subscriptions are `raw=True`: rclpy hands each sample's serialized bytes to a callback, which
  appends them to a bounded deque (keep last `depth`, what the DDS reader itself keeps); the
  receiver thread takes them with `take_raw()` and decodes them with our decoders, so validation
  and named rejections are the same as on the cyclonedds path.
- Publishers take CDR bytes (`Publisher.publish(bytes)` publishes a serialized message).
- The executor is spun by the transport's own thread; `wait` returns when a callback delivered
  a sample, so the receiver thread sleeps between samples. Publishing (from the publisher
  thread) needs no executor.
- The message classes come from the ROS 2 Python packages (`sensor_msgs.msg.Imu`, ...). A type
  whose package is not importable (tf2_msgs, livox_ros_driver2 where only the pip wheels are
  installed) is carried by a cyclonedds participant in this process instead: the same wire
  format and DDS domain, so a stock ROS 2 node cannot tell; a sample on either path ends `wait`.

Security (SROS2): when a keystore is configured, ROS_SECURITY_KEYSTORE / ROS_SECURITY_ENABLE /
ROS_SECURITY_STRATEGY=Enforce are set and the node runs in the configured enclave. A ROS 2 build
without DDS Security then fails to start, which is what Enforce means.
"""
from __future__ import annotations

import contextlib
import importlib
import os
import threading
from collections import deque
from pathlib import Path

from runtime.io.ros.messages import ros_type_name
from runtime.io.ros.transport import (
    MiddlewareError, PublisherInfo, QosSpec, TopicReader, TopicWriter, Transport, TransportOptions, discovery_env,
)


#: Fast DDS's participant profile for our node: shared memory and socket buffers that carry a
#: camera image best effort (Fast DDS's defaults drop most samples above ~200 kB; the file says
#: why). Used unless the environment names a profile of its own.
FASTDDS_PROFILE = str(Path(__file__).with_name("fastdds_profile.xml"))
_FASTDDS_PROFILE_VARS = ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE")


def ros_message_class(type_name: str):
    """`sensor_msgs/msg/Imu` -> the rclpy message class, or None when its package is missing."""
    pkg, kind, name = type_name.split("/")
    try:
        return getattr(importlib.import_module(f"{pkg}.{kind}"), name)
    except (ImportError, AttributeError):
        return None


def _policy(kind) -> str:
    """rclpy's QoSPolicyKind as DDS names it (RELIABILITY, DURABILITY, ...)."""
    return getattr(kind, "name", str(kind)).removeprefix("RMW_QOS_POLICY_")


def _rclpy_qos(spec: QosSpec):
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=spec.depth,
        reliability=ReliabilityPolicy.BEST_EFFORT if spec.reliability == "best_effort" else ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE if spec.durability == "volatile" else DurabilityPolicy.TRANSIENT_LOCAL)


class _RawSubscription(TopicReader):
    def __init__(self, topic: str, depth: int) -> None:
        self.topic = topic
        self._samples: deque[bytes] = deque(maxlen=depth)
        self._lock = threading.Lock()
        self.subscription = None

    def on_sample(self, data: bytes) -> None:
        with self._lock:
            self._samples.append(data)

    def take_raw(self, n: int = 64) -> list[bytes]:
        with self._lock:
            out = []
            while self._samples and len(out) < n:
                out.append(self._samples.popleft())
        return out


class _RawPublisher(TopicWriter):
    def __init__(self, publisher, topic: str, cls: type) -> None:
        self.publisher, self.topic, self.cls = publisher, topic, cls

    def write_cdr(self, cdr: bytes) -> None:
        self.publisher.publish(bytes(cdr))


class RclpyTransport(Transport):
    """One rclpy node in its own context (its own domain id), spun by its own thread."""

    name = "rclpy"

    def __init__(self, options: TransportOptions) -> None:
        super().__init__()
        import rclpy
        from rclpy.executors import SingleThreadedExecutor

        self.domain_id, self.discovery = int(options.domain_id), options.discovery
        self.context = rclpy.Context()
        args = ["--ros-args", "--enclave", options.security_enclave] if options.security_keystore else None
        try:
            with _environment(options):
                rclpy.init(args=args, context=self.context, domain_id=self.domain_id)
                # No parameter services: the node has no ROS parameters (the config file is its
                # settings), and each service is one more entity the executor waits on per spin.
                self.node = rclpy.create_node(options.node_name, context=self.context,
                                              start_parameter_services=False)
        except MiddlewareError:
            raise
        except Exception as exc:  # noqa: BLE001 - rcl's errors (security files, rmw) as one line
            self.context.try_shutdown()
            why = str(exc).split("[INFO]")[0].splitlines()[0][:300]  # (rcl appends its log lines)
            raise MiddlewareError(f"rclpy could not start node {options.node_name!r} on domain {self.domain_id}: "
                                  f"{why}") from exc
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._guard = self.node.create_guard_condition(lambda: None)  # ends a spin_once at once
        self._cyclone = None
        self._fallback_readers: list = []
        self._lock = threading.Lock()
        self._arrived = threading.Condition()
        self._seq = self._seen = 0
        self._stopping = threading.Event()
        self.spin_errors = 0
        self.last_spin_error: str | None = None
        self._thread = threading.Thread(target=self._spin, name="ros_io-rclpy", daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        """The executor's thread: runs the subscriptions' callbacks as samples arrive."""
        while not self._stopping.is_set():
            try:
                self.executor.spin_once(timeout_sec=0.1)
            except Exception as exc:  # noqa: BLE001 - shutdown while spinning; anything else: counted, spin again
                if self._stopping.is_set():
                    return
                self.spin_errors += 1
                self.last_spin_error = f"{type(exc).__name__}: {exc}".splitlines()[0][:200]
                self._stopping.wait(0.1)  # the inputs go stale meanwhile and the monitor holds the robot

    def _notify(self) -> None:
        with self._arrived:
            self._seq += 1
            self._arrived.notify_all()

    def _fallback(self):
        """The in-process cyclonedds participant for types rclpy has no class for."""
        from runtime.io.ros.dds import CycloneTransport

        if self._cyclone is None:
            self._cyclone = CycloneTransport(self.domain_id, self.discovery)
        return self._cyclone

    def reader(self, topic: str, cls: type, qos: QosSpec) -> TopicReader:
        from rclpy.event_handler import SubscriptionEventCallbacks

        type_name = ros_type_name(cls)
        msg_cls = ros_message_class(type_name)
        if msg_cls is None:
            return self._fallback_reader(topic, cls, qos, type_name)
        sub = _RawSubscription(topic, qos.depth)

        def on_sample(data: bytes) -> None:
            sub.on_sample(data)
            self._notify()

        events = SubscriptionEventCallbacks(
            incompatible_qos=lambda info: self.incompatible_qos("in", topic, _policy(info.last_policy_kind)))
        sub.subscription = self.node.create_subscription(msg_cls, topic, on_sample, _rclpy_qos(qos), raw=True,
                                                         event_callbacks=events)
        self._route("in", topic, cls, qos, self.name)
        return sub

    def _fallback_reader(self, topic: str, cls: type, qos: QosSpec, type_name: str) -> TopicReader:
        fallback = self._fallback()
        fallback.incompatible_qos = self.incompatible_qos  # said (and counted) as this transport's
        # End `wait` when a sample arrives on the cyclonedds side too.
        reader = fallback.reader(topic, cls, qos, on_data=lambda _r: self._notify())
        self._fallback_readers.append(reader)
        self._route("in", topic, cls, qos, "cyclonedds",
                    f"rclpy has no {type_name} here (its Python package is not installed)")
        return reader

    def writer(self, topic: str, cls: type, qos: QosSpec) -> TopicWriter:
        from rclpy.event_handler import PublisherEventCallbacks

        type_name = ros_type_name(cls)
        msg_cls = ros_message_class(type_name)
        if msg_cls is None:
            self._route("out", topic, cls, qos, "cyclonedds",
                        f"rclpy has no {type_name} here (its Python package is not installed)")
            fallback = self._fallback()
            fallback.incompatible_qos = self.incompatible_qos
            return fallback.writer(topic, cls, qos)
        self._route("out", topic, cls, qos, self.name)
        events = PublisherEventCallbacks(
            incompatible_qos=lambda info: self.incompatible_qos("out", topic, _policy(info.last_policy_kind)))
        return _RawPublisher(self.node.create_publisher(msg_cls, topic, _rclpy_qos(qos), event_callbacks=events),
                             topic, cls)

    def wait(self, timeout_s: float) -> None:
        """Until a sample arrived since the last wait (or `wake`), at most timeout_s."""
        with self._arrived:
            if self._seq == self._seen and timeout_s > 0:
                self._arrived.wait(timeout_s)
            self._seen = self._seq

    def wake(self) -> None:
        self._notify()

    def publishers(self, topic: str) -> list[PublisherInfo]:
        """The writers rclpy's graph knows on `topic` (stock nodes and bare DDS apps alike); for a
        topic this transport carries through cyclonedds, the writers that participant sees."""
        from rclpy.qos import DurabilityPolicy, ReliabilityPolicy

        if self._cyclone is not None and any(r.topic == topic and r.via == "cyclonedds" for r in self._routes):
            return self._cyclone.publishers(topic)

        rel = {ReliabilityPolicy.RELIABLE: "reliable", ReliabilityPolicy.BEST_EFFORT: "best_effort"}
        dur = {DurabilityPolicy.VOLATILE: "volatile", DurabilityPolicy.TRANSIENT_LOCAL: "transient_local"}
        out = []
        for info in self.node.get_publishers_info_by_topic(topic):
            node = info.node_name if info.node_name != "_CREATED_BY_BARE_DDS_APP_" else ""
            who = f"node {info.node_namespace.rstrip('/')}/{node}" if node else "a bare DDS participant"
            out.append(PublisherInfo(topic, info.topic_type, rel.get(info.qos_profile.reliability),
                                     dur.get(info.qos_profile.durability), who))
        return out

    def close(self) -> None:
        with self._lock:
            if self.context is None:
                return
            for reader in self._fallback_readers:
                reader.set_listener(None)
            self._stopping.set()
            self._guard.trigger()
            self._thread.join(2.0)
            try:
                self.executor.shutdown(timeout_sec=1.0)
                self.node.destroy_node()
            finally:
                self.context.try_shutdown()
                self.context = None
                if self._cyclone is not None:
                    self._cyclone.close()


@contextlib.contextmanager
def _environment(options: TransportOptions):
    """rcl reads the discovery range and the SROS2 settings from the environment when the
    context and the node are made; they are set for that moment only, so that another node in
    this process (a test's) is not changed by them."""
    env = dict(discovery_env(options.discovery))
    env.pop("CYCLONEDDS_URI", None)   # ours is passed to cyclonedds directly (dds.CycloneTransport)
    if not any(os.environ.get(k) for k in _FASTDDS_PROFILE_VARS):  # a user's own profile wins
        env["FASTRTPS_DEFAULT_PROFILES_FILE"] = FASTDDS_PROFILE
    if options.security_keystore:
        if not os.path.isdir(options.security_keystore):
            raise MiddlewareError(f"ros.security.keystore: {options.security_keystore} is not a folder (create it "
                                  "with `ros2 security create_keystore` and the enclave with "
                                  "`ros2 security create_enclave`)")
        env.update({"ROS_SECURITY_KEYSTORE": options.security_keystore, "ROS_SECURITY_ENABLE": "true",
                    "ROS_SECURITY_STRATEGY": "Enforce"})
    env.update(options.extra_env)
    saved = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


__all__ = ["RclpyTransport", "ros_message_class"]
