"""`dct bench replay`: does `dct replay` give back what the robot's controller did?

One real-time episode (`dct hil run SCENARIO --realtime --record live.mcap`: the simulator and
`dct run` as two processes, the controller recording its inputs as received), then `dct replay
live.mcap` in a process of its own. The figures:

- the replay's odometry against the live run's (/dct/pose) at every tick: max and mean position
  difference, max heading difference (the acceptance: within 1 cm);
- the replay's commands (/dct/tick) and P_mov counts (/dct/partition) against the live run's, per tick;
- how long the replay took against the recording's length (--rate max);
- the recording's size per minute, whole and per input channel (uncompressed), and what the live
  ICP did (frames registered, frames its busy worker dropped);
- the replay's latency report (latency.html), and a screenshot of it where chromium is installed.
"""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

#: The replay must give the live odometry back within this (metres, at every tick).
ACCEPT_M = 0.01


def input_sizes(path: Path) -> dict:
    """Bytes per minute of the recording, whole (the file) and per channel (message bytes), over
    the span of its raw sensor messages."""
    from mcap.reader import make_reader

    from runtime.io.recording.raw_inputs import STREAM_KEY

    per: dict[str, int] = {}
    first = last = None
    with open(path, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages(log_time_order=False):
            per[channel.topic] = per.get(channel.topic, 0) + len(message.data)
            if STREAM_KEY in channel.metadata:
                t = message.log_time * 1e-9
                first, last = (t if first is None else min(first, t)), (t if last is None else max(last, t))
    span = (last - first) if first is not None and last > first else float("nan")
    per_min = lambda b: b / span * 60.0 / 1e6  # noqa: E731
    return {"span_s": span, "file_mb": path.stat().st_size / 1e6, "file_mb_per_min": per_min(path.stat().st_size),
            "channels_mb_per_min": {k: round(per_min(v), 2) for k, v in sorted(per.items(), key=lambda kv: -kv[1])}}


def _per_tick(path: Path) -> tuple[dict, dict]:
    """tick -> (v, omega) command (/dct/tick) and tick -> P_mov count (/dct/partition) of a recording."""
    from runtime.io.recording.reader import read_recording
    from runtime.io.recording.schemas import TOPIC_PARTITION, TOPIC_TICK

    rec = read_recording(path, topics=[TOPIC_TICK, TOPIC_PARTITION])
    cmds = {int(m["tick"]): (m["v_cmd_mps"], m["omega_cmd_radps"]) for _, m in rec.messages.get(TOPIC_TICK, [])}
    parts = {int(m["tick"]): m["p_mov"] for _, m in rec.messages.get(TOPIC_PARTITION, [])}
    return cmds, parts


def outputs_vs_live(live: Path, replay: Path) -> dict:
    """On the ticks both recordings have: how many commands are equal (exactly) and how many
    partition samples have the same P_mov count, and the largest command difference."""
    live_cmd, live_part = _per_tick(live)
    rep_cmd, rep_part = _per_tick(replay)
    ticks = sorted(set(live_cmd) & set(rep_cmd))
    diff = [max(abs((a or 0.0) - (b or 0.0)) for a, b in zip(live_cmd[t], rep_cmd[t])) for t in ticks]
    samples = sorted(set(live_part) & set(rep_part))
    return {"command_ticks": len(ticks), "commands_equal": sum(live_cmd[t] == rep_cmd[t] for t in ticks),
            "command_max_diff": max(diff, default=0.0),
            "partition_samples": len(samples), "partitions_equal": sum(live_part[t] == rep_part[t] for t in samples),
            "partition_movable_live": sum(live_part[t] or 0 for t in samples)}


def screenshot(html: Path, png: Path) -> str | None:
    """A headless chromium's screenshot of the report; None where there is no chromium."""
    exe = next((shutil.which(n) for n in ("chromium", "chromium-browser", "google-chrome") if shutil.which(n)), None)
    if exe is None:
        return None
    subprocess.run([exe, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars", f"--screenshot={png}",
                    "--window-size=1280,2400", html.resolve().as_uri()], capture_output=True, timeout=120)
    return str(png) if png.is_file() else None


def replay_bench(scenario: str, out_dir: Path, *, seed: int = 0, planner: str | None = None,
                 domain_id: int | None = None, echo=None) -> dict:
    """Record one real-time episode into out_dir/live.mcap, replay it into out_dir/replay/; the
    figures (module docstring)."""
    from hil_sim.episode.realtime import run_realtime_episode

    out_dir.mkdir(parents=True, exist_ok=True)
    live = out_dir / "live.mcap"
    t0 = time.monotonic()
    metrics = run_realtime_episode(scenario, seed, planner=planner, record_path=live, force=True, echo=echo,
                                   domain_id=domain_id)
    live_s = time.monotonic() - t0
    replay_dir = out_dir / "replay"
    cmd = [sys.executable, "-m", "runtime.app.replay", str(live), "--out", str(replay_dir), "--force"]
    t0 = time.monotonic()
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=1800)
    process_s = time.monotonic() - t0
    if run.returncode != 0:
        raise RuntimeError(f"dct replay exited {run.returncode}: {run.stderr.strip()[-2000:]}")
    summary = json.loads((replay_dir / "replay.json").read_text())
    odo = metrics.get("controller", {}).get("odometry", {})
    cmp = summary["odometry_vs_live"] or {}
    return {
        "scenario": scenario, "seed": seed, "live": {
            "goal_reached": metrics.get("goal_reached"), "failure_reason": metrics.get("failure_reason"),
            "wall_s": live_s, "recording": metrics.get("realtime", {}).get("recording"),
            "icp_frames_submitted": odo.get("icp_frames_submitted"), "icp_dropped": odo.get("icp_dropped")},
        "odometry_vs_live": cmp,
        "outputs_vs_live": outputs_vs_live(live, replay_dir / "replay.mcap"),
        "accepted": bool(cmp.get("matched")) and cmp["max_m"] <= ACCEPT_M,
        "replay": {"ticks": summary["ticks"], "recording_s": summary["recording_s"],
                   "replay_wall_s": summary["replay_wall_s"], "process_wall_s": process_s,
                   "inputs": summary["inputs"], "icp": summary["icp"], "vlm": summary.get("vlm")},
        "size": input_sizes(live),
        "report": {"html": str(replay_dir / "latency.html"), "html_bytes": (replay_dir / "latency.html").stat().st_size,
                   "screenshot": screenshot(replay_dir / "latency.html", out_dir / "latency.png")},
        "replay_stderr": run.stderr.strip().splitlines()[-1:],
    }


def summary_lines(r: dict) -> list[str]:
    c, rp, sz = r["odometry_vs_live"], r["replay"], r["size"]
    lines = [f"live {r['scenario']}: goal reached {r['live']['goal_reached']}, ICP frames {r['live']['icp_frames_submitted']}"
             f" (dropped by the busy worker: {r['live']['icp_dropped']})"]
    if c.get("matched"):
        lines.append(f"replay odometry vs live: max {c['max_m'] * 1e3:.3f} mm, mean {c['mean_m'] * 1e3:.3f} mm over "
                     f"{c['matched']} ticks: {'ACCEPTED' if r['accepted'] else 'NOT within 1 cm'}")
    o = r["outputs_vs_live"]
    lines.append(f"replay commands vs live: {o['commands_equal']} of {o['command_ticks']} ticks equal (largest "
                 f"difference {o['command_max_diff']:.4f}); P_mov counts (/dct/partition) equal on {o['partitions_equal']} "
                 f"of {o['partition_samples']} samples (live P_mov total {o['partition_movable_live']})")
    if rp.get("vlm"):
        lines.append("replay VLM: " + ", ".join(f"{k} {v}" for k, v in rp["vlm"].items()))
    lines.append(f"replay: {rp['ticks']} ticks in {rp['replay_wall_s']:.1f} s ({rp['process_wall_s']:.1f} s with start-up) "
                 f"for a {rp['recording_s']:.1f} s recording")
    lines.append(f"recording: {sz['file_mb']:.1f} MB over {sz['span_s']:.1f} s = {sz['file_mb_per_min']:.0f} MB per minute; "
                 "per channel (MB/min, uncompressed): " + ", ".join(f"{k} {v}" for k, v in
                                                                  list(sz["channels_mb_per_min"].items())[:5]))
    lines.append(f"latency report: {r['report']['html']} ({r['report']['html_bytes']} bytes)"
                 + (f", screenshot {r['report']['screenshot']}" if r["report"]["screenshot"] else ""))
    return lines
