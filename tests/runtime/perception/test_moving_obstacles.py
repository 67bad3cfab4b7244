"""Moving obstacles (runtime/perception/moving_obstacles.py and the modules it uses: cluster_tracking,
way_prediction, exit_channel): P_fix clusters followed scan to scan, their
velocity, and the predicted way of one that would meet the robot."""
from __future__ import annotations

import math

import numpy as np
import pytest

from runtime.perception.cluster_tracking import Track
from runtime.perception.exit_channel import exit_channel
from runtime.perception.moving_obstacles import MovingObstacles, PredictorSettings


def _disc(cx: float, cy: float, r: float = 0.25, n: int = 30) -> np.ndarray:
    """The lidar-facing half of a person-sized cylinder (seen from -x)."""
    a = np.linspace(math.pi / 2, 3 * math.pi / 2, n)
    return np.column_stack([cx + r * np.cos(a), cy + r * np.sin(a)])


def _wall(y: float, x0: float = -3.0, x1: float = 3.0) -> np.ndarray:
    x = np.arange(x0, x1, 0.04)
    return np.column_stack([x, np.full_like(x, y)])


def _run(mo: MovingObstacles, person_at, robot_pose=(0.0, 0.0, 0.0), speed=0.0, seconds=1.0, walls=True):
    """Scans at 10 Hz of a person at person_at(t) (and two walls); returns the last prediction."""
    pred = None
    for k in range(int(seconds * 10) + 1):
        t = 0.1 * k
        pts = [_disc(*person_at(t))]
        if walls:
            pts += [_wall(2.5), _wall(-2.5)]
        pred = mo.update(t, np.concatenate(pts), robot_pose, speed)
    return pred


def test_a_walking_person_is_tracked_with_its_velocity_and_walls_are_not():
    mo = MovingObstacles()
    _run(mo, lambda t: (2.0, -1.5 + 1.0 * t))
    moving = [t for t in mo.tracks if t.moving]
    assert len(moving) == 1, "the walls (long) and nothing else must not move"
    assert moving[0].velocity == pytest.approx([0.0, 1.0], abs=0.1)


def test_a_standing_person_or_box_is_not_moving():
    mo = MovingObstacles()
    pred = _run(mo, lambda t: (2.0, 0.5))
    assert not any(t.moving for t in mo.tracks) and len(pred) == 0


def test_a_person_crossing_where_the_robot_will_be_gives_the_way_ahead():
    """The robot at 0.6 m/s towards +x; the person crossing its line 1 m ahead at 1 m/s, due
    there when the robot is: its way ahead (over the horizon) is predicted, ahead of it."""
    mo = MovingObstacles()
    pred = _run(mo, lambda t: (1.0, -1.4 + 1.0 * t), robot_pose=(0.0, 0.0, 0.0), speed=0.6, seconds=0.6)
    assert len(pred) > 0
    person_y = -1.4 + 0.6
    assert pred[:, 1].max() > person_y + 1.0, "the way ahead of the person, not only where it is"
    assert pred[:, 1].min() > person_y - 0.3, "nothing behind the person"


def test_a_crossing_the_robot_clears_first_or_one_far_to_the_side_gives_nothing():
    # the person walks away from the robot's line: no meeting
    mo = MovingObstacles()
    assert len(_run(mo, lambda t: (1.5, 0.6 + 1.0 * t), speed=0.8)) == 0
    # the robot (at cruise speed) is past the crossing before the person comes
    mo = MovingObstacles()
    assert len(_run(mo, lambda t: (1.0, -3.0 + 1.0 * t), robot_pose=(0.5, 0.0, 0.0), speed=1.0, seconds=1.0,
                    walls=False)) == 0
    assert any(t.moving for t in mo.tracks), "the person was seen walking"
    # ... while a robot at a walk would meet the person: the way ahead is predicted
    slow = MovingObstacles(PredictorSettings(cruise_speed_mps=0.3, min_extrapolation_speed_mps=0.3))
    assert len(_run(slow, lambda t: (1.0, -3.0 + 1.0 * t), robot_pose=(0.5, 0.0, 0.0), speed=0.3, seconds=1.0,
                    walls=False)) > 0


def test_a_robot_that_cannot_stop_short_of_the_lane_goes_on_and_one_that_can_yields():
    """A person found walking late, 1 m/s across the robot's line; the robot at 1 m/s. With the
    lane 0.3 m ahead its front is in it already: braking stops it in the lane, going on clears it
    first, so it goes on (no prediction; measured in person_crossing seeds 15 and 24: braking,
    it was walked into). With the lane 1 m ahead it stops short of it, and yields."""
    for lane_x, yields in ((0.3, False), (1.0, True)):
        mo = MovingObstacles()
        pred = _run(mo, lambda t: (lane_x, -2.0 + 1.0 * t), robot_pose=(0.0, 0.0, 0.0), speed=1.0, seconds=0.6,
                    walls=False)
        (track,) = [t for t in mo.tracks if t.moving]
        assert (len(pred) > 0) == yields, lane_x
        assert track.passing_first == (not yields), lane_x
        if not yields:
            went = mo
    # ... and a person who stops is decided afresh when walking again (nothing kept from before)
    for k in range(7, 20):
        went.update(0.1 * k, _disc(0.3, -2.0 + 0.6), (0.0, 0.0, 0.0), 1.0)
    (track,) = went.tracks
    assert not track.moving and not track.passing_first and track.exit_side is None and track.moving_from is None
    # a robot at a walk, the person closer: going on does not clear the lane first either, it yields
    mo = MovingObstacles()
    assert len(_run(mo, lambda t: (0.3, -1.6 + 1.0 * t), robot_pose=(0.0, 0.0, 0.0), speed=0.2, seconds=0.6,
                    walls=False)) > 0


def test_a_robot_in_the_persons_way_keeps_no_prediction_on_itself():
    """A robot already standing in the person's way leaves it: the predicted points on itself and
    in a channel out to its side of the line are left out; one beside the way keeps them all and
    holds."""
    cfg = PredictorSettings()
    mo = MovingObstacles(cfg)
    pred = _run(mo, lambda t: (0.05, -1.6 + 1.0 * t), robot_pose=(0.0, 0.0, 0.0), speed=0.0, seconds=0.6)
    assert len(pred) > 0 and np.hypot(*pred.T).min() > cfg.far_side_m
    # the robot is 5 cm on the -x side of the person's line: its channel out runs to -x
    channel = (np.abs(pred[:, 1]) <= cfg.own_clearance_m) & (pred[:, 0] < cfg.far_side_m)
    assert not channel.any()
    mo = MovingObstacles(cfg)
    beside = _run(mo, lambda t: (0.6, -1.6 + 1.0 * t), robot_pose=(0.0, 0.0, 0.0), speed=0.0, seconds=0.6)
    assert len(beside) > 0 and np.hypot(*beside.T).min() < cfg.own_clearance_m + 0.3


def test_a_wall_cut_by_the_range_is_not_a_moving_obstacle():
    """The end of a wall the lidar sees to its range shifts as the robot drives along it."""
    mo = MovingObstacles()
    for k in range(11):
        t = 0.1 * k
        x = 1.0 * t  # the robot drives along +x; the wall's visible end moves with it
        wall = _wall(1.5, x - 5.7, x + 5.7)
        mo.update(t, wall[np.hypot(wall[:, 0] - x, wall[:, 1]) < 6.0], (x, 0.0, 0.0), 1.0)
    assert not any(t.moving for t in mo.tracks)


def test_shift_moves_tracks_and_predictions_with_the_odom_frame():
    mo = MovingObstacles()
    pred = _run(mo, lambda t: (1.0, -1.4 + 1.0 * t), speed=0.6, seconds=0.6).copy()
    assert len(pred)
    t0 = next(t for t in mo.tracks if t.moving)
    past0, vel0 = [q.copy() for _, q in t0.past], t0.velocity.copy()
    c, s = math.cos(0.3), math.sin(0.3)
    R = np.array([[c, -s], [s, c]])
    mo.shift(np.array([0.1, -0.2, 0.3]))
    np.testing.assert_allclose(mo.predicted, pred @ R.T + [0.1, -0.2])
    np.testing.assert_allclose(t0.velocity, R @ vel0)
    for q0, (_, q) in zip(past0, t0.past):  # the vacated test's old points too
        np.testing.assert_allclose(q, q0 @ R.T + [0.1, -0.2])


def test_disabled_it_predicts_nothing():
    mo = MovingObstacles(PredictorSettings(enabled=False))
    assert len(_run(mo, lambda t: (1.5, -1.4 + 1.0 * t), speed=0.6)) == 0
    assert len(mo.with_predictions(np.zeros((3, 2)))) == 3


def test_a_static_box_whose_visible_faces_change_is_not_moving():
    """Driving past a box shows its side after its front: the visible centroid shifts by
    decimetres, but the cells its front filled are still filled (the vacated test)."""
    s = np.linspace(-0.2, 0.2, 11)
    front = np.column_stack([np.full_like(s, 1.8), s])
    d = np.linspace(0.0, 0.6, 25)  # a long side (a 0.4 x 0.6 m box), densely seen
    side = np.column_stack([1.8 + d, np.full_like(d, 0.2)])
    def run(config):
        mo = MovingObstacles(config)
        seen_moving = False
        for k in range(9):
            t = 0.1 * k
            n = int(np.clip((k - 3) / 2, 0, 1) * len(side))  # the side comes into view in 0.2 s
            pts = np.concatenate([front, side[:n], _wall(2.5), _wall(-2.5)])
            mo.update(t, pts, (1.0 * t, 0.6, 0.0), 1.0)
            seen_moving |= any(t.moving for t in mo.tracks)
        return seen_moving

    assert not run(PredictorSettings())
    # the centroid alone says "moving": without the vacated test (every old cell may stay filled)
    # and the free-space test
    assert run(PredictorSettings(max_still_filled=1.0, min_moved_in=0.0))
    assert not run(PredictorSettings(min_moved_in=0.0)), "the vacated test alone stops this one"


def _visible_box(robot_xy) -> np.ndarray:
    """The faces of a fixed 0.4 x 0.8 m shelf (case3's: x 1.8..2.2, y -0.4..0.4) that a lidar at
    robot_xy (y > 0.4) sees."""
    x = np.arange(1.8, 2.2 + 1e-9, 0.03)
    y = np.arange(-0.4, 0.4 + 1e-9, 0.03)
    faces = [np.column_stack([x, np.full_like(x, 0.4)])]  # the side facing the robot
    if robot_xy[0] < 1.8:
        faces.append(np.column_stack([np.full_like(y, 1.8), y]))  # the front, until driven past
    if robot_xy[0] > 2.2:
        faces.append(np.column_stack([np.full_like(y, 2.2), y]))  # the back, once past it
    return np.concatenate(faces)


def test_a_shelf_driven_past_is_not_moving_though_its_front_is_hidden():
    """Driving past a shelf hides its front (its cells are empty now: the vacated test alone is
    fooled) and shows its back, which was behind its side before, never seen free: not moving."""
    def run(config):
        mo = MovingObstacles(config)
        seen = False
        for k in range(25):
            t, robot = 0.1 * k, (0.8 + 0.1 * k, 0.8)
            pts = np.concatenate([_visible_box(robot), _wall(2.5), _wall(-2.5)])
            mo.update(t, pts, (*robot, 0.0), 1.0)
            seen |= any(tr.moving for tr in mo.tracks)
        return seen

    assert not run(PredictorSettings())
    assert run(PredictorSettings(min_moved_in=0.0)), "without the moved-in test the shelf moves"


@pytest.mark.parametrize("walk", [(0.0, 1.0), (-1.0, 0.0), (-0.5, 0.0)], ids=["crossing", "head-on", "head-on slow"])
def test_a_person_walking_across_or_towards_the_robot_moves_into_space_seen_free(walk):
    """The moved-in test keeps real movers: a person crossing enters space where the wall behind
    was seen; one coming head-on enters the space in front of where it was."""
    mo = MovingObstacles()
    _run(mo, lambda t: (3.0 + walk[0] * t, -0.8 + walk[1] * t) if walk[1] else (3.0 + walk[0] * t, 0.0))
    moving = [t for t in mo.tracks if t.moving]
    assert len(moving) == 1 and moving[0].velocity == pytest.approx(list(walk), abs=0.15)


def test_a_person_coming_down_the_robots_line_is_predicted_past_the_robot():
    """Head-on, 3.5 m off at 1.1 m/s: the way reaches past the robot (max_horizon_s), so the path
    has only the sides to go to, and the robot keeps none of it on itself; with the way cut at
    horizon_s (max_horizon_s 0) it ends between them, and a path could go round its end."""
    for max_h, past in ((4.0, True), (0.0, False)):
        cfg = PredictorSettings(max_horizon_s=max_h)
        mo = MovingObstacles(cfg)
        pred = _run(mo, lambda t: (4.0 - 1.1 * t, 0.1), robot_pose=(0.0, 0.0, 0.0), speed=0.8, seconds=0.6)
        assert len(pred) > 0
        assert bool(pred[:, 0].min() < -0.3) is past
        assert np.hypot(*pred.T).min() > cfg.far_side_m
        if past:  # the robot (0.1 m off the line, on its -y side) keeps the far side, not its own
            by = pred[np.abs(pred[:, 0]) <= cfg.own_clearance_m]
            assert len(by) and (by[:, 1] > cfg.far_side_m).all()


def test_a_person_walking_away_leaves_space_seen_free_and_moves():
    """Walking straight away, a person moves into space its own body hid (never seen free): it
    moves out of space the lidar sees free now, and that is enough."""
    mo = MovingObstacles()
    _run(mo, lambda t: (1.5 + 1.0 * t, 0.0), speed=0.0)
    moving = [t for t in mo.tracks if t.moving]
    assert len(moving) == 1 and moving[0].velocity == pytest.approx([1.0, 0.0], abs=0.15)


def test_the_way_out_keeps_its_side_while_the_persons_line_is_estimated_anew():
    """A robot on a head-on person's line leaves it to one side, and keeps that side though the
    line, estimated anew every scan, passes a few centimetres to either side of it (the channel
    flipped sides and the robot dithered: person_approaching seed 10)."""
    mo = MovingObstacles()
    sides = []
    for k in range(10):
        t = 0.1 * k
        y = 0.06 * (-1) ** k  # the robot 6 cm to either side of the line, scan by scan
        mo.update(t, _disc(3.0 - 1.0 * t, 0.0, n=30), (0.0, y, 0.0), 0.0)
        tr = [x for x in mo.tracks if x.moving and x.exit_side is not None]
        if tr:
            sides.append(float(np.sign(tr[0].exit_side[1])))
    assert len(sides) >= 2 and len(set(sides)) == 1, sides


@pytest.mark.parametrize("robot_y, heading_deg", [(0.07, -30.0), (-0.07, 30.0)])
def test_a_robot_on_a_head_on_persons_line_leaves_it_to_the_side_it_heads_to(robot_y, heading_deg):
    """A robot on a head-on person's line, 7 cm to one side of it but already turned 30 deg
    towards the other, leaves to the side it heads to: sent by its offset alone to the side it
    had turned from, it turned back and was on the line when the person came
    (person_approaching seed 6)."""
    mo = MovingObstacles()
    pose = (0.0, robot_y, math.radians(heading_deg))
    for k in range(10):
        t = 0.1 * k
        mo.update(t, _disc(3.0 - 1.0 * t, 0.0, n=30), pose, 0.5)
    (track,) = [x for x in mo.tracks if x.moving]
    assert track.exit_side is not None, "the robot is in the person's way"
    assert np.sign(track.exit_side[1]) == np.sign(math.sin(pose[2])), track.exit_side


def test_the_side_chosen_is_given_up_when_the_robot_is_well_on_the_other_side_and_not_heading_back():
    """A side once chosen (here -y) is kept until the robot, led along its heading, is well on
    the other side of the line: 0.25 m on the other side heading along the line, it changes; the
    same place heading 40 deg back towards the chosen side, it keeps it (a line estimated 3 m off
    swung 0.2 m under a robot already leaving, and the side flipped: person_approaching seed 6)."""
    mo = MovingObstacles()
    way = np.array([[x, 0.0] for x in np.arange(-1.0, 3.0, 0.05)])
    for heading_deg, side_y in ((0.0, 1.0), (-40.0, -1.0)):
        track = Track(0, exit_side=np.array([0.0, -1.0]))
        h = math.radians(heading_deg)
        exit_channel(mo.config, way, np.array([3.0, 0.0]), np.array([-1.0, 0.0]), np.array([0.0, 0.25]),
                     np.array([math.cos(h), math.sin(h)]), track)
        assert track.exit_side[1] == pytest.approx(side_y), heading_deg


def test_a_person_is_left_out_of_the_odometry_once_it_has_walked_a_way():
    """moving_points (what the lidar odometry leaves out): the points of a track found moving
    that has gone odometry_travel_m since, carried to the time asked; nothing before that (a
    static object that looks moving for a few scans stays in the ICP)."""
    mo = MovingObstacles()
    seen, held = {}, 0
    for k in range(13):
        t = 0.1 * k
        mo.update(t, np.concatenate([_disc(2.0, -1.5 + 1.0 * t), _wall(2.5), _wall(-2.5)]), (0.0, 0.0, 0.0), 0.0)
        seen[k] = len(mo.moving_points(t + 0.05))
        moving = [x for x in mo.tracks if x.moving]
        if moving and moving[0].moving_from is not None:
            tr = moving[0]
            gone = math.hypot(tr.last[1] - tr.moving_from[0], tr.last[2] - tr.moving_from[1])
            assert (seen[k] > 0) == (gone >= mo.config.odometry_travel_m), (k, gone)
            held += seen[k] == 0
    assert held >= 1, "found moving, not yet left out: the travel gate"
    assert seen[12] > 0
    pts = mo.moving_points(1.25)
    assert pts[:, 1].mean() == pytest.approx(-1.5 + 1.25, abs=0.12), "carried to the time asked"
    assert np.all(np.abs(pts[:, 0] - 2.0) < 0.3)
