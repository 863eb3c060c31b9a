"""Turn a dense joint-space path into the delta-joint steps the environment executes.

The path is followed as a polyline: from the current waypoint, advance to the farthest
waypoint such that every waypoint in between lies within ``angle_tolerance`` of the
straight direction to it (so the straight chord stays on the planned path), then cover
that chord in equal steps no larger than the per-step joint limit. The environment moves
every commanded delta completely within one 0.05 s step (velocity limit x control period:
0.1575 rad for the first three joints, 0.16 rad for the wrists), so that limit replaces the
original's 0.5 rad cap on a command, which its PyBullet position controller covered over
several steps. Replaying the steps from the start configuration ends at the goal (to float32 rounding).
"""

from __future__ import annotations

import math

import numpy as np

#: Paper: 0.01 rad; the original code: 0.1 rad.
ANGLE_TOLERANCE = 0.01


def _angle(u, v) -> float:
    nu, nv = np.linalg.norm(u), np.linalg.norm(v)
    if nu == 0 or nv == 0:
        return 0.0
    return math.acos(float(np.clip(np.dot(u, v) / (nu * nv), -1.0, 1.0)))


def corner_points(path, angle_tolerance: float = ANGLE_TOLERANCE) -> np.ndarray:
    """The waypoints of ``path`` [n, D] that the decimated motion passes through."""
    path = np.asarray(path, np.float64)
    keep, current = [0], 0
    while current < len(path) - 1:
        reach = current + 1
        for candidate in range(current + 2, len(path)):
            direction = path[candidate] - path[current]
            between = path[current + 1 : candidate] - path[current]
            if any(_angle(offset, direction) > angle_tolerance for offset in between):
                break
            reach = candidate
        keep.append(reach)
        current = reach
    return path[keep]


def path_to_deltas(path, max_step, angle_tolerance: float = ANGLE_TOLERANCE) -> np.ndarray:
    """Delta-joint steps [T, k, 6] (float32) that move along ``path`` [n, k, 6].

    Args:
      path: joint waypoints from start to goal.
      max_step: [6] largest motion of each joint in one environment step (rad).
      angle_tolerance: how far (rad) skipped waypoints may lie off a chord's direction.
    """
    path = np.asarray(path, np.float64)
    num_arms = path.shape[1]
    corners = corner_points(path.reshape(len(path), -1), angle_tolerance).reshape(-1, num_arms, path.shape[2])
    limit = np.asarray(max_step, np.float64)
    steps = []
    for a, b in zip(corners[:-1], corners[1:]):
        count = max(1, math.ceil(float(np.max(np.abs(b - a) / limit)) - 1e-9))
        steps.append(np.repeat(((b - a) / count)[None], count, axis=0))
    if not steps:
        return np.zeros((0, num_arms, path.shape[2]), np.float32)
    return np.concatenate(steps).astype(np.float32)
