"""Goals only inside the configured goal workspace: the polygon and its config
(runtime/io/ros/workspace.py), the receiver's refusal of /goal_pose goals, `dct run`'s console and
`--goal` before the base is enabled."""
from __future__ import annotations

import math

import numpy as np
import pytest
import yaml
from hypothesis import example, given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from runtime.io.ros import messages as M
from runtime.io.ros.workspace import EDGE_TOLERANCE_M, GoalWorkspace, polygon_contains, polygon_problem

SQUARE = [(0.0, 0.0), (10.0, 0.0), (10.0, 6.0), (0.0, 6.0)]
L_SHAPE = [(0.0, 0.0), (6.0, 0.0), (6.0, 2.0), (2.0, 2.0), (2.0, 6.0), (0.0, 6.0)]


def test_inside_outside_edge_and_vertex():
    assert polygon_contains(SQUARE, 5.0, 3.0)
    assert not polygon_contains(SQUARE, 12.0, 3.0) and not polygon_contains(SQUARE, 5.0, -0.01)
    for x, y in ((10.0, 3.0), (5.0, 0.0), (0.0, 6.0), (10.0, 0.0), (10.0 + 5e-7, 3.0)):   # the boundary is inside
        assert polygon_contains(SQUARE, x, y), (x, y)
    assert not polygon_contains(SQUARE, 10.0 + 1e-5, 3.0)
    # concave: the notch of the L is outside, its arms inside, its inner corner on the boundary
    assert polygon_contains(L_SHAPE, 1.0, 5.0) and polygon_contains(L_SHAPE, 5.0, 1.0)
    assert not polygon_contains(L_SHAPE, 4.0, 4.0) and polygon_contains(L_SHAPE, 2.0, 2.0)
    # a ray through a vertex counts it once
    assert polygon_contains([(0, 0), (4, 2), (0, 4), (2, 2)], 1.0, 2.0) is False
    assert polygon_contains([(0, 0), (4, 2), (0, 4), (2, 2)], 3.0, 2.0)


def _star(radii, angles_seed):
    """A simple polygon: vertices at increasing angles around the origin (star-shaped)."""
    rng = np.random.default_rng(angles_seed)
    angles = np.sort(rng.uniform(0, 2 * math.pi, len(radii)))
    angles = np.unique(np.round(angles, 6))
    radii = radii[:len(angles)]
    return [(float(r * math.cos(a)), float(r * math.sin(a))) for r, a in zip(radii, angles)]


def _boundary_distance(poly, x, y):
    n = len(poly)
    best = math.inf
    for i in range(n):
        (ax, ay), (bx, by) = poly[i], poly[(i + 1) % n]
        dx, dy = bx - ax, by - ay
        s = max(0.0, min(1.0, ((x - ax) * dx + (y - ay) * dy) / (dx * dx + dy * dy)))
        best = min(best, math.hypot(x - ax - s * dx, y - ay - s * dy))
    return best


@settings(max_examples=200, deadline=None)
@given(radii=st.lists(st.floats(0.5, 50.0), min_size=3, max_size=12), seed=st.integers(0, 2**31),
       px=st.floats(-60, 60), py=st.floats(-60, 60))
@example(radii=[2.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.5], seed=969, px=1.5, py=0.0)     # 0.7 mm outside an edge: outside
def test_agrees_with_matplotlib_away_from_the_boundary(radii, seed, px, py):
    from matplotlib.path import Path

    poly = _star(radii, seed)
    if len(poly) < 3 or polygon_problem(poly) is not None:
        return
    d = _boundary_distance(poly, px, py)
    if d <= EDGE_TOLERANCE_M:                     # on the boundary: ours is inside, matplotlib's is undefined
        assert polygon_contains(poly, px, py)
        return
    if d < 100 * EDGE_TOLERANCE_M:                # ours and matplotlib's rounding may differ this close
        return
    assert polygon_contains(poly, px, py) == bool(Path(poly).contains_point((px, py)))


@pytest.mark.parametrize("polygon,says", [
    ([(0, 0), (1, 0)], "at least 3"),
    ([(0, 0), (1, 0), (1, math.inf)], "not finite"),
    ([(0, 0), (1, 0), (1, math.nan)], "not finite"),
    ([(0, 0), (4, 0), (0, 3), (4, 3)], "not a simple polygon"),           # a bow tie
    ([(0, 0), (4, 0), (4, 0), (0, 3)], "the same point"),
    ([(0, 0), (4, 0), (8, 0)], "not a simple polygon"),                    # all on a line
    ([(0, 0), (4, 0), (2, 0), (2, 3)], "overlap"),                         # folds back
    ([(0, 0), (6, 0), (6, 6), (3, 0), (0, 6)], "meets edge"),              # touches itself at (3, 0)
])
def test_bad_polygons_are_refused(polygon, says):
    with pytest.raises(ValidationError, match=says):
        GoalWorkspace(polygon=polygon)


def test_workspace_config():
    ws = GoalWorkspace(polygon=[[0, 0], [10, 0], [10, 6], [0, 6], [0, 0]])      # a closed ring: the repeat dropped
    assert ws.frame == "odom" and len(ws.polygon) == 4
    assert GoalWorkspace(frame="map", polygon=SQUARE).frame == "map"
    for bad in ({"frame": "base_link", "polygon": SQUARE}, {"polygon": SQUARE, "area": 1}, {}):
        with pytest.raises(ValidationError):
            GoalWorkspace.model_validate(bad)


def _config_file(tmp_path, workspace, **outputs):
    path = tmp_path / "c.yaml"
    doc = {"ros": {"inputs": {"goal": {"topic": "/goal_pose", "workspace": workspace}}}}
    if outputs:
        doc["ros"]["outputs"] = outputs
    path.write_text(yaml.safe_dump(doc))
    return path


def test_a_bad_polygon_in_the_config_is_one_line(tmp_path):
    from calibration.errors import ConfigFileError
    from runtime.config import load_controller_config

    ok = load_controller_config(_config_file(tmp_path, {"polygon": [[0, 0], [10, 0], [10, 6], [0, 6]]}))
    assert ok.ros.inputs.goal.workspace.polygon == tuple(SQUARE)
    for workspace, says in [({"polygon": [[0, 0], [4, 0], [0, 3], [4, 3]]}, "not a simple polygon"),
                            ({"polygon": [[0, 0], [4, 0]]}, "at least 3"),
                            ({"polygon": [[0, 0], [4, 0], [4, "x"]]}, "polygon"),
                            ({"polygon": SQUARE, "frame": "earth"}, "frame")]:
        with pytest.raises(ConfigFileError) as info:
            load_controller_config(_config_file(tmp_path, workspace))
        text = str(info.value)
        assert "\n" not in text and "ros.inputs.goal.workspace" in text and says in text, text
    with pytest.raises(ConfigFileError, match="odometry frame"):      # odom is the odometry frame's name
        load_controller_config(_config_file(tmp_path, {"polygon": SQUARE}, odom_frame="odom_ekf"))


# ----------------------------------------------------------------------------- the receiver


def _pose(x, y, frame="odom"):
    return M.PoseStamped(M.Header(M.Time(100, 0), frame), M.Pose(M.Point(x, y, 0.0), M.Quaternion(0, 0, 0, 1)))


def _goal_receiver(workspace, domain_id=163):
    from runtime.io.ros.dds import CycloneTransport
    from runtime.io.ros.receiver import GoalTopic, RosInputConfig, RosSensorReceiver
    from runtime.io.sensor_inbox import SensorInbox

    topic = GoalTopic(workspace=workspace)
    rx = RosSensorReceiver(RosInputConfig(domain_id=domain_id, goal=topic), SensorInbox(), CycloneTransport(domain_id))
    handle = rx._handler("goal", topic)
    return rx, lambda msg: rx.process("goal", "geometry_msgs/msg/PoseStamped", M.to_cdr(msg), handle)


def test_receiver_refuses_goals_outside_or_in_another_frame():
    rx, send = _goal_receiver(GoalWorkspace(polygon=[(0, 0), (10, 0), (10, 6), (0, 6)]))
    assert send(_pose(4.0, 3.0))
    assert rx.take_goal().pose.x_m == 4.0
    assert send(_pose(10.0, 6.0))                                  # a corner: inside
    assert rx.take_goal().pose.y_m == 6.0
    assert not send(_pose(12.0, 3.0))
    assert rx.take_goal() is None                                  # never reaches the controller
    assert not send(_pose(4.0, 3.0, frame="map"))
    assert rx.take_goal() is None
    assert rx.error_counts == {"goal.outside_workspace": 1, "goal.wrong_frame": 1}
    said = rx.take_goal_rejections()
    assert said == (
        "[outside_workspace] geometry_msgs/msg/PoseStamped.pose.position: (12.00, 3.00) is outside the goal workspace "
        "(odom frame, 4 vertices)",
        "[wrong_frame] geometry_msgs/msg/PoseStamped.header.frame_id: 'map' is not the frame of the goal workspace "
        "(odom frame, 4 vertices): goals are taken in 'odom'")
    assert rx.take_goal_rejections() == ()


def test_receiver_without_a_workspace_takes_any_goal_and_says_other_refusals():
    rx, send = _goal_receiver(None, domain_id=164)
    assert send(_pose(1000.0, -3000.0))
    assert rx.take_goal().pose.x_m == 1000.0
    assert not send(_pose(math.nan, 0.0))
    assert rx.take_goal_rejections()[0].startswith("[out_of_range] geometry_msgs/msg/PoseStamped.pose.position.x")
    ws_map = GoalWorkspace(frame="map", polygon=SQUARE)
    rx, send = _goal_receiver(ws_map, domain_id=165)
    assert send(_pose(1.0, 1.0, frame="map")) and not send(_pose(1.0, 1.0, frame="odom"))
    assert rx.error_counts == {"goal.wrong_frame": 1}


# ----------------------------------------------------------------------------- dct run


class _Receiver:
    def __init__(self, rejections=(), goal=None):
        self.rejections, self.goal = tuple(rejections), goal

    def take_goal_rejections(self):
        r, self.rejections = self.rejections, ()
        return r

    def take_goal(self):
        g, self.goal = self.goal, None
        return g


def test_dct_run_console_says_and_counts_refused_goals():
    from types import SimpleNamespace

    from runtime.app.run_observer import RunObserver
    from runtime.io.ros.settings import RosConfig

    requested, said = [], []
    controller = SimpleNamespace(request_goal=lambda pose, source: requested.append(pose))
    refusal = ("[outside_workspace] geometry_msgs/msg/PoseStamped.pose.position: (12.00, 3.00) is outside the goal "
               "workspace (odom frame, 4 vertices)")
    obs = RunObserver(SimpleNamespace(controller=controller), RosConfig(), None, _Receiver([refusal]), None,
                      said.append)
    obs._take_goal()
    assert said == [f"dct run: goal refused: {refusal}"] and obs.goals_ignored == 1 and requested == []


def test_dct_run_goal_outside_the_workspace_is_refused_before_the_base_is_enabled(tmp_path):
    from runtime.app.run_inputs import RunInputError, RunOptions, load_inputs

    cfg = _config_file(tmp_path, {"polygon": [[0, 0], [10, 0], [10, 6], [0, 6]]})
    loaded = load_inputs(RunOptions(config_path=cfg, goal=(10.0, 6.0, 0.0), planner="all-fixed"))    # on the edge
    assert loaded.config.ros.inputs.goal.workspace is not None
    with pytest.raises(RunInputError) as info:
        load_inputs(RunOptions(config_path=cfg, goal=(12.0, 3.0, 0.0), planner="all-fixed"))
    assert str(info.value).startswith("[outside_workspace] --goal: (12.00, 3.00) is outside the goal workspace (odom "
                                      "frame, 4 vertices)")
    cfg_map = _config_file(tmp_path, {"frame": "map", "polygon": [[0, 0], [10, 0], [10, 6], [0, 6]]})
    with pytest.raises(RunInputError, match=r"\[wrong_frame\] --goal: 'odom'"):
        load_inputs(RunOptions(config_path=cfg_map, goal=(1.0, 1.0, 0.0), planner="all-fixed"))
