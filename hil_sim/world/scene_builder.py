"""Furniture made of scenario primitives, and the odometry scenes of the library built from it.

A scenario obstacle is one box or cylinder. Realistic clutter for the lidar odometry (a world
of large flat boxes is a weak case for point-to-point ICP; docs/decisions/sim-odometry-scenes.md)
needs furniture: chairs on thin legs with a seat and a backrest, shelves with side panels and
boards at several heights, tables. The helpers here expand one piece of furniture into its
primitives (fixed obstacles, raised ones with `pose.z_m`), placed and turned as a whole.

The library files `odom_loop.yaml` and `odom_corridor.yaml` are written from the layouts below,
so that a chair stays a chair when it is moved: edit the layout here, then regenerate them with

    python -m hil_sim.world.scene_builder            # rewrites hil_sim/scenarios/odom_*.yaml
    python -m hil_sim.world.scene_builder --check    # exit 1 if a file differs from its layout

(a test runs the check). Every helper returns plain dicts in the scenario file's schema.
"""
from __future__ import annotations

import math
import sys
import textwrap
from pathlib import Path
from typing import Any, Iterable, Sequence

import yaml

Obstacle = dict[str, Any]

_CHAIR_RGBA = [0.25, 0.3, 0.45, 1.0]
_WOOD_RGBA = [0.55, 0.4, 0.25, 1.0]
_SHELF_RGBA = [0.6, 0.6, 0.62, 1.0]
_ITEM_RGBA = [0.8, 0.55, 0.3, 1.0]


def _r(v: float) -> float:
    """Millimetre rounding: the files stay readable and the same on every machine."""
    out = round(float(v), 4)
    return 0.0 if out == 0.0 else out  # no -0.0 in the files


def _place(x: float, y: float, yaw_deg: float, local_xy: tuple[float, float]) -> tuple[float, float]:
    """A point given in a piece's own frame (centre, turned by yaw_deg) in the world."""
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    lx, ly = local_xy
    return x + c * lx - s * ly, y + s * lx + c * ly


def box(name: str, x: float, y: float, size: Sequence[float], yaw_deg: float = 0.0, z_m: float = 0.0,
        rgba: Sequence[float] | None = None) -> Obstacle:
    """A fixed box: size = full extents (x, y, z) in its own frame; bottom face at z_m."""
    pose: dict[str, float] = {"x_m": _r(x), "y_m": _r(y)}
    if yaw_deg:
        pose["yaw_deg"] = _r(yaw_deg)
    if z_m:
        pose["z_m"] = _r(z_m)
    ob: Obstacle = {"name": name, "shape": "box", "size": {"xyz_m": [_r(v) for v in size]}, "pose": pose,
                    "class": "fixed"}
    if rgba is not None:
        ob["rgba"] = list(rgba)
    return ob


def cylinder(name: str, x: float, y: float, radius_m: float, height_m: float, z_m: float = 0.0,
             rgba: Sequence[float] | None = None) -> Obstacle:
    """A fixed upright cylinder (a bin, a pillar, a chair leg); bottom face at z_m."""
    pose: dict[str, float] = {"x_m": _r(x), "y_m": _r(y)}
    if z_m:
        pose["z_m"] = _r(z_m)
    ob: Obstacle = {"name": name, "shape": "cylinder", "size": {"radius_m": _r(radius_m), "height_m": _r(height_m)},
                    "pose": pose, "class": "fixed"}
    if rgba is not None:
        ob["rgba"] = list(rgba)
    return ob


def chair(name: str, x: float, y: float, yaw_deg: float, *, seat_m: float = 0.42, seat_height_m: float = 0.45,
          leg_radius_m: float = 0.016, backrest: bool = True) -> list[Obstacle]:
    """Four thin legs, a seat board with its top at seat_height_m, and a backrest on the side
    opposite to where the sitter faces (the chair's +x, turned by yaw_deg). Its footprint is
    the seat: seat_m x seat_m."""
    seat_t, back_t, back_h = 0.03, 0.025, 0.40
    inset = seat_m / 2 - 0.03
    legs = [cylinder(f"{name}_leg{k + 1}", *_place(x, y, yaw_deg, (sx * inset, sy * inset)), leg_radius_m,
                     seat_height_m - seat_t, rgba=_CHAIR_RGBA)
            for k, (sx, sy) in enumerate(((1, 1), (-1, 1), (-1, -1), (1, -1)))]
    parts = legs + [box(f"{name}_seat", x, y, (seat_m, seat_m, seat_t), yaw_deg, z_m=seat_height_m - seat_t,
                        rgba=_CHAIR_RGBA)]
    if backrest:
        parts.append(box(f"{name}_back", *_place(x, y, yaw_deg, (-seat_m / 2 + back_t / 2, 0.0)),
                         (back_t, seat_m, back_h), yaw_deg, z_m=seat_height_m, rgba=_CHAIR_RGBA))
    return parts


def table(name: str, x: float, y: float, yaw_deg: float, size_m: tuple[float, float], *,
          height_m: float = 0.74, leg_m: float = 0.05) -> list[Obstacle]:
    """Four square legs and a top board (size_m = length along its x, width along its y)."""
    lx, ly = size_m
    top_t = 0.03
    legs = [box(f"{name}_leg{k + 1}", *_place(x, y, yaw_deg, (sx * (lx / 2 - leg_m), sy * (ly / 2 - leg_m))),
                (leg_m, leg_m, height_m - top_t), yaw_deg, rgba=_WOOD_RGBA)
            for k, (sx, sy) in enumerate(((1, 1), (-1, 1), (-1, -1), (1, -1)))]
    return legs + [box(f"{name}_top", x, y, (lx, ly, top_t), yaw_deg, z_m=height_m - top_t, rgba=_WOOD_RGBA)]


def shelf(name: str, x: float, y: float, yaw_deg: float, *, width_m: float = 1.2, depth_m: float = 0.35,
          height_m: float = 1.6, boards_z_m: Iterable[float] = (0.13, 0.55, 1.0), back_panel: bool = False,
          items: Iterable[tuple[float, int, tuple[float, float, float], float]] = ()) -> list[Obstacle]:
    """An open shelf unit: two side panels, boards with their bottoms at boards_z_m plus a top
    board, an optional back panel (a shelf standing free in a room), and items on the boards.

    Its own x runs along the width, y across the depth (the back at -y). items: (x along the
    width from the centre, board index (0 = lowest), size (x, y, z), yaw_deg): boxes standing on
    that board.
    """
    t = 0.02  # panel and board thickness
    inner = width_m - 2 * t
    parts = [box(f"{name}_side{k + 1}", *_place(x, y, yaw_deg, (s * (width_m / 2 - t / 2), 0.0)),
                 (t, depth_m, height_m), yaw_deg, rgba=_SHELF_RGBA) for k, s in enumerate((1, -1))]
    boards = [*boards_z_m, height_m - t]
    parts += [box(f"{name}_board{k + 1}", x, y, (inner, depth_m, t), yaw_deg, z_m=z, rgba=_SHELF_RGBA)
              for k, z in enumerate(boards)]
    if back_panel:
        parts.append(box(f"{name}_back", *_place(x, y, yaw_deg, (0.0, -depth_m / 2 + t / 2)), (inner, t, height_m - t),
                         yaw_deg, rgba=_SHELF_RGBA))
    for k, (ix, board, size, item_yaw) in enumerate(items):
        parts.append(box(f"{name}_item{k + 1}", *_place(x, y, yaw_deg, (ix, 0.0)), size, yaw_deg + item_yaw,
                         z_m=boards[board] + t, rgba=_ITEM_RGBA))
    return parts


def room_walls(half_x_m: float, half_y_m: float, height_m: float, thickness_m: float = 0.1) -> list[dict[str, Any]]:
    """Four walls whose inner faces are at x = +-half_x_m and y = +-half_y_m."""
    cx, cy = _r(half_x_m + thickness_m / 2), _r(half_y_m + thickness_m / 2)
    return [
        {"name": "wall_south", "from": [-cx, -cy], "to": [cx, -cy], "thickness_m": thickness_m, "height_m": height_m},
        {"name": "wall_north", "from": [-cx, cy], "to": [cx, cy], "thickness_m": thickness_m, "height_m": height_m},
        {"name": "wall_west", "from": [-cx, -cy], "to": [-cx, cy], "thickness_m": thickness_m, "height_m": height_m},
        {"name": "wall_east", "from": [cx, -cy], "to": [cx, cy], "thickness_m": thickness_m, "height_m": height_m},
    ]


# ----------------------------------------------------------------------------- the odometry scenes
#: Inner half sizes of the odom_loop room (10 x 7 m).
LOOP_HALF_X_M, LOOP_HALF_Y_M = 4.95, 3.45


def _odom_loop_furniture(hx: float, hy: float) -> list[Obstacle]:
    """The furniture of odom_loop, in the file's order: along each wall, then the island in the middle."""
    ob: list[Obstacle] = []
    # Along the south wall: a shelf, a chair, a cluster of boxes (one stacked) the route jogs around.
    ob += shelf("shelf_s", -2.2, -hy + 0.175, 0.0, width_m=1.2, boards_z_m=(0.13, 0.52, 0.95),
                items=[(-0.3, 1, (0.3, 0.25, 0.22), 0.0), (0.35, 0, (0.4, 0.3, 0.3), 8.0)])
    ob.append(cylinder("bin_sw", -4.5, -3.0, 0.2, 0.6))
    ob += chair("chair_s", -0.5, -3.0, 80.0)
    ob.append(box("crate_s1", 1.0, -2.7, (0.7, 0.6, 0.5), 10.0))
    ob.append(box("crate_s1_top", 1.0, -2.7, (0.4, 0.3, 0.25), 35.0, z_m=0.5))
    ob.append(box("crate_s2", 1.85, -2.55, (0.5, 0.5, 0.8), -15.0))
    ob.append(box("crate_s3", 1.45, -3.15, (1.0, 0.45, 0.35), 0.0))
    ob.append(box("crate_s4", 2.7, -3.1, (0.3, 0.25, 0.2), 50.0))
    # East wall: a long shelf, a box in the south-east corner, a pillar.
    ob += shelf("shelf_e", hx - 0.175, -0.8, 90.0, width_m=1.4, boards_z_m=(0.12, 0.45, 0.85, 1.25),
                items=[(0.4, 2, (0.35, 0.3, 0.3), 0.0), (-0.3, 0, (0.25, 0.25, 0.35), 20.0)])
    ob.append(box("crate_se", 4.4, -2.9, (0.6, 0.6, 0.6), 25.0))
    ob.append(cylinder("pillar_e", 4.55, 1.2, 0.15, 1.5))
    ob.append(box("cabinet_e", 4.5, 2.6, (0.45, 0.9, 1.1), -5.0))
    # North wall: a shelf, a desk with two chairs, a bin.
    ob += shelf("shelf_n", 1.8, hy - 0.175, 180.0, width_m=1.6, boards_z_m=(0.12, 0.5, 0.9, 1.3),
                items=[(0.5, 1, (0.3, 0.3, 0.25), -10.0), (-0.4, 3, (0.45, 0.3, 0.2), 0.0)])
    ob.append(cylinder("bin_n", 0.25, 3.05, 0.16, 0.5))
    ob += table("desk_n", -1.5, 3.05, 0.0, (1.3, 0.7))
    ob += chair("chair_n1", -1.85, 2.4, 95.0)
    ob += chair("chair_n2", -0.95, 2.5, 70.0, backrest=False)
    # West wall: a shelf, a tall box in the north-west corner, a bin.
    ob += shelf("shelf_w", -hx + 0.175, 0.8, -90.0, width_m=1.2, boards_z_m=(0.15, 0.6, 1.05),
                items=[(0.2, 1, (0.3, 0.25, 0.3), 15.0)])
    ob.append(box("crate_nw", -4.45, 2.85, (0.7, 0.5, 0.9), 20.0))
    ob.append(cylinder("bin_w", -4.6, -1.6, 0.22, 0.5))
    # The island in the middle: a free-standing shelf with a back panel, a table with chairs,
    # boxes of several sizes, a square pillar, a cabinet turned at an angle.
    ob += shelf("shelf_c", 0.45, 0.05, 0.0, width_m=1.6, depth_m=0.45, height_m=1.4, boards_z_m=(0.13, 0.5, 0.92),
                back_panel=True, items=[(-0.45, 1, (0.35, 0.3, 0.28), 12.0), (0.4, 2, (0.3, 0.3, 0.2), -20.0)])
    ob += table("table_c", -1.45, 0.2, 8.0, (1.0, 0.7))
    ob += chair("chair_c1", -1.4, -0.65, 95.0)
    ob += chair("chair_c2", -1.5, 0.95, -80.0)
    ob.append(box("pillar_c", -2.75, -0.3, (0.3, 0.3, 1.5), 0.0))
    ob.append(box("crate_c1", 1.85, 0.65, (0.5, 0.4, 0.45), 35.0))
    ob.append(box("crate_c2", 2.05, -0.55, (0.3, 0.3, 0.3), 0.0))
    ob.append(box("crate_c3", 1.55, -0.8, (0.2, 0.35, 0.18), 60.0))
    ob.append(box("cabinet_c", 2.85, -0.25, (0.8, 0.4, 1.0), 70.0))
    ob.append(cylinder("bin_c", 2.75, 0.95, 0.18, 0.55))
    return ob


def odom_loop() -> dict[str, Any]:
    """A furnished room, 10 x 7 m, and a closed loop through it (see the description)."""
    hx, hy = LOOP_HALF_X_M, LOOP_HALF_Y_M
    ob = _odom_loop_furniture(hx, hy)
    start = (-3.4, -2.3)
    waypoints = [(-0.9, -2.3), (0.4, -1.55), (2.4, -1.55), (3.7, -2.25), (3.8, 0.3), (2.9, 2.3), (0.7, 2.3),
                 (-0.45, 1.65), (-2.4, 1.6), (-3.7, 2.25), (-3.85, -0.4), (-3.4, -2.3), (-2.6, -2.3)]
    return {
        "name": "odom_loop",
        "description": (
            "Lidar odometry in clutter: a furnished room 10 x 7 m (walls 1.5 m) with shelves "
            "(side panels, boards at several heights, boxes on them), chairs on four thin legs with raised "
            "seats and backrests, tables, boxes of many sizes and turns, bins and pillars. The route is a "
            "closed loop of 24.6 m with twelve turns through the clutter, back over its start: "
            "drift at the end of the loop measures the odometry. Generated by hil_sim/world/scene_builder.py."
        ),
        "floor": {"size_m": [_r(2 * hx + 0.4), _r(2 * hy + 0.4)], "friction": 0.8},
        "walls": room_walls(hx, hy, 1.5),
        "obstacles": ob,
        "robot": {"start": {"x_m": start[0], "y_m": start[1], "yaw_deg": 0.0}},
        "goal": {"pose": {"x_m": waypoints[-1][0], "y_m": waypoints[-1][1], "yaw_deg": 0.0}, "tolerance_m": 0.15},
        "time_limit_s": 0.0,  # filled in by _with_time_limit
        "route": {"waypoints": [list(p) for p in waypoints], "speed_mps": 0.4},
    }


#: The corridor: inner faces 2.0 m apart, 100 m long; the route's 18 m stay in the middle, so the
#: end walls are never nearer than 41 m: beyond the simulated lidar's 40 m range altogether.
CORRIDOR_HALF_LENGTH_M, CORRIDOR_HALF_WIDTH_M = 50.0, 1.0


def odom_corridor() -> dict[str, Any]:
    """A long featureless corridor (see the description)."""
    hx, hy = CORRIDOR_HALF_LENGTH_M, CORRIDOR_HALF_WIDTH_M
    walls = room_walls(hx, hy, 2.0)
    walls[0]["name"], walls[1]["name"] = "wall_right", "wall_left"
    walls[2]["name"], walls[3]["name"] = "wall_end_west", "wall_end_east"
    return {
        "name": "odom_corridor",
        "description": (
            "The degenerate case of lidar odometry: a straight corridor 100 m long and 2.0 m wide "
            "(walls 2.0 m high, smooth: no doors, no features). The route drives 18 m straight down the "
            "middle; the end walls stay more than 41 m away, beyond the lidar's range, so nothing in a scan "
            "fixes the position along the corridor: ICP alone cannot tell how far the robot went, wheels and "
            "IMU must. Generated by hil_sim/world/scene_builder.py."
        ),
        "floor": {"size_m": [_r(2 * hx + 2.0), _r(2 * hy + 2.0)], "friction": 0.8},
        "walls": walls,
        "robot": {"start": {"x_m": -9.0, "y_m": 0.0, "yaw_deg": 0.0}},
        "goal": {"pose": {"x_m": 9.0, "y_m": 0.0, "yaw_deg": 0.0}, "tolerance_m": 0.15},
        "time_limit_s": 0.0,
        "route": {"waypoints": [[9.0, 0.0]], "speed_mps": 0.4},
    }


#: Time allowed per route: driving at the route's speed plus in-place turns at this rate (the
#: skid-steer base turns slowly), plus this share again for starting and stopping.
TURN_RATE_FOR_TIME_LIMIT_RADPS = 0.5
TIME_LIMIT_SLACK = 0.5


def route_time_s(raw: dict[str, Any]) -> float:
    """Drive time of a scenario's route at its speed plus its turns at TURN_RATE_FOR_TIME_LIMIT_RADPS."""
    from hil_sim.world.scenario import Route
    from hil_sim.world.scenario_objects import Pose2D

    route = Route.model_validate(raw["route"])
    start = Pose2D.model_validate(raw["robot"]["start"])
    return (route.length_m((start.x_m, start.y_m)) / route.speed_mps
            + route.total_turn_rad(start) / TURN_RATE_FOR_TIME_LIMIT_RADPS)


def _with_time_limit(raw: dict[str, Any]) -> dict[str, Any]:
    return {**raw, "time_limit_s": float(math.ceil(route_time_s(raw) * (1.0 + TIME_LIMIT_SLACK) / 5.0) * 5.0)}


#: Library scene name -> its layout.
LAYOUTS = {"odom_loop": odom_loop, "odom_corridor": odom_corridor}


def _flow(value: Any) -> str:
    """One value in YAML flow style on one line ({name: a, size: {...}})."""
    text = yaml.safe_dump(value, default_flow_style=True, sort_keys=False, width=10**6).strip()
    return text.removesuffix("...").strip()  # a plain scalar ends with a document-end marker


def scene_yaml(name: str) -> str:
    """The library file text of a layout, in the style of the hand-written scenes (one
    obstacle per line)."""
    raw = _with_time_limit(LAYOUTS[name]())
    lines = [f"# Generated by `python -m hil_sim.world.scene_builder` from hil_sim/world/scene_builder.py ({name}):",
             "# edit the layout there and regenerate; a test checks that this file matches it."]
    for key, value in raw.items():
        if key == "description":
            lines.append("description: >")
            lines += ["  " + ln for ln in textwrap.wrap(value, 94)]
        elif isinstance(value, list):
            lines.append(f"{key}:")
            lines += [f"  - {_flow(item)}" for item in value]
        elif isinstance(value, dict) and key != "floor":
            lines.append(f"{key}:")
            lines += [f"  {k}: {_flow(v)}" for k, v in value.items()]
        else:
            lines.append(f"{key}: {_flow(value)}")
    return "\n".join(lines) + "\n"


def _library_path(name: str) -> Path:
    from hil_sim.world.scenario import library_dir

    return library_dir() / f"{name}.yaml"


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    check = args == ["--check"]
    if args and not check:
        print("usage: python -m hil_sim.world.scene_builder [--check]", file=sys.stderr)
        return 2
    stale = []
    for name in LAYOUTS:
        text, path = scene_yaml(name), _library_path(name)
        if check:
            if not path.is_file() or path.read_text() != text:
                stale.append(str(path))
        else:
            from calibration.outputs import atomic_write_text

            atomic_write_text(path, text)
            print(f"wrote {path}")
    if stale:
        print(f"out of date (run python -m hil_sim.world.scene_builder): {', '.join(stale)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
