"""`dct calibrate hil`: calibrate a simulated robot variant from its target views, as a factory would.

The robot as built (hil_sim.world.robot_variant: its camera's focal lengths, principal point and
lens distortion, its lidar and camera mounts) is put in hil-check's calibration scene
(hil_sim.eval.calibration_check) and calibrated with the project's calibration code from what
its sensors see, never from the truth:

1. checkerboard views (a board on a mocap body in front of the camera, rendered through the
   variant's lens, with a dense lidar ray grid at it): camera K and five distortion coefficients
   (calibration.intrinsics, k3 free: a wide lens needs it), then T_camera<-lidar from the board
   planes (calibration.extrinsics), starting from the robot description's nominal mounts;
2. an end-of-line fixture: the robot parked at a known pose, one board presented at
   FIXTURE_STATIONS, each at a pose known in base_link; the corners of every station together
   give the camera's pose on the base by solvePnP (OpenCV, with the calibrated K and distortion),
   and the lidar's mount follows: T_base<-lidar = T_base<-camera @ T_camera<-lidar.

The result is a calibration file (intrinsics, distortion, lidar_to_camera, lidar_mount,
provenance), and the recovered values beside the truth. Targets (TARGETS): focal lengths within
0.5 %, principal point within 2 px, both mounts within 5 mm and 0.3 deg.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import click
import numpy as np
from scipy.spatial.transform import Rotation

from calibration.cli_support import OneLineCommand

#: Recovery targets: relative focal error, principal point error (px), mount translation (m) and
#: rotation (deg) errors, the same for the lidar-camera extrinsic.
TARGETS = {"focal_rel": 0.005, "principal_px": 2.0, "mount_m": 0.005, "mount_deg": 0.3}
#: Board views for the intrinsics and the lidar-camera extrinsic.
DEFAULT_POSES = 30
#: The fixture: board centre (x, y, z) in base_link (m) and its turn (yaw about z, pitch about
#: y, deg) away from facing the robot square on: stands 0.8-1.2 m in front of it, the board's lower
#: edge above the floor, each fully in view with at least 25 px to spare for any drawn variant.
FIXTURE_STATIONS: tuple[tuple[float, float, float, float, float], ...] = (
    (0.80, 0.00, 0.22, 0.0, 0.0),
    (1.05, 0.24, 0.26, 30.0, 0.0),
    (1.05, -0.24, 0.26, -30.0, 0.0),
    (1.15, 0.00, 0.45, 0.0, -25.0),
    (1.20, 0.26, 0.42, 25.0, -15.0),
    (1.20, -0.26, 0.42, -25.0, -15.0),
)
#: The board's optical-frame orientation facing the robot: x along -y, y along -z, z along +x of base_link.
_R_FACING = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def fixture_board_poses() -> list[np.ndarray]:
    """T_base<-board (board corner frame: origin at the first inner corner) of every fixture station."""
    from hil_sim.eval.calibration_check import BOARD_PATTERN, BOARD_SQUARE_M

    cols, rows = BOARD_PATTERN
    centre = np.array([(cols - 1) / 2 * BOARD_SQUARE_M, (rows - 1) / 2 * BOARD_SQUARE_M, 0.0])
    poses = []
    for x, y, z, yaw, pitch in FIXTURE_STATIONS:
        R = Rotation.from_euler("zy", [yaw, pitch], degrees=True).as_matrix() @ _R_FACING
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = np.array([x, y, z]) - R @ centre
        poses.append(T)
    return poses


@dataclass
class FixtureResult:
    """The camera's pose on the base from the fixture: T_base<-camera and solvePnP's RMS (px)."""

    T_base_cam: np.ndarray
    rms_px: float
    n_stations: int


def calibrate_on_fixture(scene, renderer, K: np.ndarray, dist: np.ndarray, nominal_T_base_cam: np.ndarray,
                         nominal_K: np.ndarray) -> FixtureResult:
    """Render the fixture's stations, detect the corners, solvePnP them all at once (module docstring)."""
    import cv2

    from calibration.intrinsics import CalibrationError, board_object_points, detect_board
    from hil_sim.eval.calibration_check import BOARD_PATTERN, BOARD_SQUARE_M, _render, _set_mocap

    obj_board = board_object_points(BOARD_PATTERN, BOARD_SQUARE_M)
    obj, img = [], []
    for k, T_base_board in enumerate(fixture_board_poses()):
        _set_mocap(scene, "board", T_base_board)  # the scene's world frame is base_link
        det = detect_board(_render(scene, renderer)[:, :, ::-1].copy(), BOARD_PATTERN)
        if det is None:
            raise CalibrationError(f"fixture station {k}: the board was not found in the camera image")
        p_base = obj_board @ T_base_board[:3, :3].T + T_base_board[:3, 3]
        corners = _oriented(det.corners_px, p_base, nominal_T_base_cam, nominal_K)
        obj.append(p_base)
        img.append(corners)
    obj_all, img_all = np.concatenate(obj), np.concatenate(img)
    guess = np.linalg.inv(nominal_T_base_cam)
    rvec, tvec = cv2.Rodrigues(guess[:3, :3])[0], guess[:3, 3].reshape(3, 1).copy()
    ok, rvec, tvec = cv2.solvePnP(obj_all, img_all, K, dist, rvec, tvec, useExtrinsicGuess=True,
                                  flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise CalibrationError("fixture: solvePnP failed")
    rvec, tvec = cv2.solvePnPRefineLM(obj_all, img_all, K, dist, rvec, tvec)
    proj, _ = cv2.projectPoints(obj_all, rvec, tvec, K, dist)
    rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img_all) ** 2, axis=1))))
    T_cam_base = np.eye(4)
    T_cam_base[:3, :3] = cv2.Rodrigues(rvec)[0]
    T_cam_base[:3, 3] = tvec.ravel()
    return FixtureResult(np.linalg.inv(T_cam_base), rms, len(obj))


def _oriented(corners: np.ndarray, p_base: np.ndarray, T_base_cam: np.ndarray, K: np.ndarray) -> np.ndarray:
    """The detected corners in the board's order: reversed when findChessboardCorners started at the
    far corner (judged against where the nominal camera would see the first and last corners)."""
    p_cam = (p_base[[0, -1]] - T_base_cam[:3, 3]) @ T_base_cam[:3, :3]
    uv = (p_cam @ K.T)[:, :2] / p_cam[:, 2:3]
    straight = np.linalg.norm(corners[0] - uv[0]) + np.linalg.norm(corners[-1] - uv[1])
    swapped = np.linalg.norm(corners[-1] - uv[0]) + np.linalg.norm(corners[0] - uv[1])
    return corners if straight <= swapped else corners[::-1].copy()


def run_calibrate_hil(variant, seed: int = 0, n_poses: int = DEFAULT_POSES) -> dict:
    """Calibrate the variant from its simulated target views; the calibration, and the figures
    (recovered beside the truth, errors, `passed`) as a dict: {"calibration": CalibrationFile, ...}."""
    from calibration.intrinsics import calibrate_intrinsics
    from hil_sim.eval.calibration_check import (BOARD_PATTERN, BOARD_SQUARE_M, _calibrate_extrinsics, _capture,
                                                _make_renderer, build_scene)

    nominal = variant.nominal_robot
    scene = build_scene(nominal, variant)
    rng = np.random.default_rng(seed)
    pixel_offset, images, scans = _capture(scene, n_poses, rng)
    intr = calibrate_intrinsics(images, BOARD_PATTERN, BOARD_SQUARE_M, fix_k3=False)
    nominal_T_base_cam = nominal.sensors.camera.mount.transform()
    T_guess = np.linalg.inv(nominal_T_base_cam) @ nominal.sensors.lidar.mount.transform()
    ext = _calibrate_extrinsics(images, scans, intr, T_guess)
    renderer = _make_renderer(scene)
    try:
        fixture = calibrate_on_fixture(scene, renderer, intr.K, intr.dist, nominal_T_base_cam,
                                       nominal.sensors.camera.nominal_intrinsics())
    finally:
        renderer.close()
    T_base_lidar = fixture.T_base_cam @ ext.T_cam_lidar
    cal = _calibration_file(variant, intr, ext, fixture, T_base_lidar, n_poses)
    figures = recovery_figures(variant, intr.K, intr.dist, ext.T_cam_lidar, fixture.T_base_cam, T_base_lidar)
    figures.update({
        "seed": seed, "n_poses": n_poses, "n_images_used": len(intr.per_image_rms_px), "rejected": intr.rejected,
        "intrinsics_rms_px": intr.rms_px, "extrinsic_rms_point_to_plane_m": ext.rms_point_to_plane_m,
        "fixture_rms_px": fixture.rms_px, "fixture_stations": fixture.n_stations,
        "render_pixel_offset_px": pixel_offset.tolist(), "robot_variant": variant.to_dict(), "targets": dict(TARGETS),
    })
    return {"calibration": cal, "figures": figures, "intrinsics": intr, "extrinsics": ext}


def _calibration_file(variant, intr, ext, fixture: FixtureResult, T_base_lidar: np.ndarray, n_poses: int):
    """The calibration file of the recovered values (provenance says how they were found)."""
    from calibration.calibration_file import RigidTransform, make_calibration

    cal = make_calibration(
        variant.robot.name, intr.K, intr.dist, intr.width_px, intr.height_px, ext.T_cam_lidar,
        method=(f"dct calibrate hil: {len(intr.per_image_rms_px)} simulated checkerboard views, end-of-line fixture "
                f"of {fixture.n_stations} stations (robot variant {variant.label})"),
        intrinsics_rms_px=float(intr.rms_px), extrinsic_rms_m=float(ext.rms_point_to_plane_m),
        n_images=len(intr.per_image_rms_px), n_board_poses=len(ext.per_pose_rms_m),
        notes=f"fixture solvePnP RMS {fixture.rms_px:.3f} px over {n_poses} requested views",
    )
    return cal.model_copy(update={"lidar_mount": RigidTransform.from_matrix(T_base_lidar)})


def recovery_figures(variant, K: np.ndarray, dist: np.ndarray, T_cam_lidar: np.ndarray, T_base_cam: np.ndarray,
                     T_base_lidar: np.ndarray) -> dict:
    """Recovered values beside the variant's truth, their errors, and whether TARGETS are met."""
    from calibration.extrinsics import transform_error

    truth = variant.true_camera()
    Kt = truth.K
    rows = {
        "fx": (Kt[0, 0], K[0, 0]), "fy": (Kt[1, 1], K[1, 1]), "cx": (Kt[0, 2], K[0, 2]), "cy": (Kt[1, 2], K[1, 2]),
        **{name: (truth.dist[i], float(np.ravel(dist)[i])) for i, name in enumerate(("k1", "k2", "p1", "p2", "k3"))},
    }
    errors = {
        "fx_rel_err": abs(K[0, 0] / Kt[0, 0] - 1.0), "fy_rel_err": abs(K[1, 1] / Kt[1, 1] - 1.0),
        "cx_err_px": abs(K[0, 2] - Kt[0, 2]), "cy_err_px": abs(K[1, 2] - Kt[1, 2]),
    }
    transforms = {}
    for name, est, true in (("lidar_to_camera", T_cam_lidar, variant.true_T_cam_lidar()),
                            ("camera_mount", T_base_cam, variant.true_camera_mount()),
                            ("lidar_mount", T_base_lidar, variant.true_lidar_mount())):
        t_err, r_err = transform_error(est, true)
        errors[f"{name}_trans_err_m"], errors[f"{name}_rot_err_deg"] = t_err, r_err
        transforms[name] = {"true": true.tolist(), "recovered": est.tolist()}
    errors = {k: float(v) for k, v in errors.items()}
    passed = (max(errors["fx_rel_err"], errors["fy_rel_err"]) <= TARGETS["focal_rel"]
              and max(errors["cx_err_px"], errors["cy_err_px"]) <= TARGETS["principal_px"]
              and all(errors[f"{n}_trans_err_m"] <= TARGETS["mount_m"] and errors[f"{n}_rot_err_deg"] <= TARGETS[
                  "mount_deg"] for n in transforms))
    return {"intrinsics": {k: {"true": float(t), "recovered": float(r)} for k, (t, r) in rows.items()},
            "transforms": transforms, "errors": errors, "passed": bool(passed)}


def recovery_table(figures: dict) -> list[str]:
    """The figures as printed lines: each value true, recovered, error; then the transforms' errors."""
    lines = [f"{'':26s} {'true':>24s} {'recovered':>24s} {'error':>12s}"]
    for name, v in figures["intrinsics"].items():
        err = v["recovered"] - v["true"]
        text = f"{100 * err / v['true']:+.3f} %" if name in ("fx", "fy") else f"{err:+.5g}"
        lines.append(f"{name:26s} {v['true']:24.6g} {v['recovered']:24.6g} {text:>12s}")
    e = figures["errors"]
    for name, v in figures["transforms"].items():
        true, rec = np.array(v["true"]), np.array(v["recovered"])
        lines.append(f"{name + ' xyz [mm]':26s} {_xyz(true):>24s} {_xyz(rec):>24s} "
                     f"{e[name + '_trans_err_m'] * 1e3:9.2f} mm")
        lines.append(f"{name + ' rpy [deg]':26s} {_rpy(true):>24s} {_rpy(rec):>24s} "
                     f"{e[name + '_rot_err_deg']:8.3f} deg")
    lines.append(f"{'passed':26s} {figures['passed']}")
    return lines


def _xyz(T: np.ndarray) -> str:
    return ",".join(f"{x * 1e3:.1f}" for x in T[:3, 3])


def _rpy(T: np.ndarray) -> str:
    return ",".join(f"{a:.2f}" for a in Rotation.from_matrix(T[:3, :3]).as_euler("xyz", degrees=True))


@click.command(name="hil", cls=OneLineCommand)
@click.option("--robot-variant", "spec", required=True, metavar="SPEC",
              help="The simulated robot as built: nominal, a seed, or a variant YAML file (docs/simulator.md).")
@click.option("--out", "out_path", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="The calibration file to write (checked before the work, written atomically).")
@click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Also write the figures (recovered beside the truth, errors, verdict) to this JSON file.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the board poses and the lidar noise.")
@click.option("--poses", "n_poses", type=click.IntRange(10, 60), default=DEFAULT_POSES, show_default=True,
              help="Checkerboard views for the intrinsics and the lidar-camera extrinsic.")
@click.option("--robot", "robot_path", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Robot description YAML (default: the shipped LIMO).")
@click.option("--force", is_flag=True, help="Overwrite an existing --out; write a calibration that misses the "
                                            "quality targets of dct calibrate intrinsics/extrinsics.")
def calibrate_hil_command(spec: str, out_path: Path, json_path: Path | None, seed: int, n_poses: int,
                          robot_path: Path | None, force: bool) -> None:
    """Calibrate a simulated robot variant from its target views and write its calibration file.

    Prints the recovered values beside the truth. Exit 0 when every recovery target is met, 1 when
    one is not (the file and the JSON are written either way), 1 with a one-line error when it
    could not run or the calibration misses its quality target (nothing written without --force).
    """
    from calibration.calibration_file import save_calibration
    from calibration.cli_support import OneLineError, checked_output
    from calibration.errors import ConfigFileError
    from calibration.intrinsics import CalibrationError
    from calibration.outputs import atomic_write_json

    checked_output(out_path, "--out", inputs=[robot_path], overwrite=force)
    if json_path is not None:
        checked_output(json_path, "--json", inputs=[robot_path])
        if json_path.resolve() == out_path.resolve():
            raise OneLineError(f"--json {json_path} is also the --out file; write them to two files")
    try:
        variant = _variant(spec, robot_path)
        result = run_calibrate_hil(variant, seed=seed, n_poses=n_poses)
    except (CalibrationError, ConfigFileError) as exc:
        raise OneLineError(f"dct calibrate hil (robot variant {spec}, seed {seed}): {exc}") from None
    figures = result["figures"]
    for line in recovery_table(figures):
        click.echo(line)
    problems = _quality_problems(result)
    if problems and not force:
        raise OneLineError(f"calibration misses its quality target ({'; '.join(problems)}); not written "
                           "(--force writes it)")
    try:
        save_calibration(result["calibration"], out_path)
        if json_path is not None:
            atomic_write_json(json_path, figures)
    except (OSError, ValueError) as exc:
        raise OneLineError(f"output not written: {exc}") from None
    click.echo(f"wrote {out_path}")
    if not figures["passed"]:
        raise SystemExit(1)


def _variant(spec: str, robot_path: Path | None):
    from calibration.robot_description import load_robot_description
    from hil_sim.world.robot_variant import resolve_variant

    return resolve_variant(spec, load_robot_description(robot_path))


def _quality_problems(result: dict) -> list[str]:
    """The project's own quality targets (they need no truth): RMS and view counts."""
    from calibration.extrinsics import extrinsics_quality_problems
    from calibration.intrinsics import intrinsics_quality_problems

    return intrinsics_quality_problems(result["intrinsics"]) + extrinsics_quality_problems(result["extrinsics"])


__all__ = ["calibrate_hil_command", "run_calibrate_hil", "recovery_figures", "recovery_table", "fixture_board_poses",
           "calibrate_on_fixture", "FIXTURE_STATIONS", "TARGETS"]
