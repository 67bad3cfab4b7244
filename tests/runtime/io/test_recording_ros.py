"""The recording's ROS 2 channels (/tf, /tf_static: tf2_msgs/msg/TFMessage, cdr + ros2msg) and the
.msg definitions their schemas are made of (runtime.io.ros.msg_definitions)."""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

from runtime.config import load_controller_config
from runtime.io.recording import RecordingError, RunRecorder, read_recording
from runtime.io.recording import ros_channels as R
from runtime.io.ros import messages as M
from runtime.io.ros import msg_definitions as D
from tests.runtime.io.test_recording import _FakeController, _rows

SHARE = Path(sys.prefix) / "share"


# ----------------------------------------------------------------------------- msg definitions


#: Types whose package has no wheel (no .msg files under the venv's share/): their texts are
#: checked by decoding recorded messages with mcap_ros2 (test_recording_inputs, this module's /tf tests).
NOT_INSTALLED = {"tf2_msgs/TFMessage", "livox_ros_driver2/CustomMsg", "livox_ros_driver2/CustomPoint"}


@pytest.mark.parametrize("name", sorted(set(D.DEFINITIONS) - NOT_INSTALLED))
def test_definitions_are_the_installed_msg_files(name):
    pkg, type_name = name.split("/")
    path = SHARE / pkg / "msg" / f"{type_name}.msg"
    if not path.is_file():
        pytest.skip(f"{path} not installed")
    assert D.DEFINITIONS[name] == path.read_text()


def test_every_ros_channel_type_and_its_fields_are_defined_and_declared():
    for type_name in R.CHANNELS.values():
        assert type_name in M.ROS_TYPES
        names = [type_name] + D.dependencies(type_name)
        while names:
            name = names.pop()
            D.dependencies(name)  # KeyError if a definition is missing
            names += [d for d in D.dependencies(name) if d not in names]


def test_schema_text_is_rosbag2s_concatenation():
    """The top-level text, then each dependency after its delimiter, depth first in sorted order, once."""
    d = D.DEFINITIONS

    def part(name: str) -> str:
        return f"\n{'=' * 80}\nMSG: {name}\n{d[name]}"

    expected = (d["tf2_msgs/TFMessage"] + part("geometry_msgs/TransformStamped") + part("geometry_msgs/Transform")
                + part("geometry_msgs/Quaternion") + part("geometry_msgs/Vector3") + part("std_msgs/Header")
                + part("builtin_interfaces/Time"))
    assert D.schema_text("tf2_msgs/msg/TFMessage") == expected == D.schema_text("tf2_msgs/TFMessage")
    assert D.dependencies("geometry_msgs/msg/TransformStamped") == ["geometry_msgs/Transform", "std_msgs/Header"]
    for bad in ("TFMessage", "a/b/c/d", "tf2_msgs/srv/X", "/TFMessage"):
        with pytest.raises(ValueError, match="is not a ROS 2 message type name"):
            D.schema_text(bad)
    with pytest.raises(KeyError, match="no .msg definition for nav_msgs/Odometry"):
        D.schema_text("nav_msgs/msg/Odometry")


def test_mcap_ros2_parses_the_schema_text():
    from mcap_ros2._dynamic import generate_dynamic

    decoders = generate_dynamic("tf2_msgs/msg/TFMessage", D.schema_text("tf2_msgs/msg/TFMessage"))
    msg = M.TFMessage([M.TransformStamped(M.Header(M.Time(3, 4), "odom"), "base_link",
                                          M.Transform(M.Vector3(1.0, 2.0, 0.0), M.Quaternion(0.0, 0.0, 0.6, 0.8)))])
    (t,) = decoders["tf2_msgs/msg/TFMessage"](M.to_cdr(msg)).transforms
    assert (t.header.frame_id, t.child_frame_id, t.transform.translation.y, t.transform.rotation.w) == (
        "odom", "base_link", 2.0, 0.8)


# ----------------------------------------------------------------------------- the recorder

T_LIDAR = np.array([[1, 0, 0, 0.1], [0, 1, 0, 0], [0, 0, 1, 0.25], [0, 0, 0, 1]], float)
T_CAMERA = np.array([[0, 0, 1, 0.15], [-1, 0, 0, 0], [0, -1, 0, 0.2], [0, 0, 0, 1]], float)  # optical frame


def _channels(path) -> dict[str, tuple[str, str, str]]:
    """topic -> (message encoding, schema name, schema encoding), from the file's summary."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    return {c.topic: (c.message_encoding, summary.schemas[c.schema_id].name, summary.schemas[c.schema_id].encoding)
            for c in summary.channels.values()}


def test_tf_every_tick_and_tf_static_once(tmp_path):
    out = tmp_path / "tf.mcap"
    rec = RunRecorder(out)
    hook = rec.attach(_FakeController(), load_controller_config(), {"clock": "test"},
                      static_transforms=[("base_link", "lidar", T_LIDAR), ("base_link", "camera", T_CAMERA)])
    rows = _rows(6)
    for row in rows:
        hook(row)
    summary = rec.close()
    assert summary["bad_records"] == 0 and summary["dropped_total"] == 0
    channels = _channels(out)
    assert channels[R.TOPIC_TF] == channels[R.TOPIC_TF_STATIC] == ("cdr", "tf2_msgs/msg/TFMessage", "ros2msg")
    assert channels["/dct/pose"][0] == "json"
    got = read_recording(out)
    assert got.topics[R.TOPIC_TF] == "tf2_msgs/msg/TFMessage"
    tf = got.messages[R.TOPIC_TF]
    assert [t for t, _ in tf] == [round(float(r["scheduled_s"]) * 1e9) for r in rows]
    for (t_ns, msg), row in zip(tf, rows):
        (odom,) = msg.transforms
        assert (odom.header.frame_id, odom.child_frame_id) == ("odom", "base_link")
        assert odom.header.stamp == M.stamp_to_time(float(row["scheduled_s"]))
        tr, q = odom.transform.translation, odom.transform.rotation
        assert (tr.x, tr.y, tr.z) == (1.0, 2.0, 0.0)  # the fake controller's pose: (1, 2, yaw 0.5)
        assert (q.z, q.w) == pytest.approx((math.sin(0.25), math.cos(0.25)))
    ((t_ns, static),) = got.messages[R.TOPIC_TF_STATIC]
    assert t_ns == 0  # the first tick's time
    lidar, camera = static.transforms
    assert [(s.header.frame_id, s.child_frame_id) for s in static.transforms] == [("base_link", "lidar"),
                                                                                  ("base_link", "camera")]
    assert (lidar.transform.translation.x, lidar.transform.translation.z) == (0.1, 0.25)
    q = camera.transform.rotation
    assert (q.x, q.y, q.z, q.w) == pytest.approx((-0.5, 0.5, -0.5, 0.5))  # x forward -> z forward (optical)


def test_frames_follow_the_ros_outputs_and_no_mounts_means_no_tf_static(tmp_path):
    config = load_controller_config()
    outputs = config.ros.outputs.model_copy(update={"odom_frame": "world_odom", "base_frame": "base_footprint"})
    config = config.model_copy(update={"ros": config.ros.model_copy(update={"outputs": outputs})})
    out = tmp_path / "frames.mcap"
    rec = RunRecorder(out)
    hook = rec.attach(_FakeController(), config, {"clock": "test"})
    for row in _rows(3):
        hook(row)
    rec.close()
    got = read_recording(out)
    assert R.TOPIC_TF_STATIC not in got.messages
    assert {(m.transforms[0].header.frame_id, m.transforms[0].child_frame_id)
            for _, m in got.messages[R.TOPIC_TF]} == {("world_odom", "base_footprint")}


@pytest.mark.parametrize("mounts,pattern", [
    ([("base_link", "lidar", np.eye(3))], r"\[bad_shape\] static_transforms.mounts\[0\].T: must be 4x4"),
    ([("base_link", "lidar", np.diag([1.0, 1.0, 2.0, 1.0]))], r"\[not_rigid\]"),
    ([("base_link", "", np.eye(4))], r"\[bad_frame_id\]"),
    ([("base_link", "lidar")], r"\[bad_shape\] static_transforms\[0\]: expected \(parent, child, 4x4 matrix\)"),
])
def test_bad_static_transforms_are_refused_when_attached(tmp_path, mounts, pattern):
    rec = RunRecorder(tmp_path / "bad.mcap")
    try:
        with pytest.raises(RecordingError, match=r"--record: the static transforms: " + pattern) as info:
            rec.attach(_FakeController(), load_controller_config(), {"clock": "test"}, static_transforms=mounts)
        assert "\n" not in str(info.value)
    finally:
        rec.close()


def test_the_mounts_are_copied_when_attached(tmp_path):
    """The caller's matrix changing after attach() does not change what /tf_static says."""
    T = T_LIDAR.copy()
    out = tmp_path / "copy.mcap"
    rec = RunRecorder(out)
    hook = rec.attach(_FakeController(), load_controller_config(), static_transforms=[("base_link", "lidar", T)])
    T[0, 3] = 5.0
    hook(_rows(1)[0])
    rec.close()
    ((_, static),) = read_recording(out).messages[R.TOPIC_TF_STATIC]
    assert static.transforms[0].transform.translation.x == 0.1


# ----------------------------------------------------------------------------- readers we did not write

JS_DIR = Path(__file__).resolve().parents[2] / "interop" / "js"


@pytest.fixture(scope="module")
def lockstep_recording(tmp_path_factory):
    """A short lockstep episode recorded as `dct hil run --record` records it."""
    from hil_sim.episode.lockstep import run_episode
    from tests.runtime.io.test_recording import _short

    out = tmp_path_factory.mktemp("rec_ros") / "run.mcap"
    config = load_controller_config().with_planner_mode("all-fixed")
    with RunRecorder(out) as rec:
        run_episode(_short().model_copy(update={"time_limit_s": 0.8}), seed=0, recorder=rec, config=config)
    assert rec.summary()["bad_records"] == 0
    return out, read_recording(out)


def _xyz(v) -> tuple[float, float, float]:
    return (v.x, v.y, v.z)


@pytest.mark.filterwarnings("ignore::DeprecationWarning:mcap_ros2.reader")  # read_ros2_messages: still shipped
def test_mcap_ros2_reads_every_tf_message(lockstep_recording):
    """mcap_ros2 (the mcap project's ROS 2 reader, decoding from the file's ros2msg schemas) reads
    every /tf and /tf_static message; frames and translations are the controller's poses (the
    JSON /dct/pose beside them) and the robot description's sensor mounts."""
    from mcap_ros2.reader import read_ros2_messages

    from calibration.robot_description import load_robot_description

    path, ours = lockstep_recording
    theirs: dict[str, list] = {}
    for m in read_ros2_messages(str(path), topics=[R.TOPIC_TF, R.TOPIC_TF_STATIC]):
        assert m.schema.name == "tf2_msgs/msg/TFMessage" and m.channel.message_encoding == "cdr"
        theirs.setdefault(m.channel.topic, []).append((m.log_time_ns, m.ros_msg))
    poses = {t: p["pose"]["position"] for t, p in ours.messages["/dct/pose"]}
    assert len(theirs[R.TOPIC_TF]) == len(poses) == len(ours.messages["/dct/tick"]) >= 10
    for t_ns, msg in theirs[R.TOPIC_TF]:
        (tf,) = msg.transforms
        assert (tf.header.frame_id, tf.child_frame_id) == ("odom", "base_link")
        assert tf.header.stamp.sec * 10**9 + tf.header.stamp.nanosec == t_ns
        p = poses[t_ns]
        assert _xyz(tf.transform.translation) == (p["x"], p["y"], 0.0)
    ((t_static, static),) = theirs[R.TOPIC_TF_STATIC]
    assert t_static == min(poses)
    robot = load_robot_description()
    out = load_controller_config().ros.outputs  # the sensors' frames as their drivers stamp them
    expected = {out.lidar_frame: robot.sensors.lidar.mount.transform(),
                out.camera_frame: robot.sensors.camera.mount.transform()}
    assert [(s.header.frame_id, s.child_frame_id) for s in static.transforms] == [
        ("base_link", out.lidar_frame), ("base_link", out.camera_frame)]
    for s in static.transforms:
        np.testing.assert_allclose(_xyz(s.transform.translation), expected[s.child_frame_id][:3, 3], atol=1e-12)
    # our reader reads the same
    assert [(t, m.transforms[0].transform.translation.x) for t, m in ours.messages[R.TOPIC_TF]] == [
        (t, m.transforms[0].transform.translation.x) for t, m in theirs[R.TOPIC_TF]]


def test_foxglove_js_readers_decode_every_cdr_channel(lockstep_recording):
    """Foxglove's @mcap/core, @foxglove/rosmsg and @foxglove/rosmsg2-serialization under node
    (tests/interop/js/decode_mcap.mjs) decode every cdr channel: counts, schemas and values."""
    import json
    import shutil
    import subprocess

    node = shutil.which("node")
    if node is None:
        pytest.skip("node is not installed")
    if not (JS_DIR / "node_modules" / "@mcap" / "core").is_dir():
        pytest.skip(f"{JS_DIR}/node_modules is missing: run `npm ci --prefix {JS_DIR}` (make install does)")
    path, ours = lockstep_recording
    run = subprocess.run([node, str(JS_DIR / "decode_mcap.mjs"), str(path)], capture_output=True, text=True,
                         timeout=120)
    assert run.returncode == 0, run.stdout + run.stderr
    got = json.loads(run.stdout)
    assert got["errors"] == []
    assert set(got["topics"]) == set(R.CHANNELS)  # every cdr channel, and only those
    for topic, type_name in R.CHANNELS.items():
        entry = got["topics"][topic]
        assert (entry["schema"], entry["schema_encoding"], entry["message_encoding"]) == (type_name, "ros2msg", "cdr")
        assert entry["count"] == entry["decoded"] == len(ours.messages[topic]) and entry["trailing"] == 0
    for key, index in (("first", 0), ("last", -1)):
        (tf,) = got["topics"][R.TOPIC_TF][key]["transforms"]
        (mine,) = ours.messages[R.TOPIC_TF][index][1].transforms
        assert (tf["header"]["frame_id"], tf["child_frame_id"]) == ("odom", "base_link")
        assert tf["header"]["stamp"] == {"sec": mine.header.stamp.sec, "nanosec": mine.header.stamp.nanosec}
        t = tf["transform"]["translation"]
        assert (t["x"], t["y"], t["z"]) == _xyz(mine.transform.translation)
        r = tf["transform"]["rotation"]
        assert (r["z"], r["w"]) == (mine.transform.rotation.z, mine.transform.rotation.w)
    static = got["topics"][R.TOPIC_TF_STATIC]["first"]["transforms"]
    (_, mine_static), = ours.messages[R.TOPIC_TF_STATIC]
    assert [(s["child_frame_id"], s["transform"]["translation"]["z"]) for s in static] == [
        (s.child_frame_id, s.transform.translation.z) for s in mine_static.transforms]
