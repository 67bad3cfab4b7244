"""`dct run`'s inputs: every file and option loaded and checked before anything moves.

A problem is one line naming the file and the field (RunInputError, exit status 2), and the
base is never enabled.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


class RunInputError(ValueError):
    """Bad input to `dct run`: one line naming the file and the field (exit status 2)."""


#: Minutes of a recording's part (runtime.io.recording.recorder): the MCAP writer's index of a
#: part stays in memory until the part is finished, about 10 MB for ten minutes in real time.
DEFAULT_RECORD_PART_MIN = 10.0


@dataclass
class RunOptions:
    robot_path: Path | None = None
    calibration_path: Path | None = None
    config_path: Path | None = None
    goal: tuple[float, float, float] | None = None
    record_path: Path | None = None
    #: Minutes per part of the recording (runtime.io.recording.recorder); 0: one file.
    record_part_min: float = DEFAULT_RECORD_PART_MIN
    json_path: Path | None = None
    force: bool = False
    #: Overrides of the config (`dct hil run --realtime` gives each run its own domain and group).
    domain_id: int | None = None
    #: ros.middleware (auto | rclpy | cyclonedds) and ros.discovery (subnet | localhost).
    middleware: str | None = None
    discovery: str | None = None
    can_interface: str | None = None
    can_channel: str | None = None
    can_port: int | None = None
    #: Without --goal: how long to wait for the first goal on the goal topic (None: forever).
    goal_wait_s: float | None = None
    #: A preset (runtime.config.presets) in place of the config's planner and partition.
    planner: str | None = None
    #: Leave the loop thread at normal priority (config `realtime:` not asked for): real-time HIL
    #: on a machine shared with the simulator, where SCHED_FIFO could starve it.
    normal_priority: bool = False
    #: Let the blind pure-pursuit planner run (no obstacle awareness: tests and benches only).
    allow_pure_pursuit: bool = False
    #: `--resume-file`: the warm-restart state (runtime.app.resume); None: none kept.
    resume_path: Path | None = None
    resume_max_age_s: float = 60.0


@dataclass
class Loaded:
    robot: object
    config: object
    wheel_calibration: tuple[float, float] | None
    camera_K: np.ndarray
    camera_dist: np.ndarray
    bus_config: object
    #: The camera and mounts as calibrated (calibration.sensor_calibration.SensorCalibration: the
    #: calibration file's where it has them, else the robot description's nominal ones), for every
    #: stage, /tf_static and the recording.
    sensor_calibration: object = None
    notes: list[str] = field(default_factory=list)


def load_inputs(opts: RunOptions) -> Loaded:
    """Load and validate every file and option; RunInputError (one line) on the first problem."""
    robot, config, cal, wheel_calibration = _load_files(opts)
    cfg_name = str(opts.config_path or "the shipped controller config")
    from calibration.errors import ConfigFileError
    from calibration.sensor_calibration import sensor_calibration

    try:
        sensors = sensor_calibration(robot, cal, opts.calibration_path,
                                     robot_source=f"robot description {opts.robot_path}" if opts.robot_path else None)
    except ConfigFileError as exc:
        raise RunInputError(str(exc)) from None
    K, dist = np.asarray(sensors.camera.K, float), np.asarray(sensors.camera.dist, float)
    if opts.planner is not None:
        config = config.with_planner_mode(opts.planner)
    _check_planner(config, robot, opts, cfg_name)
    if opts.goal is not None:
        from runtime.common.geometry import Pose2D
        from runtime.controller.goals import GoalError, check_goal

        try:
            check_goal(Pose2D(*opts.goal), "--goal")
        except (GoalError, TypeError) as exc:
            raise RunInputError(f"--goal: {opts.goal}: {exc}") from None
        _check_goal_workspace(config, opts.goal, cfg_name)
    bus_config = _bus_config(config, opts, cfg_name)
    config = _ros_overrides(config, opts)
    if config.ros.inputs.lidar is None and config.uses_lidar:
        raise RunInputError(f"{cfg_name}: ros.inputs.lidar: planner {config.planner.algorithm} needs a lidar topic")
    if config.uses_distance_net:  # the distance net must fit this robot
        from models.distance_net import DistanceNet
        from models.errors import DistanceNetError

        try:
            DistanceNet.load(config.planner.distance_net_path, robot=robot)
        except DistanceNetError as exc:
            raise RunInputError(f"{cfg_name}: planner.distance_net_path: {exc}") from None
    return Loaded(robot, config, wheel_calibration, K, dist, bus_config, sensor_calibration=sensors)


def _ros_overrides(config, opts: RunOptions):
    """The config with the command line's DDS domain, middleware and discovery range."""
    ros = config.ros
    if opts.domain_id is not None:
        ros = ros.model_copy(update={"inputs": ros.inputs.model_copy(update={"domain_id": opts.domain_id})})
    if opts.middleware is not None:
        ros = ros.model_copy(update={"middleware": opts.middleware})
    if opts.discovery is not None:
        ros = ros.model_copy(update={"discovery": opts.discovery})
    return config if ros is config.ros else config.model_copy(update={"ros": ros})


def _check_goal_workspace(config, goal: tuple[float, float, float], cfg_name: str) -> None:
    """--goal (odometry frame) inside ros.inputs.goal.workspace, when one is configured."""
    ws = config.ros.inputs.goal.workspace if config.ros.inputs.goal is not None else None
    if ws is None:
        return
    refused = ws.refusal(float(goal[0]), float(goal[1]), config.ros.outputs.odom_frame)
    if refused is not None:
        reason, _, text = refused
        raise RunInputError(f"[{reason}] --goal: {text} ({cfg_name}: ros.inputs.goal.workspace)")


def _load_files(opts: RunOptions):
    """(robot description, config, calibration file or None, wheel calibration)."""
    from calibration.errors import ConfigFileError
    from calibration.robot_description import load_robot_description
    from calibration.wheel_odometry import wheel_params
    from runtime.config import load_controller_config

    try:
        robot = load_robot_description(opts.robot_path)
        config = load_controller_config(opts.config_path)
        cal = None
        if opts.calibration_path is not None:
            from calibration.calibration_file import load_calibration

            cal = load_calibration(opts.calibration_path)
        params = wheel_params(robot, cal)
    except ConfigFileError as exc:
        raise RunInputError(str(exc)) from None
    return robot, config, cal, (params.effective_track_m, params.wheel_scale)


def _check_planner(config, robot, opts: RunOptions, cfg_name: str) -> None:
    from runtime.config import check_against_robot

    if not config.uses_lidar and not opts.allow_pure_pursuit:
        raise RunInputError(f"{cfg_name}: planner {config.planner.algorithm} has no obstacle awareness (it drives at "
                            "the goal through whatever is there): only with --allow-pure-pursuit, never on a robot "
                            "among people")
    if config.uses_vlm_backend and config.vpp.backend.kind == "sim-oracle":
        choice = (f"planner.mode {config.planner.mode}" if config.planner.mode is not None
                  else f"partition {config.partition}")
        raise RunInputError(f"{cfg_name}: {choice} with vpp.backend.kind sim-oracle: the "
                            f"{config.partition} partition's sim-oracle exists only inside the lockstep simulator's "
                            "process; set vpp.backend.kind: openai-compatible (docs/algorithms/vpp.md, backends) or "
                            "run --planner all-fixed")
    try:
        check_against_robot(config, robot)
    except ValueError as exc:
        raise RunInputError(f"{cfg_name}: {exc}") from None


def _bus_config(config, opts: RunOptions, cfg_name: str):
    """The config's CAN bus with the command line's overrides."""
    from pydantic import ValidationError

    from firmware_bridge.buses import BusConfig

    bus = config.can_bus.model_dump()
    if opts.can_interface is not None:
        bus = {"interface": opts.can_interface, "channel": None}
    if opts.can_channel is not None:
        bus["channel"] = opts.can_channel
    if opts.can_port is not None:
        bus["udp_port"] = opts.can_port
    try:
        return BusConfig(**bus)
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(p) for p in err["loc"]) or "can_bus"
        raise RunInputError(f"{cfg_name}: can_bus.{where}: {err['msg']}") from None
