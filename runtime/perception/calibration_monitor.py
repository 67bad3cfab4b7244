"""The calibration check beside the tick: is the calibration the controller projects with right?

The tick hands over what it already has (`observe`: the camera driver's newest intrinsics, the
newest good lidar frame; references, O(1)); the checks run in the slack after the command is
written (`slack`, never in the tick), on the controller's clock:

* intrinsics: each new CameraInfo (one that differs from the last compared) against the
  calibrated camera (calibration.consistency.intrinsics_problems): one report beyond the
  tolerances is a mismatch (the camera's own calibration does not drift between two frames);
* lidar mount: every `floor_check_period_s`, the floor of the newest frame placed on base_link
  with the calibrated mount (calibration.consistency.fit_floor): `floor_confirmations` fits in a
  row tilted or off z = 0 beyond the tolerances are a mismatch (one fit may see a ramp or a
  large flat box top; a fit within them starts the count again; a frame that shows too little
  floor says nothing).

The first mismatch is kept (`mismatch`, said once by `slack`): the controller falls back to the
all-fixed partition and says why (runtime.controller.navigation). In lockstep it is
deterministic: the slack runs after every tick and the times are simulated.
"""
from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

import numpy as np

from calibration.consistency import FloorFitSettings, ReportedCamera, fit_floor, floor_problem, intrinsics_problems


class CalibrationCheckConfig(BaseModel):
    """Tolerances and cadence of the calibration check (docs/decisions/calibration-check-tolerances.md)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    enabled: bool = True
    #: |reported fx - calibrated fx| / calibrated fx (fy alike): 1% moves a point at the edge of
    #: a 640 px image by 3.2 px.
    focal_tolerance: float = Field(0.01, gt=0.0, le=0.5)
    principal_point_tolerance_px: float = Field(3.0, gt=0.0, le=500.0)
    #: The largest displacement the two distortion models make anywhere in the image.
    distortion_tolerance_px: float = Field(3.0, gt=0.0, le=500.0)
    #: The floor seen through the lidar mount: its tilt from level and its height off z = 0.
    floor_tilt_tolerance_deg: float = Field(1.0, gt=0.0, le=15.0)
    floor_height_tolerance_m: float = Field(0.025, gt=0.0, le=0.2)
    floor_check_period_s: float = Field(1.0, gt=0.0, le=60.0)
    floor_confirmations: int = Field(3, ge=1, le=100)


class CalibrationMonitor:
    """The checks of one controller (module docstring)."""

    def __init__(self, config: CalibrationCheckConfig, sensors, floor: FloorFitSettings = FloorFitSettings()) -> None:
        """sensors: the calibration in use (calibration.sensor_calibration.SensorCalibration)."""
        self.config = config
        self.sensors = sensors
        self.floor_settings = floor
        self._info = None  # the newest CameraInfo not yet compared
        self._compared = None  # (K, D, size, model) of the last one compared
        self._scan = None  # the newest good frame
        self._next_floor_s: float | None = None
        self._floor_bad_in_row = 0
        #: The first mismatch found (latched), and when.
        self.mismatch: str | None = None
        self.mismatch_at_s: float | None = None
        self._said = False
        # what it saw (describe)
        self.infos_compared = 0
        self.intrinsics: str = "not checked: no camera info received"
        self.intrinsics_notes: list[str] = []
        self.floor_fits = 0
        self.floor_no_fit = 0
        self.last_floor: dict | None = None
        self.floor_problem: str | None = None

    # -- the tick (O(1)) -------------------------------------------------------------------------
    def observe(self, camera_info, good_scan) -> None:
        if not self.config.enabled:
            return
        if camera_info is not None:
            self._info = camera_info
        if good_scan is not None:
            self._scan = good_scan

    # -- the slack ---------------------------------------------------------------------------------
    def slack(self, now_s: float, busy: bool = False) -> tuple[str | None, bool]:
        """Run what is due; (a mismatch found now, said once: None otherwise; whether any work ran).
        busy: the slack had other work already (a reference search): the floor fit (a few ms)
        waits for a later slack, unless it is a whole period overdue."""
        if not self.config.enabled:
            return None, False
        worked = self._check_intrinsics(now_s)
        due = self._next_floor_s is None or now_s >= self._next_floor_s
        if busy and self._next_floor_s is not None:
            due = now_s >= self._next_floor_s + self.config.floor_check_period_s
        if self._scan is not None and due:
            self._check_floor(now_s)
            self._next_floor_s = now_s + self.config.floor_check_period_s
            worked = True
        if self.mismatch is not None and not self._said:
            self._said = True
            return self.mismatch, worked
        return None, worked

    def _found(self, reason: str, now_s: float) -> None:
        if self.mismatch is None:
            self.mismatch, self.mismatch_at_s = reason, float(now_s)

    def _check_intrinsics(self, now_s: float) -> bool:
        info, self._info = self._info, None
        if info is None:
            return False
        key = (info.K.tobytes(), info.distortion.tobytes(), info.width_px, info.height_px, info.distortion_model)
        if key == self._compared:
            return False
        self._compared = key
        self.infos_compared += 1
        c = self.config
        reported = ReportedCamera(info.K, info.distortion, info.width_px, info.height_px, info.distortion_model)
        problems, self.intrinsics_notes = intrinsics_problems(
            self.sensors.camera, reported, self.sensors.camera_field, focal_rel=c.focal_tolerance,
            principal_px=c.principal_point_tolerance_px, distortion_px=c.distortion_tolerance_px)
        if problems:
            self.intrinsics = "; ".join(problems)
            self._found(f"camera intrinsics: {self.intrinsics}", now_s)
        else:
            self.intrinsics = "ok"
        return True

    def _check_floor(self, now_s: float) -> None:
        scan, self._scan = self._scan, None
        T = self.sensors.T_base_lidar
        points = np.asarray(scan.points_m, dtype=np.float64) @ T[:3, :3].T + T[:3, 3]
        fit = fit_floor(points, T[:3, 3], self.floor_settings)
        if fit is None:
            self.floor_no_fit += 1
            return
        self.floor_fits += 1
        self.last_floor = {"t_s": float(now_s), "tilt_deg": round(fit.tilt_deg, 3),
                           "rise_x_deg": round(fit.rise_x_deg, 3), "rise_y_deg": round(fit.rise_y_deg, 3),
                           "height_m": round(fit.height_m, 4), "inliers": fit.inliers, "rms_m": round(fit.rms_m, 4)}
        c = self.config
        problem = floor_problem(fit, self.sensors.sources["lidar_mount"], tilt_deg=c.floor_tilt_tolerance_deg,
                                height_m=c.floor_height_tolerance_m)
        self._floor_bad_in_row = self._floor_bad_in_row + 1 if problem is not None else 0
        if problem is not None:
            self.floor_problem = problem
            if self._floor_bad_in_row >= c.floor_confirmations:
                self._found(f"lidar mount: {problem} ({self._floor_bad_in_row} fits in a row)", now_s)

    def describe(self) -> dict:
        """JSON-ready: what was checked, what was found, the calibration's sources."""
        return {
            "enabled": self.config.enabled,
            "sources": dict(self.sensors.sources),
            "mismatch": self.mismatch,
            "mismatch_at_s": self.mismatch_at_s,
            "intrinsics": self.intrinsics,
            "intrinsics_notes": list(self.intrinsics_notes),
            "camera_infos_compared": self.infos_compared,
            "floor_fits": self.floor_fits,
            "floor_frames_without_fit": self.floor_no_fit,
            "floor_last": self.last_floor,
            "floor_last_problem": self.floor_problem,
        }


def check_calibration(monitor: CalibrationMonitor, partition, events, now_s: float,
                      busy: bool = False) -> tuple[str | None, bool]:
    """The monitor's due work in the slack; a mismatch it finds is said in the event log and the
    partition (runtime.perception.partition.FallbackPartition) falls back to all-fixed for the rest
    of the run: every point an obstacle, the safe side. (The mismatch found now, whether any work ran.)"""
    mismatch, worked = monitor.slack(now_s, busy)
    if mismatch is not None:
        events.add(now_s, "calibration_mismatch", mismatch)
        configured = partition.name
        if partition.fall_back(mismatch, now_s):
            events.add(now_s, "partition_fallback", f"partition all-fixed instead of {configured}: every lidar "
                                                    "point an obstacle from now on")
    return mismatch, worked


__all__ = ["CalibrationCheckConfig", "CalibrationMonitor", "check_calibration"]
