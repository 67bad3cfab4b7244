"""The goal workspace: the polygon goals must lie in, checked where a goal enters.

`ros.inputs.goal.workspace` (optional) is a simple polygon (at least 3 vertices, finite, edges
that neither cross nor touch except neighbours at their shared vertex, non-zero area) in a named
frame (`odom` by default, or `map`). A goal in another frame than the workspace's is refused
(`wrong_frame`), one outside it too (`outside_workspace`); a point on an edge or a vertex is
inside (the polygon is closed, to EDGE_TOLERANCE_M). The receiver refuses /goal_pose goals
here, so a refused goal never reaches the controller; `dct run --goal` is checked against it
before the base is enabled.

The test is a point-on-segment check followed by the even-odd (crossing number) rule, written
out: shapely is not a dependency, and matplotlib.path leaves points on the boundary undefined
(its contains_point may say either, and its `radius` trick depends on the vertex order), while
the edge is where an operator's goal at a fence lands.
"""
from __future__ import annotations

import math
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from runtime.io.ros.messages import RosMessageError

#: A point this close to an edge (m) is on it, and so inside.
EDGE_TOLERANCE_M = 1e-6
_POSE_STAMPED = "geometry_msgs/msg/PoseStamped"

Vertex = tuple[float, float]


def _orient(a: Vertex, b: Vertex, c: Vertex) -> float:
    """Twice the signed area of the triangle abc (> 0: counter-clockwise)."""
    return (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])


def _on_segment(p: Vertex, a: Vertex, b: Vertex, tol: float) -> bool:
    """p within tol of the segment ab."""
    dx, dy = b[0] - a[0], b[1] - a[1]
    L2 = dx * dx + dy * dy
    s = 0.0 if L2 == 0.0 else max(0.0, min(1.0, ((p[0] - a[0]) * dx + (p[1] - a[1]) * dy) / L2))
    return math.hypot(p[0] - (a[0] + s * dx), p[1] - (a[1] + s * dy)) <= tol


def _segments_meet(a: Vertex, b: Vertex, c: Vertex, d: Vertex) -> bool:
    """The closed segments ab and cd share a point (crossing, touching or overlapping)."""
    o1, o2, o3, o4 = _orient(a, b, c), _orient(a, b, d), _orient(c, d, a), _orient(c, d, b)
    if ((o1 > 0 > o2) or (o1 < 0 < o2)) and ((o3 > 0 > o4) or (o3 < 0 < o4)):
        return True
    return any(_on_segment(p, q, r, 0.0) for p, q, r in ((c, a, b), (d, a, b), (a, c, d), (b, c, d)))


def polygon_problem(vertices: list[Vertex]) -> str | None:
    """Why the vertices are not a simple polygon (None: they are)."""
    n = len(vertices)
    if n < 3:
        return f"{n} vertices, a polygon needs at least 3"
    for i, (x, y) in enumerate(vertices):
        if not (math.isfinite(x) and math.isfinite(y)):
            return f"vertex {i} ({x}, {y}) is not finite"
    for i in range(n):
        if vertices[i] == vertices[(i + 1) % n]:
            return f"vertices {i} and {(i + 1) % n} are the same point"
    edges = [(vertices[i], vertices[(i + 1) % n]) for i in range(n)]
    for i in range(n):
        for j in range(i + 1, n):
            if j == i + 1 or (i == 0 and j == n - 1):
                # neighbours share one vertex, q; they must not fold back onto each other
                (p, q), (_, r) = (edges[i], edges[j]) if j == i + 1 else (edges[j], edges[i])
                if _on_segment(r, p, q, 0.0) or _on_segment(p, q, r, 0.0):
                    return f"edges {i} and {j} overlap: not a simple polygon"
            elif _segments_meet(*edges[i], *edges[j]):
                return f"edge {i} {_show(edges[i])} meets edge {j} {_show(edges[j])}: not a simple polygon"
    if abs(polygon_area(vertices)) <= EDGE_TOLERANCE_M ** 2:
        return "zero area"
    return None


def _show(edge: tuple[Vertex, Vertex]) -> str:
    (ax, ay), (bx, by) = edge
    return f"({ax:g}, {ay:g})-({bx:g}, {by:g})"


def polygon_area(vertices: list[Vertex]) -> float:
    """Signed area (shoelace; > 0: counter-clockwise)."""
    n = len(vertices)
    return 0.5 * sum(vertices[i][0] * vertices[(i + 1) % n][1] - vertices[(i + 1) % n][0] * vertices[i][1]
                     for i in range(n))


def polygon_contains(vertices: list[Vertex], x: float, y: float, tol: float = EDGE_TOLERANCE_M) -> bool:
    """(x, y) inside the closed polygon: on an edge (within tol) or by the even-odd rule."""
    n = len(vertices)
    p = (x, y)
    if any(_on_segment(p, vertices[i], vertices[(i + 1) % n], tol) for i in range(n)):
        return True
    inside = False
    for i in range(n):
        (xa, ya), (xb, yb) = vertices[i], vertices[(i + 1) % n]
        if (ya > y) != (yb > y) and x < xa + (y - ya) * (xb - xa) / (yb - ya):
            inside = not inside
    return inside


class GoalWorkspace(BaseModel):
    """Where goals may be: a simple polygon of [x, y] vertices (m) in `frame` (module docstring).
    A closing vertex equal to the first is dropped."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    frame: Literal["odom", "map"] = "odom"
    polygon: tuple[Vertex, ...] = Field(min_length=3)

    @field_validator("polygon")
    @classmethod
    def _simple(cls, v: tuple[Vertex, ...]) -> tuple[Vertex, ...]:
        if len(v) > 3 and v[0] == v[-1]:
            v = v[:-1]
        problem = polygon_problem(list(v))
        if problem is not None:
            raise ValueError(problem)
        return v

    def describe(self) -> str:
        return f"the goal workspace ({self.frame} frame, {len(self.polygon)} vertices)"

    def refusal(self, x: float, y: float, frame_id: str) -> tuple[str, str, str] | None:
        """(reason, field, text) when a goal at (x, y) in frame_id is refused; None: accepted."""
        if frame_id != self.frame:
            return ("wrong_frame", "header.frame_id",
                    f"{frame_id!r} is not the frame of {self.describe()}: goals are taken in {self.frame!r}")
        if not polygon_contains(list(self.polygon), x, y):
            return "outside_workspace", "pose.position", f"({x:.2f}, {y:.2f}) is outside {self.describe()}"
        return None

    def check_goal(self, goal) -> None:
        """A /goal_pose goal (convert.GoalPose) inside the workspace, or RosMessageError naming why not."""
        refused = self.refusal(goal.pose.x_m, goal.pose.y_m, goal.frame_id)
        if refused is not None:
            reason, field, text = refused
            raise RosMessageError(text, name=reason, field_name=f"{_POSE_STAMPED}.{field}")


__all__ = ["GoalWorkspace", "polygon_contains", "polygon_problem", "polygon_area", "EDGE_TOLERANCE_M"]
