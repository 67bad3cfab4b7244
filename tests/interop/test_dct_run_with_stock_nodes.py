"""`dct run` among stock rclpy nodes in other processes, on either middleware of ours.

One run per middleware (`--middleware rclpy`, `--middleware cyclonedds`), shared by the tests
below: the emulated base on a udp_multicast CAN bus, `dct run --planner all-fixed` reading a
PointCloud2 lidar with a per-point time field `t`, an Imu at 200 Hz, an rgb8 Image and a goal on
/goal_pose, all from the stock node nodes/controller_peer.py, which reads back what the
controller publishes. Beside it nodes/qos_mismatch.py publishes goals best effort (the
controller reads them reliably) and reads P_fix reliably (the controller publishes it best
effort). The nodes report what they saw as JSON; the controller its summary.
"""
from __future__ import annotations

import math

import pytest
import yaml

from calibration.robot_description import load_robot_description
from hil_sim.episode.realtime import unique_channels
from tests.interop.harness import (
    EmulatedBase, dct, domain_id, once_per_run, read_json, require_rclpy, stock_node, wait_all,
)

require_rclpy()

SLOTS = {"rclpy": 0, "cyclonedds": 1}
GOAL = (1.0, 0.0)               # sent reliably by the peer: the one the controller takes
BEST_EFFORT_GOAL = (-1.5, 1.5)  # sent best effort by the mismatch node: never taken
# Input watchdogs widened for a loaded test machine (the defaults expect a sample every 50 ms): this
# is about what crosses between processes, not how promptly.
OVERLAY = {"inputs": {"imu_timeout_s": 1.0, "lidar": {"max_age_frames": 10}}, "ros": {"inputs": {
    "lidar": {"topic": "/lidar/points", "type": "sensor_msgs/msg/PointCloud2", "time_field": "t",
              "time_unit_s": 1.0e-9, "time_is_absolute": False},
    "imu": {"topic": "/imu/data"},
    "camera": {"topic": "/camera/image_raw", "type": "sensor_msgs/msg/Image"},
}}}


def _run(middleware: str, folder) -> dict:
    """One `dct run` with the two stock nodes until the nodes are done; what each reported."""
    domain = domain_id(SLOTS[middleware])
    _, group, port = unique_channels()
    robot = load_robot_description()
    config = folder / "overlay.yaml"
    config.write_text(yaml.safe_dump(OVERLAY))
    summary = folder / "summary.json"
    base = EmulatedBase(group, port)
    base.start()
    ctl = dct(["run", "--config", str(config), "--planner", "all-fixed", "--middleware", middleware,
               "--discovery", "localhost", "--domain-id", str(domain), "--can-interface", "udp_multicast",
               "--can-channel", group, "--can-port", str(port), "--normal-priority", "--goal-wait", "90",
               "--json", str(summary)],
              domain, folder, "dct_run")
    cam, mount = robot.sensors.camera, robot.sensors.lidar.mount.xyz_m
    peer = stock_node("controller_peer.py", folder / "peer.json", [
        "--lidar-topic", "/lidar/points", "--imu-topic", "/imu/data", "--image-topic", "/camera/image_raw",
        "--goal", *map(str, GOAL), "--width", str(cam.width_px), "--height", str(cam.height_px),
        "--lidar-mount", str(mount[0]), str(mount[2]), "--timeout-s", "60"], domain, folder)
    mismatch = stock_node("qos_mismatch.py", folder / "mismatch.json", [
        "--goal", *map(str, BEST_EFFORT_GOAL), "--timeout-s", "60"], domain, folder)
    try:
        wait_all([peer, mismatch], 150.0, watch=ctl)
    finally:
        for node in (peer, mismatch):
            node.terminate(10.0)
        rc = ctl.terminate(30.0)
        base.close()
    logs = "\n".join(p.log() for p in (ctl, peer, mismatch))
    reports = {name: (read_json(folder / f"{name}.json", proc) if (folder / f"{name}.json").is_file() else None)
               for name, proc in (("peer", peer), ("mismatch", mismatch), ("summary", ctl))}
    return {"middleware": middleware, "rc": rc, "logs": logs, **reports}


@pytest.fixture(scope="module", params=list(SLOTS))
def run(request, tmp_path_factory) -> dict:
    r = once_per_run(tmp_path_factory, f"dct-run-{request.param}", lambda folder: _run(request.param, folder))
    assert r["rc"] == 0 and r["summary"] is not None, f"dct run failed\n{r['logs']}"
    assert r["peer"] is not None and r["mismatch"] is not None, f"a stock node wrote no report\n{r['logs']}"
    return r


def test_the_controller_takes_the_stock_nodes_sensors_and_goal(run):
    s, peer = run["summary"], run["peer"]
    assert s["ros"]["middleware"] == run["middleware"], s["ros"]
    got = s["ros_received"]
    assert all(got.get(k, 0) > 0 for k in ("lidar", "imu", "camera", "goal")), (got, peer["published"])
    assert not s["sensor_errors"], (s["sensor_errors"], run["logs"])
    assert s["sensor_frames"].get("lidar", 0) > 0 and s["sensor_frames"].get("imu", 0) > 50, s["sensor_frames"]
    assert s["goal_odom"][:2] == list(GOAL), s["goal_odom"]
    assert s["realtime"]["ticks"] > 0 and s["publisher"]["published"] > 0, s["publisher"]
    # the stock node saw our readers in the graph with the QoS the docs give
    graph = peer["graph"]
    lidar_subs = graph["sub /lidar/points"]
    assert lidar_subs and all(e["type"] == "sensor_msgs/msg/PointCloud2" for e in lidar_subs), lidar_subs
    assert [e["qos"]["reliability"] for e in graph["sub /goal_pose"]] == ["reliable"], graph["sub /goal_pose"]


def test_the_stock_node_reads_odometry_plan_p_fix_and_diagnostics(run):
    peer = run["peer"]
    assert peer["done"], (
        {k: len(v) for k, v in peer["seen"].items()}, run["logs"])
    seen = peer["seen"]
    odom = seen["odom"]
    assert {(o["frame"], o["child"]) for o in odom} == {("odom", "base_link")}, odom[:3]
    assert all(o["finite"] and abs(o["quat_norm"] - 1.0) < 1e-6 and abs(o["age_s"]) < 5.0 for o in odom), odom[:3]
    plans = [p for p in seen["plan"] if p["n"] > 0]
    assert len(plans) >= 2 and all(p["frame"] == "odom" and p["finite"] for p in plans), seen["plan"][:3]
    assert all(set(p["pose_frames"]) <= {"odom", ""} for p in plans), plans[:3]
    clouds = seen["p_fix"]
    assert all(c["frame"] == "odom" and c["size_ok"] and c["finite"] for c in clouds), clouds[:3]
    assert {"x", "y", "z"} <= set(clouds[0]["fields"]), clouds[0]
    full = [c for c in clouds if c["n"] > 50]
    assert full, clouds
    # P_fix is the stock node's room (walls 2-4 m away), in the odometry frame
    assert all(c["near_walls"] >= 0.8 for c in full), [c["near_walls"] for c in full]
    diags = [d for d in seen["diagnostics"] if d["name"] == "dct: controller"]
    assert diags, seen["diagnostics"][:3]
    assert all("state" in d["values"] and d["level"] in (0, 1, 2) for d in diags), diags[:2]
    assert {d["values"]["state"] for d in diags} <= {"INITIALIZING", "ACTIVE", "GOAL_REACHED", "HOLDING", "STOPPED"}
    assert any(d["values"]["state"] in ("ACTIVE", "GOAL_REACHED") for d in diags), [d["values"] for d in diags[-3:]]
    last = diags[-1]["values"]
    assert math.isclose(float(last["goal_x"]), GOAL[0]) and math.isclose(float(last["goal_y"]), GOAL[1]), last


def _routes(run, topic: str) -> list[dict]:
    return [r for r in run["summary"]["ros"]["routes"] if r["topic"] == topic and r["direction"] == "out"]


def test_tf_and_tf_static_in_the_graph(run):
    """tf2_msgs is not installed beside the wheels: a stock node sees /tf only through the graph."""
    if not _routes(run, "/tf"):
        pytest.skip("dct run does not publish /tf yet (no /tf among the routes of its summary)")
    graph = run["peer"]["graph"]
    for topic, durability in (("/tf", "volatile"), ("/tf_static", "transient_local")):
        pubs = graph[f"pub {topic}"]
        assert pubs, f"{topic}: no publisher in the stock node's graph\n{run['logs']}"
        assert all(e["type"] == "tf2_msgs/msg/TFMessage" and e["qos"]["reliability"] == "reliable"
                   and e["qos"]["durability"] == durability for e in pubs), pubs


def test_safety_markers(run):
    if not _routes(run, "/dct/safety_markers"):
        pytest.skip("dct run does not publish /dct/safety_markers yet (not among the routes of its summary)")
    pubs = run["peer"]["graph"]["pub /dct/safety_markers"]
    assert pubs and all(e["type"] == "visualization_msgs/msg/MarkerArray" for e in pubs), pubs
    arrays = run["peer"]["seen"]["markers"]
    markers = [m for a in arrays for m in a]
    assert arrays and markers, f"no MarkerArray with markers reached the stock node ({len(arrays)} arrays)"
    assert all(m["frame"] and m["finite"] for m in markers), markers[:3]


def test_a_qos_mismatch_is_silent_and_the_graph_shows_it(run):
    m, s = run["mismatch"], run["summary"]
    assert m["done"] and m["goals_published"] > 10, m
    # silent: nothing arrives, and nothing fails
    assert m["received"]["reliable"] == 0 and m["received"]["best_effort"] >= 5, m["received"]
    assert s["goal_odom"][:2] == list(GOAL) and s["controller"]["goal_odom"][:2] == list(GOAL), s["controller"]
    assert s["controller"]["goals_received"] == 1 and s["goals_ignored"] == 0, s["controller"]
    # detectable: the graph lists the other side, the node's own endpoint matched none of it, and
    # rclpy's compatibility check names the reason
    assert [e["qos"]["reliability"] for e in m["graph"]["goal_subscriptions"]] == ["reliable"], m["graph"]
    pubs = m["graph"]["cloud_publishers"]
    assert [(e["type"], e["qos"]["reliability"]) for e in pubs] == [("sensor_msgs/msg/PointCloud2", "best_effort")]
    assert m["matched"] == {"goal_publisher": 0, "cloud_reliable": 0, "cloud_best_effort": 1}, m["matched"]
    for which in ("goal", "cloud_reliable"):
        assert [c["level"] for c in m["compatibility"][which]] == ["ERROR"], m["compatibility"]
        assert m["compatibility"][which][0]["reason"] == "ERROR: Best effort publisher and reliable subscription;"
    assert m["incompatible_qos_events"] == {"goal_publisher": 1, "cloud_subscription": 1}, m["incompatible_qos_events"]
    assert [c["level"] for c in m["compatibility"]["cloud_best_effort"]] == ["OK"], m["compatibility"]
