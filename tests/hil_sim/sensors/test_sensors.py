"""Simulated lidar, camera and IMU on small MjSpec scenes (no MJCF strings, no dependency on world.py)."""
from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calibration.robot_description import load_robot_description
from hil_sim.sensors.camera import SimCamera, add_camera_to_spec, fovy_deg_from_horizontal
from hil_sim.sensors.imu import ImuConfig, SimImu, add_imu_to_spec
from hil_sim.sensors.lidar import LidarConfig, SimLidar, pattern_directions, ray_returns
from hil_sim.world.scenario import Scenario
from hil_sim.world.model_spec import IMU_NAME, build_spec
from runtime.common.sensor_data import MAX_ACCEL_MPS2, MAX_GYRO_RADPS, CameraImage, ImuSample, LidarScan

DESC = load_robot_description()
LIDAR_MOUNT = DESC.sensors.lidar.mount
CAM = DESC.sensors.camera
DT = 0.002


def _scene(*, room: bool = False, wall_x: float | None = None, boxes=(), chassis_encloses_lidar: bool = False,
           gravity: bool = False, camera: bool = False, imu: bool = False):
    """Floor, optional closed room (walls + ceiling), optional wall at x = wall_x, named boxes
    (name, pos, half-size), and a free-floating 'robot' body at the origin with the LIMO sensors."""
    spec = mujoco.MjSpec()
    if not gravity:
        spec.option.gravity = [0.0, 0.0, 0.0]
    wb = spec.worldbody
    wb.add_light(pos=[0, 0, 2.8], dir=[0, 0, -1])
    wb.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[30, 30, 0.1])
    if room:
        for i, (x, y, sx, sy) in enumerate([(5, 0, 0.1, 5), (-5, 0, 0.1, 5), (0, 5, 5, 0.1), (0, -5, 5, 0.1)]):
            wb.add_geom(name=f"room_wall{i}", type=mujoco.mjtGeom.mjGEOM_BOX, size=[sx, sy, 1.5], pos=[x, y, 1.5])
        wb.add_geom(name="ceiling", type=mujoco.mjtGeom.mjGEOM_BOX, size=[5, 5, 0.1], pos=[0, 0, 3.1])
    if wall_x is not None:
        wb.add_geom(name="wall", type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.1, 20, 5], pos=[wall_x + 0.1, 0, 5])
    for name, pos, size in boxes:
        wb.add_geom(name=name, type=mujoco.mjtGeom.mjGEOM_BOX, size=list(size), pos=list(pos),
                    rgba=[0.8, 0.2, 0.2, 1])
    robot = wb.add_body(name="robot", pos=[0, 0, 0.0 if not gravity else 0.1])
    robot.add_freejoint()
    if chassis_encloses_lidar:  # a shell around the lidar origin: the lidar must not see it
        robot.add_geom(name="chassis", type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.3, 0.3, 0.3], pos=[0, 0, 0.2],
                       mass=4.8, group=3)
    else:
        robot.add_geom(name="chassis", type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.16, 0.11, 0.05],
                       pos=[0, 0, 0.05], mass=4.8, group=3)
    names = {}
    if camera:
        names["camera"] = add_camera_to_spec(robot, CAM.mount, CAM)
    if imu:
        names["imu"] = add_imu_to_spec(robot, DESC.sensors.imu.mount, spec=spec)
    model = spec.compile()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    return model, data, model.body("robot").id, names


def _set_pose(model, data, x=0.0, y=0.0, yaw_rad=0.0):
    data.qpos[0:3] = [x, y, 0.0]
    data.qpos[3:7] = Rotation.from_euler("z", yaw_rad).as_quat(scalar_first=True)
    mujoco.mj_kinematics(model, data)


def _run_lidar(lidar, model, data, t_end_s, pose_fn=lambda t: (0.0, 0.0, 0.0), t0_s=0.0):
    """Step physics time in DT steps, moving the robot kinematically; return all completed frames."""
    frames = []
    n = int(round((t_end_s - t0_s) / DT))
    for k in range(n + 1):
        t = t0_s + k * DT
        _set_pose(model, data, *pose_fn(t))
        lidar.step(t)
        f = lidar.pop_frame()
        while f is not None:
            frames.append(f)
            f = lidar.pop_frame()
    return frames


def _az_el_deg(p):
    az = np.degrees(np.arctan2(p[:, 1], p[:, 0]))
    el = np.degrees(np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1])))
    return az, el


# ----------------------------------------------------------------------------- lidar


@pytest.fixture(scope="module")
def room_frames():
    model, data, body, _ = _scene(room=True)
    lidar = SimLidar(model, data, body, LIDAR_MOUNT, LidarConfig(), seed=1)
    frames = _run_lidar(lidar, model, data, 0.5)
    return lidar, frames


def test_frames_at_10hz_with_about_20k_points(room_frames):
    lidar, frames = room_frames
    assert len(frames) == 5  # frames end at 0.1, 0.2, ... 0.5 s
    assert all(isinstance(f, LidarScan) for f in frames)
    np.testing.assert_allclose([f.stamp_s for f in frames], [0.0, 0.1, 0.2, 0.3, 0.4], atol=1e-9)
    for f in frames:
        assert f.frame_duration_s == pytest.approx(0.1)
        assert 19_500 <= f.num_points <= 20_000  # closed room: every ray hits
        t = f.point_time_offsets_s
        assert t.min() >= 0.0 and t.max() < 0.1
        assert t.max() > 0.09  # the frame really spans 100 ms
    assert lidar.late_slices == 0 and lidar.dropped_frames == 0


def test_vertical_range_and_fov_coverage(room_frames):
    _, frames = room_frames
    pts = np.concatenate([f.points_m for f in frames])
    az, el = _az_el_deg(pts)
    # Noise moves points along their ray only, so angles are exact.
    assert el.min() >= -7.0 - 1e-3 and el.max() <= 52.0 + 1e-3
    assert el.min() < -6.8 and el.max() > 51.8
    # One frame already covers the whole FOV coarsely: every 10 deg x 5 deg cell is hit.
    az1, el1 = _az_el_deg(frames[0].points_m)
    h, _, _ = np.histogram2d(az1, el1, bins=[36, 11], range=[[-180, 180], [-7, 48]])
    assert (h > 0).all()


def test_pattern_is_non_repetitive(room_frames):
    _, frames = room_frames

    def cells(p):  # 0.5 deg cells hit
        az, el = _az_el_deg(p)
        return set(zip(np.floor(az / 0.5).astype(int), np.floor(el / 0.5).astype(int)))

    c0, c1 = cells(frames[0].points_m), cells(frames[1].points_m)
    union = set()
    for f in frames:
        union |= cells(f.points_m)
    assert len(c0 ^ c1) > 0.5 * len(c0)          # consecutive frames differ
    assert len(union) > 2.5 * len(c0)            # coverage keeps growing over frames


def test_pattern_does_not_repeat_after_the_table_wraps():
    model, data, body, _ = _scene(room=True)
    cfg = LidarConfig(points_per_frame=2000, slices_per_frame=10, pattern_frames=2, range_noise_sigma_m=0.0)
    lidar = SimLidar(model, data, body, LIDAR_MOUNT, cfg, seed=0)
    frames = _run_lidar(lidar, model, data, 0.3)
    d0 = frames[0].points_m / np.linalg.norm(frames[0].points_m, axis=1, keepdims=True)
    d2 = frames[2].points_m / np.linalg.norm(frames[2].points_m, axis=1, keepdims=True)
    n = min(len(d0), len(d2))
    assert np.median(np.linalg.norm(d0[:n] - d2[:n], axis=1)) > 0.05


def test_pattern_directions_are_unit_and_uniform_in_solid_angle():
    d = pattern_directions(50_000, -7.0, 52.0)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    # Uniform in sin(elevation): quartiles of sin(el) are evenly spaced.
    s = np.quantile(d[:, 2], [0.25, 0.5, 0.75])
    s0, s1 = math.sin(math.radians(-7)), math.sin(math.radians(52))
    np.testing.assert_allclose(s, s0 + (s1 - s0) * np.array([0.25, 0.5, 0.75]), atol=0.005)


def _wall_points(frame, wall_dist_l, tol=0.2):
    p = frame.points_m.astype(np.float64)
    sel = (np.abs(p[:, 0] - wall_dist_l) < tol) & (p[:, 2] > -0.1) & (np.abs(p[:, 1]) < 3.0)
    return p[sel], frame.point_time_offsets_s[sel].astype(np.float64)


@pytest.mark.parametrize("sigma", [0.0, 0.02, 0.05])
def test_flat_wall_distance_and_noise_sigma(sigma):
    wall_x = 4.0
    model, data, body, _ = _scene(wall_x=wall_x)
    lidar = SimLidar(model, data, body, LIDAR_MOUNT, LidarConfig(range_noise_sigma_m=sigma), seed=3)
    frames = _run_lidar(lidar, model, data, 0.2)
    d_l = wall_x - LIDAR_MOUNT.xyz_m[0]  # wall distance along the lidar's x axis
    p = np.concatenate([_wall_points(f, d_l, tol=0.3)[0] for f in frames])
    assert len(p) > 2000
    r = np.linalg.norm(p, axis=1)
    r_true = d_l * r / p[:, 0]  # range of the wall along each point's own ray
    err = r - r_true
    assert abs(err.mean()) < 0.002
    assert np.std(err) == pytest.approx(sigma, abs=0.002, rel=0.1)


def test_ranges_within_limits_and_nothing_beyond_max_range():
    cfg = LidarConfig(min_range_m=0.5, max_range_m=3.0, range_noise_sigma_m=0.05)
    model, data, body, _ = _scene(room=True)  # walls at 5 m: beyond max range
    lidar = SimLidar(model, data, body, LIDAR_MOUNT, cfg, seed=5)
    frames = _run_lidar(lidar, model, data, 0.2)
    r = np.concatenate([np.linalg.norm(f.points_m, axis=1) for f in frames])
    assert r.min() >= 0.5 and r.max() <= 3.0
    # Only the floor closer than 3 m remains: no point is higher than the floor.
    z = np.concatenate([f.points_m[:, 2] for f in frames])
    assert z.max() < -LIDAR_MOUNT.xyz_m[2] + 0.1
    assert 0 < len(r) < 0.3 * 2 * cfg.points_per_frame


def test_empty_world_beyond_range_gives_nothing_seen_scans():
    cfg = LidarConfig(elevation_min_deg=5.0, elevation_max_deg=50.0, points_per_frame=1000, slices_per_frame=10)
    model, data, body, _ = _scene()  # only the floor, which an upward-looking lidar never sees
    lidar = SimLidar(model, data, body, LIDAR_MOUNT, cfg)
    frames = _run_lidar(lidar, model, data, 0.1)
    assert len(frames) == 1 and frames[0].num_points == 0 and frames[0].nothing_seen


def test_lidar_does_not_see_its_own_body():
    model, data, body, _ = _scene(room=True, chassis_encloses_lidar=True)
    lidar = SimLidar(model, data, body, LIDAR_MOUNT, LidarConfig(range_noise_sigma_m=0.0))
    frames = _run_lidar(lidar, model, data, 0.1)
    r = np.linalg.norm(frames[0].points_m, axis=1)
    assert frames[0].num_points > 19_000 and r.min() > 1.0  # the 0.3 m shell is invisible
    # Control: excluding nothing, the shell hides the room.
    lidar2 = SimLidar(model, data, -1, np.asarray(_mount_world(model, data)), LidarConfig(range_noise_sigma_m=0.0))
    frames2 = _run_lidar(lidar2, model, data, 0.1)
    assert np.linalg.norm(frames2[0].points_m, axis=1).max() < 0.6
    # Excluding the robot's geom group (3) instead of its body hides the shell too.
    cfg = LidarConfig(range_noise_sigma_m=0.0, geomgroup=(1, 1, 1, 0, 1, 1))
    lidar3 = SimLidar(model, data, -1, np.asarray(_mount_world(model, data)), cfg)
    frames3 = _run_lidar(lidar3, model, data, 0.1)
    assert np.linalg.norm(frames3[0].points_m, axis=1).min() > 1.0


def _mount_world(model, data):
    _set_pose(model, data)
    return LIDAR_MOUNT.transform()  # robot at the origin: body frame == world frame


@pytest.mark.parametrize("speed_mps", [0.0, 1.0])
def test_motion_distortion_moving_toward_a_wall(speed_mps):
    wall_x = 4.0
    model, data, body, _ = _scene(wall_x=wall_x)
    lidar = SimLidar(model, data, body, LIDAR_MOUNT, LidarConfig(), seed=7)
    frames = _run_lidar(lidar, model, data, 0.2, pose_fn=lambda t: (speed_mps * t, 0.0, 0.0))
    f = frames[1]  # frame 0.1 .. 0.2 s
    d_start = wall_x - LIDAR_MOUNT.xyz_m[0] - speed_mps * f.stamp_s
    p, t = _wall_points(f, d_start - speed_mps * 0.05, tol=0.3)
    early, late = p[t < 0.01, 0], p[t >= 0.09, 0]
    assert len(early) > 100 and len(late) > 100
    shift = early.mean() - late.mean()
    expected = speed_mps * (t[t >= 0.09].mean() - t[t < 0.01].mean())
    assert shift == pytest.approx(expected, abs=0.005)
    if speed_mps:
        assert shift > 0.08
    # Deskewing with the per-point times puts every wall point back at the frame-start distance.
    deskewed = p[:, 0] + speed_mps * t
    assert abs(deskewed.mean() - d_start) < 0.003 and deskewed.std() < 0.03


def test_coarse_steps_are_counted_late_and_time_must_not_go_back():
    model, data, body, _ = _scene(room=True)
    lidar = SimLidar(model, data, body, LIDAR_MOUNT, LidarConfig(slices_per_frame=50))
    lidar.step(0.0)
    lidar.step(0.05)  # 24 slices were due between: cast late at one pose
    assert lidar.late_slices > 0
    with pytest.raises(ValueError):
        lidar.step(0.04)


def test_non_finite_or_out_of_range_distances_are_no_returns():
    geomid = np.array([3, 3, 3, 3, -1, 3, 3], dtype=np.int32)
    dist = np.array([1.0, np.nan, np.inf, -np.inf, 2.0, 40.0, 40.5])
    np.testing.assert_array_equal(ray_returns(geomid, dist, 40.0), [True, False, False, False, False, True, False])


def test_a_broken_body_pose_gives_no_returns_and_no_exception():
    model, data, body, _ = _scene(room=True)
    cfg = LidarConfig(points_per_frame=2000, slices_per_frame=10, range_noise_sigma_m=0.0)
    lidar = SimLidar(model, data, body, LIDAR_MOUNT, cfg)
    _set_pose(model, data)
    for k in range(5):  # half a frame with a good pose
        lidar.step(k * 0.01)
    data.xpos[body] = np.nan  # what a diverged simulation leaves in data
    for k in range(5, 10):
        lidar.step(k * 0.01)
    data.xmat[body] = np.inf
    _set_pose(model, data)  # kinematics again: finite xpos, but put xmat back to inf
    data.xmat[body] = np.inf
    lidar.step(0.1)
    frame = lidar.pop_frame()
    assert lidar.invalid_pose_slices == 5 + 1
    assert 900 <= frame.num_points <= 1000  # only the good half, every point finite (validated)
    for k in range(11, 20):
        lidar.step(k * 0.01)
    # A frame cast wholly from a broken pose sees nothing: the controller's blind-lidar case.
    blind = lidar.pop_frame()
    assert blind.num_points == 0 and blind.nothing_seen and lidar.invalid_pose_slices == 15


def test_lidar_config_rejects_non_finite_values():
    for field in ("max_range_m", "min_range_m", "range_noise_sigma_m"):
        with pytest.raises(ValueError, match=field):
            LidarConfig(**{field: float("nan")})
    with pytest.raises(ValueError, match="min_range_m"):
        LidarConfig(min_range_m=float("inf"))


def test_lidar_config_rejects_inconsistent_values():
    with pytest.raises(ValueError):
        LidarConfig(elevation_min_deg=10, elevation_max_deg=5)
    with pytest.raises(ValueError):
        LidarConfig(min_range_m=5, max_range_m=1)
    with pytest.raises(ValueError):
        LidarConfig(unknown=1)


# ----------------------------------------------------------------------------- camera


def test_fovy_from_horizontal_fov():
    fovy = fovy_deg_from_horizontal(87.0, 640, 480)
    K = CAM.nominal_intrinsics()
    assert math.tan(math.radians(fovy) / 2) == pytest.approx(240 / K[1, 1], rel=1e-9)


def _cam_world(model, data, cam_name):
    """T_world<-optical from MuJoCo's camera pose (mjcam looks along -z, y up)."""
    cid = model.camera(cam_name).id
    r = data.cam_xmat[cid].reshape(3, 3) @ np.diag([1.0, -1.0, -1.0])
    t = np.eye(4)
    t[:3, :3], t[:3, 3] = r, data.cam_xpos[cid]
    return t


@pytest.fixture(scope="module")
def cam_scene():
    yaw = math.radians(30.0)
    fwd = np.array([math.cos(yaw), math.sin(yaw)])
    left = np.array([-math.sin(yaw), math.cos(yaw)])
    cam_h = CAM.mount.xyz_m[2]
    boxes = [
        ("ahead", (*(3.0 * fwd), cam_h), (0.1, 0.1, 0.1)),
        ("to_left", (*(2.5 * fwd + 1.2 * left), 0.2), (0.15, 0.15, 0.2)),
        ("off_axis", (*(2.0 * fwd - 0.5 * left), cam_h + 0.4), (0.05, 0.05, 0.05)),
    ]
    model, data, body, names = _scene(boxes=boxes, camera=True)
    _set_pose(model, data, 0.0, 0.0, yaw)
    mujoco.mj_forward(model, data)
    cam = SimCamera(model, data, names["camera"], CAM.width_px, CAM.height_px)
    yield model, data, cam, names
    cam.close()


def _centroid(mask):
    ys, xs = np.nonzero(mask)
    return xs.mean(), ys.mean()


def test_camera_orientation(cam_scene):
    model, data, cam, _ = cam_scene
    seg = cam.render_segmentation()
    assert seg.shape == (480, 640) and seg.dtype == np.int32
    u, v = _centroid(seg == model.geom("ahead").id)
    assert abs(u - 319.5) < 2.0 and abs(v - 239.5) < 2.0       # straight ahead -> image centre
    u, _ = _centroid(seg == model.geom("to_left").id)
    assert u < 200                                              # robot's left -> left half
    u, v = _centroid(seg == model.geom("off_axis").id)
    assert u > 320 and v < 240                                  # right and above -> right, upper half
    floor = seg == model.geom("floor").id
    assert floor[-1].all() and not floor[0].any()               # floor at the bottom, not at the top


def test_intrinsics_project_points_where_they_are_rendered(cam_scene):
    model, data, cam, names = cam_scene
    K = cam.intrinsics()
    np.testing.assert_allclose(K[0, 0], CAM.nominal_intrinsics()[0, 0], rtol=1e-9)
    seg = cam.render_segmentation()
    t_wc = _cam_world(model, data, names["camera"])
    for name in ("ahead", "off_axis"):
        p_w = np.append(data.geom_xpos[model.geom(name).id], 1.0)
        p_c = np.linalg.solve(t_wc, p_w)[:3]
        uv = (K @ (p_c / p_c[2]))[:2]
        u, v = _centroid(seg == model.geom(name).id)
        assert abs(u - uv[0]) < 1.0 and abs(v - uv[1]) < 1.5, name  # cube faces: centroid ~ centre


def test_segmentation_ids_match_geoms(cam_scene):
    model, data, cam, _ = cam_scene
    seg = cam.render_segmentation()
    ids = set(np.unique(seg).tolist())
    expected = {model.geom(n).id for n in ("floor", "ahead", "to_left", "off_axis")}
    assert expected <= ids
    assert ids - expected <= {-1}   # background only; the robot's chassis is behind the camera
    body_seg = cam.render_segmentation(kind="body")
    assert set(np.unique(body_seg).tolist()) <= {-1, 0}   # all scene geoms belong to the world body
    with pytest.raises(ValueError):
        cam.render_segmentation(kind="pixels")


def test_rgb_image(cam_scene):
    model, data, cam, _ = cam_scene
    img = cam.render_rgb(1.25)
    assert isinstance(img, CameraImage) and img.stamp_s == 1.25
    assert img.pixels.shape == (480, 640, 3) and img.pixels.dtype == np.uint8
    np.testing.assert_array_equal(img.K, cam.intrinsics())
    seg = cam.render_segmentation()
    box = seg == model.geom("ahead").id
    floor = seg == model.geom("floor").id
    red = img.pixels[box].mean(axis=0)
    assert red[0] > red[1] + 20 and red[0] > red[2] + 20            # the red box is red where segmented
    assert np.abs(img.pixels[floor].mean(axis=0) - red).max() > 20  # and differs from the floor
    both = cam.render_rgb_with_segmentation(2.0)
    np.testing.assert_array_equal(both.segmentation, seg)


def test_camera_errors():
    model, data, body, names = _scene(camera=True)
    with pytest.raises(ValueError, match="no camera"):
        SimCamera(model, data, "nope")
    with pytest.raises(ValueError, match="offscreen buffer"):
        SimCamera(model, data, names["camera"], 1280, 960)


# ----------------------------------------------------------------------------- IMU


def _imu_run(model, data, imu, t_end_s, t0_s=0.0, dt=DT):
    n = int(round((t_end_s - t0_s) / dt))
    for k in range(n):
        t = t0_s + k * dt
        imu.step(t)
        mujoco.mj_step(model, data)
    return imu.pop_samples()


def test_imu_at_rest_reads_gravity_up_and_zero_rate():
    model, data, body, names = _scene(gravity=True, imu=True)
    model.opt.timestep = DT
    for _ in range(250):  # settle on the floor
        mujoco.mj_step(model, data)
    cfg = ImuConfig()
    imu = SimImu(model, data, *names["imu"], cfg, seed=2, start_s=data.time)
    samples = _imu_run(model, data, imu, data.time + 1.0, t0_s=data.time)
    assert all(isinstance(s, ImuSample) for s in samples)
    acc = np.array([s.accel_mps2 for s in samples])
    gyr = np.array([s.gyro_radps for s in samples])
    np.testing.assert_allclose(acc.mean(axis=0), [0.0, 0.0, 9.81], atol=0.01)
    np.testing.assert_allclose(gyr.mean(axis=0), 0.0, atol=0.001)
    assert not any(s.saturated for s in samples) and imu.saturated_samples == 0
    assert acc.std(axis=0) == pytest.approx([cfg.accel_noise_sigma_mps2] * 3, rel=0.2)
    assert gyr.std(axis=0) == pytest.approx([cfg.gyro_noise_sigma_radps] * 3, rel=0.2)


def test_imu_rate_and_stamps():
    model, data, body, names = _scene(imu=True)
    model.opt.timestep = DT
    imu = SimImu(model, data, *names["imu"], ImuConfig(rate_hz=200.0))
    samples = _imu_run(model, data, imu, 1.0)
    assert len(samples) == 200
    stamps = np.array([s.stamp_s for s in samples])
    assert (np.diff(stamps) > 0).all()
    assert np.diff(stamps).mean() == pytest.approx(0.005, rel=0.01)
    assert imu.missed_samples == 0
    # Coarse stepping cannot invent samples: they are counted as missed.
    imu2 = SimImu(model, data, *names["imu"], ImuConfig(rate_hz=200.0))
    got = _imu_run(model, data, imu2, 0.2, dt=0.02)  # steps at 0, 0.02, ... 0.18 s
    assert len(got) == 10 and imu2.missed_samples == 37 - 10  # 37 instants due in [0, 0.18]
    with pytest.raises(ValueError):
        imu2.step(0.0)


def test_imu_rotation_rate_axis_and_bias():
    model, data, body, names = _scene(imu=True)  # no gravity: a free spin about z
    model.opt.timestep = DT
    data.qpos[2] = 1.0  # off the floor: no contact friction
    data.qvel[5] = 1.5  # yaw rate, rad/s
    mujoco.mj_forward(model, data)
    cfg = ImuConfig(gyro_noise_sigma_radps=0.0, accel_noise_sigma_mps2=0.0, gyro_bias_radps=(0.01, -0.02, 0.0))
    imu = SimImu(model, data, *names["imu"], cfg)
    samples = _imu_run(model, data, imu, 0.2)
    gyr = np.array([s.gyro_radps for s in samples])
    np.testing.assert_allclose(gyr.mean(axis=0), [0.01, -0.02, 1.5], atol=1e-6)
    # The IMU sits on the spin axis: centripetal acceleration is zero, and so is gravity here.
    acc = np.array([s.accel_mps2 for s in samples])
    np.testing.assert_allclose(acc, 0.0, atol=1e-6)


def test_imu_rejects_wrong_sensor_names():
    model, data, body, names = _scene(imu=True)
    gyro, accel = names["imu"]
    with pytest.raises(ValueError, match="no sensor"):
        SimImu(model, data, "nope", accel)
    with pytest.raises(ValueError, match="type"):
        SimImu(model, data, accel, gyro)


def test_imu_saturates_like_the_real_part_on_a_huge_spin():
    model, data, body, names = _scene(imu=True)  # no gravity
    model.opt.timestep = DT
    data.qpos[2] = 1.0  # off the floor
    data.qvel[3] = 100.0  # 100 rad/s roll: beyond the 2000 deg/s gyro
    mujoco.mj_forward(model, data)
    true_gyro = data.sensordata[0:3].copy()
    true_accel = data.sensordata[3:6].copy()
    # The IMU (z 0.10 m) sits 0.05 m above the centre of mass: centripetal 100^2 * 0.05 m/s^2.
    assert abs(true_gyro[0]) == pytest.approx(100.0) and np.abs(true_accel).max() > 3 * MAX_ACCEL_MPS2
    imu = SimImu(model, data, *names["imu"], ImuConfig())
    samples = _imu_run(model, data, imu, 0.05)
    assert len(samples) == 10 and imu.saturated_samples == 10 and imu.invalid_readings == 0
    for s in samples:
        assert s.saturated
        assert s.gyro_radps[0] == MAX_GYRO_RADPS  # clipped to the range exactly
        assert np.abs(s.accel_mps2).max() == MAX_ACCEL_MPS2
        assert abs(s.gyro_radps[1]) < 1.0  # the unsaturated axes keep their reading


def test_imu_without_a_physics_reading_gives_no_sample_and_counts_it():
    model, data, body, names = _scene(imu=True)
    imu = SimImu(model, data, *names["imu"], ImuConfig(rate_hz=100.0))
    gyro_adr = model.sensor("imu_gyro").adr[0]
    accel_adr = model.sensor("imu_accel").adr[0]
    imu.step(0.0)
    data.sensordata[gyro_adr + 1] = np.nan
    imu.step(0.01)
    data.sensordata[gyro_adr + 1] = 0.0
    data.sensordata[accel_adr + 2] = -np.inf
    imu.step(0.02)
    data.sensordata[accel_adr + 2] = 0.0
    imu.step(0.03)
    samples = imu.pop_samples()
    assert [s.stamp_s for s in samples] == [0.0, 0.03]
    assert imu.invalid_readings == 2 and imu.missed_samples == 0


def test_imu_config_rejects_non_finite_values():
    with pytest.raises(ValueError, match="gyro_bias_radps"):
        ImuConfig(gyro_bias_radps=(float("nan"), 0.0, 0.0))
    with pytest.raises(ValueError, match="rate_hz"):
        ImuConfig(rate_hz=float("inf"))


def test_sensors_on_a_robot_started_inside_a_wall_clip_and_never_raise():
    """The model the scenario check now refuses (World raises), built directly: the contact
    throws the robot out of the wall; the IMU saturates, the lidar keeps casting."""
    scenario = Scenario.model_validate({
        "name": "in_wall",
        "floor": {"size_m": [6.0, 6.0], "friction": 0.8},
        "walls": [{"name": "wall_north", "from": [-2.0, 0.3], "to": [2.0, 0.3], "thickness_m": 0.1,
                   "height_m": 0.5}],
        "robot": {"start": {"x_m": 0.0, "y_m": 0.25, "yaw_deg": 30.0}},
        "goal": {"pose": {"x_m": 1.5, "y_m": -1.0}, "tolerance_m": 0.1},
        "time_limit_s": 5.0,
    })
    model = build_spec(scenario, DESC).compile()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    imu = SimImu(model, data, f"{IMU_NAME}_gyro", f"{IMU_NAME}_accel", ImuConfig())
    body = model.body("base_link").id
    lidar = SimLidar(model, data, body, LIDAR_MOUNT, LidarConfig(points_per_frame=2000, slices_per_frame=10))
    for _ in range(200):
        t = data.time
        mujoco.mj_step(model, data)
        imu.step(t)
        lidar.step(t)
    samples = imu.pop_samples()
    assert len(samples) + imu.invalid_readings == 40
    assert imu.saturated_samples > 0 and all(np.abs(s.accel_mps2).max() <= MAX_ACCEL_MPS2 for s in samples)
    assert lidar.frames_completed == 2
