"""Planar poses as numpy vectors (x, y, yaw): compose, invert, relative pose, 3x3/4x4 matrices.

The fusion works on small arrays every tick; runtime.common.geometry.Pose2D (a dataclass) is the
controller's public pose type.
"""
from __future__ import annotations

import math

import numpy as np


def wrap(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def se2_compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a (+) b: b expressed in a's frame, composed onto a."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return np.array([a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], wrap(a[2] + b[2])])


def se2_inverse(a: np.ndarray) -> np.ndarray:
    c, s = math.cos(a[2]), math.sin(a[2])
    return np.array([-c * a[0] - s * a[1], s * a[0] - c * a[1], wrap(-a[2])])


def se2_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The pose of b in a's frame (a^-1 (+) b)."""
    c, s = math.cos(a[2]), math.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    return np.array([c * dx + s * dy, -s * dx + c * dy, wrap(b[2] - a[2])])


def se2_matrix(a: np.ndarray) -> np.ndarray:
    """The 4x4 homogeneous transform of a planar pose."""
    c, s = math.cos(a[2]), math.sin(a[2])
    t = np.eye(4)
    t[0, 0], t[0, 1], t[1, 0], t[1, 1] = c, -s, s, c
    t[0, 3], t[1, 3] = a[0], a[1]
    return t


def se2_of_matrix(t: np.ndarray) -> np.ndarray:
    """The planar part of a 4x4 transform (x, y, yaw about z)."""
    return np.array([t[0, 3], t[1, 3], math.atan2(t[1, 0], t[0, 0])])


def compose_jacobians(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """d(a (+) b)/da and d(a (+) b)/db (for covariance propagation)."""
    c, s = math.cos(a[2]), math.sin(a[2])
    ja = np.array([[1.0, 0.0, -s * b[0] - c * b[1]], [0.0, 1.0, c * b[0] - s * b[1]], [0.0, 0.0, 1.0]])
    jb = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return ja, jb


__all__ = ["wrap", "se2_compose", "se2_inverse", "se2_between", "se2_matrix", "se2_of_matrix", "compose_jacobians"]
