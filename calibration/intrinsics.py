"""Camera intrinsics from checkerboard images (OpenCV findChessboardCorners + calibrateCamera)."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")

#: Quality target of an intrinsic calibration: `dct calibrate intrinsics` does not write a
#: result that misses it unless --force is given. An RMS reprojection error under about
#: 0.5 px is a good checkerboard calibration, above 1 px a detection or model problem; fewer
#: than 8 views rarely constrain the distortion (OpenCV's guides ask for 10-20).
INTRINSICS_MAX_RMS_PX = 1.0
INTRINSICS_MIN_VIEWS = 8


class CalibrationError(RuntimeError):
    """A calibration could not be computed (too few usable views, degenerate data)."""


@dataclass
class BoardDetection:
    """Checkerboard inner corners found in one image (OpenCV order, (N,2) float pixels)."""

    corners_px: np.ndarray


@dataclass
class IntrinsicsResult:
    K: np.ndarray
    dist: np.ndarray
    width_px: int
    height_px: int
    rms_px: float
    per_image_rms_px: dict[str, float]
    rejected: dict[str, str]  # image name -> reason
    rvecs: dict[str, np.ndarray] = field(default_factory=dict)  # board pose in camera per used image
    tvecs: dict[str, np.ndarray] = field(default_factory=dict)


def parse_pattern(text: str) -> tuple[int, int]:
    """'9x6' -> (9, 6): inner corners per row and per column."""
    try:
        a, b = text.lower().split("x")
        cols, rows = int(a), int(b)
    except ValueError:
        raise ValueError(f"pattern must look like 9x6 (inner corners), got {text!r}") from None
    if cols < 2 or rows < 2:
        raise ValueError(f"pattern needs at least 2x2 inner corners, got {text!r}")
    return cols, rows


def board_object_points(pattern_size: tuple[int, int], square_m: float) -> np.ndarray:
    """(cols*rows, 3) corner coordinates in the board frame (z = 0), OpenCV's corner order."""
    cols, rows = pattern_size
    grid = np.zeros((rows * cols, 3), np.float64)
    grid[:, :2] = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * square_m
    return grid


def detect_board(image: np.ndarray, pattern_size: tuple[int, int]) -> BoardDetection | None:
    """Find the checkerboard's inner corners with sub-pixel refinement; None if not found."""
    import cv2

    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if gray.dtype != np.uint8:
        raise ValueError(f"images must be 8-bit, got {gray.dtype}")
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCorners(gray, pattern_size, flags=flags)
    if not found:
        return None
    # Refinement window: at most 5 px, and under half the smallest corner spacing so that a
    # foreshortened square's window never reaches a neighbouring corner or the board edge.
    c = corners.reshape(pattern_size[1], pattern_size[0], 2)
    spacing = min(np.linalg.norm(np.diff(c, axis=0), axis=2).min(), np.linalg.norm(np.diff(c, axis=1), axis=2).min())
    half = int(np.clip(np.floor(spacing * 0.4), 2, 5))
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4)
    corners = cv2.cornerSubPix(gray, corners, (half, half), (-1, -1), criteria)
    return BoardDetection(corners.reshape(-1, 2).astype(np.float64))


def load_images(folder: str | Path) -> dict[str, np.ndarray]:
    """All images in a folder (sorted by name), as BGR arrays; unreadable files raise ValueError."""
    import cv2

    folder = Path(folder)
    if not folder.is_dir():
        raise ValueError(f"{folder}: not a folder")
    out = {}
    for p in sorted(folder.iterdir()):
        if p.suffix.lower() in IMAGE_SUFFIXES:
            img = cv2.imread(str(p), cv2.IMREAD_COLOR)
            if img is None:
                raise ValueError(f"{p}: cannot be read as an image")
            out[p.name] = img
    if not out:
        raise ValueError(f"{folder}: no images ({', '.join(IMAGE_SUFFIXES)})")
    return out


def calibrate_intrinsics(
    images: Mapping[str, np.ndarray] | Sequence[np.ndarray],
    pattern_size: tuple[int, int],
    square_m: float,
    min_views: int = 5,
    max_view_rms_px: float = 2.0,
    outlier_factor: float = 5.0,
    fix_k3: bool = True,
) -> IntrinsicsResult:
    """Calibrate K and distortion (k1 k2 p1 p2 k3) from checkerboard views.

    Images where the board is not found, or whose reprojection RMS after a first calibration
    exceeds `max_view_rms_px` or `outlier_factor` x the median view RMS (a mis-detected corner),
    are rejected (with the reason) and the calibration is redone.
    """
    import cv2

    if not (np.isfinite(square_m) and square_m > 0):
        raise ValueError(f"square_m must be a positive length, got {square_m}")
    if not isinstance(images, Mapping):
        images = {f"image_{i:03d}": img for i, img in enumerate(images)}
    if not images:
        raise CalibrationError("no images given")
    (h, w), found, rejected = _find_boards(images, pattern_size)
    obj = board_object_points(pattern_size, square_m).astype(np.float32)
    views = _Views(obj, found, (w, h), cv2.CALIB_FIX_K3 if fix_k3 else 0, min_views, rejected)
    names = list(found)
    rms, K, dist, rvecs, tvecs, per = views.calibrate(names)
    limit = min(max_view_rms_px, outlier_factor * max(float(np.median(list(per.values()))), 0.1))
    bad = [n for n in names if per[n] > limit]
    if bad:
        for n in bad:
            rejected[n] = f"reprojection RMS {per[n]:.2f} px > {limit:.2f} px (outlier view)"
        names = [n for n in names if n not in bad]
        rms, K, dist, rvecs, tvecs, per = views.calibrate(names)
    return IntrinsicsResult(
        K=K, dist=dist.ravel(), width_px=w, height_px=h, rms_px=float(rms), per_image_rms_px=per, rejected=rejected,
        rvecs={n: r.ravel() for n, r in zip(names, rvecs)}, tvecs={n: t.ravel() for n, t in zip(names, tvecs)},
    )


def _find_boards(images: Mapping[str, np.ndarray], pattern_size: tuple[int, int]):
    """((h, w) of the first image, {name: board corners (float32)}, {name: why rejected}): the
    views of another size or without the board are rejected."""
    sizes = {name: img.shape[:2] for name, img in images.items()}
    h, w = next(iter(sizes.values()))
    rejected: dict[str, str] = {}
    found: dict[str, np.ndarray] = {}
    for name, img in images.items():
        if sizes[name] != (h, w):
            rejected[name] = f"image size {sizes[name][1]}x{sizes[name][0]} differs from {w}x{h}"
            continue
        det = detect_board(img, pattern_size)
        if det is None:
            rejected[name] = f"checkerboard {pattern_size[0]}x{pattern_size[1]} not found"
            continue
        found[name] = det.corners_px.astype(np.float32)
    return (h, w), found, rejected


@dataclass
class _Views:
    """The board views found, calibrated together by cv2.calibrateCamera."""

    obj: np.ndarray  # the board's corner points (N, 3) float32
    found: dict[str, np.ndarray]  # name -> detected corners
    size_wh: tuple[int, int]
    flags: int
    min_views: int
    rejected: dict[str, str]  # named in the error when too few views are left

    def calibrate(self, names: list[str]):
        """(rms, K, dist, rvecs, tvecs, {name: per-view RMS px}) over the views `names`."""
        import cv2

        obj, found = self.obj, self.found
        if len(names) < self.min_views:
            raise CalibrationError(
                f"only {len(names)} usable views (need {self.min_views}); rejected: {self.rejected or 'none'}"
            )
        rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(
            [obj] * len(names), [found[n] for n in names], self.size_wh, None, None, flags=self.flags
        )
        per = {}
        for n, rv, tv in zip(names, rvecs, tvecs):
            proj, _ = cv2.projectPoints(obj, rv, tv, K, dist)
            per[n] = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - found[n]) ** 2, axis=1))))
        return rms, K, dist, rvecs, tvecs, per


def intrinsics_quality_problems(
    res: IntrinsicsResult, max_rms_px: float | None = None, min_views: int | None = None
) -> list[str]:
    """Why `res` misses the quality target (INTRINSICS_MAX_RMS_PX, INTRINSICS_MIN_VIEWS); [] when it meets it."""
    max_rms_px = INTRINSICS_MAX_RMS_PX if max_rms_px is None else max_rms_px
    min_views = INTRINSICS_MIN_VIEWS if min_views is None else min_views
    problems = []
    if not np.isfinite(res.rms_px) or res.rms_px > max_rms_px:
        problems.append(f"RMS reprojection error {res.rms_px:.3f} px > {max_rms_px} px")
    n_views = len(res.per_image_rms_px)
    if n_views < min_views:
        problems.append(f"{n_views} usable views < {min_views}")
    return problems


def board_pose_in_camera(
    corners_px: np.ndarray, pattern_size: tuple[int, int], square_m: float, K: np.ndarray, dist: np.ndarray
) -> tuple[np.ndarray, float]:
    """solvePnP: 4x4 T_camera<-board from detected corners, and the reprojection RMS in pixels."""
    import cv2

    obj = board_object_points(pattern_size, square_m)
    img = np.asarray(corners_px, dtype=np.float64).reshape(-1, 1, 2)
    ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise CalibrationError("solvePnP failed for a board view")
    proj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
    rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img.reshape(-1, 2)) ** 2, axis=1))))
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec.ravel()
    return T, rms


__all__ = ["IntrinsicsResult", "BoardDetection", "CalibrationError", "calibrate_intrinsics", "detect_board",
           "intrinsics_quality_problems", "INTRINSICS_MAX_RMS_PX", "INTRINSICS_MIN_VIEWS",
           "board_object_points", "board_pose_in_camera", "load_images", "parse_pattern"]
