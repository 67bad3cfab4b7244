"""Fixtures for firmware_bridge tests."""
from __future__ import annotations

import uuid

import can
import pytest


class FakeClock:
    """Injected clock advanced by the test."""

    def __init__(self, t: float = 0.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


@pytest.fixture
def clock() -> FakeClock:
    return FakeClock()


@pytest.fixture
def virtual_pair():
    """(driver_bus, peer_bus) on a fresh virtual channel."""
    channel = f"fb-test-{uuid.uuid4().hex}"
    a = can.Bus(interface="virtual", channel=channel)
    b = can.Bus(interface="virtual", channel=channel)
    yield a, b
    a.shutdown()
    b.shutdown()
