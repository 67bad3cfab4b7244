"""Is the reference the same stretch of driving as the scans? (`reference_consistency`)

A reference cut from the wrong lines (a 457-line pose file cut with `head -n 120` for scans
200-319) has the right count and passes every format check, yet describes other motion. The
registration measures the scans' own motion, so the two are compared window by window.

Over windows of WINDOW_SCANS (10) scans, sliding by one (or one window over all scans when there
are fewer): the length of the translation, s (m), and the angle of the rotation, a (deg), of
T_i^-1 T_{i+W}, for the reference and for the registration. Both are independent of the frame a
trajectory is expressed in (a reference of the camera or of the vehicle body rather than the
lidar gives the same angles and nearly the same lengths), so no extrinsic is needed. A window
rather than one step: a reference's jitter (a few cm per pose) does not grow with the window
while the motion does, and a time offset between the reference and the scans is a small part
of it.

The rule, for translation and for rotation separately:

* a window is INFORMATIVE when one of the two moved more than the floor: max(s_ref, s_est) >
  FLOOR_M (0.1 m), or max(a_ref, a_est) > FLOOR_DEG (2 deg);
* an informative window DISAGREES GROSSLY when one trajectory's motion is under half the other's
  and they differ by more than the floor: |s_ref - s_est| > max(s_ref, s_est) / 2 and > FLOOR_M
  (likewise for the angles);
* the reference is INCONSISTENT when, in translation or in rotation, at least MIN_INFORMATIVE
  (5) windows are informative and more than half of them (MAX_DISAGREEING_FRACTION) disagree.

Why it cannot fire on a true reference: a working registration drifts by centimetres and tenths
of a degree over 10 scans, far from a factor of two plus 0.1 m / 2 deg; a time offset of up to
half a sweep between the reference and the scans moves a window's motion by a twentieth; a
standing robot gives no informative window, whatever the noise under the floors (tests draw
such cases). A true reference can only fail it when the registration itself failed (then the
figures are wrong too, and the warning says either may be at fault). A wrong stretch that
happens to move the same way (a straight drive at constant speed) is not detected; it also
barely changes the figures.
"""
from __future__ import annotations

import numpy as np

from runtime.odometry.metrics import rotation_angle_deg

WINDOW_SCANS = 10
FLOOR_M = 0.1
FLOOR_DEG = 2.0
MIN_INFORMATIVE = 5
MAX_DISAGREEING_FRACTION = 0.5
RULE = ("over windows of 10 scans (sliding by 1): translation length and rotation angle of the reference and of the "
        "registration; a window disagrees grossly when one is under half the other and they differ by more than "
        "0.1 m / 2 deg; inconsistent when, in translation or rotation, at least 5 windows move beyond 0.1 m / 2 deg "
        "in either trajectory and more than half of those disagree")


def window_motion(poses: np.ndarray, window: int = WINDOW_SCANS) -> tuple[np.ndarray, np.ndarray]:
    """(translation lengths m, rotation angles deg) of T_i^-1 T_{i+w}, w = min(window, N-1)."""
    w = min(window, len(poses) - 1)
    rel = np.linalg.inv(poses[:-w]) @ poses[w:]
    return np.linalg.norm(rel[:, :3, 3], axis=1), rotation_angle_deg(rel[:, :3, :3])


def _judge(ref: np.ndarray, est: np.ndarray, floor: float, unit: str) -> dict:
    """The rule (module doc) on one kind of window motion: counts, medians, and whether it fails."""
    larger = np.maximum(ref, est)
    diff = np.abs(ref - est)
    informative = larger > floor
    disagree = informative & (diff > larger / 2) & (diff > floor)
    n_inf, n_dis = int(informative.sum()), int(disagree.sum())
    judged = n_inf >= MIN_INFORMATIVE
    out = {"informative_windows": n_inf, "disagreeing_windows": n_dis, "judged": judged,
           f"median_reference_{unit}": float(np.median(ref)), f"median_estimate_{unit}": float(np.median(est)),
           "inconsistent": bool(judged and n_dis > MAX_DISAGREEING_FRACTION * n_inf)}
    if n_dis:
        out["first_disagreeing_window"] = int(np.argmax(disagree))
    return out


def reference_consistency(estimate: np.ndarray, reference: np.ndarray, scan_labels=None) -> dict:
    """The rule of the module doc on (N,4,4) poses sampled alike; `warning` is None when consistent.

    scan_labels: the scan index of each pose (to name windows in the warning); default 0..N-1.
    """
    s_est, a_est = window_motion(estimate)
    s_ref, a_ref = window_motion(reference)
    trans = _judge(s_ref, s_est, FLOOR_M, "m")
    rot = _judge(a_ref, a_est, FLOOR_DEG, "deg")
    labels = np.arange(len(estimate)) if scan_labels is None else np.asarray(scan_labels)
    w = min(WINDOW_SCANS, len(estimate) - 1)
    problems = []
    for what, r, unit, fmt in (("translation", trans, "m", ".2f"), ("rotation", rot, "deg", ".1f")):
        if r["inconsistent"]:
            k = r["first_disagreeing_window"]
            problems.append(f"{what}: {r['disagreeing_windows']} of {r['informative_windows']} moving {w}-scan windows "
                            f"disagree by more than a factor of 2 (median: reference {r[f'median_reference_{unit}']:{fmt}} "
                            f"{unit}, registration {r[f'median_estimate_{unit}']:{fmt}} {unit}; first from scan "
                            f"{int(labels[k])} to {int(labels[k + w])})")
    warning = None
    if problems:
        warning = ("the reference moves unlike the scans: " + "; ".join(problems) +
                   ". Is it the same stretch (lines, --frames) as the scans, and did the registration work?")
    return {"rule": RULE, "window_scans": int(w), "windows": int(len(s_est)), "translation": trans, "rotation": rot,
            "consistent": warning is None, "warning": warning}


__all__ = ["FLOOR_DEG", "FLOOR_M", "MAX_DISAGREEING_FRACTION", "MIN_INFORMATIVE", "RULE", "WINDOW_SCANS",
           "reference_consistency", "window_motion"]
