"""A simulated lens: a MuJoCo pinhole render turned into the image a distorting lens would make.

MuJoCo renders pinholes only. A camera with distortion (OpenCV's k1, k2, p1, p2, k3) is made in
two steps:

1. MuJoCo renders a pinhole *canvas* with the camera's focal lengths and a principal point
   moved by the canvas margins (`CameraLens.canvas_K`), large enough to hold every ray the
   distorted image sees (a barrel lens sees more than a pinhole of the same focal length);
2. `CameraLens.apply` resamples it (cv2.remap): the output pixel (u, v) takes the canvas pixel
   where the ray that the lens bends onto (u, v) meets the pinhole canvas. The map is the
   inverse of the lens model, found once with cv2.undistortPoints (iterated to convergence), so undistorting the
   output with the true K and distortion gives the pinhole image back.

A lens whose model folds over inside the image (the radial polynomial not increasing out to
the image's corners) is refused: no real lens makes that image, and projections beyond the
fold are ambiguous. A camera without distortion needs no resampling: the canvas is the image.

MuJoCo's intrinsic camera (sensor size, resolution, focal and principal point in pixels) puts
the principal point at (W - 1) / 2 - principal_pixel[0], (H - 1) / 2 - principal_pixel[1] in
OpenCV's pixel convention (measured with probe spheres; tests/hil_sim/sensors/test_camera_lens.py).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

#: Pixel pitch given to MuJoCo's intrinsic camera (m): only the ratio to the focal length in
#: pixels matters; a plausible value keeps the single-precision model fields well scaled.
SENSOR_PIXEL_PITCH_M = 3e-6
#: Extra canvas pixels beyond the rays the image needs, on each side (bilinear sampling's reach).
CANVAS_MARGIN_PX = 2
#: The undistortion must reproject onto its pixel within this (px); else the lens is refused.
MAX_INVERSE_RESIDUAL_PX = 1e-3
#: The image's rays must stay within this share of the lens model's monotone radius.
MONOTONE_SHARE = 0.95


class LensError(ValueError):
    """A lens the simulator cannot render (its model folds over inside the image)."""


@dataclass(frozen=True)
class CameraLens:
    """The true camera: K, distortion (OpenCV order), image size; and the canvas it is rendered from."""

    K: np.ndarray
    dist: np.ndarray
    width_px: int
    height_px: int
    #: Canvas margins (left, top, right, bottom) in pixels; zeros without distortion.
    margins_px: tuple[int, int, int, int] = (0, 0, 0, 0)
    #: (map_x, map_y) of cv2.remap (float32, canvas pixels), and each output pixel's nearest canvas
    #: pixel as a flat index (segmentation); None without distortion.
    _map: tuple[np.ndarray, np.ndarray, np.ndarray] | None = field(default=None, repr=False, compare=False)

    @classmethod
    def build(cls, K: np.ndarray, dist: np.ndarray, width_px: int, height_px: int) -> "CameraLens":
        """The lens and its resampling map (LensError naming the problem when it cannot be rendered)."""
        K = np.array(K, dtype=np.float64)
        dist = np.array(dist, dtype=np.float64).ravel()
        if K.shape != (3, 3) or not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0 or K[0, 1] != 0:
            raise LensError(f"K must be a finite 3x3 camera matrix without skew, got {K.tolist()}")
        if len(dist) not in (0, 5) or not np.isfinite(dist).all():
            raise LensError(f"distortion must be 5 finite coefficients (k1, k2, p1, p2, k3), got {dist.tolist()}")
        K.flags.writeable = False
        dist.flags.writeable = False
        if not np.any(dist):
            return cls(K, dist, int(width_px), int(height_px))
        pinhole = _pinhole_positions(K, dist, int(width_px), int(height_px))
        margins = _margins(pinhole, int(width_px), int(height_px))
        map_x = (pinhole[..., 0] + margins[0]).astype(np.float32)
        map_y = (pinhole[..., 1] + margins[1]).astype(np.float32)
        canvas_w = int(width_px) + margins[0] + margins[2]
        nearest = np.rint(map_y).astype(np.intp) * canvas_w + np.rint(map_x).astype(np.intp)
        return cls(K, dist, int(width_px), int(height_px), margins, (map_x, map_y, nearest))

    @property
    def distorted(self) -> bool:
        return self._map is not None

    @property
    def canvas_size(self) -> tuple[int, int]:
        """(width, height) MuJoCo renders."""
        left, top, right, bottom = self.margins_px
        return self.width_px + left + right, self.height_px + top + bottom

    @property
    def canvas_K(self) -> np.ndarray:
        """The pinhole K of the canvas: the true focal lengths, the principal point moved by the margins."""
        K = self.K.copy()
        K[0, 2] += self.margins_px[0]
        K[1, 2] += self.margins_px[1]
        return K

    def apply(self, canvas: np.ndarray) -> np.ndarray:
        """The image the lens makes from a pinhole canvas render (H x W x C, bilinear)."""
        if self._map is None:
            return canvas
        import cv2

        return cv2.remap(canvas, self._map[0], self._map[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    def apply_nearest(self, labels: np.ndarray) -> np.ndarray:
        """Per-pixel labels (segmentation ids) through the lens: the nearest canvas pixel's."""
        if self._map is None:
            return labels
        if labels.shape[:2] != self.canvas_size[::-1]:
            raise ValueError(f"labels of shape {labels.shape[:2]} are not the canvas's {self.canvas_size[::-1]}")
        return np.ascontiguousarray(labels).reshape(-1, *labels.shape[2:])[self._map[2]]


def check_lens(K: np.ndarray, dist: np.ndarray, width_px: int, height_px: int) -> None:
    """LensError unless the lens can be rendered: the rays of the image's border (where the
    normalized radius is largest) stay within the model's monotone part and invert exactly. Cheap:
    the border only."""
    h, w = int(height_px), int(width_px)
    u, v = np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64)
    border = np.concatenate([np.stack([u, np.zeros(w)], 1), np.stack([u, np.full(w, h - 1.0)], 1),
                             np.stack([np.zeros(h), v], 1), np.stack([np.full(h, w - 1.0), v], 1)])
    _normalized(np.asarray(K, dtype=np.float64), np.asarray(dist, dtype=np.float64), border)


def _normalized(K: np.ndarray, dist: np.ndarray, pix: np.ndarray) -> np.ndarray:
    """(N, 2) normalized undistorted coordinates of (N, 2) pixels; LensError when the lens folds over
    within them or the inverse does not reproject onto them."""
    import cv2

    from calibration.lens import max_monotone_radius

    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    norm = cv2.undistortPoints(pix.reshape(-1, 1, 2), K, dist, None, None, None, criteria).reshape(-1, 2)
    r_image = float(np.sqrt((norm ** 2).sum(axis=1)).max())
    r_fold = max_monotone_radius(dist)
    if not r_image < MONOTONE_SHARE * r_fold:
        raise LensError(f"the lens model folds over inside the image: the image reaches a normalized radius "
                        f"{r_image:.3f}, the distortion {dist.tolist()} increases only up to {r_fold:.3f}")
    some = slice(None, None, max(1, len(norm) // 20000))  # a spread sample: the inverse is smooth
    back, _ = cv2.projectPoints(np.concatenate([norm[some], np.ones((len(norm[some]), 1))], axis=1), np.zeros(3),
                                np.zeros(3), K, dist)
    residual = float(np.abs(back.reshape(-1, 2) - pix[some]).max())
    if not residual < MAX_INVERSE_RESIDUAL_PX:
        raise LensError(f"the distortion {dist.tolist()} cannot be inverted over the image (residual "
                        f"{residual:.2g} px)")
    return norm


def _pinhole_positions(K: np.ndarray, dist: np.ndarray, w: int, h: int) -> np.ndarray:
    """(h, w, 2): where each output pixel's ray meets a pinhole image with the same K (LensError
    when the lens folds over inside the image or the inverse does not converge)."""
    check_lens(K, dist, w, h)  # fails fast, before the whole image
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
    norm = _normalized(K, dist, np.stack([uu.ravel(), vv.ravel()], axis=1))
    pin = norm @ K[:2, :2].T + K[:2, 2]
    return pin.reshape(h, w, 2)


def _margins(pinhole: np.ndarray, w: int, h: int) -> tuple[int, int, int, int]:
    """Canvas margins (left, top, right, bottom) holding every pinhole position, plus CANVAS_MARGIN_PX."""
    u, v = pinhole[..., 0], pinhole[..., 1]
    left = max(0, math.ceil(-float(u.min()))) + CANVAS_MARGIN_PX
    top = max(0, math.ceil(-float(v.min()))) + CANVAS_MARGIN_PX
    right = max(0, math.ceil(float(u.max()) - (w - 1))) + CANVAS_MARGIN_PX
    bottom = max(0, math.ceil(float(v.max()) - (h - 1))) + CANVAS_MARGIN_PX
    return left, top, right, bottom


def set_intrinsic_camera(camera, K: np.ndarray, width_px: int, height_px: int) -> None:
    """Make an MjSpec camera render the pinhole K at width x height (focal lengths and principal
    point in pixels; fovy is then ignored)."""
    K = np.asarray(K, dtype=np.float64)
    camera.resolution = [int(width_px), int(height_px)]
    camera.sensor_size = [width_px * SENSOR_PIXEL_PITCH_M, height_px * SENSOR_PIXEL_PITCH_M]
    camera.focal_pixel = [float(K[0, 0]), float(K[1, 1])]
    camera.principal_pixel = [(width_px - 1) / 2 - float(K[0, 2]), (height_px - 1) / 2 - float(K[1, 2])]


def intrinsic_camera_K(model, camera_id: int) -> tuple[np.ndarray, tuple[int, int]]:
    """(K, (width, height)) of a compiled intrinsic (sensor-size) camera, as set_intrinsic_camera set it."""
    w, h = (int(x) for x in model.cam_resolution[camera_id])
    sx, sy = (float(x) for x in model.cam_sensorsize[camera_id])
    f_x, f_y, p_x, p_y = (float(x) for x in model.cam_intrinsic[camera_id])
    px_x, px_y = sx / w, sy / h  # metres per pixel
    K = np.array([[f_x / px_x, 0.0, (w - 1) / 2 - p_x / px_x], [0.0, f_y / px_y, (h - 1) / 2 - p_y / px_y],
                  [0.0, 0.0, 1.0]])
    return K, (w, h)


__all__ = ["CameraLens", "LensError", "check_lens", "set_intrinsic_camera", "intrinsic_camera_K", "SENSOR_PIXEL_PITCH_M"]
