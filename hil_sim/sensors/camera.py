"""Simulated RGB camera (MuJoCo offscreen rendering) with ground-truth segmentation.

Frames: the robot description gives the camera mount as the *optical* frame (z forward,
x right, y down) in base_link. A MuJoCo camera looks along its -z axis with y up, so
R_body<-mjcam = R_body<-optical @ diag(1, -1, -1) (a half turn about x).

Intrinsics: the robot description's camera is a symmetric pinhole with vertical field of view
`fovy` and square pixels, so fy = fx = (H/2) / tan(fovy/2) and the principal point is the image
centre, which in OpenCV pixel coordinates (pixel centres at integers) is ((W-1)/2, (H-1)/2).
A camera of another robot (hil_sim.world.robot_variant) is given as a CameraLens
(hil_sim.sensors.camera_lens): MuJoCo's intrinsic camera renders its focal lengths and principal
point on a canvas, and the lens's distortion is applied to each render; its images carry the
lens's true K and distortion, as a camera driver publishes its factory calibration.

Rendering is the slowest part of the simulator (about 20 ms RGB, 12 ms segmentation at 640x480):
render only when a consumer asks for a frame. Shadows and reflections are off.
"""
from __future__ import annotations

import math
import os
from typing import Any

os.environ.setdefault("MUJOCO_GL", "egl")  # no display on these machines: headless rendering through EGL

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from hil_sim.sensors.camera_lens import CameraLens, intrinsic_camera_K, set_intrinsic_camera  # noqa: E402
from runtime.common.sensor_data import CameraImage  # noqa: E402

_OPTICAL_TO_MJCAM = np.diag([1.0, -1.0, -1.0])


#: Nearest distance the simulated camera renders (m); see SimCamera.__init__.
CAMERA_NEAR_M = 0.005


def fovy_deg_from_horizontal(horizontal_fov_deg: float, width_px: int, height_px: int) -> float:
    """Vertical field of view (deg) of a square-pixel pinhole with the given horizontal one."""
    if not (0.0 < horizontal_fov_deg < 180.0) or width_px <= 0 or height_px <= 0:
        raise ValueError(f"bad camera: hfov {horizontal_fov_deg} deg, {width_px}x{height_px} px")
    f = (width_px / 2.0) / math.tan(math.radians(horizontal_fov_deg) / 2.0)
    return math.degrees(2.0 * math.atan((height_px / 2.0) / f))


def _quat_wxyz(r: np.ndarray) -> np.ndarray:
    q = np.empty(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(r, dtype=np.float64).reshape(-1))
    return q


def add_camera_to_spec(spec_body: Any, mount: Any, camera_description: Any, name: str = "camera",
                       lens: CameraLens | None = None) -> str:
    """Add a camera at the optical-frame `mount` (T_body<-optical) to an MjSpec body; return its name.

    fovy comes from the description's horizontal fov and aspect (width_px x height_px); with a
    `lens`, the camera renders the lens's canvas (its K at its canvas size) instead.
    The model's offscreen buffer must be at least that large: see `ensure_offscreen_buffer`.
    """
    t = mount.transform() if hasattr(mount, "transform") else np.asarray(mount, dtype=np.float64)
    if t.shape != (4, 4) or not np.isfinite(t).all():
        raise ValueError(f"camera mount must be a Mount or a finite 4x4 transform, got shape {t.shape}")
    r_body_mjcam = t[:3, :3] @ _OPTICAL_TO_MJCAM
    fovy = fovy_deg_from_horizontal(camera_description.horizontal_fov_deg, camera_description.width_px,
                                    camera_description.height_px)
    cam = spec_body.add_camera(name=name, pos=list(map(float, t[:3, 3])),
                               quat=list(map(float, _quat_wxyz(r_body_mjcam))), fovy=fovy)
    if lens is not None:
        set_intrinsic_camera(cam, lens.canvas_K, *lens.canvas_size)
    return name


def ensure_offscreen_buffer(spec: Any, width_px: int, height_px: int) -> None:
    """Grow the spec's offscreen framebuffer to at least width x height (MuJoCo's default is 640x480)."""
    g = spec.visual.global_
    g.offwidth = max(int(g.offwidth), int(width_px))
    g.offheight = max(int(g.offheight), int(height_px))


def camera_intrinsics(model: mujoco.MjModel, camera_id: int, width_px: int, height_px: int) -> np.ndarray:
    """3x3 K (OpenCV convention) of a MuJoCo fovy camera rendered at width x height (an intrinsic
    camera: its own K, at its resolution, which must be width x height)."""
    if np.any(model.cam_sensorsize[camera_id] > 0):
        K, size = intrinsic_camera_K(model, camera_id)
        if size != (width_px, height_px):
            raise ValueError(f"camera {camera_id} renders {size[0]}x{size[1]} px, asked for {width_px}x{height_px}")
        return K
    fovy = float(model.cam_fovy[camera_id])
    f = (height_px / 2.0) / math.tan(math.radians(fovy) / 2.0)
    return np.array([[f, 0.0, (width_px - 1) / 2.0], [0.0, f, (height_px - 1) / 2.0], [0.0, 0.0, 1.0]])


class SimCamera:
    """Offscreen renderer for one model camera; create once, render on demand.

    hidden_geom_groups: geom groups not drawn (e.g. the robot's own chassis if the camera sits
    inside it). Only groups 0-2 are drawn by MuJoCo's default; sites are never drawn.
    """

    def __init__(self, model: mujoco.MjModel, data: mujoco.MjData, camera_name: str, width: int = 640,
                 height: int = 480, frame_id: str = "camera", hidden_geom_groups: tuple[int, ...] = (),
                 lens: CameraLens | None = None, antialias: bool = True) -> None:
        """lens: the true camera of a robot variant (the model's camera renders its canvas: see
        add_camera_to_spec); None: the model camera's pinhole. antialias: False renders without
        the model's multisampling (`vis.quality.offsamples`, 4 by default): half the render's
        CPU with Mesa's software rasteriser; the segmentation is the same pixel for pixel, the
        RGB image's edges are a pinhole's hard ones."""
        cam_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera_name)
        if cam_id < 0:
            raise ValueError(f"SimCamera: the model has no camera named {camera_name!r}")
        if lens is not None and (lens.width_px, lens.height_px) != (int(width), int(height)):
            raise ValueError(f"SimCamera: the lens makes {lens.width_px}x{lens.height_px} px images, asked for "
                             f"{width}x{height}")
        render_w, render_h = lens.canvas_size if lens is not None else (int(width), int(height))
        ow, oh = int(model.vis.global_.offwidth), int(model.vis.global_.offheight)
        if render_w > ow or render_h > oh:
            raise ValueError(f"SimCamera: {render_w}x{render_h} exceeds the model's offscreen buffer {ow}x{oh}; call "
                             f"hil_sim.sensors.camera.ensure_offscreen_buffer(spec, {render_w}, {render_h}) before "
                             "compiling")
        self._m, self._d = model, data
        self.camera_name = camera_name
        self.camera_id = int(cam_id)
        self.width, self.height = int(width), int(height)
        self.frame_id = frame_id
        self._lens = lens
        self._K = camera_intrinsics(model, self.camera_id, render_w, render_h)
        self._dist = np.zeros(0)
        if lens is not None:
            if not np.allclose(self._K, lens.canvas_K, atol=1e-3):
                raise ValueError(f"SimCamera: the model camera renders K {self._K.tolist()}, the lens's canvas is "
                                 f"{lens.canvas_K.tolist()} (add the camera with add_camera_to_spec(..., lens=lens))")
            self._K, self._dist = lens.K.copy(), lens.dist.copy()
        self._K.flags.writeable = False
        self._dist.flags.writeable = False
        # MuJoCo's near clipping plane is znear * extent of the whole scene (0.1 m in a 7 x 5 m
        # room): a box the robot pushes, 3 cm in front of the lens, would be clipped away and the
        # camera would see through it. A real camera sees the box (blurred); so does this one.
        near = CAMERA_NEAR_M / max(float(model.stat.extent), 1e-9)
        if model.vis.map.znear > near:
            model.vis.map.znear = near
        samples = int(model.vis.quality.offsamples)
        if not antialias:  # read when the renderer's GL context is made; the model keeps its own
            model.vis.quality.offsamples = 0
        try:
            self._renderer = mujoco.Renderer(model, height=render_h, width=render_w)
        finally:
            model.vis.quality.offsamples = samples
        flags = self._renderer.scene.flags
        flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
        flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
        self._option = mujoco.MjvOption()
        self._option.sitegroup[:] = 0
        for g in hidden_geom_groups:
            if not 0 <= g < len(self._option.geomgroup):
                raise ValueError(f"SimCamera: geom group {g} out of range")
            self._option.geomgroup[g] = 0
        self._geom_body = np.asarray(model.geom_bodyid, dtype=np.int32)
        self.renders = 0

    def intrinsics(self) -> np.ndarray:
        """K (3x3, read-only): the true one its images carry."""
        return self._K

    @property
    def distortion(self) -> np.ndarray:
        """The true distortion its images carry (OpenCV order; empty for a pinhole)."""
        return self._dist

    def render_rgb(self, stamp_s: float) -> CameraImage:
        """Render the current state of `data` as an RGB CameraImage stamped stamp_s."""
        r = self._renderer
        r.disable_segmentation_rendering()
        r.update_scene(self._d, self.camera_id, self._option)
        px = r.render()
        if self._lens is not None:
            px = self._lens.apply(px)
        px.flags.writeable = False     # fresh array: hand it over without a copy
        self.renders += 1
        return CameraImage(stamp_s=stamp_s, pixels=px, K=self._K, distortion=self._dist, frame_id=self.frame_id)

    def render_segmentation(self, kind: str = "geom") -> np.ndarray:
        """(H, W) int32 ids of what each pixel sees: geom ids (kind='geom') or body ids (kind='body'); -1 background."""
        if kind not in ("geom", "body"):
            raise ValueError(f"render_segmentation: kind must be 'geom' or 'body', got {kind!r}")
        r = self._renderer
        r.enable_segmentation_rendering()
        try:
            r.update_scene(self._d, self.camera_id, self._option)
            seg = r.render()
        finally:
            r.disable_segmentation_rendering()
        self.renders += 1
        is_geom = seg[:, :, 1] == int(mujoco.mjtObj.mjOBJ_GEOM)
        ids = np.where(is_geom, seg[:, :, 0], -1).astype(np.int32)
        if self._lens is not None:
            ids = self._lens.apply_nearest(ids)
        if kind == "body":
            ids = np.where(ids >= 0, self._geom_body[np.maximum(ids, 0)], -1).astype(np.int32)
        return ids

    def render_rgb_with_segmentation(self, stamp_s: float, kind: str = "geom") -> CameraImage:
        """RGB plus ground-truth segmentation of the same state, in one CameraImage."""
        img = self.render_rgb(stamp_s)
        seg = self.render_segmentation(kind)
        seg.flags.writeable = False
        return CameraImage(stamp_s=img.stamp_s, pixels=img.pixels, K=img.K, distortion=img.distortion,
                           frame_id=img.frame_id, segmentation=seg)

    def warm_up(self, segmentation: bool = False) -> None:
        """Render the state in data once (with segmentation too when asked), thrown away and not
        counted in `renders`: a renderer's first pass compiles its shaders (about 60 ms more than a
        steady frame with Mesa's llvmpipe), which start-up pays instead of the first frame."""
        renders = self.renders
        if segmentation:
            self.render_rgb_with_segmentation(0.0)
        else:
            self.render_rgb(0.0)
        self.renders = renders

    def close(self) -> None:
        self._renderer.close()


__all__ = ["add_camera_to_spec", "ensure_offscreen_buffer", "camera_intrinsics", "fovy_deg_from_horizontal",
           "SimCamera"]
