"""The MuJoCo world of one scenario, built with `mujoco.MjSpec` (no MJCF strings).

Contents: a floor plane, walls and fixed obstacles (static geoms of the world body), movable
and heavy obstacles (free bodies), fragile ones (free bodies or static geoms, as the file says),
deformable ones (a curtain: light slats on hinge joints along its top edge, which the robot
swings aside), people (kinematic mocap cylinders walking their waypoints: World.step moves
them before each physics step; nothing pushes them), and the robot: a chassis with a free joint and four wheels on
hinge joints driven by torque (motor) actuators. The firmware emulator closes the wheel-speed
loop; this module only applies the torques it computes.

Frames: world x, y on the floor, z up. The robot body frame is base_link (centre of the
footprint on the ground, x forward, y left). Wheel order: FR, FL, RL, RR (motor 1..4).

Friction model: MuJoCo mixes two geoms' friction by taking the maximum unless one has a
higher `priority`. Robot geoms carry a very low friction, so the wheel-floor coefficient is
`floor.friction` of the scenario; free-body obstacles have priority 1, so their coefficient
(`friction`) is used against the floor and against the robot.
"""
from __future__ import annotations

import math
import os

os.environ.setdefault("MUJOCO_GL", "egl")  # before mujoco is imported: no display here, headless EGL

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from calibration.robot_description import RobotDescription  # noqa: E402
from hil_sim.sensors.camera import add_camera_to_spec, ensure_offscreen_buffer
from hil_sim.sensors.imu import add_imu_to_spec
from hil_sim.world.scenario import Scenario
from hil_sim.world.scenario_checks import DEFAULT_GROUND_CLEARANCE_M, check_scenario_against_robot
from hil_sim.world.scenario_objects import BoxObstacle, CylinderObstacle

#: Physics step. 1 ms: the firmware's discrete wheel-speed loop (run once per step) on the
#: light wheel inertia needs it to stop a wheel within a few ms without chatter (see the
#: module docstring of firmware_bridge.firmware_emulator and the tests).
TIMESTEP_S = 0.001

#: Geom groups: the scene (floor, walls, fixed obstacles), free-body obstacles, the robot.
#: Sensors exclude ROBOT_GEOM_GROUP (e.g. mj_multiRay's geomgroup mask).
SCENE_GEOM_GROUP = 0
FREE_BODY_GEOM_GROUP = 1
ROBOT_GEOM_GROUP = 2
#: The tyre spheres that carry the floor contact (hidden by default in renderers).
TYRE_GEOM_GROUP = 3
#: What the robot's own sensors must not see: its chassis and wheels (the LIMO camera and lidar
#: mounts lie inside the chassis boxes, which are a coarse collision shape, not the real cover).
ROBOT_OWN_GEOM_GROUPS: tuple[int, int] = (ROBOT_GEOM_GROUP, TYRE_GEOM_GROUP)
#: mj_multiRay geomgroup flags for the robot's lidar: every group but the robot's own.
LIDAR_GEOMGROUP: tuple[int, int, int, int, int, int] = tuple(  # type: ignore[assignment]
    0 if g in ROBOT_OWN_GEOM_GROUPS else 1 for g in range(6))
#: Names of the robot's sensors in the model.
CAMERA_NAME = "camera"
IMU_NAME = "imu"

WHEEL_NAMES: tuple[str, str, str, str] = ("fr", "fl", "rl", "rr")
#: Lateral side of each wheel: +1 left, -1 right (order FR, FL, RL, RR).
WHEEL_SIDE = np.array([-1.0, 1.0, 1.0, -1.0])
#: Longitudinal side of each wheel: +1 front, -1 rear.
WHEEL_END = np.array([1.0, 1.0, -1.0, -1.0])

WHEEL_MASS_KG = 0.25  # hub motor + tyre, each
#: Share of the chassis mass in the lower box (battery, electronics): keeps the centre of mass
#: low (about 8 cm) so that full braking (mu g) cannot tip the short-wheelbase body forward.
LOWER_MASS_FRACTION = 0.75
NOSLIP_ITERATIONS = 0
ROBOT_GEOM_FRICTION = 0.05  # low, so the other geom's friction governs each robot contact
GROUND_CLEARANCE_M = 0.025
FIXED_DEFAULT_FRICTION = 0.5
CONE = mujoco.mjtCone.mjCONE_ELLIPTIC
IMPRATIO = 10.0  # stiffer friction: less creep of a wheel held at zero speed
#: Reflected rotor inertia of the (geared) hub motor, kg m^2, added to each wheel joint.
WHEEL_ARMATURE = 5e-4
WALL_FRICTION = 0.5

# Collision bits: the floor touches chassis, obstacles and tyre spheres; tyre spheres touch
# only the floor; wheel cylinders touch only obstacles.
_BIT_FLOOR, _BIT_OBJECT, _BIT_TYRE = 1, 2, 4
_WALL_RGBA = (0.75, 0.75, 0.72, 1.0)
_FIXED_RGBA = (0.45, 0.35, 0.25, 1.0)
_FREE_RGBA = (0.85, 0.6, 0.25, 1.0)  # movable and heavy look alike on purpose
_ROBOT_RGBA = (0.2, 0.2, 0.22, 1.0)
_WHEEL_RGBA = (0.05, 0.05, 0.05, 1.0)
_CURTAIN_RGBA = (0.55, 0.2, 0.25, 1.0)
_PERSON_RGBA = (0.25, 0.4, 0.75, 1.0)

#: Curtain slats: the gap between neighbours (m), the free space under them (m, above the
#: controller's ground cut so that the lidar keeps their points), mass of one slat when the
#: file gives no mass_kg (kg), hinge damping (N m s/rad) so that a swung slat settles in a
#: second or two, and their friction (low: the slats slide over the robot's cover).
CURTAIN_SLAT_GAP_M = 0.004
CURTAIN_BOTTOM_CLEARANCE_M = 0.05
CURTAIN_SLAT_MASS_KG = 0.05
CURTAIN_HINGE_DAMPING = 0.01
CURTAIN_FRICTION = 0.15


class WorldError(ValueError):
    """A bad argument to the simulated world (wrong torque vector, unknown obstacle)."""


def _yaw_quat(yaw_rad: float) -> list[float]:
    return [math.cos(yaw_rad / 2), 0.0, 0.0, math.sin(yaw_rad / 2)]


def build_spec(scenario: Scenario, robot: RobotDescription) -> mujoco.MjSpec:
    """The MjSpec of a scenario with the robot at its start pose (uncompiled)."""
    spec = mujoco.MjSpec()
    spec.modelname = f"{scenario.name}_{robot.name}"
    opt = spec.option
    opt.timestep = TIMESTEP_S
    opt.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    opt.cone = CONE
    opt.impratio = IMPRATIO
    opt.iterations = 50
    opt.ls_iterations = 20
    opt.noslip_iterations = NOSLIP_ITERATIONS
    spec.visual.global_.offwidth = 1280
    spec.visual.global_.offheight = 960
    world = spec.worldbody

    # Floor: an infinite plane for collision; size sets the rendered extent.
    fx, fy = scenario.floor.size_m
    world.add_geom(
        name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[fx / 2, fy / 2, 0.05],
        friction=[scenario.floor.friction, 0.005, 0.0001], rgba=[0.55, 0.55, 0.5, 1.0],
        group=SCENE_GEOM_GROUP, contype=_BIT_FLOOR, conaffinity=_BIT_TYRE,
    )
    world.add_light(name="sun", pos=[0, 0, 6], dir=[0, 0, -1], type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL, castshadow=False)

    for wall, name in zip(scenario.walls, scenario.wall_names()):
        # The same box as hil_sim.world.footprints.wall_footprint (what the scenario check measures).
        (hx, hy), (cx, cy) = wall.half_extents_m, wall.centre_xy_m
        world.add_geom(
            name=name, type=mujoco.mjtGeom.mjGEOM_BOX,
            size=[hx, hy, wall.height_m / 2],
            pos=[cx, cy, wall.height_m / 2], quat=_yaw_quat(wall.yaw_rad),
            friction=[WALL_FRICTION, 0.005, 0.0001], rgba=_WALL_RGBA, group=SCENE_GEOM_GROUP,
            contype=_BIT_OBJECT, conaffinity=_BIT_OBJECT,
        )

    for ob in scenario.obstacles:
        if ob.obstacle_class == "deformable":
            _add_curtain(world, ob)
            continue
        if ob.obstacle_class == "person":
            # A kinematic body: its position is set before every step (World.step), so a
            # contact never moves it (and, a child of the world body, it ignores walls).
            body = world.add_body(name=ob.name, mocap=True, pos=[ob.pose.x_m, ob.pose.y_m, ob.height_m / 2])
            body.add_geom(
                name=ob.name, type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[ob.size.radius_m, ob.height_m / 2, 0.0],
                friction=[FIXED_DEFAULT_FRICTION, 0.005, 0.0001], rgba=ob.rgba or _PERSON_RGBA,
                group=FREE_BODY_GEOM_GROUP, contype=_BIT_OBJECT, conaffinity=_BIT_OBJECT,
            )
            continue
        if ob.shape == "box":
            gtype, size = mujoco.mjtGeom.mjGEOM_BOX, [v / 2 for v in ob.size.xyz_m]
        else:
            gtype, size = mujoco.mjtGeom.mjGEOM_CYLINDER, [ob.size.radius_m, ob.size.height_m / 2, 0.0]
        # The geom's bottom face at pose.z_m (0 but for raised fixed geoms: seats, shelf boards).
        pos = [ob.pose.x_m, ob.pose.y_m, ob.bottom_z_m + ob.height_m / 2]
        if ob.is_free_body:  # movable, heavy, a fragile one with mass
            body = world.add_body(name=ob.name, pos=pos, quat=_yaw_quat(ob.pose.yaw_rad))
            body.add_freejoint(name=f"{ob.name}_free")
            body.add_geom(
                name=ob.name, type=gtype, size=size, mass=ob.mass_kg, priority=1,
                friction=[ob.friction, 0.005, 0.0001], rgba=ob.rgba or _FREE_RGBA,
                group=FREE_BODY_GEOM_GROUP, contype=_BIT_OBJECT, conaffinity=_BIT_FLOOR | _BIT_OBJECT,
            )
        else:
            world.add_geom(
                name=ob.name, type=gtype, size=size, pos=pos, quat=_yaw_quat(ob.pose.yaw_rad),
                friction=[ob.friction or FIXED_DEFAULT_FRICTION, 0.005, 0.0001],
                rgba=ob.rgba or _FIXED_RGBA, group=SCENE_GEOM_GROUP,
                contype=_BIT_OBJECT, conaffinity=_BIT_OBJECT,
            )

    _add_robot(spec, scenario, robot)
    return spec


def curtain_slat_layout(ob: BoxObstacle) -> tuple[np.ndarray, float, float]:
    """A curtain's slats: ((N, 2) hinge centres in the world xy, slat width m, slat length m).

    The box `size` is (depth, width, height): the slats span the width (the curtain's local y)
    and hang from hinges at the top (z = height) down to CURTAIN_BOTTOM_CLEARANCE_M.
    """
    depth, width, height = ob.size.xyz_m
    n = ob.slat_count
    pitch = width / n
    offsets = (np.arange(n) + 0.5) * pitch - width / 2
    c, s = math.cos(ob.pose.yaw_rad), math.sin(ob.pose.yaw_rad)
    centres = np.stack([ob.pose.x_m - s * offsets, ob.pose.y_m + c * offsets], axis=1)
    return centres, max(pitch - CURTAIN_SLAT_GAP_M, 0.25 * pitch), height - CURTAIN_BOTTOM_CLEARANCE_M


def _add_curtain(world: mujoco.MjsBody, ob: BoxObstacle) -> None:
    """Light hinged slats (cheaper and steadier than a flex in MuJoCo, and seen as boxes by
    mj_multiRay and the renderer): each a body hanging from a hinge along the curtain's width.
    The slats touch the robot and free bodies, not each other, the floor or the walls."""
    depth, _, height = ob.size.xyz_m
    centres, slat_w, slat_len = curtain_slat_layout(ob)
    mass = (ob.mass_kg / len(centres)) if ob.mass_kg is not None else CURTAIN_SLAT_MASS_KG
    for k, (x, y) in enumerate(centres):
        body = world.add_body(name=f"{ob.name}/slat_{k}", pos=[float(x), float(y), height], quat=_yaw_quat(ob.pose.yaw_rad))
        body.add_joint(name=f"{ob.name}/hinge_{k}", type=mujoco.mjtJoint.mjJNT_HINGE, axis=[0, 1, 0],
                       damping=CURTAIN_HINGE_DAMPING, range=[-170.0, 170.0])
        body.add_geom(
            name=f"{ob.name}/slat_{k}", type=mujoco.mjtGeom.mjGEOM_BOX,
            size=[depth / 2, slat_w / 2, slat_len / 2], pos=[0.0, 0.0, -slat_len / 2], mass=mass, priority=1,
            friction=[CURTAIN_FRICTION, 0.005, 0.0001], rgba=ob.rgba or _CURTAIN_RGBA,
            group=FREE_BODY_GEOM_GROUP, contype=0, conaffinity=_BIT_OBJECT,
        )


def _add_robot(spec: mujoco.MjSpec, scenario: Scenario, robot: RobotDescription) -> None:
    """The LIMO-class base: two chassis boxes, four wheels, four motor actuators."""
    length, width = robot.footprint.length_m, robot.footprint.width_m
    r, w_wheel = robot.drive.wheel_radius_m, robot.drive.wheel_width_m
    half_base, half_track = robot.drive.wheelbase_m / 2, robot.drive.track_m / 2
    height = robot.body_height_m
    chassis_mass = robot.mass_kg - 4 * WHEEL_MASS_KG
    if chassis_mass <= 0:
        raise WorldError(f"robot mass_kg {robot.mass_kg} is not more than four wheels of {WHEEL_MASS_KG} kg")
    friction = [ROBOT_GEOM_FRICTION, 0.005, 0.0001]

    start = scenario.robot.start
    base = spec.worldbody.add_body(name="base_link", pos=[start.x_m, start.y_m, 0.0005],
                                   quat=_yaw_quat(start.yaw_rad))
    base.add_freejoint(name="base_free")
    # Lower box between the wheels (battery; front and rear bumpers at full length), upper
    # box over the wheels with the full footprint up to the body height.
    lower_top = 2 * r + 0.005
    lower_w = max(0.02, 2 * half_track - w_wheel - 0.01)
    lower_h = lower_top - GROUND_CLEARANCE_M
    upper_h = height - lower_top
    base.add_geom(
        name="robot/chassis_lower", type=mujoco.mjtGeom.mjGEOM_BOX,
        size=[length / 2, lower_w / 2, lower_h / 2], pos=[0, 0, GROUND_CLEARANCE_M + lower_h / 2],
        mass=LOWER_MASS_FRACTION * chassis_mass, friction=friction, rgba=_ROBOT_RGBA, group=ROBOT_GEOM_GROUP,
        contype=_BIT_OBJECT, conaffinity=_BIT_FLOOR | _BIT_OBJECT,
    )
    base.add_geom(
        name="robot/chassis_upper", type=mujoco.mjtGeom.mjGEOM_BOX,
        size=[length / 2, width / 2, upper_h / 2], pos=[0, 0, lower_top + upper_h / 2],
        mass=(1.0 - LOWER_MASS_FRACTION) * chassis_mass, friction=friction, rgba=_ROBOT_RGBA, group=ROBOT_GEOM_GROUP,
        contype=_BIT_OBJECT, conaffinity=_BIT_FLOOR | _BIT_OBJECT,
    )
    # Wheels: cylinders with the axle along body y; positive hinge speed rolls the robot forward.
    axle_quat = [math.cos(-math.pi / 4), math.sin(-math.pi / 4), 0.0, 0.0]  # local z -> +y
    for i, name in enumerate(WHEEL_NAMES):
        wb = base.add_body(name=f"wheel_{name}", pos=[WHEEL_END[i] * half_base, WHEEL_SIDE[i] * half_track, r])
        wb.add_joint(name=f"wheel_{name}", type=mujoco.mjtJoint.mjJNT_HINGE, axis=[0, 1, 0],
                     damping=1e-4, armature=WHEEL_ARMATURE)
        # Floor contact: a sphere (one smooth contact point, cheap); obstacle contact: the
        # cylinder, so that the wheels stay inside the footprint for everything but the floor.
        wb.add_geom(
            name=f"robot/wheel_{name}", type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[r, w_wheel / 2, 0],
            quat=axle_quat, mass=WHEEL_MASS_KG, friction=friction, rgba=_WHEEL_RGBA,
            group=ROBOT_GEOM_GROUP, contype=_BIT_OBJECT, conaffinity=_BIT_OBJECT,
        )
        wb.add_geom(
            name=f"robot/tyre_{name}", type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[r, 0, 0],
            mass=0.0, friction=friction, condim=3, rgba=[0.1, 0.1, 0.1, 1.0],
            group=TYRE_GEOM_GROUP, contype=_BIT_TYRE, conaffinity=0,
        )
        act = spec.add_actuator(name=f"motor_{name}", target=f"wheel_{name}",
                                trntype=mujoco.mjtTrn.mjTRN_JOINT)
        act.set_to_motor()
        act.ctrllimited = mujoco.mjtLimited.mjLIMITED_FALSE

    # Sensors: the camera (optical-frame mount) and the IMU site with gyro + accelerometer.
    cam = robot.sensors.camera
    add_camera_to_spec(base, cam.mount, cam, name=CAMERA_NAME)
    ensure_offscreen_buffer(spec, cam.width_px, cam.height_px)
    add_imu_to_spec(base, robot.sensors.imu.mount, spec=spec, name=IMU_NAME)


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
    """

    def __init__(self, scenario: Scenario, robot: RobotDescription, seed: int = 0, *,
                 ground_clearance_m: float = DEFAULT_GROUND_CLEARANCE_M) -> None:
        # First: a scenario this robot cannot start in (inside a wall, an invisible obstacle,
        # an unreachable goal) is a ScenarioError naming the field, before any physics runs.
        #: Warnings of hil_sim.world.scenario_checks.check_scenario_against_robot (each names its field).
        self.scenario_warnings: list[str] = check_scenario_against_robot(
            scenario, robot, ground_clearance_m=ground_clearance_m)
        self.scenario = scenario
        self.robot = robot
        self.spec = build_spec(scenario, robot)
        self.model: mujoco.MjModel = self.spec.compile()
        self.data = mujoco.MjData(self.model)
        m = self.model
        self.timestep_s: float = float(m.opt.timestep)

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

        # Obstacles (file order) then walls; walls are fixed obstacles for the metrics.
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

        self.camera_name: str = CAMERA_NAME
        self.camera_id: int = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_CAMERA, CAMERA_NAME)
        self.camera_hidden_geom_groups: tuple[int, ...] = ROBOT_OWN_GEOM_GROUPS
        self.imu_sensor_names: tuple[str, str] = (f"{IMU_NAME}_gyro", f"{IMU_NAME}_accel")
        self.lidar_mount = robot.sensors.lidar.mount
        self.lidar_geomgroup: tuple[int, int, int, int, int, int] = LIDAR_GEOMGROUP

        self.seed = seed
        self.reset(seed)

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
            d.qpos[adr + 3:adr + 7] = _yaw_quat(ob.pose.yaw_rad + dyaw)
        self._move_people(float(d.time))
        mujoco.mj_forward(m, d)

    def _move_people(self, t_s: float) -> None:
        for _, mocap, start, ob in self._people:
            if ob.walk is not None:
                self.data.mocap_pos[mocap, :2] = ob.walk.positions(start, t_s)[0]

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
        if not np.all(np.isfinite(t)):
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


__all__ = [
    "World",
    "WorldError",
    "build_spec",
    "TIMESTEP_S",
    "WHEEL_NAMES",
    "SCENE_GEOM_GROUP",
    "FREE_BODY_GEOM_GROUP",
    "ROBOT_GEOM_GROUP",
    "TYRE_GEOM_GROUP",
    "ROBOT_OWN_GEOM_GROUPS",
    "LIDAR_GEOMGROUP",
    "CAMERA_NAME",
    "IMU_NAME",
    "curtain_slat_layout",
]
