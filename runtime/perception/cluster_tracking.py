"""Tracks of P_fix clusters for the moving-obstacle predictor (runtime.perception.moving_obstacles):
steps 1-3 of it, per scan.

1. Clusters: the connected components (8-connected) of an occupancy grid of `cell_m` over the
   points within `range_m` of the robot (scipy.ndimage.label). A component wider than
   `max_extent_m` (a wall, a run of furniture), with fewer than `min_points`, or reaching to
   within `range_margin_m` of the range (the end of a wall the lidar sees that far: it shifts as
   the robot moves) is not followed.
2. Tracks: each cluster joins the track whose last centroid, carried on by its velocity, is
   nearest and within `gate_m` plus what `max_speed_mps` covers since; the others start tracks;
   a track not seen for `lost_s` is dropped.
3. Velocity: the least-squares line through the track's centroids over the last `window_s`. A
   track is moving when that speed is at least `min_speed_mps` and its centroids span at least
   `min_span_s` and `min_travel_m`, and it left where it was: of the points it had
   `vacated_lag_s` ago, at most `max_still_filled` lie in cells this scan fills (a static box
   seen from a moving robot shows new faces and its visible centroid shifts, but the cells it
   filled are still filled; a walking person's are empty). And it came into space the lidar saw
   free `vacated_lag_s` ago (`min_moved_in`): of its points now, that share lies nearer than the
   return that scan had on their bearing from where the robot was then (or, walking away, its
   points then lie in space this scan sees free). The faces a static object shows a robot
   driving past it were hidden behind its other faces before (never seen free), and its old
   faces are hidden now, not empty. A person crossing walks into space where the wall behind was
   seen; one coming head-on walks into the space in front of where it was
   (docs/decisions/people-moving-test.md).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from runtime.common.geometry import least_return_near, nearest_returns

_EIGHT = np.ones((3, 3), dtype=bool)


def rotate_bins(profile: np.ndarray, shift_bins: float) -> np.ndarray:
    """A bearing profile turned by shift_bins (nearest whole bin)."""
    k = int(round(shift_bins))
    return np.roll(profile, k) if k else profile


@dataclass
class Track:
    """One followed cluster: its centroids (time, x, y), velocity (m/s, odom frame), last points."""

    track_id: int
    history: list[tuple[float, float, float]] = field(default_factory=list)
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(2))
    moving: bool = False
    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    conflict_until_s: float = -math.inf  # its way ahead is given to the planner until then
    past: list = field(default_factory=list)  # (time, points) over the window
    moving_since_s: float | None = None  # moving in every scan since then
    moving_from: np.ndarray | None = None  # its centroid then
    passing_first: bool = False  # the robot goes on in front of it (step 5), until a conflict
    exit_side: np.ndarray | None = None  # the odom direction of the robot's way out of its way
    corridor_conflict_s: float = -math.inf  # the last scan whose corridor test met the robot

    @property
    def last(self) -> tuple[float, float, float]:
        return self.history[-1]


class ClusterTracker:
    """Steps 1-3 (module docstring); config: PredictorSettings."""

    def __init__(self, config) -> None:
        self.config = config
        self.tracks: list[Track] = []
        self._next_id = 0
        self._grid: np.ndarray | None = None  # this scan's occupancy grid, round the robot's xy
        self._grid_robot = np.zeros(2)
        #: (time, robot xy, nearest return per bearing bin) of the scans over the window (step 3)
        self._profiles: list[tuple[float, np.ndarray, np.ndarray]] = []

    def reset(self) -> None:
        self.tracks.clear()
        self._profiles.clear()

    def scan(self, now_s: float, points_fix: np.ndarray, robot_xy: tuple[float, float]) -> None:
        """One scan's P_fix (odom (N, 2)) seen from robot_xy: profiles, clusters, tracks."""
        c = self.config
        if c.min_moved_in > 0.0:
            self._profiles = [x for x in self._profiles if now_s - x[0] <= c.window_s]
            self._profiles.append((float(now_s), np.asarray(robot_xy), self._profile(points_fix, robot_xy)))
        clusters = self._clusters(points_fix, robot_xy)
        self._associate(float(now_s), clusters)

    def shift(self, move, R: np.ndarray, shift_bins: float) -> None:
        """An odometry correction moved the odom frame's points: move(points) moves points, R
        turns directions, shift_bins turns the bearing profiles."""
        # a profile turns with the frame: its bins are bearings in the odom frame
        self._profiles = [(tp, move(xy[None])[0], rotate_bins(prof, shift_bins)) for tp, xy, prof in self._profiles]
        for t in self.tracks:
            xy = move(np.array([[h[1], h[2]] for h in t.history]))
            t.history = [(h[0], float(q[0]), float(q[1])) for h, q in zip(t.history, xy)]
            t.velocity = R @ t.velocity
            t.points = move(t.points)
            if t.moving_from is not None:
                t.moving_from = move(t.moving_from[None])[0]
            if t.exit_side is not None:
                t.exit_side = R @ t.exit_side
            if t.past:  # the past scans' points, moved together as one array
                moved = move(np.concatenate([q for _, q in t.past]))
                ends = np.cumsum([len(q) for _, q in t.past])
                t.past = [(tp, moved[end - len(q):end]) for (tp, q), end in zip(t.past, ends)]

    # -- step 3's evidence ----------------------------------------------------------------------
    def _profile(self, points: np.ndarray, origin) -> np.ndarray:
        """The scan's nearest return (m) per bearing bin round origin (odom bearings; inf: none
        within range_m: unknown, not free)."""
        c = self.config
        return nearest_returns(points - np.asarray(origin), int(round(360.0 / c.bearing_bin_deg)), c.range_m)

    def _moved_in(self, now: float, points: np.ndarray) -> float:
        """The share of `points` lying in space the scan of vacated_lag_s ago saw free: nearer
        than its nearest return on their bearing, and on the bins either side, by free_margin_m
        (1.0 without such a scan: no evidence against)."""
        c = self.config
        old = [x for x in self._profiles if now - x[0] >= c.vacated_lag_s]
        if not old or not len(points):
            return 1.0
        return self._seen_free(old[-1], points)

    def _seen_free(self, profile, points: np.ndarray) -> float:
        """The share of `points` nearer by free_margin_m than every return the profile has on
        the bearings within free_lateral_m of them (none: open to range_m): space that scan saw
        free (0.0 without a profile). Not a single bearing bin: see
        docs/decisions/people-moving-test.md."""
        c = self.config
        if profile is None or not len(points):
            return 0.0
        _, origin, prof = profile
        r, least = least_return_near(prof, points - origin, c.free_lateral_m)
        return float(np.mean(r + c.free_margin_m < least))

    def _occupied(self, points: np.ndarray) -> np.ndarray:
        """(N,) bool: the points' cells are occupied in this scan's grid."""
        if self._grid is None or not len(points):
            return np.zeros(len(points), dtype=bool)
        n = self._grid.shape[0]
        c = self.config
        ij = np.floor((points - self._grid_robot + c.range_m) / c.cell_m).astype(np.intp)  # as _clusters
        inside = ((ij >= 0) & (ij < n)).all(axis=1)
        out = np.zeros(len(points), dtype=bool)
        out[inside] = self._grid[ij[inside, 0], ij[inside, 1]]
        return out

    # -- steps 1-3 ------------------------------------------------------------------------------
    def _clusters(self, p: np.ndarray, robot_xy) -> list[np.ndarray]:
        c = self.config
        self._grid = None
        if not len(p):
            return []
        near = np.abs(p - np.asarray(robot_xy)).max(axis=1) < c.range_m
        p = p[near]
        if not len(p):
            return []
        n = int(math.ceil(2 * c.range_m / c.cell_m))
        ij = np.clip(np.floor((p - np.asarray(robot_xy) + c.range_m) / c.cell_m).astype(np.intp), 0, n - 1)
        grid = np.zeros((n, n), dtype=bool)
        grid[ij[:, 0], ij[:, 1]] = True
        self._grid, self._grid_robot = grid, np.asarray(robot_xy, dtype=np.float64)
        labels, count = ndimage.label(grid, structure=_EIGHT)
        if not count:
            return []
        lab = labels[ij[:, 0], ij[:, 1]]
        far = np.hypot(*(p - np.asarray(robot_xy)).T) >= c.range_m - c.range_margin_m
        order = np.argsort(lab, kind="stable")
        bounds = np.searchsorted(lab[order], np.arange(1, count + 2))
        out = []
        for k, sl in enumerate(ndimage.find_objects(labels)):
            if sl is None:
                continue
            ext = math.hypot(sl[0].stop - sl[0].start, sl[1].stop - sl[1].start) * c.cell_m
            idx = order[bounds[k]:bounds[k + 1]]
            # one cut by the edge of the range (the end of a wall the lidar sees to range_m) shifts
            # as the robot moves
            if ext > c.max_extent_m or len(idx) < c.min_points or far[idx].any():
                continue
            out.append(p[idx])
        return out

    def _associate(self, now: float, clusters: list[np.ndarray]) -> None:
        c = self.config
        self.tracks = [t for t in self.tracks if now - t.last[0] <= c.lost_s]
        centroids = [q.mean(axis=0) for q in clusters]
        # predicted track positions now; greedy nearest pairs under the gate
        pairs = []
        if self.tracks and centroids:
            dt = np.array([now - t.last[0] for t in self.tracks])
            guess = np.array([t.last[1:] for t in self.tracks]) + np.array([t.velocity for t in self.tracks]) * dt[:, None]
            cen = np.array(centroids)
            d = np.hypot(cen[None, :, 0] - guess[:, 0, None], cen[None, :, 1] - guess[:, 1, None])  # (tracks, clusters)
            ti, ci = np.nonzero(d <= (c.gate_m + c.max_speed_mps * dt)[:, None])
            pairs = list(zip(d[ti, ci].tolist(), ti.tolist(), ci.tolist()))
        used_t, used_c = set(), set()
        for _, ti, ci in sorted(pairs):
            if ti in used_t or ci in used_c:
                continue
            used_t.add(ti)
            used_c.add(ci)
            self._extend(self.tracks[ti], now, centroids[ci], clusters[ci])
        for ci, q in enumerate(centroids):
            if ci not in used_c:
                t = Track(self._next_id)
                self._next_id += 1
                self._extend(t, now, q, clusters[ci])
                self.tracks.append(t)

    def _extend(self, t: Track, now: float, centroid: np.ndarray, points: np.ndarray) -> None:
        c = self.config
        t.history.append((now, float(centroid[0]), float(centroid[1])))
        t.history = [h for h in t.history if now - h[0] <= c.window_s]
        t.points = points
        h = np.asarray(t.history)
        span = h[-1, 0] - h[0, 0]
        if len(h) < 3 or span < c.min_span_s:
            t.velocity, t.moving = np.zeros(2), False
            self._stopped(t)
            return
        tt = h[:, 0] - h[:, 0].mean()
        denom = float(tt @ tt)
        t.velocity = np.array([tt @ (h[:, 1] - h[:, 1].mean()), tt @ (h[:, 2] - h[:, 2].mean())]) / denom
        travel = math.hypot(h[-1, 1] - h[0, 1], h[-1, 2] - h[0, 2])
        t.moving = bool(np.hypot(*t.velocity) >= c.min_speed_mps and travel >= c.min_travel_m)
        t.past.append((now, points))
        t.past = [x for x in t.past if now - x[0] <= c.window_s]
        if t.moving:
            # Did it leave where it was? A static object seen from a moving robot shows new faces
            # (its centroid shifts) but the cells it filled lag_s ago are still filled; a person's
            # are empty.
            old = [x for x in t.past if now - x[0] >= c.vacated_lag_s]
            if not old or float(np.mean(self._occupied(old[-1][1]))) > c.max_still_filled:
                t.moving = False
            elif (c.min_moved_in > 0.0 and self._moved_in(now, points) < c.min_moved_in
                  and self._seen_free(self._profiles[-1] if self._profiles else None, old[-1][1]) < c.min_moved_in):
                t.moving = False
        if not t.moving:
            self._stopped(t)
        elif t.moving_since_s is None:
            t.moving_since_s = now
            t.moving_from = centroid.copy()

    @staticmethod
    def _stopped(t: Track) -> None:
        """A track not moving: what was decided about its walk is forgotten."""
        t.moving_since_s = t.moving_from = t.exit_side = None
        t.passing_first = False
