"""`dct calibrate`: camera intrinsics, lidar-camera extrinsics, projection overlay, report.

Sub-commands from other packages (`hil-check` from hil_sim, `wheels` from runtime.odometry: it reads
a recorded run) come from the entry point group "dct.calibrate" and are imported only when invoked;
this module never imports hil_sim or runtime.
Heavy libraries (cv2) are imported inside the commands.

Rules every sub-command follows:

* An input error (missing folder, no images, an unreadable image, a bad YAML file, an empty or
  malformed point cloud, a bad option) is ONE line on stderr ("Error: ...") and a non-zero exit
  (2 for a usage error, 1 otherwise), never a traceback.
* Outputs: the path is checked before the work (`calibration.outputs.check_output_path`: its
  folder exists and is writable, it is not one of the command's inputs, not a shipped artifact)
  and the file is written atomically, only after the command succeeded.
* A calibration that misses its quality target (see `calibration.intrinsics.INTRINSICS_*` and
  `calibration.extrinsics.EXTRINSIC_*`) is not written unless --force is given: the command
  prints the figures and exits 1.
"""
from __future__ import annotations

import math
from pathlib import Path

import click

from calibration.cli_support import LazyGroup, OneLineError, OneLineGroup, checked_output
from calibration.errors import ConfigFileError
from calibration.extrinsics import EXTRINSIC_MAX_RMS_M, EXTRINSIC_MIN_POSES
from calibration.intrinsics import INTRINSICS_MAX_RMS_PX, INTRINSICS_MIN_VIEWS


class _CalibrateGroup(OneLineGroup, LazyGroup):
    """Built-in sub-commands plus lazily loaded ones from the "dct.calibrate" entry points."""

    entry_point_group = "dct.calibrate"
    unavailable_what = "calibrate command"


# ---------------------------------------------------------------------------- option checks
def _pattern(ctx, param, value: str) -> tuple[int, int]:
    from calibration.intrinsics import parse_pattern

    try:
        return parse_pattern(value)
    except ValueError as exc:
        raise click.BadParameter(str(exc)) from None


def _positive_length(ctx, param, value: float) -> float:
    if not (math.isfinite(value) and value > 0):
        raise click.BadParameter(f"must be a positive length in metres, got {value}")
    return value


def _non_negative_length(ctx, param, value: float) -> float:
    if not (math.isfinite(value) and value >= 0):
        raise click.BadParameter(f"must be a length >= 0 in metres, got {value}")
    return value


def _load_cal(path: Path):
    from calibration.calibration_file import load_calibration

    try:
        return load_calibration(path)
    except ConfigFileError as exc:
        raise OneLineError(str(exc)) from None


def _load_images(folder: Path) -> dict:
    from calibration.intrinsics import load_images

    try:
        return load_images(folder)
    except ValueError as exc:
        raise OneLineError(str(exc)) from None


def _image_files(folder: Path) -> list[Path]:
    from calibration.intrinsics import IMAGE_SUFFIXES

    return [p for p in sorted(folder.iterdir()) if p.suffix.lower() in IMAGE_SUFFIXES]


def _check_image_size(name: str, img, cal) -> None:
    h, w = img.shape[:2]
    if (w, h) != (cal.camera.width_px, cal.camera.height_px):
        raise OneLineError(f"{name}: image is {w}x{h}, the calibration's intrinsics are for "
                           f"{cal.camera.width_px}x{cal.camera.height_px}")


def _quality_refused(what: str, problems: list[str], out: Path) -> OneLineError:
    return OneLineError(f"{what} miss the quality target: {'; '.join(problems)}; {out} not written "
                        f"(pass --force to write it anyway)")


def _save(cal, out: Path) -> None:
    from calibration.calibration_file import save_calibration

    try:
        save_calibration(cal, out)
    except (ConfigFileError, OSError) as exc:
        raise OneLineError(f"{out}: not written: {exc}") from None


@click.group(name="calibrate", cls=_CalibrateGroup)
def calibrate_group() -> None:
    """Camera intrinsics, lidar-camera extrinsics, projection checks, calibration reports."""


# ---------------------------------------------------------------------------- intrinsics
def _existing_calibration(out: Path, robot: str | None):
    """The calibration already at --out (None if there is none); refuses a file that is not one."""
    from calibration.calibration_file import load_calibration

    if not out.exists():
        return None
    try:
        existing = load_calibration(out)
    except ConfigFileError as exc:
        raise OneLineError(f"--out {out} exists and is not a valid calibration file, so it is left alone: {exc}; "
                           f"choose another --out") from None
    if robot is not None and existing.robot != robot:
        raise OneLineError(f"--out {out} is the calibration of robot '{existing.robot}', not '{robot}'; "
                           f"choose another --out")
    return existing


INTRINSICS_HELP = f"""Calibrate K and distortion from checkerboard images in FOLDER; write a calibration file.

If --out already holds a calibration file, the new intrinsics are merged into it: its
lidar_to_camera extrinsic and that extrinsic's provenance are kept (the output line says
so). A file at --out that is not a valid calibration is never overwritten.

Quality target: RMS reprojection error at most {INTRINSICS_MAX_RMS_PX} px over at least
{INTRINSICS_MIN_VIEWS} usable views. A result that misses it is printed, not written, and
the command exits 1, unless --force is given.
"""


@calibrate_group.command("intrinsics", help=INTRINSICS_HELP)
@click.argument("folder", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--pattern", default="9x6", show_default=True, callback=_pattern, help="inner corners, COLSxROWS")
@click.option("--square-m", type=float, default=0.025, show_default=True, callback=_positive_length,
              help="square side in metres")
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), required=True,
              help="calibration YAML; an existing calibration file keeps its lidar_to_camera extrinsic")
@click.option("--robot", default=None, help="robot name stored in the file [default: the --out file's, else limo]")
@click.option("--force", is_flag=True,
              help="write even if the quality target is missed (see above)")
def intrinsics_cmd(*, folder: Path, pattern, square_m: float, out: Path, robot: str | None, force: bool) -> None:
    """See INTRINSICS_HELP."""
    from calibration.calibration_file import make_calibration
    from calibration.intrinsics import CalibrationError, calibrate_intrinsics, intrinsics_quality_problems

    checked_output(out, "calibration file", inputs=_image_files(folder))
    existing = _existing_calibration(out, robot)
    robot = robot or (existing.robot if existing is not None else "limo")
    images = _load_images(folder)
    try:
        res = calibrate_intrinsics(images, pattern, square_m)
    except (CalibrationError, ValueError) as exc:
        raise OneLineError(f"{folder}: {exc}") from None
    n_views = len(res.per_image_rms_px)
    click.echo(f"RMS reprojection error {res.rms_px:.3f} px over {n_views} images")
    for name, why in res.rejected.items():
        click.echo(f"  rejected {name}: {why}")
    problems = intrinsics_quality_problems(res)
    if problems and not force:
        raise _quality_refused("intrinsics", problems, out)
    method = f"checkerboard {pattern[0]}x{pattern[1]} inner corners, {square_m} m squares; cv2.calibrateCamera"
    kept = existing is not None and existing.lidar_to_camera is not None
    extra = {}
    if kept:
        method += f"; lidar_to_camera kept from the previous file ({existing.provenance.date.isoformat()})"
        extra = {"extrinsic_rms_m": existing.provenance.extrinsic_rms_m,
                 "n_board_poses": existing.provenance.n_board_poses}
    try:
        cal = make_calibration(robot, res.K, res.dist, res.width_px, res.height_px, None, method=method,
                               intrinsics_rms_px=res.rms_px, per_image_rms_px=res.per_image_rms_px,
                               n_images=n_views, **extra)
    except ConfigFileError as exc:
        raise OneLineError(f"{folder}: the intrinsics found are not usable: {exc}") from None
    if kept:
        cal.lidar_to_camera = existing.lidar_to_camera
    _save(cal, out)
    note = f" (kept the lidar_to_camera extrinsic already in {out})" if kept else ""
    forced = f" (quality target missed, written because of --force: {'; '.join(problems)})" if problems else ""
    click.echo(f"intrinsics -> {out}{note}{forced}")


# ---------------------------------------------------------------------------- extrinsics
def _load_scans(folder: Path, names: list[str]) -> dict:
    """{image name: (M,3) finite lidar points} for the images that have a NAME.pcd / NAME.ply next to them."""
    from calibration.pointcloud_io import PointCloudFormatError, finite_xyz, load_point_cloud

    scans = {}
    for name in names:
        stem = Path(name).stem
        scan = next((folder / f"{stem}{s}" for s in (".pcd", ".ply") if (folder / f"{stem}{s}").exists()), None)
        if scan is None:
            click.echo(f"  skipped {name}: no {stem}.pcd or {stem}.ply")
            continue
        try:
            scans[name] = finite_xyz(load_point_cloud(scan), str(scan))
        except PointCloudFormatError as exc:
            raise OneLineError(str(exc)) from None
    return scans


EXTRINSICS_HELP = f"""Lidar-camera extrinsic from board views: FOLDER holds NAME.png (or .jpg) + NAME.pcd (or .ply) pairs.

The input calibration file is never modified: the result (its intrinsics plus the new
lidar_to_camera) goes to --out, which must be another file. A scan that cannot be read, or
has no finite point, is an error; a view whose board is not found is skipped.

Quality target: point-to-plane RMS of the board points at most {EXTRINSIC_MAX_RMS_M * 100:g} cm
over at least {EXTRINSIC_MIN_POSES} board poses. A result that misses it is printed, not
written, and the command exits 1, unless --force is given.
"""


@calibrate_group.command("extrinsics", help=EXTRINSICS_HELP)
@click.argument("folder", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--calibration", "cal_path", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              required=True, help="calibration YAML with the intrinsics (read only)")
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), required=True,
              help="calibration YAML to write (the intrinsics plus the new extrinsic); not --calibration")
@click.option("--pattern", default="9x6", show_default=True, callback=_pattern)
@click.option("--square-m", type=float, default=0.025, show_default=True, callback=_positive_length)
@click.option("--border-m", type=float, default=0.0, show_default=True, callback=_non_negative_length,
              help="white margin around the squares")
@click.option("--robot-description", type=click.Path(exists=True, dir_okay=False, path_type=Path), default=None,
              help="for the initial guess of T_camera<-lidar (default: the shipped LIMO description)")
@click.option("--force", is_flag=True,
              help="write even if the quality target is missed (see above)")
def extrinsics_cmd(*, folder: Path, cal_path: Path, out: Path, pattern, square_m: float, border_m: float,
                   robot_description: Path | None, force: bool) -> None:
    """See EXTRINSICS_HELP."""
    import numpy as np
    from pydantic import ValidationError

    from calibration.calibration_file import RigidTransform
    from calibration.errors import format_validation_error
    from calibration.extrinsics import BoardGeometry, calibrate_lidar_camera, extrinsics_quality_problems
    from calibration.intrinsics import CalibrationError

    checked_output(out, "calibration file", inputs=[cal_path, robot_description, *folder.iterdir()])
    cal = _load_cal(cal_path)
    T_guess = _initial_extrinsic(cal, robot_description)
    board = BoardGeometry(pattern, square_m, border_m)
    images = _load_images(folder)
    for name, img in images.items():
        _check_image_size(str(folder / name), img, cal)
    scans = _load_scans(folder, list(images))
    K, dist = cal.camera.K(), np.array(cal.camera.distortion)
    observations = _board_observations(images, scans, board, K, dist, T_guess)
    try:
        res = calibrate_lidar_camera(observations, board)
    except CalibrationError as exc:
        raise OneLineError(f"{folder}: {exc}") from None
    n_poses = len(res.per_pose_rms_m)
    click.echo(f"T_camera<-lidar from {n_poses} poses, {res.n_points} board points, "
               f"point-to-plane RMS {res.rms_point_to_plane_m * 100:.2f} cm")
    problems = extrinsics_quality_problems(res)
    if problems and not force:
        raise _quality_refused("extrinsics", problems, out)
    try:
        cal.lidar_to_camera = RigidTransform.from_matrix(res.T_cam_lidar)
    except ValidationError as exc:
        raise OneLineError(f"{folder}: the extrinsic found is implausible: {format_validation_error(exc)}") from None
    cal.provenance.extrinsic_rms_m = res.rms_point_to_plane_m
    cal.provenance.n_board_poses = n_poses
    cal.provenance.method += f"; lidar-camera board planes ({n_poses} poses, point-to-plane)"
    _save(cal, out)
    forced = f" (quality target missed, written because of --force: {'; '.join(problems)})" if problems else ""
    click.echo(f"extrinsic -> {out}{forced}")


def _initial_extrinsic(cal, robot_description: Path | None):
    """The first guess of T_camera<-lidar: the calibration's own, else the robot description's mounts."""
    import numpy as np

    from calibration.robot_description import load_robot_description

    if cal.lidar_to_camera is not None:
        return cal.T_cam_lidar()
    try:
        desc = load_robot_description(robot_description)
    except ConfigFileError as exc:
        raise OneLineError(str(exc)) from None
    return np.linalg.inv(desc.sensors.camera.mount.transform()) @ desc.sensors.lidar.mount.transform()


def _board_observations(images: dict, scans: dict, board, K, dist, T_guess) -> list:
    """One BoardObservation per view whose board is found in the image and segmented in the scan;
    the other views are skipped, each with a line saying why."""
    from calibration.extrinsics import BoardObservation, segment_board
    from calibration.intrinsics import CalibrationError, board_pose_in_camera, detect_board

    pattern, square_m = board.pattern_size, board.square_m
    observations = []
    for name, pts_all in scans.items():
        det = detect_board(images[name], pattern)
        if det is None:
            click.echo(f"  skipped {name}: checkerboard not found")
            continue
        try:
            T_cb, _ = board_pose_in_camera(det.corners_px, pattern, square_m, K, dist)
            pts = segment_board(pts_all, board, T_cb, T_guess)
        except CalibrationError as exc:
            click.echo(f"  skipped {name}: {exc}")
            continue
        observations.append(BoardObservation(T_cb, pts, Path(name).stem))
    return observations


# ---------------------------------------------------------------------------- import, project, report
@calibrate_group.command("import-opencalib")
@click.argument("intrinsic_json", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.argument("extrinsic_json", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--width", type=click.IntRange(1, 16384), required=True)
@click.option("--height", type=click.IntRange(1, 16384), required=True)
@click.option("--robot", default="opencalib", show_default=True)
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), required=True)
def import_opencalib_cmd(*, intrinsic_json: Path, extrinsic_json: Path, width: int, height: int, robot: str,
                         out: Path) -> None:
    """Convert OpenCalib camera-intrinsic + lidar-to-camera JSON files into a calibration YAML."""
    from calibration.calibration_file import calibration_from_opencalib

    checked_output(out, "calibration file", inputs=[intrinsic_json, extrinsic_json])
    try:
        cal = calibration_from_opencalib(intrinsic_json, extrinsic_json, width, height, robot)
    except ConfigFileError as exc:
        raise OneLineError(str(exc)) from None
    _save(cal, out)
    click.echo(f"wrote {out}")


@calibrate_group.command("project")
@click.argument("scan", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.argument("image", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--calibration", "cal_path", type=click.Path(exists=True, dir_okay=False, path_type=Path), required=True)
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), required=True,
              help="overlay image (.png, .jpg, ...)")
@click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path), default=None)
def project_cmd(*, scan: Path, image: Path, cal_path: Path, out: Path, json_path: Path | None) -> None:
    """Project SCAN into IMAGE; write an overlay (colour = depth) and stats."""
    import json

    import cv2
    import numpy as np

    from calibration.extrinsics import edge_alignment_score, image_edge_map
    from calibration.outputs import atomic_write_bytes, atomic_write_json
    from calibration.pointcloud_io import PointCloudFormatError, finite_xyz, load_point_cloud

    inputs = [scan, image, cal_path]
    checked_output(out, "overlay image", inputs=inputs)
    if not cv2.haveImageWriter(str(out)):
        raise OneLineError(f"overlay image {out}: no image format for suffix {out.suffix!r} (use .png or .jpg)")
    if json_path is not None:
        checked_output(json_path, "JSON output", inputs=[*inputs, out])
    cal = _load_cal(cal_path)
    cam = cal.camera_model()
    try:
        T = cal.T_cam_lidar()
        pts = finite_xyz(load_point_cloud(scan), str(scan))
    except ConfigFileError as exc:
        raise OneLineError(f"calibration file {cal_path}: {exc}") from None
    except PointCloudFormatError as exc:
        raise OneLineError(str(exc)) from None
    img = cv2.imread(str(image), cv2.IMREAD_COLOR)
    if img is None:
        raise OneLineError(f"{image}: cannot be read as an image")
    _check_image_size(str(image), img, cal)
    uv, valid, z = cam.depths_and_project_lidar(pts, T)
    overlay = img.copy()
    zs = z[valid]
    levels = np.clip(255 * np.log(np.maximum(zs, 1e-3) / 1.0) / np.log(100.0), 0, 255).astype(np.uint8)
    colours = cv2.applyColorMap(levels.reshape(-1, 1), cv2.COLORMAP_JET).reshape(-1, 3)
    for (u, v), c in zip(np.round(uv[valid]).astype(int), colours):
        cv2.circle(overlay, (int(u), int(v)), 2, tuple(int(x) for x in c), -1)
    stats = {
        "points": int(len(pts)),
        "in_front": int(np.sum(z > 0)),
        "in_image": int(valid.sum()),
        "depth_m_median": float(np.median(zs)) if len(zs) else None,
        "edge_alignment_score": edge_alignment_score(cam, pts, T, image_edge_map(img)),
    }
    ok, encoded = cv2.imencode(out.suffix, overlay)
    if not ok:
        raise OneLineError(f"overlay image {out}: cannot be encoded as {out.suffix}")
    atomic_write_bytes(out, encoded.tobytes())
    click.echo(json.dumps(stats, indent=2))
    if json_path is not None:
        atomic_write_json(json_path, stats)


@calibrate_group.command("report")
@click.argument("cal_path", metavar="CALFILE", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--images", type=click.Path(exists=True, file_okay=False, path_type=Path), default=None,
              help="recompute per-image reprojection errors on these checkerboard images")
@click.option("--pattern", default="9x6", show_default=True, callback=_pattern)
@click.option("--square-m", type=float, default=0.025, show_default=True, callback=_positive_length)
def report_cmd(*, cal_path: Path, images: Path | None, pattern, square_m: float) -> None:
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
        _report_images(cal, images, pattern, square_m)


def _report_images(cal, folder: Path, pattern, square_m: float) -> None:
    import numpy as np

    from calibration.intrinsics import CalibrationError, board_pose_in_camera, detect_board

    K, dist = cal.camera.K(), np.array(cal.camera.distortion)
    loaded = _load_images(folder)
    for name, img in loaded.items():
        _check_image_size(str(folder / name), img, cal)
    errs = []
    for name, img in loaded.items():
        det = detect_board(img, pattern)
        if det is None:
            click.echo(f"  {name}: board not found")
            continue
        try:
            _, rms = board_pose_in_camera(det.corners_px, pattern, square_m, K, dist)
        except CalibrationError as exc:
            click.echo(f"  {name}: {exc}")
            continue
        errs.append(rms)
        click.echo(f"  {name}: {rms:.3f} px (solvePnP with the file's intrinsics)")
    if errs:
        click.echo(f"mean per-image RMS {np.mean(errs):.3f} px over {len(errs)} images")


__all__ = ["calibrate_group"]
