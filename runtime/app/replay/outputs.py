"""What `dct replay` writes into its --out folder, each file written atomically:

  replay.mcap    the replay's recording (runtime.io.recording): ticks, poses, the CAN frames the
                 controller would have sent, P_fix, plans; `dct report latency` reads it
  odometry.tum   the odometry trajectory in the odom frame, TUM format (`t x y z qx qy qz qw`, one
                 pose per tick, t the tick's scheduled time): evo and `dct odom eval` read it
  latency.html   the latency report of replay.mcap (`dct report latency`'s code)
  replay.json    the summary: inputs fed and missing, ICP, timings, and for a dct recording the
                 difference between the replay's odometry and the live run's (/dct/pose)

The folder is checked before any work (it may exist; a file of these names in it is not
overwritten without --force).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

FILES = {"recording": "replay.mcap", "trajectory": "odometry.tum", "report": "latency.html",
         "summary": "replay.json"}


def output_paths(out_dir: Path, force: bool, inputs=()) -> dict[str, Path]:
    """The output files in `out_dir`, checked (calibration.outputs.OutputPathError otherwise):
    the folder is a folder or does not exist yet (its parent does), and no output would overwrite
    a file without `force` or be one of the inputs."""
    from calibration.outputs import OutputPathError, check_output_path

    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise OutputPathError(f"--out {out} is a file; give a folder")
    parent = out.parent if str(out.parent) else Path(".")
    if not out.exists() and not parent.is_dir():
        raise OutputPathError(f"--out {out}: folder {parent} does not exist (create it first)")
    paths = {k: out / name for k, name in FILES.items()}
    if out.is_dir():
        for p in paths.values():
            check_output_path(p, what="--out", inputs=inputs, overwrite=force)
    return paths


def tum_text(poses) -> str:
    """`t x y z qx qy qz qw` lines of planar poses (t, x, y, yaw); z = 0, yaw about z."""
    lines = []
    for t, x, y, yaw in poses:
        lines.append(f"{t:.9f} {x:.9f} {y:.9f} 0 0 0 {math.sin(0.5 * yaw):.9f} {math.cos(0.5 * yaw):.9f}")
    return "\n".join(lines) + ("\n" if lines else "")


def _ns(t_s: float) -> int:
    """A time as the recorder writes log times (runtime.io.recording): the same float gives the same ns."""
    return max(0, int(round(t_s * 1e9)))


def compare_odometry(live, replay) -> dict:
    """The position and heading difference between two trajectories at the ticks both have
    (live: (log time ns, x, y, yaw) from /dct/pose; replay: (scheduled time s, x, y, yaw)): max and
    mean in metres, max heading difference in radians."""
    ours = {_ns(t): (x, y, yaw) for t, x, y, yaw in replay}
    d, dyaw = [], []
    for t_ns, x, y, yaw in live:
        other = ours.get(t_ns)
        if other is None:
            continue
        d.append(math.hypot(other[0] - x, other[1] - y))
        dyaw.append(abs(math.atan2(math.sin(other[2] - yaw), math.cos(other[2] - yaw))))
    if not d:
        return {"matched": 0, "live_poses": len(live), "max_m": None, "mean_m": None, "max_yaw_rad": None}
    a = np.asarray(d)
    return {"matched": len(d), "live_poses": len(live), "max_m": float(a.max()), "mean_m": float(a.mean()),
            "max_yaw_rad": float(max(dyaw))}


def write_report(recording: Path, html: Path, label: str) -> dict:
    """The latency report of the replay's recording as HTML (`dct report latency --html`); returns
    the report's figures."""
    from calibration.outputs import atomic_write_text
    from runtime.app.reports.html import render_html
    from runtime.app.reports.latency import latency_report, load_ticks
    from runtime.app.reports.plots import all_figures

    data = load_ticks(recording)
    rep = latency_report(data)
    atomic_write_text(html, render_html([(label, rep, all_figures(data))], f"Latency report: {label}"))
    return rep


__all__ = ["FILES", "compare_odometry", "output_paths", "tum_text", "write_report"]
