"""Sensor cost benchmark (wired into `dct bench sensors` by the CLI): ms per 20k-point lidar
frame, per RGB render and per segmentation render, in a cluttered room built with MjSpec."""
from __future__ import annotations

import os
import statistics
import time

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402


def build_bench_scene(n_boxes: int = 60, seed: int = 0) -> tuple[mujoco.MjSpec, str]:
    """A 12 m x 12 m room (walls, 3 m ceiling in geom group 1) with `n_boxes` random boxes and a free 'robot' body at the
    centre carrying the LIMO camera. Returns (spec, camera_name)."""
    from calibration.robot_description import load_robot_description
    from hil_sim.sensors.camera import add_camera_to_spec

    desc = load_robot_description()
    rng = np.random.default_rng(seed)
    spec = mujoco.MjSpec()
    wb = spec.worldbody
    wb.add_light(pos=[0, 0, 6], dir=[0, 0, -1])
    wb.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[8, 8, 0.1], rgba=[0.5, 0.5, 0.5, 1])
    for i, (x, y, sx, sy) in enumerate([(6, 0, 0.1, 6), (-6, 0, 0.1, 6), (0, 6, 6, 0.1), (0, -6, 6, 0.1)]):
        wb.add_geom(name=f"wall{i}", type=mujoco.mjtGeom.mjGEOM_BOX, size=[sx, sy, 1.5], pos=[x, y, 1.5])
    wb.add_geom(name="ceiling", type=mujoco.mjtGeom.mjGEOM_BOX, size=[6, 6, 0.05], pos=[0, 0, 3.05], group=1)
    for i in range(n_boxes):
        while True:
            x, y = rng.uniform(-5.5, 5.5, 2)
            if np.hypot(x, y) > 1.0:
                break
        s = rng.uniform(0.1, 0.5, 3)
        wb.add_geom(name=f"box{i}", type=mujoco.mjtGeom.mjGEOM_BOX, size=s.tolist(), pos=[x, y, s[2]],
                    rgba=[*rng.uniform(0.2, 1.0, 3), 1.0])
    body = wb.add_body(name="robot", pos=[0, 0, 0])
    body.add_freejoint()
    body.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.16, 0.11, 0.08], pos=[0, 0, 0.1], mass=4.8, group=3)
    cam = add_camera_to_spec(body, desc.sensors.camera.mount, desc.sensors.camera)
    return spec, cam


def run_sensor_benchmark(n_frames: int = 10, n_renders: int = 10, n_boxes: int = 60, seed: int = 0) -> dict:
    """Median cost of one 20k-ray lidar frame (cast while the robot moves at 1 m/s, 2 ms steps),
    one 640x480 RGB render and one segmentation render. Returns a dict of figures."""
    from calibration.robot_description import load_robot_description
    from hil_sim.sensors.camera import SimCamera
    from hil_sim.sensors.lidar import LidarConfig, SimLidar

    desc = load_robot_description()
    spec, cam = build_bench_scene(n_boxes, seed)
    model = spec.compile()
    data = mujoco.MjData(model)
    body = model.body("robot").id
    cfg = LidarConfig()
    lidar = SimLidar(model, data, body, desc.sensors.lidar.mount, cfg, seed=seed)
    dt = 0.002
    steps_per_frame = int(round(cfg.frame_duration_s / dt))
    frame_ms, points = [], []
    t = 0.0
    k = 0
    for _ in range(n_frames):
        spent = 0.0
        for _ in range(steps_per_frame):
            data.qpos[0] = -1.0 + 1.0 * t          # 1 m/s along x
            mujoco.mj_kinematics(model, data)
            t0 = time.perf_counter()
            lidar.step(t)
            spent += time.perf_counter() - t0
            k += 1
            t = k * dt
        frame_ms.append(spent * 1e3)
        scan = lidar.pop_frame()
        while scan is not None:
            points.append(scan.num_points)
            scan = lidar.pop_frame()

    camera = SimCamera(model, data, cam, desc.sensors.camera.width_px, desc.sensors.camera.height_px,
                       hidden_geom_groups=(3,))
    camera.render_rgb(0.0)  # warm-up (first render uploads textures)
    rgb_ms, seg_ms = [], []
    for i in range(n_renders):
        t0 = time.perf_counter()
        camera.render_rgb(float(i))
        rgb_ms.append((time.perf_counter() - t0) * 1e3)
        t0 = time.perf_counter()
        camera.render_segmentation()
        seg_ms.append((time.perf_counter() - t0) * 1e3)
    camera.close()
    return {
        "lidar_rays_per_frame": cfg.points_per_frame,
        "lidar_slices_per_frame": cfg.slices_per_frame,
        "lidar_points_per_frame_mean": float(np.mean(points)) if points else 0.0,
        "lidar_ms_per_frame_median": statistics.median(frame_ms),
        "lidar_ms_per_frame_max": max(frame_ms),
        "rgb_ms_median": statistics.median(rgb_ms),
        "segmentation_ms_median": statistics.median(seg_ms),
        "image_size": f"{desc.sensors.camera.width_px}x{desc.sensors.camera.height_px}",
        "n_boxes": n_boxes,
        "mujoco_gl": os.environ.get("MUJOCO_GL", ""),
    }


if __name__ == "__main__":
    import json

    print(json.dumps(run_sensor_benchmark(), indent=2))
