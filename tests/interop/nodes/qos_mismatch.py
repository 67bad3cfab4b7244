"""A stock ROS 2 node whose QoS does not match the controller's, in rclpy only.

- It publishes goals (geometry_msgs/PoseStamped) best effort on the goal topic, which the
  controller reads reliably: DDS never matches the two, so no goal arrives, and nothing says so
  on the data path.
- It subscribes reliably to the P_fix cloud, which the controller publishes best effort: nothing
  arrives. A best-effort subscription beside it is the control: the cloud does flow.

What shows the mismatch: the ROS graph lists the controller's endpoints with their QoS
(`get_subscriptions_info_by_topic`, `get_publishers_info_by_topic`) while the node's own
endpoints have matched none of them (`get_subscription_count`, `get_publisher_count`);
`rclpy.qos.qos_check_compatible` on the two profiles says ERROR with the reason; and the
middleware may raise incompatible-QoS events, counted here.

What it saw goes to --out as JSON. Exit 0 when it ran, 1 on a crash.
"""
from __future__ import annotations

import argparse
import sys
import time

from geometry_msgs.msg import PoseStamped
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.qos import qos_check_compatible
from sensor_msgs.msg import PointCloud2

from stock_common import endpoints, public, qos, run_node


def compatibility(pub_profile, sub_profile) -> dict:
    level, reason = qos_check_compatible(pub_profile, sub_profile)
    return {"level": level.name, "reason": reason.strip()}


class Mismatch:
    def __init__(self, node, args) -> None:
        self.node, self.args = node, args
        self.events = {"goal_publisher": 0, "cloud_subscription": 0}
        self.received = {"reliable": 0, "best_effort": 0}
        self.goals_published = 0
        self.goal_qos = qos("best_effort", 1)
        self.reliable_qos, self.best_effort_qos = qos("reliable", 1), qos("best_effort", 1)
        self.goal_pub = node.create_publisher(
            PoseStamped, args.goal_topic, self.goal_qos,
            event_callbacks=PublisherEventCallbacks(incompatible_qos=lambda _s: self.count("goal_publisher")))
        self.reliable_sub = node.create_subscription(
            PointCloud2, args.cloud_topic, lambda _m: self.got("reliable"), self.reliable_qos,
            event_callbacks=SubscriptionEventCallbacks(incompatible_qos=lambda _s: self.count("cloud_subscription")))
        self.control_sub = node.create_subscription(PointCloud2, args.cloud_topic, lambda _m: self.got("best_effort"),
                                                    self.best_effort_qos)
        self.first_control_at: float | None = None
        node.create_timer(0.1, self.publish_goal)

    def count(self, which: str) -> None:
        self.events[which] += 1

    def got(self, which: str) -> None:
        self.received[which] += 1
        if which == "best_effort" and self.first_control_at is None:
            self.first_control_at = time.monotonic()

    def publish_goal(self) -> None:
        msg = PoseStamped()
        msg.header.stamp = self.node.get_clock().now().to_msg()
        msg.header.frame_id = "odom"
        msg.pose.position.x, msg.pose.position.y = self.args.goal
        msg.pose.orientation.w = 1.0
        self.goal_pub.publish(msg)
        self.goals_published += 1

    def done(self) -> bool:
        """The cloud has flowed to the control subscription for a while (the reliable one had its chance)."""
        return (self.first_control_at is not None and time.monotonic() - self.first_control_at > self.args.collect_s
                and self.received["best_effort"] >= 5)

    def report(self) -> dict:
        goal_subs = endpoints(self.node, self.args.goal_topic, "sub")
        cloud_pubs = [e for e in endpoints(self.node, self.args.cloud_topic, "pub")]
        return {
            "goal": list(self.args.goal), "goals_published": self.goals_published, "received": self.received,
            "incompatible_qos_events": self.events,
            "matched": {"goal_publisher": self.goal_pub.get_subscription_count(),
                        "cloud_reliable": self.reliable_sub.get_publisher_count(),
                        "cloud_best_effort": self.control_sub.get_publisher_count()},
            "graph": {"goal_subscriptions": public(goal_subs), "cloud_publishers": public(cloud_pubs)},
            "compatibility": {
                "goal": [compatibility(self.goal_qos, e["profile"]) for e in goal_subs],
                "cloud_reliable": [compatibility(e["profile"], self.reliable_qos) for e in cloud_pubs],
                "cloud_best_effort": [compatibility(e["profile"], self.best_effort_qos) for e in cloud_pubs],
            },
            "done": self.done(),
        }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--goal-topic", default="/goal_pose")
    ap.add_argument("--goal", nargs=2, type=float, default=(-1.5, 1.5))
    ap.add_argument("--cloud-topic", default="/dct/p_fix")
    ap.add_argument("--collect-s", type=float, default=3.0)
    ap.add_argument("--timeout-s", type=float, default=90.0)
    args = ap.parse_args()
    return run_node("stock_qos_mismatch", lambda node: Mismatch(node, args), args.out, args.timeout_s)


if __name__ == "__main__":
    sys.exit(main())
