"""dct preflight's sensor topic checks: topics published over DDS on a domain of this process."""
from __future__ import annotations

from runtime.app.preflight.topics import check_topics, default_topics, topics_from_config
from tests.runtime.app.preflight.fakes import SensorPublisher, unique_domain
from tests.runtime.app.preflight.helpers import by_name


def test_topics_alive_pass_and_a_silent_topic_fails():
    domain = unique_domain()
    ros = default_topics(domain)
    rates = {"lidar": 10.0, "imu": 200.0, "camera": 15.0}
    with SensorPublisher(domain, {"lidar": 10.0, "imu": 200.0}):
        checks = by_name(check_topics(ros, rates, listen_s=1.5))
    for s in ("lidar", "imu"):
        assert checks[f"topic:{s}"].ok, checks[f"topic:{s}"].line()
        assert "Hz (expected" in checks[f"topic:{s}"].message
    cam = checks["topic:camera"]          # not required by planner mode all-fixed: a WARN
    assert cam.status == "WARN" and "sensor topic silent" in cam.message
    checks = by_name(check_topics(ros, rates, listen_s=0.5, required=("lidar", "imu", "camera")))
    assert checks["topic:camera"].status == "FAIL" and "/camera/color/image_raw" in checks["topic:camera"].message
    assert checks["topic:lidar"].status == "FAIL" and "start the lidar driver" in checks["topic:lidar"].text()


def test_topics_come_from_the_controller_configs_ros_inputs():
    """The shipped config's `ros:` is a RosConfig: the topic check takes its inputs."""
    from runtime.config import load_controller_config

    topics = topics_from_config(load_controller_config(None), 7)
    assert topics.domain_id == 7 and topics.lidar.topic == load_controller_config(None).ros.inputs.lidar.topic
