"""Task difficulty: how much the arms' workspaces overlap (paper section 5).

For each arm, the fraction of its workspace hemisphere (radius ``REACH``, z >= 0, centred
on its base) that lies inside the union of the other arms' hemispheres; a task's
difficulty is the maximum over its arms (0 for one arm).

Bases stand on the ground, so every hemisphere covers, above a ground point at planar
distance r from its base, exactly the heights [0, h(r)] with h(r) = sqrt(REACH^2 - r^2).
All these intervals start at 0, so above a point of arm i's disk the union of the other
hemispheres covers [0, max_j h_j] and the overlapping volume is the 2-D integral of
min(h_i, max_j h_j) over arm i's disk: exact in height, integrated on a fixed grid of
``GRID`` cells per radius in the plane (deterministic; within 0.002 of the exact two-ball
overlap at every distance).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from mjx_multiarm.geometry.robot import REACH

#: Grid cells per workspace radius.
GRID = 12
#: Tasks per vectorized chunk.
CHUNK = 256


@functools.cache
def disk_points(grid: int = GRID) -> np.ndarray:
    """Cell centres [n, 2] of a regular grid over the unit disk."""
    ticks = (np.arange(-grid, grid) + 0.5) / grid
    points = np.stack(np.meshgrid(ticks, ticks, indexing="ij"), axis=-1).reshape(-1, 2)
    return points[np.linalg.norm(points, axis=-1) <= 1.0]


@functools.partial(jax.jit, static_argnames=("grid",))
def _overlaps(xy, active, grid: int):
    """[N, A] overlap fractions for planar base positions [N, A, 2]."""
    points = jnp.asarray(disk_points(grid) * REACH, xy.dtype)  # [P, 2]
    own = jnp.sqrt(jnp.maximum(REACH**2 - jnp.sum(points**2, -1), 0.0))  # [P]
    num_arms = xy.shape[-2]

    def one_task(xy, active):
        world = xy[:, None, :] + points  # [A(i), P, 2]
        dist2 = jnp.sum((world[:, None] - xy[None, :, None]) ** 2, -1)  # [A(i), A(j), P]
        height = jnp.sqrt(jnp.maximum(REACH**2 - dist2, 0.0))
        others = active[None, :] & ~jnp.eye(num_arms, dtype=bool)  # [A(i), A(j)]
        covered = jnp.max(jnp.where(others[..., None], height, 0.0), axis=1)  # [A(i), P]
        fraction = jnp.sum(jnp.minimum(own, covered), -1) / jnp.sum(own)
        return jnp.where(active, fraction, 0.0)

    return jax.lax.map(lambda args: one_task(*args), (xy, active), batch_size=CHUNK)


def arm_overlaps(base_pos, active, grid: int = GRID) -> np.ndarray:
    """[..., A] fraction of each active arm's hemisphere inside the others' (0 if inactive).

    Args:
      base_pos: [..., A, 3] (or [..., A, 2]) base positions on the ground plane.
      active: [..., A] bool.
    """
    base_pos = np.asarray(base_pos, np.float64)
    active = np.asarray(active, bool)
    batch, num_arms = active.shape[:-1], active.shape[-1]
    xy = jnp.asarray(base_pos[..., :2].reshape(-1, num_arms, 2), jnp.float32)
    fractions = _overlaps(xy, jnp.asarray(active.reshape(-1, num_arms)), grid)
    return np.asarray(fractions, np.float64).reshape(*batch, num_arms)


def task_difficulty(base_pos, active, grid: int = GRID) -> np.ndarray:
    """[...] difficulty of each task: the largest overlap fraction over its arms."""
    return arm_overlaps(base_pos, active, grid).max(axis=-1)
