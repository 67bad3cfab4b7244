"""`dct calibrate`: camera intrinsics, lidar-camera extrinsics, projection overlay, report.

Sub-commands from other packages (e.g. `hil-check` from hil_sim) come from the entry point group
"dct.calibrate" and are imported only when invoked; this module never imports hil_sim or runtime.
Heavy libraries (cv2) are imported inside the commands.
"""
from __future__ import annotations

import json
from importlib.metadata import entry_points
from pathlib import Path

import click

from calibration.errors import ConfigFileError


def _plugin_entry_points() -> dict:
    return {ep.name: ep for ep in entry_points(group="dct.calibrate")}


class LazyCalibrateGroup(click.Group):
    """Built-in sub-commands plus lazily loaded ones from the "dct.calibrate" entry points."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(set(super().list_commands(ctx)) | set(_plugin_entry_points()))

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        cmd = super().get_command(ctx, name)
        if cmd is not None:
            return cmd
        ep = _plugin_entry_points().get(name)
        if ep is None:
            return None
        try:
            return ep.load()
        except ImportError as exc:
            @click.command(name=name, help=f"(unavailable: {exc})")
            def unavailable() -> None:
                raise click.ClickException(f"calibrate command '{name}' cannot be loaded: {exc}")

            return unavailable


def _pattern(ctx, param, value: str) -> tuple[int, int]:
    from calibration.intrinsics import parse_pattern

    try:
        return parse_pattern(value)
    except ValueError as exc:
        raise click.BadParameter(str(exc)) from None


def _load_cal(path: Path):
    from calibration.calibration_file import load_calibration

    try:
        return load_calibration(path)
    except ConfigFileError as exc:
        raise click.ClickException(str(exc)) from None


@click.group(name="calibrate", cls=LazyCalibrateGroup)
def calibrate_group() -> None:
    """Camera intrinsics, lidar-camera extrinsics, projection checks, calibration reports."""


@calibrate_group.command("intrinsics")
@click.argument("folder", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--pattern", default="9x6", show_default=True, callback=_pattern, help="inner corners, COLSxROWS")
@click.option("--square-m", type=float, default=0.025, show_default=True, help="square side in metres")
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), required=True, help="calibration YAML")
@click.option("--robot", default="limo", show_default=True)
def intrinsics_cmd(folder: Path, pattern, square_m: float, out: Path, robot: str) -> None:
    """Calibrate K and distortion from checkerboard images in FOLDER; write a calibration file."""
    from calibration.calibration_file import make_calibration, save_calibration
    from calibration.intrinsics import CalibrationError, calibrate_intrinsics, load_images

    try:
        res = calibrate_intrinsics(load_images(folder), pattern, square_m)
    except (CalibrationError, ValueError) as exc:
        raise click.ClickException(str(exc)) from None
    cal = make_calibration(
        robot, res.K, res.dist, res.width_px, res.height_px, None,
        method=f"checkerboard {pattern[0]}x{pattern[1]} inner corners, {square_m} m squares; cv2.calibrateCamera",
        intrinsics_rms_px=res.rms_px, per_image_rms_px=res.per_image_rms_px, n_images=len(res.per_image_rms_px),
    )
    save_calibration(cal, out)
    click.echo(f"RMS reprojection error {res.rms_px:.3f} px over {len(res.per_image_rms_px)} images -> {out}")
    for name, why in res.rejected.items():
        click.echo(f"  rejected {name}: {why}")


@calibrate_group.command("extrinsics")
@click.argument("folder", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--calibration", "cal_path", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              required=True, help="calibration YAML with the intrinsics (updated in place unless --out)")
@click.option("--pattern", default="9x6", show_default=True, callback=_pattern)
@click.option("--square-m", type=float, default=0.025, show_default=True)
@click.option("--border-m", type=float, default=0.0, show_default=True, help="white margin around the squares")
@click.option("--robot-description", type=click.Path(exists=True, dir_okay=False, path_type=Path), default=None,
              help="for the initial guess of T_camera<-lidar (default: the shipped LIMO description)")
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), default=None)
def extrinsics_cmd(folder: Path, cal_path: Path, pattern, square_m: float, border_m: float,
                   robot_description: Path | None, out: Path | None) -> None:
    """Lidar-camera extrinsic from board views: FOLDER holds NAME.png (or .jpg) + NAME.pcd (or .ply) pairs."""
    import numpy as np

    from calibration.calibration_file import RigidTransform, save_calibration
    from calibration.extrinsics import BoardGeometry, BoardObservation, calibrate_lidar_camera, segment_board
    from calibration.intrinsics import CalibrationError, board_pose_in_camera, detect_board, load_images
    from calibration.pointcloud_io import PointCloudFormatError, load_point_cloud
    from calibration.robot_description import load_robot_description

    cal = _load_cal(cal_path)
    K, dist = cal.camera.K(), np.array(cal.camera.distortion)
    if cal.lidar_to_camera is not None:
        T_guess = cal.T_cam_lidar()
    else:
        try:
            desc = load_robot_description(robot_description)
        except ConfigFileError as exc:
            raise click.ClickException(str(exc)) from None
        T_guess = np.linalg.inv(desc.sensors.camera.mount.transform()) @ desc.sensors.lidar.mount.transform()
    board = BoardGeometry(pattern, square_m, border_m)
    observations = []
    try:
        images = load_images(folder)
    except ValueError as exc:
        raise click.ClickException(str(exc)) from None
    for name, img in images.items():
        stem = Path(name).stem
        scan = next((folder / f"{stem}{s}" for s in (".pcd", ".ply") if (folder / f"{stem}{s}").exists()), None)
        if scan is None:
            click.echo(f"  skipped {name}: no {stem}.pcd or {stem}.ply")
            continue
        det = detect_board(img, pattern)
        if det is None:
            click.echo(f"  skipped {name}: checkerboard not found")
            continue
        try:
            T_cb, rms = board_pose_in_camera(det.corners_px, pattern, square_m, K, dist)
            pts = segment_board(load_point_cloud(scan).xyz, board, T_cb, T_guess)
        except (CalibrationError, PointCloudFormatError) as exc:
            click.echo(f"  skipped {name}: {exc}")
            continue
        observations.append(BoardObservation(T_cb, pts, stem))
    try:
        res = calibrate_lidar_camera(observations, board)
    except CalibrationError as exc:
        raise click.ClickException(str(exc)) from None
    cal.lidar_to_camera = RigidTransform.from_matrix(res.T_cam_lidar)
    cal.provenance.extrinsic_rms_m = res.rms_point_to_plane_m
    cal.provenance.n_board_poses = len(observations)
    cal.provenance.method += f"; lidar-camera board planes ({len(observations)} poses, point-to-plane)"
    save_calibration(cal, out or cal_path)
    click.echo(f"T_camera<-lidar from {len(observations)} poses, {res.n_points} board points, "
               f"point-to-plane RMS {res.rms_point_to_plane_m * 100:.2f} cm -> {out or cal_path}")


@calibrate_group.command("import-opencalib")
@click.argument("intrinsic_json", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.argument("extrinsic_json", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--width", type=int, required=True)
@click.option("--height", type=int, required=True)
@click.option("--robot", default="opencalib", show_default=True)
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), required=True)
def import_opencalib_cmd(intrinsic_json: Path, extrinsic_json: Path, width: int, height: int, robot: str, out: Path) -> None:
    """Convert OpenCalib camera-intrinsic + lidar-to-camera JSON files into a calibration YAML."""
    from calibration.calibration_file import calibration_from_opencalib, save_calibration

    try:
        cal = calibration_from_opencalib(intrinsic_json, extrinsic_json, width, height, robot)
    except ConfigFileError as exc:
        raise click.ClickException(str(exc)) from None
    save_calibration(cal, out)
    click.echo(f"wrote {out}")


@calibrate_group.command("project")
@click.argument("scan", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.argument("image", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--calibration", "cal_path", type=click.Path(exists=True, dir_okay=False, path_type=Path), required=True)
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), required=True, help="overlay PNG")
@click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path), default=None)
def project_cmd(scan: Path, image: Path, cal_path: Path, out: Path, json_path: Path | None) -> None:
    """Project SCAN into IMAGE; write an overlay (colour = depth) and stats."""
    import cv2
    import numpy as np

    from calibration.extrinsics import edge_alignment_score, image_edge_map
    from calibration.pointcloud_io import PointCloudFormatError, load_point_cloud

    cal = _load_cal(cal_path)
    cam = cal.camera_model()
    try:
        cloud = load_point_cloud(scan)
        T = cal.T_cam_lidar()
    except (PointCloudFormatError, ConfigFileError) as exc:
        raise click.ClickException(str(exc)) from None
    img = cv2.imread(str(image), cv2.IMREAD_COLOR)
    if img is None:
        raise click.ClickException(f"{image}: cannot be read as an image")
    if img.shape[:2] != (cam.height_px, cam.width_px):
        raise click.ClickException(f"{image}: size {img.shape[1]}x{img.shape[0]} differs from the calibration's "
                                   f"{cam.width_px}x{cam.height_px}")
    pts = cloud.xyz
    uv, valid, z = cam.depths_and_project_lidar(pts, T)
    overlay = img.copy()
    zs = z[valid]
    levels = np.clip(255 * np.log(np.maximum(zs, 1e-3) / 1.0) / np.log(100.0), 0, 255).astype(np.uint8)
    colours = cv2.applyColorMap(levels.reshape(-1, 1), cv2.COLORMAP_JET).reshape(-1, 3)
    for (u, v), c in zip(np.round(uv[valid]).astype(int), colours):
        cv2.circle(overlay, (int(u), int(v)), 2, tuple(int(x) for x in c), -1)
    cv2.imwrite(str(out), overlay)
    stats = {
        "points": int(len(pts)),
        "in_front": int(np.sum(z > 0)),
        "in_image": int(valid.sum()),
        "depth_m_median": float(np.median(zs)) if len(zs) else None,
        "edge_alignment_score": edge_alignment_score(cam, pts, T, image_edge_map(img)),
    }
    click.echo(json.dumps(stats, indent=2))
    if json_path:
        json_path.write_text(json.dumps(stats, indent=2))


@calibrate_group.command("report")
@click.argument("cal_path", metavar="CALFILE", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--images", type=click.Path(exists=True, file_okay=False, path_type=Path), default=None,
              help="recompute per-image reprojection errors on these checkerboard images")
@click.option("--pattern", default="9x6", show_default=True, callback=_pattern)
@click.option("--square-m", type=float, default=0.025, show_default=True)
def report_cmd(cal_path: Path, images: Path | None, pattern, square_m: float) -> None:
    """Print a calibration file's values and reprojection errors (stored, or recomputed on --images)."""
    import numpy as np

    cal = _load_cal(cal_path)
    c = cal.camera
    click.echo(f"robot {cal.robot}: {c.width_px}x{c.height_px}, fx {c.fx:.2f} fy {c.fy:.2f} "
               f"cx {c.cx:.2f} cy {c.cy:.2f}, distortion {np.round(c.distortion, 5).tolist()}")
    if cal.lidar_to_camera is not None:
        click.echo(f"T_camera<-lidar:\n{np.array2string(cal.T_cam_lidar(), precision=4, suppress_small=True)}")
    else:
        click.echo("T_camera<-lidar: not calibrated")
    p = cal.provenance
    click.echo(f"provenance: {p.date.isoformat()} - {p.method}")
    if p.intrinsics_rms_px is not None:
        click.echo(f"intrinsics RMS reprojection error: {p.intrinsics_rms_px:.3f} px")
    for name, err in (p.per_image_rms_px or {}).items():
        click.echo(f"  {name}: {err:.3f} px")
    if p.extrinsic_rms_m is not None:
        click.echo(f"extrinsic point-to-plane RMS: {p.extrinsic_rms_m * 100:.2f} cm over {p.n_board_poses} poses")
    if images is not None:
        from calibration.intrinsics import board_pose_in_camera, detect_board, load_images

        K, dist = c.K(), np.array(c.distortion)
        errs = []
        for name, img in load_images(images).items():
            det = detect_board(img, pattern)
            if det is None:
                click.echo(f"  {name}: board not found")
                continue
            _, rms = board_pose_in_camera(det.corners_px, pattern, square_m, K, dist)
            errs.append(rms)
            click.echo(f"  {name}: {rms:.3f} px (solvePnP with the file's intrinsics)")
        if errs:
            click.echo(f"mean per-image RMS {np.mean(errs):.3f} px over {len(errs)} images")


__all__ = ["calibrate_group"]
