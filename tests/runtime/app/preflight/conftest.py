"""The preflight tests' fixture: a nominal calibration of the shipped LIMO.

Machine state is faked where it cannot be real here: a /sys tree under tmp_path (SocketCAN does
not exist on these machines), `ip -details -json` text, the clock commands, disk usage and the
real-time request. The CAN base is the emulated firmware on a python-can virtual bus; the
sensor topics are published over DDS on a domain of this process."""
from __future__ import annotations

from pathlib import Path

import pytest

from calibration.robot_description import load_robot_description
from runtime.app.deploy.bundle import nominal_calibration_yaml


@pytest.fixture(scope="module")
def nominal_cal(tmp_path_factory) -> Path:
    p = tmp_path_factory.mktemp("cal") / "calibration.yaml"
    p.write_text(nominal_calibration_yaml(load_robot_description()))
    return p
