"""APE and RPE of an estimated trajectory as evo (the `eval` extra, pinned 1.38.1) computes them,
evo's time association of a TUM reference, and the trajectory plot of `dct odom eval --plot`.

Figures (`evo_figures`), all of the translation part (m), with evo.core.metrics:

* `ape.aligned`: APE after evo's Umeyama SE(3) alignment of the estimate onto the reference
  (rotation and translation, no scale: `align(correct_scale=False)`). Umeyama needs positions
  that span a plane; a straight or 2-pose trajectory has no aligned APE (`skipped` says why).
* `ape.unaligned`: APE without any fitted alignment. Both trajectories are first put at their
  own first pose (T_0^-1 T_i): odometry starts at the identity wherever the reference's world
  frame is, so this is the APE of the motion since the first scan (evo's --align_origin).
* `rpe`: RPE between poses `delta` apart: 1 frame (scan to scan), and 1 m and 10 m of reference
  path where the path is at least that long (evo's consecutive, non-overlapping pairs, path
  tolerance 10 %); a delta the path is too short for is listed in `skipped`.

Each figure holds evo's statistics: rmse, mean, median, std, min, max, sse, and the number of
pose pairs.

Time association (`associate`): evo's `matching_time_indices` (what `associate_trajectories`
uses): each scan takes the reference pose nearest in time if it is at most `max_diff_s` away.

evo.tools.plot is not used for the plot: importing it writes ~/.evo/settings.json and prints
to stdout (docs/decisions/odometry-evo.md); the plot is plain matplotlib (Agg).
"""
from __future__ import annotations

import io

import numpy as np

from runtime.odometry.metrics import relative_to_first
from runtime.odometry.pose_files import EVAL_EXTRA, SequenceInputError

#: RPE deltas in metres of reference path (besides 1 frame).
RPE_DELTAS_M = (1.0, 10.0)
#: evo's default association window (s).
DEFAULT_MAX_TIME_DIFF_S = 0.01


def require_evo() -> str:
    """evo's version; SequenceInputError (one line, the pip command) when it cannot be imported."""
    try:
        import evo
        import evo.core.metrics  # noqa: F401 - the parts used here
        import evo.core.sync  # noqa: F401
    except ImportError as exc:
        raise SequenceInputError(f"APE and RPE need evo ({exc}): {EVAL_EXTRA}") from None
    return evo.__version__.lstrip("v")


def associate(scan_times: np.ndarray, ref_times: np.ndarray, max_diff_s: float) -> tuple[np.ndarray, np.ndarray]:
    """(scan indices, reference indices) of the matched pairs (module doc)."""
    from evo.core.sync import matching_time_indices

    i, j = matching_time_indices(np.asarray(scan_times, float), np.asarray(ref_times, float), max_diff=max_diff_s)
    return np.asarray(i, dtype=int), np.asarray(j, dtype=int)


def _path(poses: np.ndarray):
    from evo.core.trajectory import PosePath3D

    return PosePath3D(poses_se3=[np.array(T) for T in poses])


def _stats(metric, pairs: int) -> dict:
    return {**{k: float(v) for k, v in metric.get_all_statistics().items()}, "pairs": int(pairs)}


def _ape(ref, est) -> dict:
    from evo.core.metrics import APE, PoseRelation

    m = APE(PoseRelation.translation_part)
    m.process_data((ref, est))
    return _stats(m, ref.num_poses)


def aligned_estimate(estimate: np.ndarray, reference: np.ndarray) -> tuple[np.ndarray, str | None]:
    """The estimate after evo's Umeyama SE(3) alignment onto the reference, or (the estimate put
    at the reference's first pose, why alignment was impossible)."""
    from evo.core.geometry import GeometryException

    est, ref = _path(estimate), _path(reference)
    try:
        est.align(ref, correct_scale=False)
    except GeometryException as exc:
        start = reference[0] @ np.linalg.inv(estimate[0])
        return start @ estimate, f"no SE(3) alignment: {exc}"
    return np.array(est.poses_se3), None


def _rpe(ref, est, delta: float, unit) -> dict:
    from evo.core.filters import FilterException
    from evo.core.metrics import RPE, MetricsException, PoseRelation

    m = RPE(PoseRelation.translation_part, delta=delta, delta_unit=unit, all_pairs=False)
    try:
        m.process_data((ref, est))
    except (FilterException, MetricsException) as exc:
        return {"skipped": " ".join(str(exc).split())}
    return _stats(m, len(m.error))


def evo_figures(estimate: np.ndarray, reference: np.ndarray) -> dict:
    """evo's APE and RPE (module doc) of (N,4,4) poses sampled alike (N >= 2)."""
    from evo.core.units import Unit

    est0, ref0 = relative_to_first(estimate), relative_to_first(reference)
    aligned, why = aligned_estimate(estimate, reference)
    ape = {"unaligned": _ape(_path(ref0), _path(est0)),
           "aligned": {"skipped": why} if why else _ape(_path(reference), _path(aligned))}
    ref_path = _path(ref0)
    rpe = {"1_frame": _rpe(ref_path, _path(est0), 1, Unit.frames)}
    length = float(ref_path.path_length)
    for d in RPE_DELTAS_M:
        key = f"{d:g}_m"
        rpe[key] = (_rpe(ref_path, _path(est0), d, Unit.meters) if length >= d
                    else {"skipped": f"the reference path is {length:.2f} m, shorter than {d:g} m"})
    return {"pose_relation": "translation_part", "unit": "m", "alignment": "SE(3) Umeyama, no scale",
            "ape": ape, "rpe": rpe, "path_length_m": length}


def plot_png(estimate: np.ndarray, reference: np.ndarray, title: str) -> bytes:
    """A top view (x, y) of the reference and the aligned estimate, as PNG bytes (matplotlib Agg)."""
    from matplotlib.figure import Figure

    aligned, why = aligned_estimate(estimate, reference)
    fig = Figure(figsize=(7, 6), dpi=110)
    ax = fig.add_subplot(111)
    ax.plot(reference[:, 0, 3], reference[:, 1, 3], "-", color="0.3", lw=1.5, label="reference")
    ax.plot(aligned[:, 0, 3], aligned[:, 1, 3], "-", color="tab:blue", lw=1.2,
            label="estimate (" + ("put at the reference's first pose" if why else "SE(3) aligned") + ")")
    ax.plot(reference[0, 0, 3], reference[0, 1, 3], "o", color="0.3", ms=5)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title, fontsize=9)
    ax.grid(True, lw=0.3)
    ax.legend(loc="best", fontsize=8)
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


__all__ = ["DEFAULT_MAX_TIME_DIFF_S", "RPE_DELTAS_M", "aligned_estimate", "associate", "evo_figures",
           "plot_png", "require_evo"]
