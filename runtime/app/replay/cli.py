"""`dct replay RUN.mcap|BAG`: the controller run open loop on a recording of the robot's inputs.

Reads a recording of `dct run --record` (its sensor messages as received, the base's CAN frames,
what each tick took in) or a rosbag2 / MCAP bag of the robot's drivers, runs the controller on it
through the code the robot runs (runtime.app.replay.session), and writes the replay's recording,
odometry trajectory, latency report and summary into --out (runtime.app.replay.outputs).

The config: --config, else the one the recording was made with, else the shipped one; the sensor
topics: --lidar-topic / --imu-topic / --image-topic / --camera-info-topic, else the config's `ros.inputs`
(a dct recording's own config by default: the topics it recorded). The camera driver's CameraInfo is
replayed like the other samples, so the calibration check runs as it did live. Exit status 2 on
bad input (one line naming the file and the field), before any work.
"""
from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import click

from runtime.app.replay.source import ReplaySourceError
from runtime.app.run_inputs import DEFAULT_RECORD_PART_MIN

_FILE = click.Path(dir_okay=False, path_type=Path)
_STREAM_OF_OPTION = {"lidar_topic": "lidar", "imu_topic": "imu", "image_topic": "camera",
                     "camera_info_topic": "camera_info"}


class InputError(click.ClickException):
    exit_code = 2


@click.command("replay")
@click.argument("recording", type=click.Path(path_type=Path))
@click.option("--config", "config_path", type=_FILE,
              help="Controller config YAML (an overlay on the shipped one). Default: the config the recording "
                   "was made with (a bag: the shipped one).")
@click.option("--robot", "robot_path", type=_FILE, help="Robot description YAML (default: the shipped LIMO).")
@click.option("--calibration", "calibration_path", type=_FILE,
              help="The robot's calibration file (camera, wheel odometry); default: nominal values.")
@click.option("--rate", type=click.Choice(["max", "recorded"]), default="max", show_default=True,
              help="max: as fast as the work allows; recorded: ticks at the recorded pace on the wall clock.")
@click.option("--out", "out_dir", type=click.Path(file_okay=False, path_type=Path),
              help="Folder for the outputs (default: RECORDING's name + .replay, beside it).")
@click.option("--force", is_flag=True, help="Overwrite outputs already in --out.")
@click.option("--record-part-minutes", "record_part_min", type=click.FloatRange(0.0), default=DEFAULT_RECORD_PART_MIN,
              show_default=True, metavar="MINUTES",
              help="The replay's recording in parts of this many minutes (as `dct run --record-part-minutes`); "
                   "0: one file.")
@click.option("--lidar-topic", help="The lidar topic to replay (default: the config's ros.inputs.lidar).")
@click.option("--imu-topic", help="The IMU topic (default: the config's ros.inputs.imu).")
@click.option("--image-topic", help="The camera topic (default: the config's ros.inputs.camera).")
@click.option("--camera-info-topic",
              help="The camera driver's CameraInfo topic, held against the calibration as live (default: the "
                   "config's ros.inputs.camera_info).")
@click.option("--goal", nargs=3, type=float, metavar="X Y YAW",
              help="A bag only: a goal in the odometry frame (default: none, the controller stands by). A dct "
                   "recording replays its own goals.")
def replay_command(**o) -> None:
    """Replay RECORDING (a `dct run --record` MCAP, or a rosbag2 folder / MCAP bag of the robot's drivers)
    through the controller, open loop and deterministic: the same recording gives the same outputs."""
    from calibration.errors import ConfigFileError
    from calibration.outputs import OutputPathError
    from runtime.app.replay.outputs import output_paths
    from runtime.app.replay.source import open_source

    for what, key in (("--robot", "robot_path"), ("--calibration", "calibration_path"), ("--config", "config_path")):
        if o[key] is not None and not o[key].is_file():
            raise InputError(f"{what}: {o[key]}: no such file")
    rec_path: Path = o["recording"]
    out_dir = o["out_dir"] or rec_path.parent / f"{rec_path.name.removesuffix('.mcap')}.replay"
    try:
        paths = output_paths(out_dir, o["force"], inputs=[rec_path])
        loaded = _load_robot(o)
        configs: dict = {}

        def topics_for(run_info: dict) -> dict:
            configs["config"] = cfg = _config(o, run_info, loaded)
            return {s: o[k] or _topic(cfg, s) for k, s in _STREAM_OF_OPTION.items()}

        src = open_source(rec_path, topics_for)
        if src.kind == "bag" and src.first_s is None:
            raise InputError(f"{rec_path}: the bag has no messages")
        config = _with_streams(configs["config"], src.streams)
        if src.kind == "bag" and o["config_path"] is None:
            config = without_base(config)
        loaded = dataclasses.replace(loaded, config=config)
    except (OutputPathError, ReplaySourceError, ConfigFileError) as exc:
        raise InputError(str(exc)) from None
    say = lambda s: click.echo(s, err=True)  # noqa: E731
    say(_describe(src, loaded.config))
    if loaded.config.uses_vlm_backend:
        say(_vlm_line(src))
    if src.kind == "bag":
        goal = tuple(o["goal"]) if o["goal"] else None
    else:  # its own goals (a replay that stood by, standing by again)
        goal = None if src.run_info.get("standby") is True else src.ticks[0].goal
    part_s = o["record_part_min"] * 60.0 if o["record_part_min"] > 0 else None
    summary = _run(src, loaded, goal, paths, o["rate"] == "recorded", say, part_s)
    say(_result_line(summary, paths["summary"].parent))


def _load_robot(o: dict):
    """The robot description and calibration as `dct run` loads them (runtime.app.run_inputs); the
    config is chosen later (_config). The all-fixed preset only gets the loading past `dct run`'s
    planner checks, which are about driving a robot, not replaying one."""
    from runtime.app.run_inputs import RunInputError, RunOptions, load_inputs

    try:
        return load_inputs(RunOptions(robot_path=o["robot_path"], calibration_path=o["calibration_path"],
                                      planner="all-fixed"))
    except RunInputError as exc:
        raise InputError(str(exc)) from None


def _config(o: dict, run_info: dict, loaded):
    """--config, else the recording's own config, else the shipped one; checked against the robot."""
    from runtime.config import check_against_robot, load_controller_config
    from runtime.config.schema import ControllerConfig

    recorded = run_info.get("controller_config")
    if o["config_path"] is not None or recorded is None:
        config = load_controller_config(o["config_path"])
        where = str(o["config_path"] or "the shipped controller config")
    else:
        from pydantic import ValidationError

        where = f"{o['recording']} (the config it was recorded with)"
        try:
            config = ControllerConfig.model_validate_json(json.dumps(recorded))
        except ValidationError as exc:
            err = exc.errors()[0]
            raise InputError(f"{where}: {'.'.join(str(p) for p in err['loc'])}: {err['msg']}") from None
    try:
        check_against_robot(config, loaded.robot)
    except ValueError as exc:
        raise InputError(f"{where}: {exc}") from None
    return config


def _topic(config, stream: str) -> str | None:
    t = getattr(config.ros.inputs, stream)
    return None if t is None else t.topic


def _with_streams(config, streams: dict):
    """The config's ros.inputs reading the topics found, as the types found (a bag's PointCloud2
    lidar where the config says CustomMsg is read as PointCloud2)."""
    from runtime.io.ros.receiver import CameraInfoTopic, CameraTopic, ImuTopic, LidarTopic

    inputs = config.ros.inputs
    update = {}
    for stream, cls in (("lidar", LidarTopic), ("imu", ImuTopic), ("camera", CameraTopic),
                        ("camera_info", CameraInfoTopic)):
        if stream not in streams:
            continue
        topic, type_name = streams[stream]
        old = getattr(inputs, stream)
        if old is not None and old.type == type_name:
            update[stream] = old.model_copy(update={"topic": topic})
        else:
            update[stream] = cls(topic=topic, type=type_name)
    ros = config.ros.model_copy(update={"inputs": inputs.model_copy(update=update)})
    return config.model_copy(update={"ros": ros})


def without_base(config):
    """The odometry settings for a recording without the base's feedback (a drivers' bag): no wheel
    odometry comes, so the fusion is told the wheels know nothing (their noise floor at its
    largest, the plausibility gate wide open) and ICP predicts with its own constant-velocity model:
    the pose follows the lidar alone. (The IMU only calibrates the gyro bias: without a base the
    controller never leaves its start-up, where the IMU is used for that.)"""
    odo = config.odometry
    fusion = odo.fusion.model_copy(update={"wheel_floor_m": 1.0, "wheel_floor_rad": 1.0, "gate_m": 10.0,
                                           "gate_rad": 3.2})
    odo = odo.model_copy(update={"fusion": fusion, "icp_prior": "constant_velocity"})
    return config.model_copy(update={"odometry": odo})


def _describe(src, config) -> str:
    streams = "; ".join(f"{s} {t} ({ty.split('/')[-1]})" for s, (t, ty) in src.streams.items())
    if src.kind == "dct" and src.can_rx:
        acc = src.recorder_account or {}
        drops = acc.get("dropped_total")
        return (f"dct replay: {src.path} (a dct run recording: {len(src.ticks)} ticks, {src.duration_s:.1f} s"
                + ("" if src.complete else f", cut off: {src.stopped_by}")
                + (f", {drops} records dropped by the recorder" if drops else "")
                + (f", tick {', '.join(map(str, src.now_repaired))} replayed at its start (scheduled + lateness): "
                   "recorded with a deadline stop's time" if src.now_repaired else "")
                + f"): {streams}; the base: {len(src.can_rx)} CAN frames; planner {config.preset}")
    return (f"dct replay: {src.path} ({'a replay' if src.kind == 'dct' else 'a bag'}: {src.duration_s:.1f} s): "
            f"{streams}; no base feedback: the controller waits for the base (its watchdogs say so) and the "
            f"odometry follows the lidar alone (odometry.fusion {config.odometry.fusion.wheel_floor_m:g} m wheel "
            f"noise floor, icp_prior {config.odometry.icp_prior}); planner {config.preset}")


def _vlm_line(src) -> str:
    """What the VPP's VLM does in this replay (runtime.app.replay.vlm)."""
    if src.vlm_answers is None:
        return ("dct replay: the recording carries no VLM answers (/dct/vpp/backend_answer): every VLM request "
                "fails at once, so the VPP partition and the commands may differ from the live run's")
    failed = sum(a.error is not None for _, a in src.vlm_answers)
    return (f"dct replay: the VLM's answers as the live run received them: {len(src.vlm_answers)} "
            f"({failed} failed), each delivered at its live tick")


def _run(src, loaded, goal, paths: dict, pace: bool, say, part_s: float | None) -> dict:
    from calibration.outputs import atomic_write_json, atomic_write_text
    from runtime.app.replay.outputs import compare_odometry, tum_text, write_report
    from runtime.app.replay.session import ReplaySetup, run_replay
    from models.errors import DistanceNetError

    paths["summary"].parent.mkdir(exist_ok=True)
    t0 = time.perf_counter()
    try:
        res = run_replay(ReplaySetup(src, loaded, goal, paths["recording"], pace, part_s), say)
    except DistanceNetError as exc:
        raise InputError(f"planner.distance_net_path: {exc}") from None
    atomic_write_text(paths["trajectory"], tum_text(res.poses))
    rep = write_report(paths["recording"], paths["report"], f"replay of {src.path.name}")
    summary = {
        "recording": str(src.path), "kind": src.kind, "streams": {s: list(v) for s, v in src.streams.items()},
        "ticks": res.ticks, "recording_s": src.duration_s, "replay_wall_s": res.wall_s,
        "total_wall_s": time.perf_counter() - t0,
        "inputs": {"sensor_samples": res.samples_fed, "sensor_samples_missing": res.samples_missing,
                   "can_frames": res.can_frames_fed, "frames_sent": res.frames_sent,
                   "ticks_now_repaired": list(src.now_repaired)},
        "icp": res.icp, "vlm": res.vlm, "sensor_errors": res.sensor_errors, "controller_state": res.controller.get("state"),
        "calibration_check": _calibration_check(res.controller.get("calibration")),
        "odometry_vs_live": compare_odometry(src.live_poses, res.poses) if src.live_poses else None,
        "latency": {"tick": rep["tick"], "deadline_misses": rep["deadline_misses"]["count"]},
        "outputs": {k: str(p) for k, p in paths.items()},
    }
    atomic_write_json(paths["summary"], summary)
    return summary


def _calibration_check(d: dict | None) -> dict | None:
    """What the calibration check saw in the replay (runtime.perception.calibration_monitor)."""
    if d is None:
        return None
    keys = ("mismatch", "mismatch_at_s", "intrinsics", "camera_infos_compared", "floor_fits", "floor_last_problem")
    return {k: d.get(k) for k in keys}


def _result_line(s: dict, out: Path) -> str:
    line = (f"dct replay: {s['ticks']} ticks in {s['replay_wall_s']:.1f} s (the recording: {s['recording_s']:.1f} s); "
            f"{s['inputs']['sensor_samples']} sensor samples, {s['inputs']['can_frames']} CAN frames")
    if s["inputs"]["sensor_samples_missing"]:
        line += f" ({s['inputs']['sensor_samples_missing']} missing from the recording: not exact)"
    check = s.get("calibration_check") or {}
    if check.get("mismatch"):
        line += f"; the calibration check found a mismatch at {check['mismatch_at_s']:.2f} s (see calibration_check)"
    if (s.get("vlm") or {}).get("mismatched"):
        line += f"; {s['vlm']['mismatched']} VLM answers out of step with the live run"
    if s["icp"].get("out_of_step"):
        line += f"; {s['icp']['out_of_step']} ICP frames out of step with the live run"
    cmp = s["odometry_vs_live"]
    if cmp and cmp["matched"]:
        line += (f"; odometry vs the live run: max {cmp['max_m'] * 1e3:.2f} mm, mean {cmp['mean_m'] * 1e3:.2f} mm "
                 f"over {cmp['matched']} poses")
    return line + f"; outputs in {out}"
