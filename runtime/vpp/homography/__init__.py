"""Phase I of the VPP (DCT eq. 4): carry a mask from the image where it was captured to the
image at the robot's current pose, with the homography the object's plane induces.

Frames and conventions (fixed here, used by the whole VPP):

- Camera frames are OpenCV optical frames (z forward, x right, y down), as calibration/camera_model.
- A camera pose is T_odom_cam (4x4): p_odom = T_odom_cam p_cam.
- The relative motion from the capture camera (time tau) to the current camera (time t) is
  (R, t) with X_cur = R X_cap + t, i.e. T_cur_cap = inv(T_odom_cur) T_odom_cap
  (`relative_motion`).
- The object's plane lives in the CAPTURE camera frame as n^T X_cap = d, n a unit normal and
  d > 0 its distance (so n points from the camera towards the plane; a fronto-parallel plane at
  depth Z is n = (0, 0, 1), d = Z).
- For X_cap on that plane n^T X_cap / d = 1, so X_cur = R X_cap + t n^T X_cap / d and the
  plane-induced homography in normalized coordinates is Hn = R + t n^T / d, in pixels
  H = K (R + t n^T / d) K^-1. This is the textbook K (R - t n^T / d) K^-1 written with the
  plane as n^T X = d: the minus sign belongs to Hartley-Zisserman's plane n^T X + d = 0 (normal
  away from the camera). The test that renders the plane directly at both poses pins the sign.
- Without a plane (no lidar points fell in the mask) the fallback is the plane at infinity,
  Hn = R, H = K R K^-1: exact for a pure rotation, wrong by the parallax t/depth otherwise.

Lens distortion: masks live in the RAW (distorted) image, the image a backend answered on and
the image Phase III projects lidar points into with distortion included (eq. 7). The warp is
therefore exact with distortion: for every pixel of the current image, undistort it (a
per-camera grid computed once), map it through Hn^-1 to the capture camera, distort it with the
camera model and sample the capture mask there (one cv2.remap, nearest neighbour). A camera
without distortion takes the plain path, cv2.warpPerspective with H (nearest neighbour).

Per scan the stage does not warp images at all (lookup.py: WarpLookup, WarpSource): Phase III needs a
warped mask only at the pixels its lidar points fall on, so it evaluates the same map there,
exactly (current pixel -> its undistorted ray, cached per camera -> Hn^-1 -> capture normalized
-> distort -> nearest capture pixel -> the capture mask), with the same half-planes. A bounding
box per warped mask (the capture outline carried forward) prunes the lookups, and the warped
area the stage's growth test needs is counted in that box (on a stride grid when the box is
large). Full-image warps remain for Phase II (once per answer) and for evaluation.

Safety: a pixel of the current image is set only if its ray meets the plane in front of the
current camera and that point lies in front of the capture camera (both half-planes of the
image, linear in the pixel); a homography otherwise maps points from behind a camera to mirrored
garbage, and a false "movable" pixel is the unsafe error. If the current camera has crossed the
plane (it sees the plane's back) the warped mask is empty.

Modules: plane.py (the plane, the motion, the homography, the plane's estimate), image_warp.py
(full-image warps: MaskWarper), lookup.py (the per-pixel warp the tick uses: WarpSource,
WarpLookup), kernels.py (its compiled map: a current pixel to its capture pixel).
"""
