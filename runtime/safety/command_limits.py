"""Clamp a wheel command to the robot's speed and acceleration limits."""
from __future__ import annotations

import math


class CommandLimiter:
    def __init__(
        self,
        max_linear_speed_mps: float,
        max_angular_speed_radps: float,
        max_linear_accel_mps2: float,
        max_angular_accel_radps2: float,
    ) -> None:
        self.v_max = max_linear_speed_mps
        self.w_max = max_angular_speed_radps
        self.a_max = max_linear_accel_mps2
        self.alpha_max = max_angular_accel_radps2
        self.v = 0.0
        self.w = 0.0

    def reset(self) -> None:
        self.v = self.w = 0.0

    def limit(self, v_mps: float, omega_radps: float, dt_s: float) -> tuple[float, float]:
        if not (math.isfinite(v_mps) and math.isfinite(omega_radps)):
            raise ValueError(f"non-finite wheel command v={v_mps} m/s, omega={omega_radps} rad/s")
        v = min(self.v_max, max(-self.v_max, v_mps))
        w = min(self.w_max, max(-self.w_max, omega_radps))
        dv = self.a_max * dt_s
        dw = self.alpha_max * dt_s
        self.v = min(self.v + dv, max(self.v - dv, v))
        self.w = min(self.w + dw, max(self.w - dw, w))
        return self.v, self.w
