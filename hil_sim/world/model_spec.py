"""The MuJoCo model of one scenario, built with `mujoco.MjSpec` (no MJCF strings), and its constants.

Contents: a floor plane, walls and fixed obstacles (static geoms of the world body), movable
and heavy obstacles (free bodies), fragile ones (free bodies or static geoms, as the file says),
deformable ones (a curtain: light slats on hinge joints along its top edge, which the robot
swings aside), people (kinematic mocap cylinders walking their waypoints: World.step moves
them before each physics step; nothing pushes them), and the robot: a chassis with a free joint and four wheels on
hinge joints driven by torque (motor) actuators. The firmware emulator closes the wheel-speed
loop; hil_sim.world.mujoco_world.World only applies the torques it computes.

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
from hil_sim.sensors.camera import add_camera_to_spec, ensure_offscreen_buffer  # noqa: E402
from hil_sim.sensors.camera_lens import CameraLens  # noqa: E402
from hil_sim.sensors.imu import add_imu_to_spec  # noqa: E402
from hil_sim.world.scenario import Scenario  # noqa: E402
from hil_sim.world.scenario_objects import BoxObstacle, CylinderObstacle  # noqa: E402

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


def yaw_quat(yaw_rad: float) -> list[float]:
    """The MuJoCo quaternion (w, x, y, z) of a turn by yaw_rad about the vertical."""
    return [math.cos(yaw_rad / 2), 0.0, 0.0, math.sin(yaw_rad / 2)]


def build_spec(scenario: Scenario, robot: RobotDescription, lens: CameraLens | None = None) -> mujoco.MjSpec:
    """The MjSpec of a scenario with the robot at its start pose (uncompiled). lens: the camera as
    built (a robot variant: hil_sim.world.robot_variant); None: the description's pinhole."""
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
    # The offscreen framebuffer stays MuJoCo's 640x480 unless the camera's canvas needs more
    # (_add_robot: ensure_offscreen_buffer). Each render clears the whole 4x multisampled buffer,
    # in software (llvmpipe) here: a larger one cost ~10% of every camera frame, same pixels.
    world = spec.worldbody
    _add_floor_and_walls(world, scenario)
    for ob in scenario.obstacles:
        _add_obstacle(world, ob)
    _add_robot(spec, scenario, robot, lens)
    return spec


def _add_floor_and_walls(world: mujoco.MjsBody, scenario: Scenario) -> None:
    """The floor plane, the light and the walls (static boxes)."""
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
            pos=[cx, cy, wall.height_m / 2], quat=yaw_quat(wall.yaw_rad),
            friction=[WALL_FRICTION, 0.005, 0.0001], rgba=_WALL_RGBA, group=SCENE_GEOM_GROUP,
            contype=_BIT_OBJECT, conaffinity=_BIT_OBJECT,
        )


def _add_obstacle(world: mujoco.MjsBody, ob: BoxObstacle | CylinderObstacle) -> None:
    """One obstacle: a curtain, a person, a free body or a static geom (module docstring)."""
    if ob.obstacle_class == "deformable":
        _add_curtain(world, ob)
        return
    if ob.obstacle_class == "person":
        _add_person(world, ob)
        return
    if ob.shape == "box":
        gtype, size = mujoco.mjtGeom.mjGEOM_BOX, [v / 2 for v in ob.size.xyz_m]
    else:
        gtype, size = mujoco.mjtGeom.mjGEOM_CYLINDER, [ob.size.radius_m, ob.size.height_m / 2, 0.0]
    # The geom's bottom face at pose.z_m (0 but for raised fixed geoms: seats, shelf boards).
    pos = [ob.pose.x_m, ob.pose.y_m, ob.bottom_z_m + ob.height_m / 2]
    if ob.is_free_body:  # movable, heavy, a fragile one with mass
        body = world.add_body(name=ob.name, pos=pos, quat=yaw_quat(ob.pose.yaw_rad))
        body.add_freejoint(name=f"{ob.name}_free")
        body.add_geom(
            name=ob.name, type=gtype, size=size, mass=ob.mass_kg, priority=1,
            friction=[ob.friction, 0.005, 0.0001], rgba=ob.rgba or _FREE_RGBA,
            group=FREE_BODY_GEOM_GROUP, contype=_BIT_OBJECT, conaffinity=_BIT_FLOOR | _BIT_OBJECT,
        )
    else:
        world.add_geom(
            name=ob.name, type=gtype, size=size, pos=pos, quat=yaw_quat(ob.pose.yaw_rad),
            friction=[ob.friction or FIXED_DEFAULT_FRICTION, 0.005, 0.0001],
            rgba=ob.rgba or _FIXED_RGBA, group=SCENE_GEOM_GROUP,
            contype=_BIT_OBJECT, conaffinity=_BIT_OBJECT,
        )


def _add_person(world: mujoco.MjsBody, ob: CylinderObstacle) -> None:
    """A kinematic body: its position is set before every step (World.step), so a contact never
    moves it (and, a child of the world body, it ignores walls)."""
    body = world.add_body(name=ob.name, mocap=True, pos=[ob.pose.x_m, ob.pose.y_m, ob.height_m / 2])
    body.add_geom(
        name=ob.name, type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[ob.size.radius_m, ob.height_m / 2, 0.0],
        friction=[FIXED_DEFAULT_FRICTION, 0.005, 0.0001], rgba=ob.rgba or _PERSON_RGBA,
        group=FREE_BODY_GEOM_GROUP, contype=_BIT_OBJECT, conaffinity=_BIT_OBJECT,
    )


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
        body = world.add_body(name=f"{ob.name}/slat_{k}", pos=[float(x), float(y), height], quat=yaw_quat(ob.pose.yaw_rad))
        body.add_joint(name=f"{ob.name}/hinge_{k}", type=mujoco.mjtJoint.mjJNT_HINGE, axis=[0, 1, 0],
                       damping=CURTAIN_HINGE_DAMPING, range=[-170.0, 170.0])
        body.add_geom(
            name=f"{ob.name}/slat_{k}", type=mujoco.mjtGeom.mjGEOM_BOX,
            size=[depth / 2, slat_w / 2, slat_len / 2], pos=[0.0, 0.0, -slat_len / 2], mass=mass, priority=1,
            friction=[CURTAIN_FRICTION, 0.005, 0.0001], rgba=ob.rgba or _CURTAIN_RGBA,
            group=FREE_BODY_GEOM_GROUP, contype=0, conaffinity=_BIT_OBJECT,
        )


def _add_robot(spec: mujoco.MjSpec, scenario: Scenario, robot: RobotDescription, lens: CameraLens | None) -> None:
    """The LIMO-class base: two chassis boxes, four wheels, four motor actuators, the sensors."""
    chassis_mass = robot.mass_kg - 4 * WHEEL_MASS_KG
    if chassis_mass <= 0:
        raise WorldError(f"robot mass_kg {robot.mass_kg} is not more than four wheels of {WHEEL_MASS_KG} kg")
    friction = [ROBOT_GEOM_FRICTION, 0.005, 0.0001]

    start = scenario.robot.start
    base = spec.worldbody.add_body(name="base_link", pos=[start.x_m, start.y_m, 0.0005],
                                   quat=yaw_quat(start.yaw_rad))
    base.add_freejoint(name="base_free")
    _add_chassis(base, robot, chassis_mass, friction)
    _add_wheels(spec, base, robot, friction)

    # Sensors: the camera (optical-frame mount) and the IMU site with gyro + accelerometer.
    cam = robot.sensors.camera
    add_camera_to_spec(base, cam.mount, cam, name=CAMERA_NAME, lens=lens)
    ensure_offscreen_buffer(spec, *(lens.canvas_size if lens is not None else (cam.width_px, cam.height_px)))
    add_imu_to_spec(base, robot.sensors.imu.mount, spec=spec, name=IMU_NAME)


def _add_chassis(base: mujoco.MjsBody, robot: RobotDescription, chassis_mass: float, friction: list[float]) -> None:
    """Lower box between the wheels (battery; front and rear bumpers at full length), upper box
    over the wheels with the full footprint up to the body height."""
    length, width = robot.footprint.length_m, robot.footprint.width_m
    r, w_wheel = robot.drive.wheel_radius_m, robot.drive.wheel_width_m
    half_track = robot.drive.track_m / 2
    height = robot.body_height_m
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


def _add_wheels(spec: mujoco.MjSpec, base: mujoco.MjsBody, robot: RobotDescription, friction: list[float]) -> None:
    """Four wheels on hinge joints, each with its motor actuator."""
    r, w_wheel = robot.drive.wheel_radius_m, robot.drive.wheel_width_m
    half_base, half_track = robot.drive.wheelbase_m / 2, robot.drive.track_m / 2
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


__all__ = [
    "build_spec", "curtain_slat_layout", "yaw_quat", "WorldError", "TIMESTEP_S", "WHEEL_NAMES", "WHEEL_SIDE",
    "WHEEL_END", "SCENE_GEOM_GROUP", "FREE_BODY_GEOM_GROUP", "ROBOT_GEOM_GROUP", "TYRE_GEOM_GROUP",
    "ROBOT_OWN_GEOM_GROUPS", "LIDAR_GEOMGROUP", "CAMERA_NAME", "IMU_NAME",
]
