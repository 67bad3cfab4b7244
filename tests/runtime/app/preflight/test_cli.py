"""`dct preflight`: the exit code, the JSON, and which bus it checks."""
from __future__ import annotations

import json
import re

import yaml
from click.testing import CliRunner

from firmware_bridge.buses import BusConfig
from runtime.app.preflight.cli import preflight_command
from runtime.app.preflight.run import PreflightOptions, can_settings
from tests.runtime.app.preflight.fakes import EmulatedBase
from tests.runtime.app.preflight.helpers import SHIPPED_CONFIG, write_yaml


def test_command_exit_code_and_json(tmp_path, nominal_cal):
    out = tmp_path / "preflight.json"
    cfg = BusConfig(interface="virtual", channel="preflight-cli")
    args = ["--calibration", str(nominal_cal), "--can-interface", "virtual", "--can-channel", "preflight-cli",
            "--skip", "sensors", "--skip", "clock", "--log-dir", str(tmp_path), "--min-free-gb", "0",
            "--json", str(out)]
    with EmulatedBase(cfg):
        res = CliRunner().invoke(preflight_command, args)
    assert res.exit_code == 0, res.output
    assert "PASS  base" in res.output and "preflight: ready to drive" in res.output
    doc = json.loads(out.read_text())
    assert {"name", "ok", "message"} <= set(doc["checks"][0]) and all(c["ok"] for c in doc["checks"])
    # No base on the bus: exit 1, and the JSON says which check failed.
    res = CliRunner().invoke(preflight_command, args)
    assert res.exit_code == 1 and "FAIL  base" in res.output and "NOT ready to drive" in res.output
    doc = json.loads(out.read_text())
    assert [c["name"] for c in doc["checks"] if not c["ok"]] == ["base"]


def test_the_configs_can_bus_is_checked_when_no_can_option_is_given(tmp_path, nominal_cal):
    """`--config K.yaml` with no --can-* option checks the bus `dct run --config K.yaml` opens (its
    can_bus section), and the can_link line says which bus it checked."""
    from runtime.config import load_controller_config

    raw = yaml.safe_load(SHIPPED_CONFIG.read_text())
    raw["can_bus"] = {"interface": "virtual", "channel": "preflight-cfg"}
    cfg_file = write_yaml(tmp_path / "k.yaml", raw)
    base = ["--calibration", str(nominal_cal), "--config", str(cfg_file), "--skip", "sensors", "--skip", "clock",
            "--log-dir", str(tmp_path), "--min-free-gb", "0"]
    with EmulatedBase(BusConfig(interface="virtual", channel="preflight-cfg")):
        res = CliRunner().invoke(preflight_command, base)
        (link,) = [line for line in res.output.splitlines() if " can_link " in line]
        assert link.startswith("PASS") and "'preflight-cfg'" in link and f"bus from {cfg_file} can_bus" in link
        assert "PASS  base" in res.output, res.output
        # A --can-* option overrides the config's (as in `dct run`), and the line says so.
        res = CliRunner().invoke(preflight_command, base + ["--can-channel", "preflight-elsewhere"])
        (link,) = [line for line in res.output.splitlines() if " can_link " in line]
        assert "'preflight-elsewhere'" in link and "with the command line's --can-* options" in link
        assert "FAIL  base" in res.output and res.exit_code == 1
    # Without --config: the command line's bus (socketcan unless told), whatever the shipped config says.
    bus, source = can_settings(PreflightOptions(), load_controller_config(None))
    assert bus["interface"] == "socketcan" and source == "bus from the command line (default socketcan)"
    bus, source = can_settings(PreflightOptions(config=str(cfg_file), can_interface="udp_multicast"),
                               load_controller_config(cfg_file))
    assert bus == {"interface": "udp_multicast", "channel": None, "udp_port": None, "serial_baud": None}


def test_ros_lines_and_the_bundles_manifest(tmp_path, nominal_cal):
    """The ROS 2 set-up lines come after CAN, before the topics; --manifest says which ROS 2 the
    bundle carries (here: the robot's own, whose setup script is missing: ros:install FAILs)."""
    manifest = tmp_path / "MANIFEST.json"
    manifest.write_text(json.dumps({"format": 2, "files": [], "ros": {"mode": "system", "distro": "jazzy"}}))
    args = ["--calibration", str(nominal_cal), "--skip", "can", "--skip", "sensors", "--skip", "clock",
            "--log-dir", str(tmp_path), "--min-free-gb", "0", "--manifest", str(manifest)]
    res = CliRunner().invoke(preflight_command, args, env={"DCT_ROS_SETUP": str(tmp_path / "nope" / "setup.bash")})
    names = [line[6:].split()[0] for line in res.output.splitlines() if line[:4] in ("PASS", "WARN", "FAIL")]
    assert names.index("base") < names.index("ros:install") < names.index("ros:middleware") < \
        names.index("ros:discovery") < names.index("ros:security") < names.index("topics")
    assert res.exit_code == 1 and "FAIL  ros:install" in res.output and "setup.bash does not exist" in res.output
    # the shipped config: discovery open to the network and no SROS2: WARNs, not failures
    assert "WARN  ros:discovery" in res.output and "WARN  ros:security" in res.output
    manifest.write_text(json.dumps({"format": 2, "files": [], "ros": {"mode": "none"}}))
    res = CliRunner().invoke(preflight_command, args)
    assert res.exit_code == 0, res.output
    assert re.search(r"PASS  ros:install +cyclonedds", res.output), res.output
