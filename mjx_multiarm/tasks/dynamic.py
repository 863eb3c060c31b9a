"""Moving targets of dynamic-mode tasks (paper section 4.1).

A dynamic target starts at ``FK(dynamic_start_joints)`` and moves along
``FK(interp(dynamic_start_joints -> goal_joints, s))`` so that the end-effector position
travels at the task's constant ``speed`` (m/s); it stops at the goal, the static target.
The path is parametrized by arc length from a table of ``PATH_SAMPLES`` FK samples per arm,
computed once per task (:func:`path_lengths`) and reused at every step
(:func:`target_at`). All functions are pure JAX and broadcast over leading dims.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from mjx_multiarm.geometry.kinematics import forward_kinematics
from mjx_multiarm.geometry.robot import ArmModel

#: FK samples along each arm's joint-space segment for the arc-length table.
PATH_SAMPLES = 64


def path_lengths(arm: ArmModel, base_pos, base_quat, joints_from, joints_to, samples: int = PATH_SAMPLES):
    """[..., samples] cumulative end-effector path length at s = 0, 1/(samples-1), ..., 1."""
    s = jnp.linspace(0.0, 1.0, samples, dtype=jnp.result_type(joints_from))
    joints = joints_from[..., None, :] + s[:, None] * (joints_to - joints_from)[..., None, :]
    ee = forward_kinematics(arm, base_pos[..., None, :], base_quat[..., None, :], joints).ee_pos
    steps = jnp.linalg.norm(jnp.diff(ee, axis=-2), axis=-1)
    return jnp.concatenate([jnp.zeros_like(steps[..., :1]), jnp.cumsum(steps, axis=-1)], axis=-1)


def target_at(arm: ArmModel, base_pos, base_quat, joints_from, joints_to, lengths, distance):
    """Target pose after the target has travelled ``distance`` [...] metres along its path.

    Args:
      lengths: [..., samples] from :func:`path_lengths`.
      distance: [...] speed * elapsed time; beyond the path's end the target stays at the goal.

    Returns:
      (position [..., 3], quaternion wxyz [..., 4], interpolation parameter s [...]).
    """
    samples = lengths.shape[-1]
    grid = jnp.linspace(0.0, 1.0, samples, dtype=lengths.dtype)
    distance = jnp.broadcast_to(jnp.asarray(distance, lengths.dtype), lengths.shape[:-1])
    flat_lengths = lengths.reshape(-1, samples)
    s = jax.vmap(lambda d, table: jnp.interp(d, table, grid))(distance.reshape(-1), flat_lengths)
    s = jnp.where(flat_lengths[:, -1] > 0, s, 1.0).reshape(distance.shape)  # a still target is at its goal
    joints = joints_from + s[..., None] * (joints_to - joints_from)
    frames = forward_kinematics(arm, base_pos, base_quat, joints)
    return frames.ee_pos, frames.ee_quat, s
