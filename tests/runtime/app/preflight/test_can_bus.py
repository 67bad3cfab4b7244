"""dct preflight's CAN checks: the SocketCAN link from a fake /sys, the base on a virtual bus."""
from __future__ import annotations

import json
from pathlib import Path

from firmware_bridge.buses import BusConfig
from runtime.app.preflight.can_bus import check_can, check_socketcan_link
from tests.runtime.app.preflight.fakes import EmulatedBase
from tests.runtime.app.preflight.helpers import by_name


def fake_sys(root: Path, name: str = "can0", operstate: str = "up", flags: str = "0x40c1") -> Path:
    d = root / "sys" / "class" / "net" / name
    d.mkdir(parents=True)
    (d / "operstate").write_text(operstate + "\n")
    (d / "flags").write_text(flags + "\n")
    (d / "type").write_text("280\n")
    return root


def ip_json(bitrate=500000, state="ERROR-ACTIVE"):
    info = {"state": state} if state else {}
    if bitrate is not None:
        info["bittiming"] = {"bitrate": bitrate, "sample-point": "0.875"}
    return lambda ch: json.dumps([{"ifname": ch, "linkinfo": {"info_kind": "can", "info_data": info}}])


def test_socketcan_up_at_500k_passes(tmp_path):
    c = check_socketcan_link("can0", 500_000, sys_root=fake_sys(tmp_path), ip_link_json=ip_json())
    assert c.status == "PASS" and "can0 up at 500000 bit/s" in c.message


def test_socketcan_down_fails_and_says_how_to_bring_it_up(tmp_path):
    c = check_socketcan_link("can0", 500_000, sys_root=fake_sys(tmp_path, operstate="down", flags="0x0"),
                             ip_link_json=ip_json())
    assert c.status == "FAIL" and c.message.startswith("CAN down")
    assert "ip link set can0 up type can bitrate 500000" in c.text()


def test_socketcan_wrong_bitrate_missing_interface_bus_off_and_unknown_bitrate(tmp_path):
    root = fake_sys(tmp_path)
    c = check_socketcan_link("can0", 500_000, sys_root=root, ip_link_json=ip_json(bitrate=250_000))
    assert c.status == "FAIL" and "250000" in c.message
    c = check_socketcan_link("can1", 500_000, sys_root=root, ip_link_json=ip_json())
    assert c.status == "FAIL" and "no network interface can1" in c.message and "can0" in c.message
    c = check_socketcan_link("can0", 500_000, sys_root=root, ip_link_json=ip_json(state="BUS-OFF"))
    assert c.status == "FAIL" and "BUS-OFF" in c.message
    c = check_socketcan_link("can0", 500_000, sys_root=root, ip_link_json=lambda ch: None)
    assert c.status == "WARN" and "bit rate unknown" in c.message


def test_socketcan_down_through_check_can_fails_both_lines(tmp_path):
    checks = check_can("socketcan", "can0", bitrate_bps=500_000,
                       sys_root=fake_sys(tmp_path, operstate="down", flags="0x0"), ip_link_json=ip_json())
    c = by_name(checks)
    assert c["can_link"].status == "FAIL" and c["base"].status == "FAIL"


def test_base_answers_on_a_virtual_bus():
    cfg = BusConfig(interface="virtual", channel="preflight-ok")
    with EmulatedBase(cfg):
        checks = by_name(check_can("virtual", "preflight-ok", bitrate_bps=500_000))
    assert checks["can_link"].status == "PASS"
    assert checks["base"].status == "PASS", checks["base"].line()
    assert "ms after 0x421" in checks["base"].message and "state normal" in checks["base"].message


def test_base_silent_fails():
    c = by_name(check_can("virtual", "preflight-nobody", bitrate_bps=500_000))["base"]
    assert c.status == "FAIL" and "did not answer: no 0x221 within 100 ms" in c.message
    assert "power the base on" in c.text()


def test_base_in_estop_fails():
    cfg = BusConfig(interface="virtual", channel="preflight-estop")
    with EmulatedBase(cfg, estop=True):
        c = by_name(check_can("virtual", "preflight-estop", bitrate_bps=500_000))["base"]
    assert c.status == "FAIL" and "E-stop" in c.message and "release" in c.text()


def test_bad_can_settings_fail():
    c = check_can("udp_multicast", "10.0.0.1", bitrate_bps=500_000)
    assert [x.status for x in c] == ["FAIL"] and "multicast group" in c[0].message
