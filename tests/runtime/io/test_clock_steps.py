"""A step of the system clock (NTP, `date -s`): the drivers' stamps jump with it, the loop's clock
does not; the sensor inbox puts the stamps back onto the loop's clock (runtime.io.sensor_inbox),
reading the step from the loop's clock (runtime.loop.clocks.EpochMonotonicClock)."""
from __future__ import annotations

import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from runtime.common.sensor_data import ImuSample, LidarScan
from runtime.io.sensor_inbox import CLOCK_STEP_MIN_S, FUTURE_REFUSED_S, SensorInbox
from runtime.loop import clocks
from runtime.loop.clocks import EpochMonotonicClock


class SteppedClock:
    """The loop's clock at `now`, with the system clock stepped by `step` (what the OS would say)."""

    def __init__(self) -> None:
        self.now_s, self.step = 100.0, 0.0

    def now(self) -> float:
        return self.now_s

    def system_step_s(self) -> float:
        return self.step


def _imu(stamp: float) -> ImuSample:
    return ImuSample(stamp, np.zeros(3), np.array([0.0, 0.0, 9.81]))


def _scan(stamp: float, seed: int) -> LidarScan:
    pts = np.random.default_rng(seed).uniform(1, 5, (50, 3)).astype(np.float32)
    return LidarScan(stamp, pts, np.linspace(0, 0.1, 50, dtype=np.float32), 0.1)


@pytest.mark.parametrize("step", [2.0, -2.0])
def test_stamps_from_a_stepped_clock_land_on_the_loops_clock(step):
    clock = SteppedClock()
    inbox = SensorInbox(stamp_clock=clock)
    for k in range(5):  # before the step: stamps as they come
        clock.now_s = 100.0 + 0.005 * k
        assert inbox.put_imu(_imu(clock.now_s))
    clock.step = step
    for k in range(5, 10):  # after it: the driver stamps with the stepped clock
        clock.now_s = 100.0 + 0.005 * k
        assert inbox.put_imu(_imu(clock.now_s + step))
    assert inbox.put_scan(_scan(clock.now_s - 0.1 + step, 0))
    snap = inbox.take()
    stamps = [s.stamp_s for s in snap.imu]
    assert stamps == pytest.approx([100.0 + 0.005 * k for k in range(10)])  # every stamp on the loop's clock
    assert snap.scan.stamp_s == pytest.approx(clock.now_s - 0.1) and not snap.rejected
    assert inbox.clock_steps == 1 and inbox.clock_step_s == step
    assert f"{step:+.3f} s" in inbox.last_clock_step


def test_a_change_below_the_step_size_moves_no_stamp():
    clock = SteppedClock()
    inbox = SensorInbox(stamp_clock=clock)
    clock.step = 0.5 * CLOCK_STEP_MIN_S  # read jitter, a slewed offset: not a step
    assert inbox.put_imu(_imu(100.0))
    assert inbox.take().imu[0].stamp_s == 100.0 and inbox.clock_steps == 0


@pytest.mark.parametrize("step", [2.0, -2.0])
def test_data_stamped_before_the_step_that_arrives_after_it_keeps_its_place(step):
    clock = SteppedClock()
    inbox = SensorInbox(stamp_clock=clock)
    assert inbox.put_imu(_imu(99.995))
    clock.step = step
    assert inbox.put_imu(_imu(100.0))  # stamped just before the step, in flight across it
    clock.now_s = 100.005
    assert inbox.put_imu(_imu(100.005 + step))  # stamped after it
    clock.now_s = 100.0 + 1.5  # long after the step: the old clock no longer fits anything
    assert not inbox.put_imu(_imu(100.01))
    snap = inbox.take()
    assert [s.stamp_s for s in snap.imu] == pytest.approx([99.995, 100.0, 100.005])
    # put back with the step in force: 2 s behind the last (forward step) or ahead of now (back)
    assert [r.name for r in snap.rejected] == ["non_monotonic_stamp" if step > 0 else "future_stamp"]


def test_data_stamped_ahead_of_the_loops_clock_is_refused_at_the_inbox():
    clock = SteppedClock()
    inbox = SensorInbox(stamp_clock=clock)
    assert not inbox.put_imu(_imu(100.0 + 2 * FUTURE_REFUSED_S))
    assert inbox.put_imu(_imu(100.0))  # the refused stamp did not become the stream's last
    snap = inbox.take()
    assert [r.name for r in snap.rejected] == ["future_stamp"]
    assert "ahead of the controller's clock" in snap.rejected[0].message and len(snap.imu) == 1


def test_without_a_stamp_clock_stamps_are_taken_as_they_come():
    inbox = SensorInbox()
    assert inbox.put_imu(_imu(5.0 + FUTURE_REFUSED_S * 10))  # no clock to judge the future by
    assert inbox.take().imu[0].stamp_s == pytest.approx(5.0 + FUTURE_REFUSED_S * 10)


def test_the_loop_clock_reads_a_step_of_the_system_clock(monkeypatch):
    clock = EpochMonotonicClock()
    assert abs(clock.system_step_s()) < 1e-3
    real = time.time
    monkeypatch.setattr(clocks.time, "time", lambda: real() - 2.0)  # the system clock set back 2 s
    t0 = time.monotonic()
    now = clock.now()
    assert clock.system_step_s() == pytest.approx(-2.0, abs=1e-3)
    assert now - clock.offset_s == pytest.approx(t0, abs=0.05)  # the loop's clock did not jump


@settings(max_examples=200, deadline=None)
@given(step=st.floats(0.1, 30.0), sign=st.sampled_from([1.0, -1.0]), at=st.integers(1, 40),
       latencies=st.lists(st.floats(0.0, 0.004), min_size=60, max_size=60), back_after=st.integers(2, 19))
def test_every_stamp_lands_at_its_capture_time_across_steps_and_latencies(step, sign, at, latencies, back_after):
    """Samples captured every 5 ms, stamped by a driver with the system clock, arriving 0-4 ms later;
    the clock stepped at one capture and back at least two captures later (a step the inbox sees). Every
    sample taken, each at the
    loop-clock time of its capture."""
    clock = SteppedClock()
    inbox = SensorInbox(stamp_clock=clock)
    step *= sign

    def system_step(t):  # the step in force at loop time t
        return step if at * 0.005 <= t - 100.0 < (at + back_after) * 0.005 else 0.0

    captured = [100.0 + 0.005 * k for k in range(60)]
    for t, lat in zip(captured, latencies):
        clock.now_s = t + lat
        clock.step = system_step(clock.now_s)
        assert inbox.put_imu(_imu(t + system_step(t))), inbox.last_error
    snap = inbox.take()
    assert [s.stamp_s for s in snap.imu] == pytest.approx(captured, abs=1e-9)
