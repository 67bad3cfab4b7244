"""The sensor rig in a scenario world: rates, inbox delivery, own-body exclusion, what the sensors see."""
from __future__ import annotations

import math
import os
import threading
import time

import numpy as np
import pytest

from calibration.robot_description import load_robot_description
from hil_sim.sensors.lidar import LidarConfig
from hil_sim.world.scenario import load_scenario
from hil_sim.world.sensor_rig import SensorRig, SensorRigConfig, SensorRigError
from hil_sim.world.mujoco_world import World
from runtime.common.sensor_data import MAX_GYRO_RADPS
from runtime.io.sensor_inbox import SensorInbox

ROBOT = load_robot_description()
SCENARIO = load_scenario("case1")


def _run(world: World, rig: SensorRig, inbox: SensorInbox, seconds: float):
    """Step physics and the rig like LockstepSimulation (rig gets the pre-step time); collect the inbox."""
    scans, images, imu = [], [], []
    for _ in range(int(round(seconds / world.timestep_s))):
        t_before = world.time_s
        world.step()
        rig.step(t_before)
        snap = inbox.take()
        if snap.scan is not None:
            scans.append(snap.scan)
        if snap.image is not None:
            images.append(snap.image)
        imu.extend(snap.imu)
    return scans, images, imu


def _raised_within(call, timeout_s: float) -> str:
    """The RuntimeError `call` raises in a thread, which must end within timeout_s (not hang)."""
    raised = []

    def run():
        try:
            call()
        except RuntimeError as exc:
            raised.append(exc)

    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(timeout=timeout_s)
    assert not t.is_alive(), "the simulator's step hangs"
    assert len(raised) == 1, "no RuntimeError"
    return str(raised[0])


@pytest.fixture(scope="module")
def one_second():
    world = World(SCENARIO, ROBOT)
    inbox = SensorInbox()
    rig = SensorRig(world, ROBOT, inbox, SensorRigConfig(camera_rate_hz=2.0, camera_segmentation=True, seed=3))
    scans, images, imu = _run(world, rig, inbox, 1.0)
    stats = rig.stats()
    rig.close()
    return world, scans, images, imu, stats


def test_rates_over_one_second(one_second):
    world, scans, images, imu, stats = one_second
    assert len(scans) == 10 and stats["scans_produced"] == 10
    assert len(imu) == 200 and stats["imu_samples_produced"] == 200
    assert len(images) == 2 and stats["images_produced"] == 2
    assert stats["renders"] == 4  # RGB + segmentation per image, nothing else
    assert [im.stamp_s for im in images] == pytest.approx([0.0, 0.5], abs=1e-9)
    assert [s.stamp_s for s in scans] == pytest.approx([0.1 * k for k in range(10)], abs=1e-9)
    np.testing.assert_allclose([s.stamp_s for s in imu], 0.005 * np.arange(200), atol=1e-9)
    assert stats["rejected"] == {"lidar": 0, "camera": 0, "imu": 0}
    assert stats["lidar_late_slices"] == 0 and stats["imu_missed_samples"] == 0
    for scan in scans:
        scan.validate()
        assert scan.frame_id == "lidar"
        # 20k rays per frame; rays above the 0.8 m walls escape (no ceiling), so fewer returns.
        assert 5_000 < scan.num_points <= LidarConfig().points_per_frame
    for im in images:
        im.validate()
        assert im.pixels.shape == (ROBOT.sensors.camera.height_px, ROBOT.sensors.camera.width_px, 3)


def test_imu_reads_gravity_at_rest(one_second):
    _, _, _, imu, _ = one_second
    late = [s for s in imu if s.stamp_s > 0.5]  # after the drop onto the floor has settled
    accel = np.mean([s.accel_mps2 for s in late], axis=0)
    gyro = np.mean([s.gyro_radps for s in late], axis=0)
    assert accel == pytest.approx([0.0, 0.0, 9.81], abs=0.05)
    assert np.abs(gyro).max() < 0.01


def test_lidar_sees_the_box_straight_ahead_at_the_right_range(one_second):
    world, scans, _, _, _ = one_second
    box = next(o for o in SCENARIO.obstacles if o.name == "box")
    start = SCENARIO.robot.start
    assert start.yaw_rad == 0.0 and start.y_m == box.pose.y_m  # the box is straight ahead
    lidar_x = start.x_m + ROBOT.sensors.lidar.mount.xyz_m[0]
    expected = (box.pose.x_m - box.size.xyz_m[0] / 2) - lidar_x  # to the near face
    p = scans[-1].points_m.astype(np.float64)
    az = np.degrees(np.arctan2(p[:, 1], p[:, 0]))
    el = np.degrees(np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1])))
    ahead = (np.abs(az) < 3.0) & (np.abs(el) < 3.0)
    assert ahead.sum() >= 10
    ranges = np.linalg.norm(p[ahead], axis=1)
    assert np.median(ranges) == pytest.approx(expected, abs=0.05)


def test_lidar_sees_nothing_of_the_robot_itself(one_second):
    """No point inside the footprint (chassis, wheels, tyres are excluded from the rays)."""
    _, scans, _, _, _ = one_second
    mount = ROBOT.sensors.lidar.mount.transform()
    hl, hw = ROBOT.footprint.length_m / 2, ROBOT.footprint.width_m / 2
    for scan in scans:
        base = scan.points_m.astype(np.float64) @ mount[:3, :3].T + mount[:3, 3]
        inside = (np.abs(base[:, 0]) <= hl + 0.03) & (np.abs(base[:, 1]) <= hw + 0.03) & (base[:, 2] > 0.02)
        assert not inside.any(), f"{inside.sum()} lidar points inside the robot footprint"


def test_camera_segmentation_shows_the_box_near_the_image_centre(one_second):
    world, _, images, _, _ = one_second
    seg = images[-1].segmentation
    assert seg is not None
    robot_geoms = set(world.robot_geom_ids.tolist())
    assert robot_geoms.isdisjoint(np.unique(seg).tolist())  # chassis hidden from its own camera
    ys, xs = np.nonzero(seg == world.obstacle_geom_id("box"))
    assert xs.size > 1000
    h, w = seg.shape
    assert abs(xs.mean() - (w - 1) / 2) < 0.05 * w
    assert abs(ys.mean() - (h - 1) / 2) < 0.1 * h


def test_camera_off_renders_nothing():
    world = World(SCENARIO, ROBOT)
    inbox = SensorInbox()
    rig = SensorRig(world, ROBOT, inbox, SensorRigConfig(camera_rate_hz=0.0, lidar_enabled=False))
    scans, images, imu = _run(world, rig, inbox, 0.6)
    assert images == [] and scans == [] and rig.camera is None and rig.renders == 0
    assert len(imu) == 120


def test_rig_rejects_a_lidar_that_sees_the_robot_and_time_going_back():
    world = World(SCENARIO, ROBOT)
    cfg = SensorRigConfig(lidar=LidarConfig(geomgroup=(1, 1, 1, 1, 1, 1)))
    with pytest.raises(SensorRigError, match="robot's own geom groups"):
        SensorRig(world, ROBOT, SensorInbox(), cfg)
    rig = SensorRig(world, ROBOT, SensorInbox(), SensorRigConfig(lidar_enabled=False))
    rig.step(0.01)
    with pytest.raises(SensorRigError, match="backwards"):
        rig.step(0.0)
    with pytest.raises(SensorRigError, match="not finite"):
        rig.step(math.nan)


def test_violent_motion_saturates_the_imu_and_the_inbox_takes_the_flagged_samples():
    world = World(SCENARIO, ROBOT)
    inbox = SensorInbox()
    rig = SensorRig(world, ROBOT, inbox, SensorRigConfig(camera_rate_hz=0.0))
    adr = world.model.jnt_dofadr[world.model.body_jntadr[world.robot_body_id]]
    world.data.qvel[adr + 3] = 80.0  # roll at 80 rad/s: beyond the gyro's 2000 deg/s
    scans, _, imu = _run(world, rig, inbox, 0.1)
    stats = rig.stats()
    assert len(imu) == 20 and stats["rejected"]["imu"] == 0
    assert stats["imu_saturated_samples"] == sum(s.saturated for s in imu) > 0
    assert imu[0].saturated and max(abs(s.gyro_radps[0]) for s in imu) == MAX_GYRO_RADPS
    assert len(scans) == 1 and stats["imu_invalid_readings"] == 0


def test_a_broken_physics_state_never_raises_from_the_rig():
    world = World(SCENARIO, ROBOT)
    inbox = SensorInbox()
    rig = SensorRig(world, ROBOT, inbox, SensorRigConfig(camera_rate_hz=20.0))
    _run(world, rig, inbox, 0.05)
    assert rig.images_produced == 1
    # What a diverged simulation leaves in data: NaN sensor readings and body and camera poses.
    world.data.sensordata[:] = np.nan
    world.data.xpos[world.robot_body_id] = np.nan
    world.data.cam_xpos[world.camera_id] = np.nan
    for k in range(1, 11):  # 0.051 .. 0.060 s (the last good step was at 0.049 s)
        rig.step(0.05 + k * 0.001)
    rig.step(0.07)  # a coarse step: 5 lidar slices at once
    stats = rig.stats()
    rig.close()
    assert stats["imu_invalid_readings"] == 4  # samples due at 0.050, 0.055, 0.060 and 0.065 s
    assert stats["lidar_invalid_pose_slices"] == 6 + 5  # slices every 2 ms from 0.050 s
    assert stats["camera_invalid_poses"] == 1 and stats["images_produced"] == 1  # no blank image
    assert stats["rejected"] == {"lidar": 0, "camera": 0, "imu": 0}


def test_the_real_time_camera_renders_beside_the_physics_what_the_inline_one_renders():
    """camera_async (dct hil serve): the frame instant's state is copied and rendered in the
    camera's thread; the image is that of the inline camera, pixel for pixel, with the same
    stamp and segmentation, and a frame due while the last one renders is skipped and counted."""
    world = World(SCENARIO, ROBOT)
    inline_rig = SensorRig(world, ROBOT, SensorInbox(), SensorRigConfig(camera_rate_hz=2.0, camera_segmentation=True,
                                                                       lidar_enabled=False, imu_enabled=False))
    got = []
    inbox = SensorInbox()
    rig = SensorRig(world, ROBOT, inbox, SensorRigConfig(camera_rate_hz=2.0, camera_segmentation=True,
                                                        camera_async=True, lidar_enabled=False, imu_enabled=False))
    rig.listeners.append(got.append)
    try:
        expected = inline_rig.camera.render_rgb_with_segmentation(0.0)
        rig.step(0.0)
        for _ in range(500):  # the thread delivers within a few tens of ms
            if got:
                break
            time.sleep(0.01)
        assert len(got) == 1 and got[0].stamp_s == 0.0
        np.testing.assert_array_equal(got[0].pixels, expected.pixels)
        np.testing.assert_array_equal(got[0].segmentation, expected.segmentation)
        assert inbox.take().image is got[0]
        # busy: the next frame is due but the thread has not finished the one before
        rig.camera._idle.clear()
        rig.step(0.5)
        assert rig.camera_frames_missed == 1 and rig.images_produced == 1
        rig.camera._idle.set()
    finally:
        rig.close()
        inline_rig.close()


def test_a_camera_with_latency_hands_each_frame_over_at_its_instant_plus_the_latency():
    """camera_latency_s (lockstep): the frame rendered at its instant reaches the inbox exactly
    latency later in simulated time, stamped with its instant, whether it rendered inline or in
    the camera's thread (pixel for pixel the same), and never earlier however fast the thread."""
    latency = 0.1
    got = {}
    for mode in (False, True):
        world = World(SCENARIO, ROBOT)
        inbox = SensorInbox()
        rig = SensorRig(world, ROBOT, inbox, SensorRigConfig(
            camera_rate_hz=2.0, camera_segmentation=True, camera_async=mode, camera_latency_s=latency,
            lidar_enabled=False, imu_enabled=False))
        arrivals = []
        try:
            for _ in range(int(round(1.2 / world.timestep_s))):
                t_before = world.time_s
                world.step()
                rig.step(t_before)
                if mode:
                    time.sleep(0)  # let the thread run ahead: delivery still waits for the instant
                image = inbox.take().image
                if image is not None:
                    arrivals.append((t_before, image))
        finally:
            rig.close()
        got[mode] = arrivals
    for arrivals in got.values():
        assert [round(t, 6) for t, _ in arrivals] == [0.1, 0.6, 1.1]
        assert [im.stamp_s for _, im in arrivals] == pytest.approx([0.0, 0.5, 1.0], abs=1e-9)
    for (_, inline), (_, threaded) in zip(got[False], got[True]):
        np.testing.assert_array_equal(inline.pixels, threaded.pixels)
        np.testing.assert_array_equal(inline.segmentation, threaded.segmentation)


def test_a_camera_latency_is_checked():
    with pytest.raises(ValueError, match="camera_latency_s"):
        SensorRigConfig(camera_latency_s=-0.01)
    with pytest.raises(ValueError, match="camera_latency_s"):
        SensorRigConfig(camera_latency_s=float("nan"))
    with pytest.raises(ValueError, match="shorter than the camera period"):  # every other frame would be lost
        SensorRigConfig(camera_rate_hz=20.0, camera_latency_s=0.05)
    assert SensorRigConfig(camera_rate_hz=2.0, camera_latency_s=0.49).camera_latency_s == 0.49


def test_a_render_that_fails_in_the_camera_thread_raises_in_the_simulator_not_hangs(monkeypatch):
    from hil_sim.sensors.camera import SimCamera

    calls = []

    def broken(self, stamp_s, kind="geom"):
        calls.append(stamp_s)
        if len(calls) > 1:  # the thread's warm-up render went through
            raise RuntimeError("EGL context lost")

    monkeypatch.setattr(SimCamera, "render_rgb_with_segmentation", broken)
    world = World(SCENARIO, ROBOT)
    rig = SensorRig(world, ROBOT, SensorInbox(), SensorRigConfig(
        camera_rate_hz=2.0, camera_segmentation=True, camera_async=True, camera_latency_s=0.05,
        lidar_enabled=False, imu_enabled=False))
    try:
        rig.step(0.0)
        # the frame's hand-over waits for the render, which failed
        assert "EGL context lost" in _raised_within(lambda: rig.step(0.05), 20.0)
    finally:
        rig.close()


def test_a_deferred_hand_over_lets_the_physics_run_beside_a_slow_render_and_the_reader_gets_the_same_frame(
        monkeypatch):
    """defer_hand_over (lockstep, which calls hand_over_due before each tick): a frame whose render
    is not done at its instant plus the latency does not stop the physics there; hand_over_due
    puts it into the inbox (waiting for the render), stamped with its instant. Without deferral the step
    at that instant waits for the render. A capture due while a frame is still undelivered
    hands that frame over first."""
    from hil_sim.sensors.camera import SimCamera

    render = SimCamera.render_rgb_with_segmentation
    slow_s = 0.6

    warmed = set()

    def slow(self, stamp_s, kind="geom"):
        if id(self) in warmed:  # not the camera thread's warm-up render
            time.sleep(slow_s)
        warmed.add(id(self))
        return render(self, stamp_s, kind)

    monkeypatch.setattr(SimCamera, "render_rgb_with_segmentation", slow)
    config = SensorRigConfig(camera_rate_hz=5.0, camera_segmentation=True, camera_async=True, camera_latency_s=0.05,
                             lidar_enabled=False, imu_enabled=False)
    for defer in (True, False):
        world = World(SCENARIO, ROBOT)
        inbox = SensorInbox()
        rig = SensorRig(world, ROBOT, inbox, config)
        rig.defer_hand_over = defer
        try:
            rig.step(0.0)  # the capture: rendering starts
            t0 = time.perf_counter()
            for k in range(1, 61):  # past its instant + latency (0.05 s)
                rig.step(0.001 * k)
            stepped_s = time.perf_counter() - t0
            if defer:
                assert stepped_s < 0.5 * slow_s and rig.images_produced == 0
                rig.hand_over_due()  # waits for the render
                image = inbox.take().image
                assert image is not None and image.stamp_s == 0.0 and rig.images_produced == 1
                rig.step(0.2)  # the next capture...
                for k in range(1, 61):
                    rig.step(0.2 + 0.001 * k)
                rig.step(0.4)  # ...is still undelivered when the one after is due: handed over first
                assert rig.images_produced == 2 and rig.camera_frames_missed == 0
                assert inbox.take().image.stamp_s == pytest.approx(0.2)
                rig.hand_over_due()  # nothing due: nothing handed over
                assert rig.images_produced == 2
            else:
                assert stepped_s > 0.5 * slow_s and rig.images_produced == 1
                assert inbox.take().image.stamp_s == 0.0
        finally:
            rig.close()


def test_a_camera_without_antialiasing_renders_the_same_segmentation_and_leaves_the_model_as_it_was():
    from hil_sim.sensors.camera import SimCamera

    world = World(SCENARIO, ROBOT)
    import mujoco

    mujoco.mj_forward(world.model, world.data)
    samples = int(world.model.vis.quality.offsamples)
    args = (world.camera_name, 640, 480, "camera", world.camera_hidden_geom_groups, world.camera_lens)
    smooth, hard = SimCamera(world.model, world.data, *args), SimCamera(world.model, world.data, *args, False)
    try:
        a, b = smooth.render_rgb_with_segmentation(0.0), hard.render_rgb_with_segmentation(0.0)
        np.testing.assert_array_equal(a.segmentation, b.segmentation)
        assert len(np.unique(a.segmentation)) > 2  # the scene is in view, not an empty frame
        edges = np.abs(a.pixels.astype(int) - b.pixels.astype(int)).max(axis=2) > 0
        assert 0 < edges.mean() < 0.2  # only the edges differ
        assert int(world.model.vis.quality.offsamples) == samples
    finally:
        smooth.close()
        hard.close()


def _frames_inline_and_in_a_process(scenario: str, seconds: float, torques) -> tuple[list, list]:
    world = World(load_scenario(scenario), ROBOT)
    lidar = LidarConfig(ground_truth_frames=8)
    rigs, inboxes = [], []
    for in_process in (False, True):
        inboxes.append(SensorInbox())
        rigs.append(SensorRig(world, ROBOT, inboxes[-1], SensorRigConfig(
            camera_rate_hz=0.0, imu_enabled=False, lidar=lidar, lidar_process=in_process, seed=5)))
    frames = ([], [])
    try:
        for k in range(int(round(seconds / world.timestep_s))):
            world.set_wheel_torques(np.asarray(torques(k), float))
            t_before = world.time_s
            world.step()
            for rig, inbox, got in zip(rigs, inboxes, frames):
                rig.step(t_before)
                scan = inbox.take().scan
                if scan is not None:
                    got.append((k, scan, rig.lidar.ground_truth_geom_ids(scan.stamp_s)))
    finally:
        for rig in rigs:
            rig.close()
    return frames


def test_the_lidar_cast_in_a_process_gives_the_inline_frames_bit_for_bit():
    """lidar_process: each slice is cast in a child process from a copy of the state of its
    instant; the frames (points, time offsets, stamps, the geoms each point hit) are the inline
    lidar's, with the robot turning past the boxes, each handed over at the same physics step;
    and a second lidar takes the idle process over with the same result."""
    def turn(k):
        return np.array([0.4, -0.2, 0.4, -0.2]) * (1 if k < 150 else -1)

    for _ in range(2):
        inline, in_process = _frames_inline_and_in_a_process("case2", 0.6, turn)
        assert len(inline) == 6 and [f[0] for f in inline] == [f[0] for f in in_process]
        for (_, a, ga), (_, b, gb) in zip(inline, in_process):
            assert a.stamp_s == b.stamp_s and len(a.points_m) > 10000
            np.testing.assert_array_equal(a.points_m, b.points_m)
            np.testing.assert_array_equal(a.point_time_offsets_s, b.point_time_offsets_s)
            np.testing.assert_array_equal(ga, gb)
        assert not b.points_m.flags.writeable


def test_a_cast_process_that_dies_is_named_at_the_frame_not_waited_for():
    world = World(SCENARIO, ROBOT)
    rig = SensorRig(world, ROBOT, SensorInbox(), SensorRigConfig(camera_rate_hz=0.0, imu_enabled=False,
                                                                lidar_process=True))

    def frame():
        for k in range(60):
            rig.step(0.002 * k)

    try:
        rig.lidar._caster._proc.kill()
        assert "cast process" in _raised_within(frame, 30.0)
        # the frame is lost, and so is every later one: each later step names the failure
        assert "SimLidar failed earlier" in _raised_within(lambda: rig.step(0.2), 30.0)
    finally:
        rig.close()
        rig.close()  # once is enough; twice does nothing


def test_a_cast_process_that_fails_to_start_is_named_and_closed_at_once(monkeypatch):
    import time as time_module

    from hil_sim.sensors import lidar_cast

    real = lidar_cast._shared_file

    def gone():  # the child cannot open it: it fails to start
        fd, path = real()
        os.unlink(path)
        return fd, path + "-gone"

    monkeypatch.setattr(lidar_cast, "_shared_file", gone)
    world = World(SCENARIO, ROBOT)
    rig = SensorRig(world, ROBOT, SensorInbox(), SensorRigConfig(camera_rate_hz=0.0, imu_enabled=False,
                                                                lidar_process=True))
    try:
        assert "failed to start" in _raised_within(rig.wait_ready, 60.0)
    finally:
        t0 = time_module.perf_counter()
        rig.close()
        assert time_module.perf_counter() - t0 < 5.0


def test_a_cast_process_that_ended_while_idle_is_replaced():
    from hil_sim.sensors import lidar_cast

    inline, in_process = _frames_inline_and_in_a_process("case1", 0.1, lambda k: np.zeros(4))  # leaves one idle
    assert len(lidar_cast._IDLE) == 1
    proc, _ = lidar_cast._IDLE[0]
    proc.kill()
    proc.wait()
    inline, in_process = _frames_inline_and_in_a_process("case1", 0.1, lambda k: np.zeros(4))
    assert len(in_process) == 1 and np.array_equal(inline[0][1].points_m, in_process[0][1].points_m)
    assert lidar_cast._IDLE and lidar_cast._IDLE[0][0] is not proc


def test_the_cast_process_shares_memory_through_the_temporary_directory_without_dev_shm(monkeypatch):
    import tempfile as tempfile_module

    from hil_sim.sensors import lidar_cast

    made = []
    real = tempfile_module.mkstemp

    def mkstemp(prefix="", dir=None):
        if dir == "/dev/shm":
            raise PermissionError(13, "Permission denied", dir)
        made.append(real(prefix=prefix, dir=dir))
        return made[-1]

    monkeypatch.setattr(lidar_cast.tempfile, "mkstemp", mkstemp)
    inline, in_process = _frames_inline_and_in_a_process("case1", 0.1, lambda k: np.zeros(4))
    assert made and np.array_equal(inline[0][1].points_m, in_process[0][1].points_m)
    assert not os.path.exists(made[0][1])  # unlinked once both ends had it mapped
