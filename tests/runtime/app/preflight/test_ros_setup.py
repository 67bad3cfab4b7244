"""dct preflight's ROS 2 set-up checks: the middleware, discovery, SROS2 and the bundle's ROS 2
install mode. rclpy's availability, the environment, the keystore and the ROS 2 install are faked."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from runtime.app.preflight.ros_setup import (
    ENCLAVE_FILES, ManifestError, RosInstall, check_discovery, check_middleware, check_ros_install, check_security,
    discovery_reach, read_ros_install,
)
from runtime.io.ros.settings import RosConfig


def ros(**kw) -> RosConfig:
    return RosConfig.model_validate(kw)


def yes():
    return True, "rclpy 7.1.6"


def no():
    return False, "ModuleNotFoundError: No module named 'rclpy'"


def test_middleware_resolves_as_dct_run_does():
    c = check_middleware(ros(middleware="rclpy"), no)
    assert c.status == "FAIL" and "rclpy does not import (ModuleNotFoundError" in c.message
    assert "source /opt/ros/jazzy/setup.bash" in c.text() and "ros.middleware: cyclonedds" in c.text()
    c = check_middleware(ros(), no)
    assert c.status == "PASS" and c.message.startswith("ros.middleware auto -> cyclonedds (rclpy does not import")
    c = check_middleware(ros(middleware="cyclonedds"), yes)
    assert c.status == "PASS" and "rclpy is not used" in c.message
    c = check_middleware(ros(), yes)
    assert c.status == "PASS" and c.message.startswith("ros.middleware auto -> rclpy: rclpy 7.1.6")


def test_middleware_names_the_types_rclpy_cannot_carry():
    pytest.importorskip("rclpy", reason="the ROS 2 wheels are not installed")
    c = check_middleware(ros(middleware="rclpy"))
    assert c.status == "PASS" and "livox_ros_driver2/msg/CustomMsg through cyclonedds" in c.message


def test_discovery_open_to_the_network_warns_about_goals():
    c = check_discovery(ros(), "rclpy", environ={})
    assert c.status == "WARN" and "any host on the network that joins DDS domain 0 can publish a goal on " \
        "/goal_pose" in c.message
    assert "ros.discovery: localhost" in c.text() and "ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST" in c.text()
    assert "SROS2" in c.text()
    c = check_discovery(ros(discovery="localhost"), "cyclonedds", environ={})
    assert c.status == "PASS" and "this computer only (ros.discovery: localhost)" in c.message
    c = check_discovery(ros(middleware="cyclonedds"), "cyclonedds", environ={"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"})
    assert c.status == "WARN" and "the middleware is cyclonedds, which does not read it" in c.message
    c = check_discovery(ros(middleware="cyclonedds", inputs={"domain_id": 5}), "cyclonedds",
                        environ={"CYCLONEDDS_URI": "file:///etc/cyclone.xml"})
    assert c.status == "WARN" and "CYCLONEDDS_URI is set" in c.message and "domain 5" in c.message


def test_rclpys_environment_keeps_rclpy_local_but_not_its_cyclonedds_participant():
    env = {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    cfg = ros(middleware="rclpy", inputs={"imu": {"topic": "/imu"}, "goal": {}})  # types rclpy has packages for
    pytest.importorskip("sensor_msgs", reason="the ROS 2 wheels are not installed")
    assert discovery_reach(cfg, "rclpy", env) == ("localhost", "ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST")
    where, why = discovery_reach(ros(middleware="rclpy"), "rclpy", env)    # the Livox CustomMsg: cyclonedds
    assert where == "network" and "livox_ros_driver2/msg/CustomMsg" in why


def make_enclave(root: Path, enclave: str = "/dct_controller", skip=()) -> Path:
    d = root / "keystore" / "enclaves" / enclave.lstrip("/")
    d.mkdir(parents=True)
    for f in ENCLAVE_FILES:
        if f not in skip:
            (d / f).write_text("x")
    return root / "keystore"


def test_security_keystore_enclave_and_middleware(tmp_path):
    ks = make_enclave(tmp_path)
    cfg = ros(security={"keystore": str(ks)})
    c = check_security(cfg, "rclpy", "network")
    assert c.status == "PASS" and "SROS2 enclave /dct_controller" in c.message
    c = check_security(cfg, "cyclonedds", "network")
    assert c.status == "FAIL" and "only rclpy runs SROS2" in c.message
    c = check_security(ros(security={"keystore": str(tmp_path / "none")}), "rclpy", "network")
    assert c.status == "FAIL" and "is not a folder" in c.message and "create_keystore" in c.text()
    ks2 = make_enclave(tmp_path / "b", skip=("permissions.p7s", "key.pem"))
    c = check_security(ros(security={"keystore": str(ks2)}), "rclpy", "network")
    assert c.status == "FAIL" and "key.pem, permissions.p7s missing" in c.message and "create_enclave" in c.text()
    c = check_security(ros(security={"keystore": str(ks), "enclave": "/../../etc"}), "rclpy", "network")
    assert c.status == "FAIL" and "is not an enclave name" in c.message


def test_no_security_is_one_line_saying_goals_are_unauthenticated():
    c = check_security(ros(), "rclpy", "network")
    assert c.status == "WARN" and "goals on /goal_pose are not authenticated" in c.message
    c = check_security(ros(), "rclpy", "localhost")
    assert c.status == "PASS" and "only processes on this computer can send them" in c.message


def manifest(path: Path, ros_section=None) -> Path:
    doc = {"format": 2, "files": []}
    if ros_section is not None:
        doc["ros"] = ros_section
    path.write_text(json.dumps(doc))
    return path


def test_manifest_ros_section_is_validated(tmp_path):
    assert read_ros_install(manifest(tmp_path / "a.json", {"mode": "system", "distro": "jazzy"})).mode == "system"
    assert read_ros_install(manifest(tmp_path / "old.json")).mode == "none"     # a bundle from before --ros
    with pytest.raises(ManifestError, match=r"ros.mode must be one of wheels, system, none, got 'apt'"):
        read_ros_install(manifest(tmp_path / "b.json", {"mode": "apt"}))
    with pytest.raises(ManifestError, match=r"ros.distro must be"):
        read_ros_install(manifest(tmp_path / "c.json", {"mode": "system", "distro": "../x"}))
    (tmp_path / "d.json").write_text("{")
    with pytest.raises(ManifestError, match="cannot be read as JSON"):
        read_ros_install(tmp_path / "d.json")
    with pytest.raises(ManifestError, match="not a dct deploy bundle"):
        read_ros_install(_write(tmp_path / "e.json", []))


def _write(path: Path, doc) -> Path:
    path.write_text(json.dumps(doc))
    return path


def test_install_wheels_needs_rclpy_from_this_venv():
    pytest.importorskip("rclpy", reason="the ROS 2 wheels are not installed")
    wheels = RosInstall("wheels", source="M.json")
    c = check_ros_install(wheels, ros())
    assert c.status == "PASS" and "from the bundle's venv" in c.message and "--ros wheels" in c.message
    c = check_ros_install(wheels, ros(), prefix="/somewhere/else")
    assert c.status == "WARN" and "not from this venv" in c.message
    c = check_ros_install(wheels, ros(), available=no)
    assert c.status == "FAIL" and "the ROS 2 wheels do not import" in c.message


def test_install_system_sources_the_setup_script_then_imports_rclpy(tmp_path):
    pytest.importorskip("rclpy", reason="the ROS 2 wheels are not installed")
    system = RosInstall("system", "jazzy", "M.json")
    c = check_ros_install(system, ros(), environ={"DCT_ROS_SETUP": str(tmp_path / "missing.bash")})
    assert c.status == "FAIL" and "missing.bash does not exist" in c.message and "--ros wheels" in c.text()
    good = tmp_path / "setup.bash"
    good.write_text("export ROS_DISTRO=jazzy\n")
    c = check_ros_install(system, ros(), environ={"DCT_ROS_SETUP": str(good)})
    assert c.status == "PASS" and f"rclpy imports after sourcing {good}" in c.message
    shadow = tmp_path / "shadow" / "rclpy"              # a ROS 2 for another CPython: its rclpy cannot load
    shadow.mkdir(parents=True)
    (shadow / "__init__.py").write_text("raise ImportError('rclpy built for CPython 3.12')\n")
    bad = tmp_path / "bad.bash"
    bad.write_text(f"export PYTHONPATH={shadow.parent}\n")
    c = check_ros_install(system, ros(), environ={"DCT_ROS_SETUP": str(bad)})
    assert c.status == "FAIL" and "rclpy built for CPython 3.12" in c.message
    broken = tmp_path / "broken.bash"
    broken.write_text("return 1\n")
    c = check_ros_install(system, ros(), environ={"DCT_ROS_SETUP": str(broken)})
    assert c.status == "FAIL" and "sourcing" in c.message


def test_install_none_is_cyclonedds_and_refuses_a_config_that_asks_for_rclpy():
    none = RosInstall("none", source="M.json")
    c = check_ros_install(none, ros())
    assert c.status == "PASS" and c.message.startswith("cyclonedds ")
    c = check_ros_install(none, ros(middleware="rclpy"))
    assert c.status == "FAIL" and "the bundle carries no ROS 2" in c.message and "--ros wheels" in c.text()


def test_socket_buffer_limits_below_what_images_need_warn_with_the_sysctl(tmp_path):
    from runtime.app.preflight.ros_setup import SOCKET_BUFFER_BYTES, check_socket_buffers

    core = tmp_path / "proc/sys/net/core"
    core.mkdir(parents=True)
    (core / "rmem_max").write_text("212992\n")
    (core / "wmem_max").write_text(f"{SOCKET_BUFFER_BYTES}\n")
    c = check_socket_buffers("rclpy", tmp_path)
    assert c.status == "WARN" and "net.core.rmem_max 208 kB" in c.message and "wmem" not in c.message
    assert f"sysctl -w net.core.rmem_max={SOCKET_BUFFER_BYTES}" in c.fix
    (core / "rmem_max").write_text(f"{8 * SOCKET_BUFFER_BYTES}\n")
    assert check_socket_buffers("rclpy", tmp_path).status == "PASS"
    (core / "wmem_max").unlink()
    assert check_socket_buffers("rclpy", tmp_path).status == "WARN"
