"""runtime.loop.realtime_setup: what the loop asks for (SCHED_FIFO, CPU pinning) and the start-up line.

The OS calls are faked (granting or refusing); the one real request runs on a throwaway thread
so that the test process itself never becomes SCHED_FIFO."""
from __future__ import annotations

import os
import threading

import pytest
from pydantic import ValidationError

from runtime.config import load_controller_config
from runtime.loop.realtime_setup import RealtimeConfig, request_realtime, request_realtime_from_config


def refuse(errno_, text):
    def f(*args):
        raise OSError(errno_, text)
    return f


def test_config_section_defaults_and_validation():
    rt = load_controller_config().realtime
    assert rt.fifo and rt.fifo_priority == 50 and rt.cpus is None
    assert RealtimeConfig(cpus=[2, 1]).cpus == (1, 2) and RealtimeConfig(cpus=[]).cpus is None
    for bad in ({"fifo_priority": 0}, {"fifo_priority": 100}, {"cpus": [-1]}, {"cpus": [1, 1]}, {"nice": 5}):
        with pytest.raises(ValidationError):
            RealtimeConfig(**bad)


def test_granted():
    calls = []
    g = request_realtime(60, [1], setscheduler=lambda *a: calls.append(("fifo", a[1], a[2].sched_priority)),
                         setaffinity=lambda pid, cpus: calls.append(("aff", cpus)), getaffinity=lambda pid: {1})
    assert calls == [("fifo", os.SCHED_FIFO, 60), ("aff", {1})]
    assert g.fifo_granted and g.affinity_granted
    assert g.summary() == "real-time: SCHED_FIFO priority 60; pinned to CPUs 1"


def test_refused_says_what_the_loop_does_and_how_to_allow_it():
    g = request_realtime(50, [3], setscheduler=refuse(1, "Operation not permitted"),
                         setaffinity=refuse(22, "Invalid argument"), getaffinity=lambda pid: {0, 1})
    assert g.fifo_granted is False and g.affinity_granted is False
    s = g.summary()
    assert s.startswith("real-time: SCHED_OTHER: SCHED_FIFO priority 50 refused (Operation not permitted [EPERM]")
    assert "LimitRTPRIO" in s and "not pinned: CPUs 3 refused (Invalid argument [EINVAL]" in s


def test_not_requested():
    g = request_realtime(50, None, fifo=False, getaffinity=lambda pid: {0, 1})
    assert g.fifo_granted is None and g.affinity_granted is None
    assert g.summary() == "real-time: SCHED_OTHER (realtime.fifo is off); not pinned (CPUs 0,1)"
    with pytest.raises(ValueError, match="1..99"):
        request_realtime(0)


def test_real_request_on_a_thread_leaves_the_caller_alone():
    before = os.sched_getscheduler(0)
    out = []
    t = threading.Thread(target=lambda: out.append(request_realtime_from_config(RealtimeConfig(fifo_priority=1))))
    t.start()
    t.join()
    assert out[0].summary().startswith("real-time: ")
    assert os.sched_getscheduler(0) == before


def test_the_configs_switch_interval_is_set_for_the_process_and_said():
    """The loop thread waits at most this long for the interpreter lock held by a helper thread."""
    import sys

    from runtime.loop.realtime_setup import RealtimeConfig, request_realtime_from_config

    before = sys.getswitchinterval()
    try:
        grant = request_realtime_from_config(RealtimeConfig(fifo=False, gil_switch_interval_ms=0.7))
        assert sys.getswitchinterval() == pytest.approx(0.0007)
        assert grant.switch_interval_ms == 0.7 and grant.summary().endswith("; GIL switch interval 0.7 ms")
    finally:
        sys.setswitchinterval(before)
