"""A stock ROS 2 node listening to the simulated robot's sensors, in rclpy only.

It subscribes to the IMU (sensor_msgs/Imu) and the camera (sensor_msgs/Image) with the ROS 2
sensor-data profile, as RViz or a recorder would, and measures from the first IMU sample: the IMU
for --window-s seconds, the camera until it has --min-images images too (best-effort images of
~1 MB travel as UDP fragments and some are lost); how many arrived, their rates by arrival and by
stamp, and what they carry (frame ids, finite values, the image's size and encoding). The lidar is a Livox CustomMsg,
whose package (livox_ros_driver2) is not installed here: the node reads its type name and QoS
from the ROS graph instead.

What it saw goes to --out as JSON. Exit 0 when it ran, 1 on a crash.
"""
from __future__ import annotations

import argparse
import math
import statistics
import sys
import time

from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import Image, Imu

from stock_common import endpoints, finite, public, stamp_s, run_node


def rates(arrivals: list[float], stamps: list[float], gaps: bool = True) -> dict:
    """Counts and rates of one stream: by arrival (wall) and by its stamps (and each stamp gap)."""
    n = len(arrivals)
    stamp_gaps = [b - a for a, b in zip(stamps, stamps[1:])]
    return {
        "count": n,
        "arrival_hz": (n - 1) / (arrivals[-1] - arrivals[0]) if n > 1 and arrivals[-1] > arrivals[0] else None,
        "stamp_hz": (n - 1) / (stamps[-1] - stamps[0]) if n > 1 and stamps[-1] > stamps[0] else None,
        "median_stamp_gap_s": statistics.median(stamp_gaps) if stamp_gaps else None,
        "stamp_gaps_s": stamp_gaps if gaps else None,
        "stamps_increasing": all(g > 0 for g in stamp_gaps),
        "max_age_s": max((a - s for a, s in zip(arrivals, stamps)), default=None),
    }


class Listener:
    def __init__(self, node, args) -> None:
        self.node, self.args = node, args
        self.imu = {"arrivals": [], "stamps": [], "frames": set(), "finite": True, "accel_norms": [], "gyro_max": 0.0}
        self.camera = {"arrivals": [], "stamps": [], "frames": set(), "shapes": set(), "size_ok": True,
                       "mean_pixel": []}
        self.window_start: float | None = None
        node.create_subscription(Imu, args.imu_topic, self.on_imu, qos_profile_sensor_data)
        node.create_subscription(Image, args.camera_topic, self.on_image, qos_profile_sensor_data)

    def in_window(self) -> bool:
        return self.window_start is not None and time.monotonic() - self.window_start <= self.args.window_s

    def on_imu(self, m: Imu) -> None:
        if self.window_start is None:
            self.window_start = time.monotonic()
        if not self.in_window():
            return
        a, w = m.linear_acceleration, m.angular_velocity
        d = self.imu
        d["arrivals"].append(time.time())
        d["stamps"].append(stamp_s(m.header))
        d["frames"].add(m.header.frame_id)
        d["finite"] &= finite(a.x, a.y, a.z, w.x, w.y, w.z)
        d["accel_norms"].append(math.sqrt(a.x * a.x + a.y * a.y + a.z * a.z))
        d["gyro_max"] = max(d["gyro_max"], abs(w.x), abs(w.y), abs(w.z))

    def on_image(self, m: Image) -> None:
        if self.window_start is None or self.done():
            return
        d = self.camera
        d["arrivals"].append(time.time())
        d["stamps"].append(stamp_s(m.header))
        d["frames"].add(m.header.frame_id)
        d["shapes"].add((m.width, m.height, m.encoding, m.step))
        d["size_ok"] &= len(m.data) == m.step * m.height
        data = bytes(m.data)
        d["mean_pixel"].append(sum(data[::997]) / max(1, len(data[::997])))

    def done(self) -> bool:
        return (self.window_start is not None and time.monotonic() - self.window_start > self.args.window_s
                and len(self.camera["arrivals"]) >= self.args.min_images)

    def report(self) -> dict:
        imu, cam = self.imu, self.camera
        norms = sorted(imu["accel_norms"])
        return {
            "done": self.done(),
            "imu": {**rates(imu["arrivals"], imu["stamps"], gaps=False), "frames": sorted(imu["frames"]),
                    "finite": imu["finite"],
                    "accel_norm_median": norms[len(norms) // 2] if norms else None, "gyro_max": imu["gyro_max"]},
            "camera": {**rates(cam["arrivals"], cam["stamps"]), "frames": sorted(cam["frames"]),
                       "shapes": sorted(cam["shapes"]), "size_ok": cam["size_ok"],
                       "mean_pixel": cam["mean_pixel"]},
            "graph": {topic: public(endpoints(self.node, topic, "pub"))
                      for topic in (self.args.lidar_topic, self.args.imu_topic, self.args.camera_topic)},
        }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--imu-topic", default="/livox/imu")
    ap.add_argument("--camera-topic", default="/camera/color/image_raw")
    ap.add_argument("--lidar-topic", default="/livox/lidar")
    ap.add_argument("--window-s", type=float, default=4.0)
    ap.add_argument("--min-images", type=int, default=5)
    ap.add_argument("--timeout-s", type=float, default=90.0)
    args = ap.parse_args()
    return run_node("stock_sensor_listener", lambda node: Listener(node, args), args.out, args.timeout_s)


if __name__ == "__main__":
    sys.exit(main())
