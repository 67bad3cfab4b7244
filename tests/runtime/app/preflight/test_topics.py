"""dct preflight's sensor topic checks: topics published over DDS on a domain of this process, heard
through either middleware; the graph's publishers (types, QoS) from cyclonedds writers and stock
rclpy publishers; the sensors' stamps against this computer's clock.

Each test has its own DDS domain (190-199: entities of an earlier test may linger in the process
until collected, and would show in a later test's graph)."""
from __future__ import annotations

import pytest

from runtime.app.preflight.topics import check_topics, default_topics, topics_from_config
from runtime.io.ros.transport import TransportOptions
from tests.runtime.app.preflight.fakes import RclpyPublisher, SensorPublisher
from tests.runtime.app.preflight.helpers import by_name

RATES = {"lidar": 10.0, "imu": 200.0, "camera": 15.0}


@pytest.fixture(params=["cyclonedds", "rclpy"])
def middleware(request) -> str:
    if request.param == "rclpy":
        pytest.importorskip("rclpy", reason="the ROS 2 wheels are not installed")
    return request.param


def options(middleware: str) -> TransportOptions:
    return TransportOptions(middleware=middleware, node_name="dct_preflight")


def test_topics_alive_pass_and_a_silent_topic_fails(middleware):
    domain = {"cyclonedds": 190, "rclpy": 191}[middleware]
    ros = default_topics(domain)
    with SensorPublisher(domain, {"lidar": 10.0, "imu": 200.0}):
        checks = by_name(check_topics(ros, RATES, listen_s=1.5, options=options(middleware)))
    for s in ("lidar", "imu"):
        assert checks[f"topic:{s}"].status == "PASS", checks[f"topic:{s}"].line()
        assert "Hz (expected" in checks[f"topic:{s}"].message
        assert checks[f"match:{s}"].status == "PASS", checks[f"match:{s}"].line()
    # each line says which middleware carried the topic: where rclpy has no Livox package, the
    # lidar goes through its cyclonedds participant, as in dct run
    from runtime.io.ros.rclpy_transport import ros_message_class

    lidar_via = "rclpy" if middleware == "rclpy" and ros_message_class(ros.lidar.type) else "cyclonedds"
    assert f"domain {domain}, {middleware})" in checks["topic:imu"].message
    assert f"domain {domain}, {lidar_via})" in checks["topic:lidar"].message
    assert "1 publisher of livox_ros_driver2/msg/CustomMsg (best effort/volatile)" in checks["match:lidar"].message
    cam = checks["topic:camera"]          # not required by planner mode all-fixed: a WARN
    assert cam.status == "WARN" and "sensor topic silent" in cam.message
    assert checks["match:camera"].status == "WARN" and "no publisher" in checks["match:camera"].message
    assert checks["match:goal"].status == "PASS" and "no publisher on /goal_pose yet" in checks["match:goal"].message
    assert checks["ros:clock"].status == "PASS", checks["ros:clock"].line()
    assert "lidar +" in checks["ros:clock"].message and "imu +" in checks["ros:clock"].message
    checks = by_name(check_topics(ros, RATES, listen_s=0.5, required=("lidar", "imu", "camera"),
                                  options=options(middleware)))
    assert checks["topic:camera"].status == "FAIL" and "/camera/color/image_raw" in checks["topic:camera"].message
    assert checks["topic:lidar"].status == "FAIL" and "start the lidar driver" in checks["topic:lidar"].text()


def test_a_driver_on_another_clock_fails_naming_the_offset():
    domain = 192
    with SensorPublisher(domain, {"lidar": 10.0, "imu": 200.0}, clock_offset_s=2.0):
        checks = by_name(check_topics(default_topics(domain), RATES, listen_s=1.0, options=options("cyclonedds")))
    c = checks["ros:clock"]
    assert c.status == "FAIL", c.line()
    assert "imu -2.00 s" in c.message and "s ahead of this computer's clock" in c.message and "chrony" in c.text()
    assert checks["topic:imu"].status == "PASS"          # the rate check does not care about the stamps


def test_type_and_qos_mismatches_of_cyclonedds_writers_and_stock_rclpy_publishers(middleware):
    """Publishers the controller would never hear, and DDS would not say so: another type, or best
    effort where the goal is read reliably. One domain, the same graph seen through either middleware."""
    pytest.importorskip("rclpy", reason="the ROS 2 wheels are not installed")
    from cyclonedds.domain import DomainParticipant
    from geometry_msgs.msg import PoseStamped
    from sensor_msgs.msg import CompressedImage
    from std_msgs.msg import String

    from runtime.io.ros import messages as M
    from runtime.io.ros.dds import RosWriter, ros_qos

    domain = {"cyclonedds": 193, "rclpy": 194}[middleware]
    dp, dp2 = DomainParticipant(domain), DomainParticipant(domain)  # one topic QoS per participant
    writers = [RosWriter(dp, "/livox/lidar", M.PointCloud2, ros_qos()),                      # another type
               RosWriter(dp, "/goal_pose", M.PoseStamped, ros_qos("best_effort")),          # best effort goal
               RosWriter(dp2, "/goal_pose", M.PoseStamped, ros_qos("reliable", 1, "transient_local"))]  # matches
    with RclpyPublisher(domain, "/livox/imu", String), \
            RclpyPublisher(domain, "/goal_pose", PoseStamped, reliability="best_effort"), \
            RclpyPublisher(domain, "/camera/color/image_raw", CompressedImage):
        checks = by_name(check_topics(default_topics(domain), RATES, listen_s=2.0, options=options(middleware)))
    assert writers
    lidar = checks["match:lidar"]
    assert lidar.status == "FAIL" and "publishes sensor_msgs/msg/PointCloud2, the config reads " \
        "livox_ros_driver2/msg/CustomMsg" in lidar.message
    assert "set ros.inputs.lidar.type: sensor_msgs/msg/PointCloud2" in lidar.text()
    imu = checks["match:imu"]
    assert imu.status == "FAIL" and "publishes std_msgs/msg/String, the config reads sensor_msgs/msg/Imu" in imu.message
    assert "publish sensor_msgs/msg/Imu on /livox/imu" in imu.text()
    cam = checks["match:camera"]                         # optional (all-fixed): a WARN
    assert cam.status == "WARN" and "set ros.inputs.camera.type: sensor_msgs/msg/CompressedImage" in cam.text()
    goal = checks["match:goal"]
    assert goal.status == "FAIL", goal.line()
    assert goal.message.count("publishes best effort, we read reliable") == 2, goal.message
    assert "set ros.inputs.goal.qos.reliability: best_effort" in goal.text() and "publish reliably" in goal.text()
    if middleware == "rclpy":                            # rclpy's graph names the stock node
        assert "node /stock_publisher" in goal.message and "a bare DDS participant" in goal.message


def test_topics_come_from_the_controller_configs_ros_inputs():
    """The shipped config's `ros:` is a RosConfig: the topic check takes its inputs."""
    from runtime.config import load_controller_config

    topics = topics_from_config(load_controller_config(None), 7)
    assert topics.domain_id == 7 and topics.lidar.topic == load_controller_config(None).ros.inputs.lidar.topic


def test_a_middleware_that_cannot_start_is_one_failed_line():
    checks = check_topics(default_topics(195), RATES, listen_s=0.2,
                          options=TransportOptions(middleware="cyclonedds", security_keystore="/nonexistent"))
    assert [c.name for c in checks] == ["topics"] and checks[0].status == "FAIL"
    assert "cannot open the cyclonedds middleware on domain 195" in checks[0].message and "SROS2" in checks[0].message
