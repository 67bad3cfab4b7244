"""A real-time two-process episode on rclpy reaches case3's goal with no fixed contact, and the
controller's recording of it carries /tf, /tf_static and the sensor messages as received, which
readers we did not write decode:
mcap_ros2 in Python and Foxglove's JavaScript readers under node."""
from __future__ import annotations

import json
import shutil
import subprocess
import sys

import pytest

from tests.interop.harness import REPO, require_rclpy

require_rclpy()

JS = REPO / "tests" / "interop" / "js"


@pytest.mark.slow
@pytest.mark.realtime
def test_case3_on_rclpy_reaches_the_goal_and_its_recording_decodes_elsewhere(tmp_path):
    mcap, out = tmp_path / "case3.mcap", tmp_path / "case3.json"
    run = subprocess.run([sys.executable, "-m", "runtime.app.cli", "hil", "run", "case3", "--realtime",
                          "--planner", "all-fixed", "--middleware", "rclpy", "--record", str(mcap), "--json", str(out)],
                         cwd=REPO, capture_output=True, text=True, timeout=600)
    m = json.loads(out.read_text())
    assert m["realtime"]["middleware"] == "rclpy", run.stderr[-2000:]
    assert m["goal_reached"] and m["fixed_contacts"] == 0, (m.get("failure_reason"), run.stderr[-2000:])

    from mcap_ros2.reader import read_ros2_messages

    msgs: dict[str, list] = {}
    for r in read_ros2_messages(str(mcap), topics=["/tf", "/tf_static"]):
        msgs.setdefault(r.channel.topic, []).append(r.ros_msg)
    (static,) = msgs["/tf_static"]
    assert {t.child_frame_id for t in static.transforms} == {"livox_frame", "camera_color_optical_frame"}
    last = msgs["/tf"][-1].transforms[0]
    assert (last.header.frame_id, last.child_frame_id) == ("odom", "base_link")
    assert last.transform.translation.x > 4.5  # case3's goal is 5.1 m ahead

    node = shutil.which("node")
    if node is None or not (JS / "node_modules" / "@mcap" / "core").is_dir():
        pytest.skip("node or tests/interop/js/node_modules missing (make install provides both)")
    js = subprocess.run([node, str(JS / "decode_mcap.mjs"), str(mcap)], capture_output=True, text=True, timeout=120)
    got = json.loads(js.stdout)
    assert js.returncode == 0 and got["errors"] == [], js.stderr
    topics = {k: (v["count"], v["decoded"]) for k, v in got["topics"].items()}
    assert topics["/tf"] == (len(msgs["/tf"]), len(msgs["/tf"])) and topics["/tf_static"] == (1, 1)
    # The sensor messages as received (for `dct replay`), each decoded from its ros2msg schema (a
    # sample cyclonedds padded to 4 bytes ends in padding the reader leaves: `trailing`).
    assert {"/livox/lidar", "/livox/imu"} <= set(topics) and all(n == d > 0 for n, d in topics.values()), topics
