"""The MuJoCo world of one scenario: the compiled model (hil_sim.world.model_spec builds it) and
its data, stepped one physics step at a time, with the accessors the firmware emulator, the
sensors and the metrics read (robot pose and wheels, obstacles, people).
"""
from __future__ import annotations

import math
import os

os.environ.setdefault("MUJOCO_GL", "egl")  # before mujoco is imported: no display here, headless EGL

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from calibration.robot_description import RobotDescription  # noqa: E402
from hil_sim.world.model_spec import (CAMERA_NAME, IMU_NAME, LIDAR_GEOMGROUP, ROBOT_OWN_GEOM_GROUPS,  # noqa: E402
                                      WHEEL_NAMES, WorldError, build_spec, yaw_quat)
from hil_sim.world.robot_variant import RobotVariant  # noqa: E402
from hil_sim.world.scenario import Scenario  # noqa: E402
from hil_sim.world.scenario_checks import DEFAULT_GROUND_CLEARANCE_M, check_scenario_against_robot  # noqa: E402
from hil_sim.world.scenario_objects import CylinderObstacle  # noqa: E402


class World:
    """A compiled scenario: MuJoCo model and data plus the robot/obstacle accessors.

    The scenario is checked against the robot first (hil_sim.world.scenario_checks.check_scenario_against_robot:
    ScenarioError for a start pose in an obstacle, an unreachable goal, an obstacle the lidar
    cannot see; its warnings are kept in `scenario_warnings`). ground_clearance_m: the
    controller's ground cut (ObstaclePointsConfig.ground_clearance_m).

    Sensors in the model: the camera `camera_name` on base_link (render it with
    `camera_hidden_geom_groups` hidden: it sits inside the chassis box), the IMU's gyro and
    accelerometer `imu_sensor_names`. The lidar is cast by hil_sim.sensors.lidar.SimLidar from
    `lidar_mount` on base_link with `lidar_geomgroup` (robot groups excluded).
    hil_sim.world.sensor_rig.SensorRig wires all three.

    variant: the robot as built (hil_sim.world.robot_variant.RobotVariant of `robot`): its lidar
    and camera at their true mounts, its camera's true intrinsics and distortion (`camera_lens`);
    None: the robot as described. `robot` is then the variant's built robot.
    """

    def __init__(self, scenario: Scenario, robot: RobotDescription, seed: int = 0, *,
                 ground_clearance_m: float = DEFAULT_GROUND_CLEARANCE_M, variant: RobotVariant | None = None) -> None:
        if variant is not None:
            if variant.nominal_robot != robot:
                raise WorldError(f"the robot variant {variant.label} was made from another description of robot "
                                 f"'{variant.nominal_robot.name}' than the one given ('{robot.name}')")
            robot = variant.robot
        #: The robot variant the world is built as (None: the robot description as it is).
        self.robot_variant = variant
        #: The camera as built (None: the description's pinhole).
        self.camera_lens = variant.lens if variant is not None else None
        # First: a scenario this robot cannot start in (inside a wall, an invisible obstacle,
        # an unreachable goal) is a ScenarioError naming the field, before any physics runs.
        #: Warnings of hil_sim.world.scenario_checks.check_scenario_against_robot (each names its field).
        self.scenario_warnings: list[str] = check_scenario_against_robot(
            scenario, robot, ground_clearance_m=ground_clearance_m)
        self.scenario = scenario
        self.robot = robot
        self.spec = build_spec(scenario, robot, self.camera_lens)
        self.model: mujoco.MjModel = self.spec.compile()
        self.data = mujoco.MjData(self.model)
        m = self.model
        self.timestep_s: float = float(m.opt.timestep)
        self._index_robot(m)
        self._index_obstacles(m, scenario)

        self.camera_name: str = CAMERA_NAME
        self.camera_id: int = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_CAMERA, CAMERA_NAME)
        self.camera_hidden_geom_groups: tuple[int, ...] = ROBOT_OWN_GEOM_GROUPS
        self.imu_sensor_names: tuple[str, str] = (f"{IMU_NAME}_gyro", f"{IMU_NAME}_accel")
        self.lidar_mount = robot.sensors.lidar.mount
        self.lidar_geomgroup: tuple[int, int, int, int, int, int] = LIDAR_GEOMGROUP

        self.seed = seed
        self.reset(seed)

    def _index_robot(self, m: mujoco.MjModel) -> None:
        """The robot's body, geoms, base free joint, wheel joints and actuators in the model."""
        self.robot_body_id: int = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "base_link")
        robot_bodies = {self.robot_body_id} | {
            mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, f"wheel_{n}") for n in WHEEL_NAMES
        }
        self.robot_geom_ids: np.ndarray = np.flatnonzero(np.isin(m.geom_bodyid, list(robot_bodies)))
        self._is_robot_geom = np.zeros(m.ngeom, dtype=bool)
        self._is_robot_geom[self.robot_geom_ids] = True
        self._base_qpos = int(m.jnt_qposadr[m.body_jntadr[self.robot_body_id]])
        self._base_qvel = int(m.jnt_dofadr[m.body_jntadr[self.robot_body_id]])
        wheel_joints = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, f"wheel_{n}") for n in WHEEL_NAMES]
        self._wheel_qpos = np.array([m.jnt_qposadr[j] for j in wheel_joints])
        self._wheel_qvel = np.array([m.jnt_dofadr[j] for j in wheel_joints])
        self._wheel_act = np.array(
            [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_ACTUATOR, f"motor_{n}") for n in WHEEL_NAMES]
        )

    def _index_obstacles(self, m: mujoco.MjModel, scenario: Scenario) -> None:
        """Obstacles (file order) then walls, their classes, geoms, free bodies and costs; the people."""
        # Walls are fixed obstacles for the metrics.
        self.obstacle_names: list[str] = [o.name for o in scenario.obstacles] + scenario.wall_names()
        self._class = {o.name: o.obstacle_class for o in scenario.obstacles}
        self._class.update({n: "fixed" for n in scenario.wall_names()})
        self._index = {n: i for i, n in enumerate(self.obstacle_names)}
        #: geom id -> obstacle index (-1: not an obstacle: floor or robot).
        self.geom_obstacle_index = np.full(m.ngeom, -1, dtype=np.int64)
        self._obstacle_body: dict[str, int] = {}
        self._obstacle_geoms: dict[str, list[int]] = {}
        free = {o.name for o in scenario.obstacles if o.is_free_body}
        curtains = {o.name: o for o in scenario.obstacles if o.obstacle_class == "deformable"}
        for name, i in self._index.items():
            if name in curtains:  # one geom per slat
                gids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, f"{name}/slat_{k}")
                        for k in range(curtains[name].slat_count)]
            else:
                gids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, name)]
            self.geom_obstacle_index[gids] = i
            self._obstacle_geoms[name] = gids
            if name in free:
                self._obstacle_body[name] = int(m.geom_bodyid[gids[0]])
        self._obstacle_geom: dict[str, int] = {n: g[0] for n, g in self._obstacle_geoms.items()}
        self.obstacle_classes: list[str] = [self._class[n] for n in self.obstacle_names]
        #: Contact cost 0..10 per obstacle (obstacle_names order; walls 10).
        costs = scenario.contact_costs()
        self.obstacle_costs: np.ndarray = np.array([costs[n] for n in self.obstacle_names], dtype=float)
        # People: (name, mocap index, pose xy, the scenario obstacle with its walk).
        self._people: list[tuple[str, int, tuple[float, float], CylinderObstacle]] = [
            (o.name, int(m.body_mocapid[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, o.name)]),
             (o.pose.x_m, o.pose.y_m), o)
            for o in scenario.obstacles if o.obstacle_class == "person"
        ]
        #: Their walks measured once (None: standing), asked at every physics step.
        self._paths = [None if ob.walk is None else ob.walk.path(start) for _, _, start, ob in self._people]

    # --- state -------------------------------------------------------------------------
    def reset(self, seed: int = 0) -> None:
        """Back to the scenario's initial state; `seed` drives the optional randomization."""
        m, d = self.model, self.data
        self.seed = int(seed)
        mujoco.mj_resetData(m, d)
        rng = np.random.default_rng(self.seed)
        rnd = self.scenario.randomization
        for ob in self.scenario.obstacles:
            if not ob.is_free_body:
                continue
            body = self._obstacle_body[ob.name]
            adr = int(m.jnt_qposadr[m.body_jntadr[body]])
            dx, dy = rng.normal(0.0, rnd.free_body_xy_noise_m, 2) if rnd.free_body_xy_noise_m > 0 else (0.0, 0.0)
            dyaw = math.radians(rng.normal(0.0, rnd.free_body_yaw_noise_deg)) if rnd.free_body_yaw_noise_deg > 0 else 0.0
            d.qpos[adr:adr + 3] = [ob.pose.x_m + dx, ob.pose.y_m + dy, ob.height_m / 2]
            d.qpos[adr + 3:adr + 7] = yaw_quat(ob.pose.yaw_rad + dyaw)
        self._move_people(float(d.time))
        mujoco.mj_forward(m, d)

    def _move_people(self, t_s: float) -> None:
        for (_, mocap, _, _), path in zip(self._people, self._paths):
            if path is not None:
                self.data.mocap_pos[mocap, :2] = path.at(t_s)

    def person_position(self, name: str, t_s: float | None = None) -> np.ndarray:
        """(x, y) of a person now, or where its walk puts it at time t_s."""
        for pname, mocap, start, ob in self._people:
            if pname == name:
                if t_s is None:
                    return self.data.mocap_pos[mocap, :2].copy()
                if ob.walk is None:
                    return np.array(start, dtype=float)
                return ob.walk.positions(start, t_s)[0]
        raise WorldError(f"no person named '{name}'; people: {', '.join(p[0] for p in self._people) or '(none)'}")

    def step(self) -> None:
        """One physics step (mj_step) with the torques last set; people first walk to where
        their waypoints put them at this step's time."""
        if self._people:
            self._move_people(float(self.data.time))
        mujoco.mj_step(self.model, self.data)

    @property
    def time_s(self) -> float:
        return float(self.data.time)

    # --- robot ---------------------------------------------------------------------------
    def set_wheel_torques(self, torques_nm: np.ndarray) -> None:
        """Motor torques (N m) for FR, FL, RL, RR; positive drives the robot forward."""
        t = np.asarray(torques_nm, dtype=float)
        if t.shape != (4,):
            raise WorldError(f"set_wheel_torques: expected 4 torques (FR, FL, RL, RR), got shape {t.shape}")
        if not all(map(math.isfinite, t.tolist())):
            raise WorldError(f"set_wheel_torques: torques must be finite, got {t.tolist()}")
        self.data.ctrl[self._wheel_act] = t

    def wheel_speeds_radps(self) -> np.ndarray:
        """Wheel angular speeds relative to the chassis (rad/s, FR, FL, RL, RR; + = forward)."""
        return self.data.qvel[self._wheel_qvel].copy()

    def wheel_angles_rad(self) -> np.ndarray:
        """Accumulated wheel angles (rad, FR, FL, RL, RR; + = forward)."""
        return self.data.qpos[self._wheel_qpos].copy()

    def robot_pose(self) -> tuple[float, float, float]:
        """Ground-truth (x_m, y_m, yaw_rad) of base_link in the world."""
        q = self.data.qpos[self._base_qpos:self._base_qpos + 7]
        w, x, y, z = q[3], q[4], q[5], q[6]
        yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
        return float(q[0]), float(q[1]), yaw

    def robot_xy(self) -> tuple[float, float]:
        """Ground-truth (x_m, y_m) of base_link in the world (robot_pose without the yaw)."""
        q, i = self.data.qpos, self._base_qpos
        return float(q[i]), float(q[i + 1])

    def robot_body_velocity(self) -> tuple[float, float, float]:
        """Ground-truth (forward_mps, lateral_mps, yaw_rate_radps) of base_link, planar."""
        v = self.data.qvel[self._base_qvel:self._base_qvel + 6]
        _, _, yaw = self.robot_pose()
        c, s = math.cos(yaw), math.sin(yaw)
        # Free joint: linear velocity in the world frame, angular velocity in the body frame.
        omega_world = self.data.xmat[self.robot_body_id].reshape(3, 3) @ v[3:6]
        return float(c * v[0] + s * v[1]), float(-s * v[0] + c * v[1]), float(omega_world[2])

    # --- obstacles -------------------------------------------------------------------------
    def obstacle_class(self, name: str) -> str:
        """The scenario class: fixed, movable, heavy, fragile, deformable or person (walls: fixed)."""
        try:
            return self._class[name]
        except KeyError:
            raise WorldError(f"no obstacle named '{name}'; known: {', '.join(self.obstacle_names)}") from None

    def obstacle_position(self, name: str) -> np.ndarray:
        """Current (x, y, z) of an obstacle's centre in the world (walls: the wall's centre)."""
        cls = self.obstacle_class(name)
        if name in self._obstacle_body:
            return self.data.xpos[self._obstacle_body[name]].copy()
        if cls == "person":
            return self.data.mocap_pos[self.model.body_mocapid[self.model.geom_bodyid[self._obstacle_geom[name]]]].copy()
        if cls == "deformable":  # where it hangs (its slats swing, the curtain stays)
            ob = self.scenario.obstacle(name)
            return np.array([ob.pose.x_m, ob.pose.y_m, ob.height_m / 2])
        return self.data.geom_xpos[self._obstacle_geom[name]].copy()

    def obstacle_geom_id(self, name: str) -> int:
        """The obstacle's geom (a curtain's first slat: see obstacle_geom_ids)."""
        self.obstacle_class(name)
        return self._obstacle_geom[name]

    def obstacle_geom_ids(self, name: str) -> list[int]:
        """Every geom of the obstacle (one, or a curtain's slats)."""
        self.obstacle_class(name)
        return list(self._obstacle_geoms[name])


__all__ = ["World"]
