"""Odometry: planar pose algebra, degeneracy from the Hessian, the increment EKF, the ICP engine
on synthetic scenes, and the worker's two clocks."""
from __future__ import annotations

import functools
import math
import os

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from runtime.odometry.degeneracy import DegeneracyConfig, planar_constraint
from runtime.odometry.fusion import FusionConfig, PoseFusion
from runtime.odometry.icp import IcpEngine, IcpJob, IcpResult, deskew_with_motion, warm_up
from runtime.odometry.icp_config import IcpConfig
from runtime.odometry.kiss_pipeline import TIMED_PARTS
from runtime.odometry.se2 import se2_between, se2_compose, se2_inverse, wrap
from runtime.odometry.worker import InlineIcpWorker, ProcessIcpWorker

MOUNT = np.eye(4)
MOUNT[:3, 3] = [0.05, 0.0, 0.20]

finite = st.floats(-50, 50, allow_nan=False)
angle = st.floats(-math.pi, math.pi, allow_nan=False)


@settings(max_examples=200, deadline=None)
@given(finite, finite, angle, finite, finite, angle)
def test_se2_compose_between_and_inverse_agree(ax, ay, ath, bx, by, bth):
    a, b = np.array([ax, ay, ath]), np.array([bx, by, bth])
    np.testing.assert_allclose(se2_compose(a, se2_between(a, b))[:2], b[:2], atol=1e-9)
    assert abs(wrap(se2_compose(a, se2_between(a, b))[2] - bth)) < 1e-9
    np.testing.assert_allclose(se2_compose(a, se2_inverse(a)), [0, 0, 0], atol=1e-9)


# -- synthetic scenes --------------------------------------------------------------------------

def _wall(p0, p1, z0=0.0, z1=1.5, step=0.05):
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    n = max(int(np.linalg.norm(p1 - p0) / step), 2)
    s = np.linspace(0, 1, n)
    zs = np.arange(z0, z1, step)
    xy = p0 + s[:, None] * (p1 - p0)
    return np.array([[x, y, z] for x, y in xy for z in zs])


def _cylinder(c, r, z1=1.0, step=0.05):
    n = max(int(2 * math.pi * r / step), 8)
    a = np.linspace(0, 2 * math.pi, n, endpoint=False)
    zs = np.arange(0.0, z1, step)
    return np.array([[c[0] + r * math.cos(t), c[1] + r * math.sin(t), z] for t in a for z in zs])


def _floor(half=5.0, step=0.2):
    g = np.arange(-half, half, step)
    return np.array([[x, y, 0.0] for x in g for y in g])


def test_a_straight_corridor_is_degenerate_along_its_axis_and_a_room_is_not():
    corridor = np.vstack([_wall((-20, -1), (20, -1)), _wall((-20, 1), (20, 1)), _floor()])
    c = planar_constraint(corridor)
    assert c.degenerate_xy and not c.too_few_points
    weak = c.weak_direction_xy
    assert abs(weak[0]) > 0.99, weak  # along x, the corridor's axis
    assert c.eigenvalues_xy[1] > 0.3  # across it: well constrained
    room = np.vstack([corridor, _wall((-3, -1), (-3, 1)), _wall((3, -1), (3, 1)), _cylinder((1, 0.5), 0.1)])
    r = planar_constraint(room)
    assert not r.degenerate_xy and r.eigenvalues_xy[0] > 0.03
    assert "well constrained" in r.describe() and "unconstrained along" in c.describe()


def test_a_round_room_leaves_yaw_unconstrained_and_little_data_is_too_little():
    round_room = np.vstack([_cylinder((0, 0), 3.0, z1=1.5), _floor()])
    c = planar_constraint(round_room)
    assert c.degenerate_yaw and not c.degenerate_xy
    few = planar_constraint(_wall((1, -0.1), (1, 0.1), z1=0.2))
    assert few.too_few_points and few.degenerate and "sees too little" in few.describe()
    empty = planar_constraint(np.zeros((0, 3)))
    assert empty.too_few_points


# -- the fusion ----------------------------------------------------------------------------------

def _result(seq, t_prev, t, delta, constraint=None, pose=np.zeros(3)):
    return IcpResult(seq=seq, stamp_s=t - 0.1, end_s=t, ready_at_s=t + 0.1, pose_base=pose,
                     delta_base=None if delta is None else np.asarray(delta, float), prev_end_s=t_prev,
                     constraint=constraint, points_in=1000, points_registered=500, deskewed=True, compute_s=0.0)


def _room_constraint():
    return planar_constraint(np.vstack([_wall((-3, -2), (3, -2)), _wall((-3, 2), (3, 2)), _wall((-3, -2), (-3, 2)),
                                        _wall((3, -2), (3, 2)), _cylinder((1, 1), 0.2)]))


def _corridor_constraint():
    return planar_constraint(np.vstack([_wall((-20, -1), (20, -1)), _wall((-20, 1), (20, 1))]))


def _drive(fusion, steps, wheel_step, icp_step, constraint, dt=0.1):
    """Straight drive: wheels report wheel_step per frame, ICP icp_step; returns the fused pose."""
    d = np.zeros(3)
    fusion.add_dead_reckoning(0.0, d.copy())
    fusion.icp_update(_result(0, None, 0.0, None, constraint))  # the first frame: anchor only
    for k in range(1, steps + 1):
        d = se2_compose(d, np.asarray(wheel_step, float))
        fusion.add_dead_reckoning(k * dt, d.copy())
        assert fusion.icp_update(_result(k, (k - 1) * dt, k * dt, icp_step, constraint)) is None
    return fusion.pose_now(d, steps * dt)


def test_without_icp_the_pose_is_the_dead_reckoning_and_its_covariance_grows():
    f = PoseFusion(FusionConfig())
    f.add_dead_reckoning(0.0, np.zeros(3))
    p0, c0 = f.pose_now(np.zeros(3), 0.0)
    pose, cov = f.pose_now(np.array([1.0, 0.2, 0.3]), 0.0)
    np.testing.assert_allclose(pose, [1.0, 0.2, 0.3], atol=1e-12)
    assert np.all(np.diag(cov) > np.diag(c0))


def test_in_a_room_the_fused_pose_follows_icp_when_the_wheels_overstate_the_distance():
    # Wheels say 4.4 cm a frame (10% scale error, as a slipping base), ICP the true 4 cm.
    pose, _ = _drive(PoseFusion(FusionConfig()), 50, [0.044, 0, 0], [0.040, 0, 0], _room_constraint())
    # The wheels alone would say 2.2 m; ICP (weighted by its drift, and kept smooth: fusion.py)
    # takes more than half of that error away.
    assert abs(pose[0] - 2.0) < 0.09


def test_in_a_corridor_the_wheels_carry_the_axis_and_icp_the_rest():
    # ICP slides (says no motion along the axis) and corrects a sideways wheel error.
    pose, cov = _drive(PoseFusion(FusionConfig()), 50, [0.04, 0.002, 0], [0.0, 0.0, 0], _corridor_constraint())
    assert abs(pose[0] - 2.0) < 0.01  # along the axis: the wheels (ICP alone: 0 m)
    assert abs(pose[1]) < 0.05  # across: ICP takes more than half the wheels' 0.1 m error away
    assert cov[0, 0] > 3 * cov[1, 1]  # and the covariance says which direction is weak


def test_an_implausible_icp_increment_is_refused_and_named():
    f = PoseFusion(FusionConfig())
    f.add_dead_reckoning(0.0, np.zeros(3))
    f.icp_update(_result(0, None, 0.0, None, _room_constraint()))
    f.add_dead_reckoning(0.1, np.array([0.04, 0.0, 0.0]))
    why = f.icp_update(_result(1, 0.0, 0.1, [0.60, 0.0, 0.0], _room_constraint()))
    assert why is not None and "implausible" in why and f.stats.refused == 1
    pose, _ = f.pose_now(np.array([0.04, 0.0, 0.0]), 0.1)
    assert abs(pose[0] - 0.04) < 1e-9  # the wheels' increment was used


def test_while_the_base_says_nothing_of_its_motion_icp_gives_the_translation():
    # a bus-off: the wheels stand still for 0.5 s (no distances, no speed), the robot does not
    f = PoseFusion(FusionConfig())
    f.add_dead_reckoning(0.0, np.zeros(3))
    f.icp_update(_result(0, None, 0.0, None, _room_constraint()))
    for k in range(1, 6):
        f.add_dead_reckoning(0.1 * k, np.zeros(3), translation_known=False)
        assert f.icp_update(_result(k, 0.1 * (k - 1), 0.1 * k, [0.08, 0.0, 0.0], _room_constraint())) is None
    pose, _ = f.pose_now(np.zeros(3), 0.5)
    assert abs(pose[0] - 0.40) < 0.005 and f.stats.wheels_blind == 5 and f.stats.refused == 0
    # a rotation the gyro did not see is still refused
    f.add_dead_reckoning(0.6, np.zeros(3), translation_known=False)
    assert "implausible" in f.icp_update(_result(6, 0.5, 0.6, [0.08, 0.0, 0.5], _room_constraint()))
    # the wheels back: an increment judged against them again
    f.add_dead_reckoning(0.7, np.array([0.04, 0.0, 0.0]))
    f.add_dead_reckoning(0.8, np.array([0.08, 0.0, 0.0]))
    f.icp_update(_result(7, 0.6, 0.7, [0.04, 0.0, 0.0], _room_constraint()))
    assert "implausible" in f.icp_update(_result(8, 0.7, 0.8, [0.60, 0.0, 0.0], _room_constraint()))


def test_a_result_older_than_the_history_is_dropped_not_fused():
    f = PoseFusion(FusionConfig())
    f.add_dead_reckoning(10.0, np.zeros(3))
    why = f.icp_update(_result(0, None, 1.0, None, _room_constraint()))
    assert why is not None and "history" in why and f.stats.too_old == 1


# -- the ICP engine and the worker ---------------------------------------------------------------

def _scene():
    rng = np.random.default_rng(1)
    parts = [_wall((-4, -3), (4, -3)), _wall((-4, 3), (4, 3)), _wall((-4, -3), (-4, 3)), _wall((4, -3), (4, 3)),
             _floor(4.0, 0.15)]
    for _ in range(12):
        c = rng.uniform(-3, 3, 2)
        parts.append(_cylinder(c, rng.uniform(0.05, 0.3)))
    return np.vstack(parts)


def _frames(n=6, step=(0.05, 0.0, 0.02), noise=0.005, seed=0, world=None, wheel_scale=1.0):
    """Frames of the synthetic scene (or `world`) seen by the lidar from a base moving `step` per
    frame; the wheels' pose (the prior) runs `wheel_scale` times the true motion."""
    world = _scene() if world is None else world
    rng = np.random.default_rng(seed)
    pose = np.zeros(3)
    wheels = np.zeros(3)
    frames = []
    for k in range(n):
        c, s = math.cos(pose[2]), math.sin(pose[2])
        rel = world[:, :2] - pose[:2]
        base = np.column_stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1], world[:, 2]])
        lidar = base - MOUNT[:3, 3]
        keep = np.hypot(lidar[:, 0], lidar[:, 1]) < 12
        pts = (lidar[keep] + rng.normal(0, noise, (keep.sum(), 3))).astype(np.float32)
        offs = np.linspace(0, 0.099, len(pts)).astype(np.float32)
        frames.append(IcpJob(seq=k, stamp_s=0.1 * k, end_s=0.1 * k + 0.099, points=pts, offsets_s=offs, duration_s=0.1,
                             dead_reckoning_end=wheels.copy(), ready_at_s=0.1 * k + 0.2))
        pose = se2_compose(pose, np.asarray(step, float))
        wheels = se2_compose(wheels, np.asarray(step, float) * wheel_scale)
    return frames


def _engine(deskew="off"):
    return IcpEngine(IcpConfig(voxel_size_m=0.2, deskew=deskew), DegeneracyConfig(), MOUNT, True)


def test_kiss_icp_recovers_the_motion_of_a_synthetic_scene():
    engine = _engine()
    results = [engine.process(j) for j in _frames()]
    assert results[0].delta_base is None
    for r in results[1:]:
        np.testing.assert_allclose(r.delta_base[:2], [0.05, 0.0], atol=0.01)
        assert abs(r.delta_base[2] - 0.02) < math.radians(0.3)
        assert r.constraint is not None and not r.constraint.degenerate
        assert r.iteration_cap >= 20  # the auto cap: a well-constrained frame is not cut short
        # Its time by part (a measurement): every part, none negative, within the whole.
        assert list(r.parts_ms) == ["prepare", *TIMED_PARTS] and min(r.parts_ms.values()) >= 0.0
        assert sum(r.parts_ms.values()) <= r.compute_s * 1e3


def test_where_the_scan_constrains_the_motion_icp_corrects_wheels_that_overstate_it():
    engine = _engine()
    results = [engine.process(j) for j in _frames(step=(0.05, 0.0, 0.0), wheel_scale=1.3)]
    for r in results[1:]:
        np.testing.assert_allclose(r.delta_base[:2], [0.05, 0.0], atol=0.01)


def test_along_a_featureless_corridor_the_registered_motion_is_the_wheels_and_across_it_icps():
    # The walls run past the range on both sides: nothing fixes the motion along x. ICP's answer
    # there is a slide; the engine keeps the wheels' (here 30% long) along the axis, so the map it
    # builds agrees with the pose the fusion gives, and across the axis what the scan measured.
    corridor = np.vstack([_wall((-30, -1), (30, -1), step=0.03), _wall((-30, 1), (30, 1), step=0.03),
                          _floor(12.0, 0.15)])
    # The analysis runs before the registration: a degenerate frame gets the lower iteration cap.
    engine = IcpEngine(IcpConfig(voxel_size_m=0.2, deskew="off", degenerate_max_iterations=7), DegeneracyConfig(), MOUNT, True)
    results = [engine.process(j) for j in _frames(n=8, step=(0.05, 0.0, 0.0), world=corridor, wheel_scale=1.3)]
    for r in results[1:]:
        assert r.constraint.degenerate_xy and r.iteration_cap == 7
        assert abs(r.delta_base[0] - 0.065) < 1e-6, r.delta_base   # the wheels' 1.3 x 5 cm
        assert abs(r.delta_base[1]) < 0.01 and abs(r.delta_base[2]) < math.radians(0.3)


def test_deskew_with_motion_moves_each_point_to_the_frame_end():
    # A wall point seen at t=0 from a base that then moves 0.1 m forward: at the end it is 0.1 m closer.
    pts = np.array([[2.0, 0.0, 0.5], [2.0, 0.0, 0.5]])
    motion = np.array([[0.0, 0.0, 0.0, 0.0], [0.1, 0.1, 0.0, 0.0]])
    out = deskew_with_motion(pts, np.array([0.0, 0.1]), 0.1, motion, MOUNT)
    np.testing.assert_allclose(out[0], [1.9, 0.0, 0.5], atol=1e-12)
    np.testing.assert_allclose(out[1], [2.0, 0.0, 0.5], atol=1e-12)


def test_a_frame_whose_times_do_not_span_the_sweep_is_not_deskewed_and_says_so():
    job = _frames(1)[0]
    flat = IcpJob(**{**job.__dict__, "offsets_s": np.zeros_like(job.offsets_s)})
    r = _engine("kiss").process(flat)
    assert not r.deskewed and any("no deskew" in n for n in r.notes)


def test_lockstep_results_are_identical_from_the_process_and_inline_and_arrive_at_their_time():
    factory = functools.partial(IcpEngine, IcpConfig(voxel_size_m=0.2, deskew="kiss"), DegeneracyConfig(), MOUNT, True)
    frames = _frames(5)
    got = {}
    for name, worker in (("inline", InlineIcpWorker(factory)), ("process", ProcessIcpWorker(factory, lockstep=True))):
        try:
            out = []
            for job in frames:
                worker.submit(job)
                assert worker.poll(job.end_s) == []  # never before its simulated delivery time
                worker.settle(job.ready_at_s)  # the simulator waits here, not the tick
                res = worker.poll(job.ready_at_s)
                assert [r.seq for r in res] == [job.seq]
                out.append(res[0])
            got[name] = out
        finally:
            worker.close()
    for a, b in zip(got["inline"], got["process"]):
        np.testing.assert_array_equal(a.pose_base, b.pose_base)


def test_the_warm_up_leaves_nothing_behind_and_the_worker_is_ready_after_it():
    """The worker registers synthetic frames with a throwaway engine before it says ready: the
    engines that register real frames give the same poses, bit for bit, as without it."""
    factory = functools.partial(IcpEngine, IcpConfig(voxel_size_m=0.2, deskew="kiss"), DegeneracyConfig(), MOUNT, True)
    frames = _frames(4)
    e = factory()
    cold = [e.process(j).pose_base for j in frames]
    assert warm_up(factory) > 0.0
    e = factory()
    warm = [e.process(j).pose_base for j in frames]
    for a, b in zip(cold, warm):
        np.testing.assert_array_equal(a, b)
    worker = ProcessIcpWorker(factory, lockstep=True)
    try:
        assert not worker.ready
        worker.wait_ready()
        assert worker.ready and worker.failed is None
    finally:
        worker.close()


def test_a_reused_worker_answers_the_next_run_as_a_fresh_one_and_drops_the_last_runs_answers():
    """reuse (lockstep campaigns): a closed run leaves its worker process idle; the next run takes
    it, its engine rebuilt from the new factory, and gets the same poses as from a fresh worker,
    none of the answers the last run left unread."""
    import runtime.odometry.worker as worker_module

    factory = functools.partial(IcpEngine, IcpConfig(voxel_size_m=0.2, deskew="kiss"), DegeneracyConfig(), MOUNT, True)
    frames = _frames(4)
    expected = _fresh_worker_poses(factory, frames)
    first = ProcessIcpWorker(factory, lockstep=True, reuse=True)
    _lockstep_poses(first, frames[:2])
    for job in frames[2:]:
        first.submit(job)  # left unread: the worker answers them after the run closed
    first.close()
    second = ProcessIcpWorker(factory, lockstep=True, reuse=True)
    try:
        assert second._proc is first._proc  # the same process, no new interpreter
        got = _lockstep_poses(second, frames)
        assert len(got) == len(expected)
        for a, b in zip(got, expected):
            np.testing.assert_array_equal(a, b)
    finally:
        second.reuse = False  # this test leaves no idle worker behind
        second.close()
    assert worker_module._take_idle() is None


def _lockstep_poses(worker, jobs) -> list:
    """The worker's poses for jobs, each waited for at its delivery time (as the simulator does)."""
    worker.wait_ready()
    out = []
    for job in jobs:
        worker.submit(job)
        worker.settle(job.ready_at_s)
        out += [r.pose_base for r in worker.poll(job.ready_at_s)]
    return out


def _fresh_worker_poses(factory, jobs) -> list:
    """The poses a fresh (not reused) lockstep worker gives; the pool emptied of other tests'
    idle workers first, so that the next reuse takes the one the test leaves."""
    _no_idle_workers()
    fresh = ProcessIcpWorker(factory, lockstep=True)
    try:
        return _lockstep_poses(fresh, jobs)
    finally:
        fresh.close()


def _no_idle_workers():
    import runtime.odometry.worker as worker_module

    while (idle := worker_module._take_idle()) is not None:
        idle[0].kill()
        idle[0].wait()
        idle[1].close()


def test_a_run_that_closed_before_its_ready_does_not_hand_the_next_run_a_stale_ready():
    """A run closed before it read its worker's ready (a build that failed), with a job in flight:
    the next run on that worker waits for its own ready, and gets a fresh worker's poses."""
    import runtime.odometry.worker as worker_module

    factory = functools.partial(IcpEngine, IcpConfig(voxel_size_m=0.2, deskew="kiss"), DegeneracyConfig(), MOUNT, True)
    frames = _frames(3)
    expected = _fresh_worker_poses(factory, frames)
    _no_idle_workers()  # another test's idle worker would be the one handed on
    early = ProcessIcpWorker(factory, lockstep=True, reuse=True)
    early.submit(frames[0])
    # The worker has warmed up and said ready (left unread): on a busy machine its warm-up takes
    # seconds, and a close that cannot hand over its frame meanwhile ends the worker instead.
    assert early._conn.poll(60.0)
    early.close()  # its ready and its answer unread
    later = ProcessIcpWorker(factory, lockstep=True, reuse=True)
    try:
        assert later._proc is early._proc and later._generation != early._generation
        got = _lockstep_poses(later, frames)
        assert len(got) == len(expected)
        for a, b in zip(got, expected):
            np.testing.assert_array_equal(a, b)
    finally:
        later.reuse = False
        later.close()
    assert worker_module._take_idle() is None


def test_a_worker_handed_on_to_a_full_pool_ends_quietly_and_a_dead_idle_one_is_replaced():
    import runtime.odometry.worker as worker_module

    factory = functools.partial(IcpEngine, IcpConfig(voxel_size_m=0.2), DegeneracyConfig(), MOUNT, True)
    _no_idle_workers()
    a = ProcessIcpWorker(factory, lockstep=True, reuse=True)
    b = ProcessIcpWorker(factory, lockstep=True, reuse=True)
    a.wait_ready()
    b.wait_ready()
    a.close()  # idle: the pool holds one
    b.close()  # the pool is full: told there is no next run, it ends
    assert b._proc.wait(timeout=10) == 0
    assert len(worker_module._IDLE) == 1 and worker_module._IDLE[0][0] is a._proc
    a._proc.kill()  # the idle one dies
    a._proc.wait()
    c = ProcessIcpWorker(factory, lockstep=True, reuse=True)
    try:
        assert c._proc is not a._proc  # a fresh one instead
        c.wait_ready()
        assert c.ready and c.failed is None
    finally:
        c.reuse = False
        c.close()
    assert worker_module._take_idle() is None


def test_a_worker_that_cannot_start_is_named_by_wait_ready():
    worker = ProcessIcpWorker(functools.partial(IcpEngine, "not a config", DegeneracyConfig(), MOUNT, True),
                              lockstep=True)
    try:
        worker.wait_ready()  # returns: never hangs on a worker that failed
        assert not worker.ready and "could not start" in worker.failed
    finally:
        worker.close()


def test_real_time_worker_keeps_only_the_newest_waiting_frame_and_names_a_dead_worker():
    factory = functools.partial(IcpEngine, IcpConfig(voxel_size_m=0.2), DegeneracyConfig(), MOUNT, True)
    worker = ProcessIcpWorker(factory, lockstep=False)
    try:
        frames = _frames(4)
        for job in frames:
            worker.submit(job)  # returns at once: the first is sent, later ones wait (newest kept)
        assert worker.dropped == 2
        seen = []
        for _ in range(600):
            seen += [r.seq for r in worker.poll(0.0)]
            if 3 in seen:
                break
            worker._conn.poll(0.05)
        assert seen == [0, 3]
        # The registration runs below the controller's priority (the tick gets a contended core first).
        from runtime.odometry.worker import WORKER_NICENESS

        assert os.getpriority(os.PRIO_PROCESS, worker._proc.pid) == min(19, os.getpriority(os.PRIO_PROCESS, 0) + WORKER_NICENESS)
        worker._proc.kill()
        worker._proc.wait()
        worker.submit(frames[0])
        for _ in range(100):
            worker.poll(0.0)
            if worker.failed:
                break
            worker._conn.poll(0.05)
        assert worker.failed and "ICP worker" in worker.failed
    finally:
        worker.close()


def _scan_of(job):
    from runtime.common.sensor_data import LidarScan

    return LidarScan(stamp_s=job.stamp_s, points_m=job.points, point_time_offsets_s=job.offsets_s, frame_duration_s=0.1)


def _stage(**odometry):
    from runtime.common.events import EventLog
    from runtime.odometry.stage import OdometryConfig, OdometryStage

    cfg = OdometryConfig(icp=IcpConfig(voxel_size_m=0.2, deskew="off"), lockstep_worker="inline",
                         lockstep_latency_s=0.05, **odometry)
    stage = OdometryStage(cfg, 0.175, 3.0, MOUNT, lockstep=True, events=EventLog())
    stage.start()
    return stage


def _tick(stage, now, wheel_m, job):
    stage.settle(now)
    return stage.update(now, (wheel_m, wheel_m), (), _scan_of(job) if job is not None else None)


def test_the_stage_reports_each_correction_so_obstacle_points_move_with_the_pose():
    """When ICP results land, `correction` is exactly what they did to the pose now: applied to the
    pose the stage would have predicted without them, it gives the pose it reports (the controller
    moves P_fix by it). Synthetic frames, wheels overstating the motion by 20%."""
    stage = _stage()
    frames = _frames(6, step=(0.05, 0.0, 0.0))
    corrections = 0
    try:
        for k in range(1, 13):  # 20 Hz ticks over 6 frames at 10 Hz
            f = stage.fusion
            anchor_pose, anchor_d = f.anchor_pose.copy(), f._anchor_d.copy()
            pose = _tick(stage, 0.05 * k, k * 0.5 * 0.05 * 1.2, frames[(k - 1) // 2] if k % 2 else None)
            if stage.correction is None:
                continue
            d_now = np.array([stage.wheels.pose.x_m, stage.wheels.pose.y_m, stage.wheels.pose.yaw_rad])
            predicted = se2_compose(anchor_pose, se2_between(anchor_d, d_now))
            np.testing.assert_allclose(se2_compose(stage.correction, predicted), [pose.x_m, pose.y_m, pose.yaw_rad],
                                       atol=1e-9)
            if np.linalg.norm(stage.correction[:2]) > 1e-4:
                corrections += 1
                assert stage.correction[0] < 0.0  # pulled back against the wheels' overstatement
        assert corrections >= 3 and stage.fusion.stats.fused >= 3
        assert stage.pose.x_m < 0.34  # below the wheels' 0.36 m
    finally:
        stage.close()


def test_icp_lost_is_named_when_results_stop_or_are_all_refused_and_restored_when_they_return():
    frames = _frames(12, step=(0.05, 0.0, 0.0))
    stage = _stage()
    try:
        t = 0.0
        for k, job in enumerate(frames[:4]):  # good frames
            t = 0.1 * k + 0.1
            _tick(stage, t, 0.05 * k, job)
        for j in range(1, 11):  # 1 s without frames (a silent lidar)
            _tick(stage, t + 0.1 * j, 0.15, None)
        kinds = [e["event"] for e in stage.events.to_list()]
        assert "icp_lost" in kinds and stage.describe()["icp_age_s"] > 0.6
        later = [IcpJob(**{**j.__dict__, "stamp_s": j.stamp_s + 1.0, "end_s": j.end_s + 1.0,
                           "ready_at_s": j.ready_at_s + 1.0}) for j in frames[4:8]]
        for k, job in enumerate(later):
            _tick(stage, job.end_s + 0.06, 0.15 + 0.05 * k, job)
        assert [e["event"] for e in stage.events.to_list()][-1] == "icp_restored"
    finally:
        stage.close()
    # Wheels that claim a turn of about 0.2 rad a frame on a straight drive (and ICP left to its
    # own prediction, not theirs): every ICP increment is refused; ICP is lost even though results
    # keep arriving. (Wheels claiming more distance than a wheel can turn are re-anchored instead.)
    stage = _stage(icp_prior="constant_velocity")
    try:
        for k, job in enumerate(frames):
            stage.settle(job.end_s + 0.06)
            stage.update(job.end_s + 0.06, (0.05 * k, 0.16 * k), (), _scan_of(job))
        d = stage.describe()
        assert d["icp_refused"] >= 8 and d["icp_fused"] == 0
        lost = [e for e in stage.events.to_list() if e["event"] == "icp_lost"]
        assert lost and "implausible" in lost[0]["reason"]
    finally:
        stage.close()


def test_after_a_dropped_frame_the_prior_spans_the_motion_since_the_frame_registered_last():
    engine = _engine()
    frames = _frames(5, step=(0.05, 0.0, 0.02))
    results = [engine.process(j) for j in (frames[0], frames[1], frames[3], frames[4])]  # frame 2 dropped
    np.testing.assert_allclose(results[2].delta_base[:2], se2_compose(np.array([0.05, 0, 0.02]),
                                                                      np.array([0.05, 0, 0.02]))[:2], atol=0.01)
    assert abs(results[2].delta_base[2] - 0.04) < math.radians(0.3)


def test_without_fresh_wheel_distances_the_reported_speed_carries_the_translation_once():
    from runtime.odometry.wheels import WheelGyroOdometry

    odo = WheelGyroOdometry(0.175, 3.0)
    odo.update_with_imu((0.0, 0.0), ())
    odo.update_with_imu((0.10, 0.10), ())  # 0.10 m by the wheels
    odo.update_with_imu(None, (), fallback_distance_m=0.05)  # 0x311 lost: 0x221 says 0.05 m
    odo.update_with_imu(None, (), fallback_distance_m=0.05)
    assert odo.pose.x_m == pytest.approx(0.20)
    odo.update_with_imu((0.30, 0.30), ())  # back: re-anchored, its 0.20 m jump is not counted again
    odo.update_with_imu((0.35, 0.35), ())
    assert odo.pose.x_m == pytest.approx(0.25)
    odo.update_with_imu(None, ())  # neither: the pose holds (no invented motion)
    assert odo.pose.x_m == pytest.approx(0.25)


def test_frozen_wheel_distances_give_way_to_the_reported_speed_from_their_last_change():
    """0x311 repeating one reading while 0x221 reports 1 m/s (a stuck odometer): after
    wheels_frozen_s the distances are withheld and the speed carries the translation from their
    last change (the frozen ticks before it included); when they change again they re-anchor,
    their jump over the spell not counted beside the speed's, even after the robot stopped."""
    from runtime.common.events import EventLog
    from runtime.odometry.stage import OdometryConfig, OdometryStage

    stage = OdometryStage(OdometryConfig(source="wheels_imu"), 0.175, 1.0, MOUNT, lockstep=True, events=EventLog())
    stage.start()
    dt, v = 0.05, 1.0
    t = 0.0
    stage.update(t, (0.0, 0.0), (), None, speed_mps=0.0)
    for k in range(1, 11):  # 0.5 s at 1 m/s, the distances fresh
        t = k * dt
        stage.update(t, (v * t, v * t), (), None, speed_mps=v)
    assert stage.pose.x_m == pytest.approx(0.5)
    frozen = (v * t, v * t)
    for k in range(1, 11):  # 0.5 s more at 1 m/s: the same reading every tick
        stage.update(t + k * dt, frozen, (), None, speed_mps=v)
        if k == 2:  # 0.1 s unchanged: not yet judged (a reading may lag)
            assert not stage.describe()["wheels_frozen"]
    assert stage.describe()["wheels_frozen"] and stage.describe()["wheels_frozen_spells"] == 1
    assert stage.pose.x_m == pytest.approx(1.0)
    t += 10 * dt
    for k in range(1, 5):  # stopped (by the stuck fault's stop), still the frozen reading
        stage.update(t + k * dt, frozen, (), None, speed_mps=0.0)
    assert stage.describe()["wheels_frozen"] and stage.pose.x_m == pytest.approx(1.0)
    t += 4 * dt
    stage.update(t + dt, (1.0, 1.0), (), None, speed_mps=0.0)  # the odometer again: 0.5 m jump, re-anchored
    stage.update(t + 2 * dt, (1.01, 1.01), (), None, speed_mps=0.2)
    assert not stage.describe()["wheels_frozen"] and stage.pose.x_m == pytest.approx(1.01)
    # a robot standing still has unchanging distances: not frozen, however long
    still = OdometryStage(OdometryConfig(source="wheels_imu"), 0.175, 1.0, MOUNT, lockstep=True, events=EventLog())
    still.start()
    for k in range(1, 40):
        still.update(k * dt, (0.0, 0.0), (), None, speed_mps=0.01)
    assert still.describe()["wheels_frozen_spells"] == 0 and still.pose.x_m == pytest.approx(0.0)
    # ... and one that starts moving reports its speed a tick before its distances move
    still.update(40 * dt, (0.0, 0.0), (), None, speed_mps=0.06)
    still.update(41 * dt, (0.008, 0.008), (), None, speed_mps=0.1)
    assert still.describe()["wheels_frozen_spells"] == 0 and still.pose.x_m == pytest.approx(0.008)


def test_pose_at_a_past_time_is_the_pose_now_taken_back_by_the_wheels():
    """pose_at(t): where the robot was at t (a camera frame's capture) - the fused pose now, taken
    back by the wheel motion since t; None outside the dead-reckoning history or before any pose."""
    stage = _stage()
    try:
        assert stage.pose_at(0.0) is None
        for k in range(11):  # straight ahead at 1 m/s, 20 Hz ticks
            _tick(stage, 0.05 * k, 0.05 * k, None)
        now = stage.pose
        back = stage.pose_at(0.5 - 0.075)  # between two ticks: interpolated
        assert back.x_m == pytest.approx(now.x_m - 0.075, abs=1e-6)
        assert back.y_m == pytest.approx(now.y_m, abs=1e-9) and back.yaw_rad == pytest.approx(now.yaw_rad)
        assert stage.pose_at(0.5).x_m == pytest.approx(now.x_m)
        assert stage.pose_at(-10.0) is None  # before the history
    finally:
        stage.close()


def test_pose_at_takes_a_turn_back_along_the_arc():
    """Turning on the spot then driving: pose_at a time before the turn's end has the yaw and the
    position of then, composed through the turn (not the pose now minus a straight offset)."""
    stage = _stage()
    try:
        left = right = 0.0
        for k in range(11):  # 0.5 s turning on the spot: wheels in opposite directions
            left, right = left - 0.01, right + 0.01
            stage.settle(0.05 * k)
            stage.update(0.05 * k, (left, right), (), None)
        turned = stage.pose.yaw_rad
        assert turned > 0.1
        for k in range(11, 21):  # then straight on 0.5 m
            left, right = left + 0.05, right + 0.05
            stage.settle(0.05 * k)
            stage.update(0.05 * k, (left, right), (), None)
        now, then = stage.pose, stage.pose_at(0.5)
        assert then.yaw_rad == pytest.approx(turned, abs=1e-6)
        assert np.hypot(now.x_m - then.x_m, now.y_m - then.y_m) == pytest.approx(0.5, abs=1e-3)
        assert np.arctan2(now.y_m - then.y_m, now.x_m - then.x_m) == pytest.approx(turned, abs=1e-3)
    finally:
        stage.close()


def test_people_walking_are_left_out_of_the_icp_at_every_height():
    """exclude_movers: odom points of a person (a track of runtime.perception.moving_obstacles) are taken to
    the lidar frame with the pose and the mount (here turned 90 degrees and tilted); the next
    frame loses every point within mover_radius_m of them in x, y, from the floor to the head,
    and keeps the rest."""
    from runtime.common.events import EventLog
    from runtime.common.geometry import Pose2D
    from runtime.odometry.stage import OdometryConfig, OdometryStage
    from runtime.common.sensor_data import LidarScan

    yaw, tilt = math.pi / 2, math.radians(3.0)
    Rz = np.array([[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0], [0, 0, 1]])
    Ry = np.array([[math.cos(tilt), 0, math.sin(tilt)], [0, 1, 0], [-math.sin(tilt), 0, math.cos(tilt)]])
    mount = np.eye(4)
    mount[:3, :3] = Rz @ Ry  # lidar -> base_link
    mount[:3, 3] = [0.05, 0.02, 0.20]
    cfg = OdometryConfig(icp=IcpConfig(voxel_size_m=0.2, deskew="off"), lockstep_worker="inline")
    stage = OdometryStage(cfg, 0.175, 3.0, mount, lockstep=True, events=EventLog())
    stage.pose = Pose2D(1.0, 2.0, math.pi / 2)  # facing +y in the odom frame
    stage.exclude_movers(np.array([[1.0, 4.0]]))  # 2 m ahead of base_link
    # the person's column and a wall, made in base_link and taken to the lidar frame
    z = np.linspace(0.05, 1.7, 12)
    person_base = np.column_stack([np.full(12, 2.0), np.zeros(12), z])
    wall_base = np.column_stack([np.full(20, 4.0), np.linspace(-2, 2, 20), np.full(20, 0.3)])
    pts_base = np.concatenate([person_base, wall_base])
    pts_lidar = (pts_base - mount[:3, 3]) @ mount[:3, :3]
    scan = LidarScan(stamp_s=0.0, points_m=pts_lidar.astype(np.float32),
                     point_time_offsets_s=np.zeros(32, np.float32), frame_duration_s=0.1)
    kept = stage._without_movable(scan, stage._movers_in_lidar(0.05), stage.mover_radius_m, planar=True).points_m
    kept_base = kept.astype(np.float64) @ mount[:3, :3].T + mount[:3, 3]
    assert len(kept) == 20 and np.allclose(kept_base[:, 0], 4.0, atol=1e-4), "the wall stays, the person goes"
    stage.exclude_movers(None)
    assert stage._exclude_xy is None
