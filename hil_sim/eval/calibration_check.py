"""HIL self-check of the calibration pipeline against the simulator's true values.

A MuJoCo scene (built with mujoco.MjSpec) holds the LIMO camera and lidar at their mounts from
the robot description, and a checkerboard made of thin black/white boxes on a mocap body. For
15-25 board poses: render the camera image (mujoco.Renderer, shadows off), cast a dense ray grid
from the lidar at the board (mujoco.mj_multiRay) with Gaussian range noise; then calibrate the
intrinsics and the lidar-camera extrinsic with the project's calibration code and compare with
the truth: K from the MuJoCo camera (fx = fy = (h/2)/tan(fovy/2), principal point at the image
centre) and T_camera<-lidar from the mounts.

Pixel convention: OpenCV puts pixel centres at integer coordinates, so the image centre is
((w-1)/2, (h-1)/2). `measure_pixel_offset` checks this empirically by rendering small spheres at
known 3-D points and comparing their rendered centroids with the true-K projection.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import click
import numpy as np
from scipy.spatial.transform import Rotation

from calibration.cli_support import OneLineCommand
from calibration.robot_description import RobotDescription, load_robot_description

BOARD_PATTERN = (9, 6)  # inner corners
BOARD_SQUARE_M = 0.05
BOARD_BORDER_M = 0.04
BOARD_THICKNESS_M = 0.005
RANGE_NOISE_STD_M = 0.02

if TYPE_CHECKING:
    from hil_sim.sensors.camera_lens import CameraLens
    from hil_sim.world.robot_variant import RobotVariant


def _quat_wxyz(R: np.ndarray) -> np.ndarray:
    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return np.array([w, x, y, z])


@dataclass
class CalibrationScene:
    """The compiled MuJoCo scene and the true calibration values."""

    model: object
    data: object
    K_true: np.ndarray
    T_cam_lidar_true: np.ndarray
    T_base_cam: np.ndarray
    T_base_lidar: np.ndarray
    width_px: int
    height_px: int
    fovy_deg: float
    #: The true distortion (OpenCV order, 5 coefficients; zeros for the description's pinhole).
    dist_true: np.ndarray = field(default_factory=lambda: np.zeros(5))
    #: The camera as built (a robot variant); None: the description's pinhole.
    lens: CameraLens | None = None

    def camera_model(self):
        """The true camera (calibration.camera_model.CameraModel)."""
        from calibration.camera_model import CameraModel

        return CameraModel(self.K_true, self.dist_true, self.width_px, self.height_px)


def build_scene(desc: RobotDescription, variant: RobotVariant | None = None) -> CalibrationScene:
    """MjSpec scene: camera + lidar site at the description's mounts (or the variant's, with its
    camera's intrinsics and lens), a checkerboard and a probe sphere."""
    import mujoco

    from hil_sim.sensors.camera import add_camera_to_spec, ensure_offscreen_buffer

    lens = variant.lens if variant is not None else None
    built = variant.robot if variant is not None else desc
    cam_desc = built.sensors.camera
    w, h = cam_desc.width_px, cam_desc.height_px
    fx = cam_desc.nominal_intrinsics()[0, 0]
    fovy_deg = float(np.degrees(2 * np.arctan((h / 2) / fx)))

    spec = mujoco.MjSpec()
    spec.modelname = "calibration_check"
    spec.visual.global_.offwidth = max(w, 640)
    spec.visual.global_.offheight = max(h, 480)
    ensure_offscreen_buffer(spec, *(lens.canvas_size if lens is not None else (w, h)))
    # Flat, shadow-free lighting: the board's colours come out as their rgba.
    spec.visual.headlight.ambient = [1.0, 1.0, 1.0]
    spec.visual.headlight.diffuse = [0.0, 0.0, 0.0]
    spec.visual.headlight.specular = [0.0, 0.0, 0.0]
    spec.stat.extent = 3.0  # sets the clip planes for a scene a few metres across

    T_base_cam = cam_desc.mount.transform()
    T_base_lidar = built.sensors.lidar.mount.transform()
    add_camera_to_spec(spec.worldbody, T_base_cam, cam_desc, name="camera", lens=lens)
    spec.worldbody.add_site(name="lidar", pos=T_base_lidar[:3, 3], quat=_quat_wxyz(T_base_lidar[:3, :3]))

    # Board frame = OpenCV corner frame: origin at the first inner corner, z into the board,
    # front face at z = 0. Squares (cols+1) x (rows+1) plus a white border, all one flat layer.
    board = spec.worldbody.add_body(name="board", mocap=True, pos=[0, 0, -50])
    cols, rows = BOARD_PATTERN
    sq, half_t = BOARD_SQUARE_M, BOARD_THICKNESS_M / 2
    black, white = [0.05, 0.05, 0.05, 1.0], [0.95, 0.95, 0.95, 1.0]
    for i in range(cols + 1):
        for j in range(rows + 1):
            board.add_geom(
                type=mujoco.mjtGeom.mjGEOM_BOX, size=[sq / 2, sq / 2, half_t],
                pos=[(i - 0.5) * sq, (j - 0.5) * sq, half_t], rgba=black if (i + j) % 2 == 0 else white,
            )
    x0, x1 = -sq - BOARD_BORDER_M, cols * sq + BOARD_BORDER_M
    y0, y1 = -sq - BOARD_BORDER_M, rows * sq + BOARD_BORDER_M
    b = BOARD_BORDER_M
    for cx, cy, sx, sy in [
        ((x0 + x1) / 2, y0 + b / 2, (x1 - x0) / 2, b / 2), ((x0 + x1) / 2, y1 - b / 2, (x1 - x0) / 2, b / 2),
        (x0 + b / 2, (y0 + y1) / 2, b / 2, (y1 - y0) / 2 - b), (x1 - b / 2, (y0 + y1) / 2, b / 2, (y1 - y0) / 2 - b),
    ]:
        board.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[sx, sy, half_t], pos=[cx, cy, half_t], rgba=white)

    probe = spec.worldbody.add_body(name="probe", mocap=True, pos=[0, 0, -60])
    probe.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.01, 0, 0], rgba=[1, 1, 1, 1], group=3)

    model = spec.compile()
    data = mujoco.MjData(model)
    K_true = np.array([[fx, 0.0, (w - 1) / 2], [0.0, fx, (h - 1) / 2], [0.0, 0.0, 1.0]])
    dist_true = np.zeros(5)
    if lens is not None:
        K_true = lens.K.copy()
        dist_true[: len(lens.dist)] = lens.dist
    T_cam_lidar = np.linalg.inv(T_base_cam) @ T_base_lidar
    return CalibrationScene(model, data, K_true, T_cam_lidar, T_base_cam, T_base_lidar, w, h, fovy_deg, dist_true, lens)


def _make_renderer(scene: CalibrationScene):
    import mujoco

    rw, rh = scene.lens.canvas_size if scene.lens is not None else (scene.width_px, scene.height_px)
    r = mujoco.Renderer(scene.model, height=rh, width=rw)
    for flag in (mujoco.mjtRndFlag.mjRND_SHADOW, mujoco.mjtRndFlag.mjRND_REFLECTION, mujoco.mjtRndFlag.mjRND_SKYBOX):
        r.scene.flags[flag] = 0
    return r


def _set_mocap(scene: CalibrationScene, body: str, T_world: np.ndarray) -> None:
    import mujoco

    mid = scene.model.body(body).mocapid[0]
    scene.data.mocap_pos[mid] = T_world[:3, 3]
    scene.data.mocap_quat[mid] = _quat_wxyz(T_world[:3, :3])
    mujoco.mj_forward(scene.model, scene.data)


def _render(scene: CalibrationScene, renderer) -> np.ndarray:
    import mujoco

    opt = mujoco.MjvOption()
    opt.geomgroup[:] = 1
    renderer.update_scene(scene.data, camera="camera", scene_option=opt)
    img = renderer.render()
    return scene.lens.apply(img) if scene.lens is not None else img


PROBE_POINTS_CAM = ([0.0, 0.0, 1.0], [0.25, -0.15, 1.2], [-0.3, 0.2, 1.0], [0.4, 0.3, 1.5])


def measure_pixel_offset(scene: CalibrationScene, renderer=None) -> np.ndarray:
    """Mean (du, dv) of rendered probe-sphere centroids minus their true projections (pixels)."""
    return np.mean(probe_offsets(scene, renderer), axis=0)


def probe_offsets(scene: CalibrationScene, renderer=None, points_cam=PROBE_POINTS_CAM) -> np.ndarray:
    """(N, 2): rendered probe-sphere centroids minus where the true K and distortion project the
    sphere's centre (points in the optical frame, metres)."""
    own = renderer is None
    renderer = renderer or _make_renderer(scene)
    try:
        return _probe_offsets(scene, renderer, points_cam)
    finally:
        if own:
            renderer.close()


def _probe_offsets(scene: CalibrationScene, renderer, points_cam) -> np.ndarray:
    camera = scene.camera_model()
    _set_mocap(scene, "board", _far())
    offsets = []
    for p_cam in points_cam:
        T = np.eye(4)
        T[:3, 3] = scene.T_base_cam[:3, :3] @ p_cam + scene.T_base_cam[:3, 3]
        _set_mocap(scene, "probe", T)
        img = _render(scene, renderer).astype(np.float64).mean(axis=2)
        vv, uu = np.mgrid[0: img.shape[0], 0: img.shape[1]]
        wgt = img / img.sum()
        centroid = np.array([(wgt * uu).sum(), (wgt * vv).sum()])
        uv, _ = camera.project(np.asarray([p_cam], dtype=float))
        offsets.append(centroid - uv[0])
    _set_mocap(scene, "probe", _far())
    return np.array(offsets)


def _far() -> np.ndarray:
    T = np.eye(4)
    T[2, 3] = -50.0
    return T


def sample_board_poses(scene: CalibrationScene, n: int, rng: np.random.Generator) -> list[np.ndarray]:
    """T_camera<-board poses with the whole board in view, tilted in varied directions."""
    from calibration.camera_model import transform_points

    cam = scene.camera_model()
    cols, rows = BOARD_PATTERN
    sq, b = BOARD_SQUARE_M, BOARD_BORDER_M
    outline = np.array([[-sq - b, -sq - b, 0], [cols * sq + b, -sq - b, 0], [cols * sq + b, rows * sq + b, 0],
                        [-sq - b, rows * sq + b, 0]])
    centre = np.array([(cols - 1) / 2 * sq, (rows - 1) / 2 * sq, 0.0])
    poses: list[np.ndarray] = []
    while len(poses) < n:
        k = len(poses)
        # Alternate tilt directions so that the board normals span 3-D.
        tilt = np.radians([rng.uniform(-35, 35), rng.uniform(-35, 35), rng.uniform(-20, 20)])
        if k % 4 == 0:
            tilt[0] = np.radians(rng.choice([-1, 1]) * rng.uniform(20, 35))
        elif k % 4 == 1:
            tilt[1] = np.radians(rng.choice([-1, 1]) * rng.uniform(20, 35))
        R = Rotation.from_euler("xyz", tilt).as_matrix()
        z = rng.uniform(0.8, 1.7)
        if k % 2 == 0:  # near the optical axis
            pos = np.array([rng.uniform(-0.35, 0.35), rng.uniform(-0.25, 0.25), z])
        else:  # towards the image's edges and corners, where the lens distorts most: a fit without
            # views there extrapolates its distortion into them (tens of pixels in a corner)
            pos = np.array([rng.uniform(-0.75, 0.75) * z, rng.uniform(-0.55, 0.55) * z, z])
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = pos - R @ centre
        uv, valid = cam.project(transform_points(T, outline))
        margin = 10
        if valid.all() and uv[:, 0].min() > margin and uv[:, 1].min() > margin \
                and uv[:, 0].max() < scene.width_px - margin and uv[:, 1].max() < scene.height_px - margin:
            poses.append(T)
    return poses


def cast_lidar(scene: CalibrationScene, T_cam_board: np.ndarray, rng: np.random.Generator,
               n_side: int = 120, noise_std_m: float = RANGE_NOISE_STD_M) -> np.ndarray:
    """Dense ray grid from the lidar over the board's angular extent; (M,3) hits in the lidar frame."""
    import mujoco

    from calibration.camera_model import transform_points

    cols, rows = BOARD_PATTERN
    sq, b = BOARD_SQUARE_M, BOARD_BORDER_M
    outline = np.array([[-sq - b, -sq - b, 0], [cols * sq + b, -sq - b, 0], [cols * sq + b, rows * sq + b, 0],
                        [-sq - b, rows * sq + b, 0]])
    T_lidar_board = np.linalg.inv(scene.T_cam_lidar_true) @ T_cam_board
    corners = transform_points(T_lidar_board, outline)
    az = np.arctan2(corners[:, 1], corners[:, 0])
    el = np.arctan2(corners[:, 2], np.hypot(corners[:, 0], corners[:, 1]))
    pad = np.radians(2.0)
    A, E = np.meshgrid(np.linspace(az.min() - pad, az.max() + pad, n_side),
                       np.linspace(el.min() - pad, el.max() + pad, n_side))
    dirs = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], axis=-1).reshape(-1, 3)
    R_wl = scene.T_base_lidar[:3, :3]
    vec = np.ascontiguousarray((dirs @ R_wl.T).ravel())
    nray = len(dirs)
    geomid = np.zeros(nray, dtype=np.int32)
    dist = np.zeros(nray)
    group = np.array([1, 1, 1, 0, 0, 0], dtype=np.uint8)  # the probe sphere (group 3) is invisible to the lidar
    mujoco.mj_multiRay(scene.model, scene.data, scene.T_base_lidar[:3, 3].copy(), vec, group, 1, -1,
                       geomid, dist, None, nray, 50.0)
    hit = geomid >= 0
    r = dist[hit] + rng.normal(0.0, noise_std_m, hit.sum())
    return dirs[hit] * r[:, None]


def run_hil_check(seed: int = 0, n_poses: int = 20, desc: RobotDescription | None = None,
                  T_guess_error: tuple[float, float] = (0.05, 3.0)) -> dict:
    """Render, ray-cast, calibrate and compare with the truth; returns the figures as a dict."""
    from calibration.intrinsics import calibrate_intrinsics

    desc = desc or load_robot_description()
    rng = np.random.default_rng(seed)
    scene = build_scene(desc)
    pixel_offset, images, scans = _capture(scene, n_poses, rng)
    intr = calibrate_intrinsics(images, BOARD_PATTERN, BOARD_SQUARE_M)
    # A rough prior, as a user would take from the robot description: truth perturbed.
    T_guess = _perturbed(scene.T_cam_lidar_true, T_guess_error, rng)
    ext = _calibrate_extrinsics(images, scans, intr, T_guess)
    return _figures(seed, n_poses, scene, intr, ext, pixel_offset)


def _capture(scene: CalibrationScene, n_poses: int, rng: np.random.Generator) -> tuple[np.ndarray, dict, dict]:
    """(the renderer's pixel offset, BGR image per view, lidar points per view) of n_poses board poses."""
    renderer = _make_renderer(scene)
    try:
        pixel_offset = measure_pixel_offset(scene, renderer)
        poses = sample_board_poses(scene, n_poses, rng)
        images, scans = {}, {}
        for k, T_cb in enumerate(poses):
            _set_mocap(scene, "board", scene.T_base_cam @ T_cb)
            name = f"pose_{k:02d}"
            images[name] = _render(scene, renderer)[:, :, ::-1].copy()  # RGB -> BGR (OpenCV)
            scans[name] = cast_lidar(scene, T_cb, rng)
    finally:
        renderer.close()
    return pixel_offset, images, scans


def _perturbed(T_true: np.ndarray, error: tuple[float, float], rng: np.random.Generator) -> np.ndarray:
    """T_true moved by `error` = (metres, degrees) in random directions."""
    dt, dr = error
    T_guess = T_true.copy()
    T_guess[:3, 3] += dt * rng.normal(size=3) / np.sqrt(3)
    axis = rng.normal(size=3)
    T_guess[:3, :3] = Rotation.from_rotvec(np.radians(dr) * axis / np.linalg.norm(axis)).as_matrix() @ T_guess[:3, :3]
    return T_guess


def _calibrate_extrinsics(images: dict, scans: dict, intr, T_guess: np.ndarray):
    """The lidar-camera extrinsics from the views the intrinsic calibration used."""
    from calibration.extrinsics import BoardGeometry, BoardObservation, calibrate_lidar_camera, segment_board
    from calibration.intrinsics import board_pose_in_camera, detect_board

    K, dist = intr.K, intr.dist
    board = BoardGeometry(BOARD_PATTERN, BOARD_SQUARE_M, BOARD_BORDER_M)
    observations = []
    for name in intr.per_image_rms_px:
        det = detect_board(images[name], BOARD_PATTERN)
        T_cb, _ = board_pose_in_camera(det.corners_px, BOARD_PATTERN, BOARD_SQUARE_M, K, dist)
        pts = segment_board(scans[name], board, T_cb, T_guess)
        observations.append(BoardObservation(T_cb, pts, name))
    return calibrate_lidar_camera(observations, board)


def _figures(seed: int, n_poses: int, scene: CalibrationScene, intr, ext, pixel_offset: np.ndarray) -> dict:
    """The calibration's errors against the simulator's truth, and the verdict (`passed`)."""
    from calibration.extrinsics import transform_error

    K, dist = intr.K, intr.dist
    t_err, r_err = transform_error(ext.T_cam_lidar, scene.T_cam_lidar_true)
    K_true = scene.K_true
    result = {
        "seed": seed,
        "n_poses": n_poses,
        "n_images_used": len(intr.per_image_rms_px),
        "rejected": intr.rejected,
        "intrinsics_rms_px": intr.rms_px,
        "fx_rel_err": abs(K[0, 0] - K_true[0, 0]) / K_true[0, 0],
        "fy_rel_err": abs(K[1, 1] - K_true[1, 1]) / K_true[1, 1],
        "cx_err_px": abs(K[0, 2] - K_true[0, 2]),
        "cy_err_px": abs(K[1, 2] - K_true[1, 2]),
        "extrinsic_trans_err_m": t_err,
        "extrinsic_rot_err_deg": r_err,
        "extrinsic_rms_point_to_plane_m": ext.rms_point_to_plane_m,
        "lidar_points_on_board": ext.n_points,
        "range_noise_std_m": RANGE_NOISE_STD_M,
        "render_pixel_offset_px": pixel_offset.tolist(),
        "K_true": K_true.tolist(),
        "K_est": K.tolist(),
        "dist_est": dist.tolist(),
        "T_cam_lidar_true": scene.T_cam_lidar_true.tolist(),
        "T_cam_lidar_est": ext.T_cam_lidar.tolist(),
    }
    result["passed"] = bool(
        result["fx_rel_err"] < 0.01 and result["fy_rel_err"] < 0.01 and result["cx_err_px"] < 2.0
        and result["cy_err_px"] < 2.0 and t_err < 0.01 and r_err < 0.5
    )
    return result


def write_board_views(folder: str | Path, seed: int = 0, n_poses: int = 20,
                      desc: RobotDescription | None = None) -> dict:
    """Write NAME.png + NAME.pcd (binary, lidar frame) board views to `folder`, as a real capture would.

    Returns the truth: {"K": 3x3, "T_cam_lidar": 4x4, "pattern": (cols, rows), "square_m", "border_m"}.
    The folder can be fed to `dct calibrate intrinsics` / `dct calibrate extrinsics`.
    """
    import cv2

    from calibration.pointcloud_write import write_pcd

    desc = desc or load_robot_description()
    rng = np.random.default_rng(seed)
    scene = build_scene(desc)
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    renderer = _make_renderer(scene)
    try:
        for k, T_cb in enumerate(sample_board_poses(scene, n_poses, rng)):
            _set_mocap(scene, "board", scene.T_base_cam @ T_cb)
            cv2.imwrite(str(folder / f"pose_{k:02d}.png"), _render(scene, renderer)[:, :, ::-1])
            pts = cast_lidar(scene, T_cb, rng).astype(np.float32)
            write_pcd(folder / f"pose_{k:02d}.pcd", {"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2]}, "binary")
    finally:
        renderer.close()
    return {"K": scene.K_true, "T_cam_lidar": scene.T_cam_lidar_true, "pattern": BOARD_PATTERN,
            "square_m": BOARD_SQUARE_M, "border_m": BOARD_BORDER_M}


@click.command(name="hil-check", cls=OneLineCommand)
@click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="write the figures to this JSON file (checked before the run, written atomically)")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--poses", "n_poses", type=click.IntRange(5, 60), default=20, show_default=True)
def hil_check_command(json_path: Path | None, seed: int, n_poses: int) -> None:
    """Calibrate from simulated checkerboard views and compare with the simulator's true values.

    Exit 0 when the targets are met, 1 when they are not (the JSON is written in both cases:
    it is the check's verdict), 1 with a one-line error when the check could not run.
    """
    from calibration.cli_support import OneLineError, checked_output
    from calibration.errors import ConfigFileError
    from calibration.intrinsics import CalibrationError
    from calibration.outputs import atomic_write_json

    if json_path is not None:
        checked_output(json_path, "JSON output")
    try:
        result = run_hil_check(seed=seed, n_poses=n_poses)
    except (CalibrationError, ConfigFileError) as exc:
        raise OneLineError(f"calibration HIL check (seed {seed}, {n_poses} poses) could not run: {exc}") from None
    keys = ["fx_rel_err", "fy_rel_err", "cx_err_px", "cy_err_px", "extrinsic_trans_err_m", "extrinsic_rot_err_deg",
            "intrinsics_rms_px", "n_images_used", "lidar_points_on_board"]
    for k in keys:
        click.echo(f"{k:28s} {result[k]:.6g}" if isinstance(result[k], float) else f"{k:28s} {result[k]}")
    click.echo(f"{'passed':28s} {result['passed']}")
    if json_path is not None:
        try:
            atomic_write_json(json_path, result)
        except (OSError, ValueError) as exc:
            raise OneLineError(f"JSON output {json_path}: not written: {exc}") from None
    if not result["passed"]:
        raise SystemExit(1)


__all__ = ["hil_check_command", "run_hil_check", "build_scene", "measure_pixel_offset", "write_board_views"]
