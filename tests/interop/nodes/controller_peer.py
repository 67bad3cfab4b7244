"""A stock ROS 2 node around `dct run`: the robot's drivers and its operator, in rclpy only.

Published, as drivers publish them:
- a lidar, sensor_msgs/PointCloud2 at 10 Hz with a per-point time field `t` (uint32, ns after the
  header stamp, as Ouster's driver writes it): about 5000 points of a static room whose walls are
  2-4 m away, placed in the sensor frame by the pose the controller itself reports on its
  odometry, so the room stays put in the odometry frame while the robot drives;
- sensor_msgs/Imu at 200 Hz (its own thread, samples stamped at their nominal times);
- sensor_msgs/Image, rgb8, at 10 Hz as a camera driver publishes it (0.9 MB each: with Fast DDS's
  defaults and a kernel's default socket buffers many are lost on the way, so it takes several);
- as an operator from RViz: a geometry_msgs/PoseStamped goal (reliable) on the goal topic, once
  a subscription is matched and until the controller's odometry shows it has started.

Read back: nav_msgs/Odometry, nav_msgs/Path, the P_fix cloud (PointCloud2),
diagnostic_msgs/DiagnosticArray and visualization_msgs/MarkerArray (the safety markers, where they
are published), and from the ROS graph the publishers of /tf and /tf_static (tf2_msgs is not
installed beside these wheels, so the graph is all a stock node can see of them).

What it saw goes to --out as JSON. Exit 0 when it ran (whatever it saw), 1 on a crash.
"""
from __future__ import annotations

import argparse
import array
import math
import sys
import threading
import time

import numpy as np
from rclpy.duration import Duration
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry, Path
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import Image, Imu, PointCloud2, PointField
from visualization_msgs.msg import MarkerArray

from stock_common import endpoints, finite, public, qos, run_node, stamp_s

ROOM = (-2.0, 3.5, -2.5, 2.5)         # x min, x max, y min, y max in the odometry frame (m)
WALL_HEIGHTS_M = (0.1, 0.2, 0.3, 0.4, 0.5)
POINTS_PER_LAYER = 1000
SWEEP_S = 0.1
CLOUD_DTYPE = np.dtype({"names": ["x", "y", "z", "intensity", "t"], "formats": ["<f4", "<f4", "<f4", "<f4", "<u4"],
                        "offsets": [0, 4, 8, 12, 16], "itemsize": 20})
PF_NUMPY = {PointField.INT8: "i1", PointField.UINT8: "u1", PointField.INT16: "i2", PointField.UINT16: "u2",
            PointField.INT32: "i4", PointField.UINT32: "u4", PointField.FLOAT32: "f4", PointField.FLOAT64: "f8"}


def room_points() -> np.ndarray:
    """(N, 3) points on the room's walls, odometry frame."""
    x0, x1, y0, y1 = ROOM
    corners = np.array([(x0, y0), (x1, y0), (x1, y1), (x0, y1), (x0, y0)])
    seg = np.diff(corners, axis=0)
    lengths = np.hypot(seg[:, 0], seg[:, 1])
    s = np.linspace(0.0, lengths.sum(), POINTS_PER_LAYER, endpoint=False)
    k = np.searchsorted(np.cumsum(lengths), s, side="right")
    start = np.concatenate([[0.0], np.cumsum(lengths)[:-1]])
    xy = corners[k] + seg[k] * ((s - start[k]) / lengths[k])[:, None]
    return np.concatenate([np.column_stack([xy, np.full(len(xy), z)]) for z in WALL_HEIGHTS_M])


def wall_distance(xy: np.ndarray) -> np.ndarray:
    """Each point's distance to the nearest wall line of the room."""
    x0, x1, y0, y1 = ROOM
    return np.min(np.abs(np.stack([xy[:, 0] - x0, xy[:, 0] - x1, xy[:, 1] - y0, xy[:, 1] - y1])), axis=0)


def cloud_array(msg: PointCloud2) -> np.ndarray:
    """The message's points as a numpy record array, from the fields it declares."""
    fields = [f for f in msg.fields if f.datatype in PF_NUMPY]
    order = ">" if msg.is_bigendian else "<"
    dtype = np.dtype({"names": [f.name for f in fields], "formats": [order + PF_NUMPY[f.datatype] for f in fields],
                      "offsets": [f.offset for f in fields], "itemsize": msg.point_step})
    n = msg.width * msg.height
    return np.frombuffer(bytes(msg.data), dtype=dtype, count=n) if n else np.zeros(0, dtype)


#: How long images go to a matched camera reader before the node is done: with a kernel's default
#: socket buffers (net.core.rmem_max 208 kB) 7 to 15 of about 50 arrived beside two busy processes.
IMAGES_FOR_S = 5.0


class Peer:
    def __init__(self, node, args) -> None:
        self.node, self.args = node, args
        self.pose = (0.0, 0.0, 0.0)
        self.yaw_rate = 0.0
        self.room = room_points()
        self.rng = np.random.default_rng(0)
        self.published = {"lidar": 0, "imu": 0, "image": 0, "goal": 0}
        self.image_matched_at: float | None = None  # when the controller's camera reader was first matched
        self.seen = {"odom": [], "plan": [], "p_fix": [], "diagnostics": [], "markers": []}
        self.first_odom_at: float | None = None
        self.imu_max_gap_s = 0.0
        self.stop = threading.Event()
        self.lidar_pub = node.create_publisher(PointCloud2, args.lidar_topic, qos_profile_sensor_data)
        self.imu_pub = node.create_publisher(Imu, args.imu_topic, qos_profile_sensor_data)
        self.image_pub = node.create_publisher(Image, args.image_topic, qos_profile_sensor_data)
        self.goal_pub = node.create_publisher(PoseStamped, args.goal_topic, qos("reliable", 1))
        node.create_subscription(Odometry, "/dct/odom", self.on_odom, qos("reliable", 10))
        node.create_subscription(Path, "/dct/plan", self.on_plan, qos("reliable", 10))
        node.create_subscription(PointCloud2, "/dct/p_fix", self.on_p_fix, qos_profile_sensor_data)
        node.create_subscription(DiagnosticArray, "/diagnostics", self.on_diagnostics, qos("reliable", 10))
        node.create_subscription(MarkerArray, "/dct/safety_markers", self.on_markers, qos("best_effort", 10))
        self.image = self.make_image(args.width, args.height)
        node.create_timer(SWEEP_S, self.publish_lidar)
        node.create_timer(0.1, self.publish_image)
        node.create_timer(1.0, self.publish_goal)
        self.imu_rng = np.random.default_rng(1)  # the IMU thread's own (the lidar's is the timer's)
        self.imu_thread = threading.Thread(target=self.imu_loop, daemon=True)
        self.imu_thread.start()

    # -- what a driver publishes

    def publish_lidar(self) -> None:
        x, y, yaw = self.pose
        c, s = math.cos(yaw), math.sin(yaw)
        room = self.room + self.rng.normal(0.0, 0.005, self.room.shape)  # range noise: no two frames alike
        dx, dy = room[:, 0] - x, room[:, 1] - y
        mx, mz = self.args.lidar_mount
        pts = np.zeros(len(self.room), CLOUD_DTYPE)
        pts["x"], pts["y"] = c * dx + s * dy - mx, -s * dx + c * dy
        pts["z"] = room[:, 2] - mz
        pts["intensity"] = 50.0
        azimuth = np.arctan2(pts["y"], pts["x"])
        pts["t"] = ((azimuth + math.pi) / (2 * math.pi) * SWEEP_S * 1e9).astype(np.uint32)
        pts = pts[np.argsort(pts["t"], kind="stable")]
        msg = PointCloud2()
        # stamped at the sweep's start, published at its end (as a spinning lidar's driver does)
        msg.header.stamp = (self.node.get_clock().now() - Duration(nanoseconds=int(SWEEP_S * 1e9))).to_msg()
        msg.header.frame_id = "lidar"
        msg.height, msg.width = 1, len(pts)
        msg.fields = [PointField(name=n, offset=o, datatype=d, count=1) for n, o, d in (
            ("x", 0, PointField.FLOAT32), ("y", 4, PointField.FLOAT32), ("z", 8, PointField.FLOAT32),
            ("intensity", 12, PointField.FLOAT32), ("t", 16, PointField.UINT32))]
        msg.is_bigendian, msg.point_step, msg.row_step, msg.is_dense = False, 20, 20 * len(pts), True
        data = array.array("B")
        data.frombytes(pts.tobytes())
        msg.data = data
        self.lidar_pub.publish(msg)
        self.published["lidar"] += 1

    def imu_loop(self) -> None:
        period = 1.0 / 200.0
        t_next = time.time()
        msg = Imu()
        msg.header.frame_id = "imu"
        msg.orientation_covariance[0] = -1.0       # no orientation (the ROS convention)
        msg.linear_acceleration.z = 9.81
        last = time.monotonic()
        while not self.stop.is_set():
            now = time.time()
            gap, last = time.monotonic() - last, time.monotonic()
            self.imu_max_gap_s = max(self.imu_max_gap_s, gap)
            if now - t_next > 0.2:                 # stalled for long: start again from now
                t_next = now
            while t_next <= now:
                msg.header.stamp.sec = int(t_next)
                msg.header.stamp.nanosec = int((t_next - int(t_next)) * 1e9)
                # a MEMS part's noise: no two samples alike (20 alike in a row is a stuck IMU)
                noise = self.imu_rng.normal(0.0, 1e-3, 6)
                msg.angular_velocity.x, msg.angular_velocity.y = float(noise[0]), float(noise[1])
                msg.angular_velocity.z = self.yaw_rate + float(noise[2])
                msg.linear_acceleration.x, msg.linear_acceleration.y = float(noise[3]), float(noise[4])
                msg.linear_acceleration.z = 9.81 + float(noise[5])
                self.imu_pub.publish(msg)
                self.published["imu"] += 1
                t_next += period
            time.sleep(max(0.0, t_next - time.time()))

    @staticmethod
    def make_image(width: int, height: int) -> Image:
        img = Image()
        img.header.frame_id = "camera"
        img.height, img.width, img.encoding, img.is_bigendian, img.step = height, width, "rgb8", 0, 3 * width
        px = np.zeros((height, width, 3), np.uint8)
        px[..., 0] = np.linspace(0, 255, width, dtype=np.uint8)[None, :]
        px[..., 1] = np.linspace(0, 255, height, dtype=np.uint8)[:, None]
        px[..., 2] = 128
        data = array.array("B")
        data.frombytes(px.tobytes())
        img.data = data
        return img

    def publish_image(self) -> None:
        if self.image_matched_at is None and self.image_pub.get_subscription_count() > 0:
            self.image_matched_at = time.monotonic()
        self.image.header.stamp = self.node.get_clock().now().to_msg()
        self.image_pub.publish(self.image)
        self.published["image"] += 1

    def publish_goal(self) -> None:
        """Until the controller has started (its odometry arrives), once a subscription is matched."""
        if self.first_odom_at is not None or self.goal_pub.get_subscription_count() == 0:
            return
        msg = PoseStamped()
        msg.header.stamp = self.node.get_clock().now().to_msg()
        msg.header.frame_id = "odom"
        msg.pose.position.x, msg.pose.position.y = self.args.goal
        msg.pose.orientation.w = 1.0
        self.goal_pub.publish(msg)
        self.published["goal"] += 1

    # -- what the controller publishes

    def age_s(self, header) -> float:
        return time.time() - stamp_s(header)

    def on_odom(self, m: Odometry) -> None:
        p, q, tw = m.pose.pose.position, m.pose.pose.orientation, m.twist.twist
        yaw = math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))
        ok = (finite(p.x, p.y, p.z, q.x, q.y, q.z, q.w, tw.linear.x, tw.linear.y, tw.angular.z)
              and finite(*m.pose.covariance, *m.twist.covariance))
        if ok:  # the lidar's room and the IMU's yaw rate follow the controller's own odometry
            self.pose, self.yaw_rate = (p.x, p.y, yaw), tw.angular.z
        if self.first_odom_at is None:
            self.first_odom_at = time.monotonic()
        self.seen["odom"].append({"frame": m.header.frame_id, "child": m.child_frame_id, "finite": ok,
                                  "quat_norm": math.sqrt(q.x ** 2 + q.y ** 2 + q.z ** 2 + q.w ** 2),
                                  "pose": [p.x, p.y, yaw], "v": tw.linear.x, "age_s": self.age_s(m.header)})

    def on_plan(self, m: Path) -> None:
        poses = [(ps.header.frame_id, ps.pose.position.x, ps.pose.position.y, ps.pose.orientation.z,
                  ps.pose.orientation.w) for ps in m.poses]
        self.seen["plan"].append({"frame": m.header.frame_id, "n": len(poses),
                                  "pose_frames": sorted({f for f, *_ in poses}),
                                  "finite": all(finite(*v) for _, *v in poses),
                                  "first": list(poses[0][1:3]) if poses else None, "age_s": self.age_s(m.header)})

    def on_p_fix(self, m: PointCloud2) -> None:
        pts = cloud_array(m)
        xy = np.column_stack([pts["x"], pts["y"]]).astype(np.float64) if len(pts) else np.zeros((0, 2))
        near = float(np.mean(wall_distance(xy) < 0.3)) if len(xy) else None
        self.seen["p_fix"].append({"frame": m.header.frame_id, "n": int(m.width * m.height),
                                   "fields": [f.name for f in m.fields], "point_step": m.point_step,
                                   "size_ok": len(m.data) == m.row_step * m.height,
                                   "finite": bool(np.all(np.isfinite(xy))), "near_walls": near,
                                   "age_s": self.age_s(m.header)})

    def on_diagnostics(self, m: DiagnosticArray) -> None:
        for s in m.status:
            level = s.level if isinstance(s.level, int) else int.from_bytes(s.level, "little")
            self.seen["diagnostics"].append({"name": s.name, "level": level,
                                             "values": {kv.key: kv.value for kv in s.values},
                                             "age_s": self.age_s(m.header)})

    def on_markers(self, m: MarkerArray) -> None:
        self.seen["markers"].append([{"frame": mk.header.frame_id, "ns": mk.ns, "type": mk.type,
                                      "action": mk.action,
                                      "finite": finite(mk.pose.position.x, mk.pose.position.y, mk.pose.position.z,
                                                       mk.pose.orientation.w, *[c for p in mk.points
                                                                                for c in (p.x, p.y, p.z)])}
                                     for mk in m.markers])

    def report(self) -> dict:
        """Stop the IMU thread; what was published and seen, and the graph as this node saw it."""
        self.stop.set()
        self.imu_thread.join(1.0)
        return {"published": self.published, "imu_max_gap_s": self.imu_max_gap_s, "seen": self.seen,
                "graph": self.graph(), "done": self.done(), "goal": list(self.args.goal)}

    def done(self) -> bool:
        s = self.seen
        now = time.monotonic()
        return (self.first_odom_at is not None and now - self.first_odom_at > self.args.collect_s
                and self.image_matched_at is not None and now - self.image_matched_at > IMAGES_FOR_S
                and len(s["odom"]) >= 5 and sum(p["n"] > 0 for p in s["plan"]) >= 2 and len(s["p_fix"]) >= 2
                and len(s["diagnostics"]) >= 3)

    def graph(self) -> dict:
        a = self.args
        out = {f"pub {t}": public(endpoints(self.node, t, "pub"))
               for t in ("/tf", "/tf_static", "/dct/safety_markers", "/dct/odom", "/dct/plan", "/dct/p_fix",
                         "/diagnostics")}
        out.update({f"sub {t}": public(endpoints(self.node, t, "sub"))
                    for t in (a.lidar_topic, a.imu_topic, a.image_topic, a.goal_topic)})
        return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--lidar-topic", default="/lidar/points")
    ap.add_argument("--imu-topic", default="/imu/data")
    ap.add_argument("--image-topic", default="/camera/image_raw")
    ap.add_argument("--goal-topic", default="/goal_pose")
    ap.add_argument("--goal", nargs=2, type=float, default=(1.0, 0.0))
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--lidar-mount", nargs=2, type=float, default=(0.0, 0.0), metavar=("X", "Z"))
    ap.add_argument("--collect-s", type=float, default=3.0)
    ap.add_argument("--timeout-s", type=float, default=90.0)
    args = ap.parse_args()
    return run_node("stock_peer", lambda node: Peer(node, args), args.out, args.timeout_s)


if __name__ == "__main__":
    sys.exit(main())
