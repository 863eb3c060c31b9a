"""Batched inverse kinematics (damped least squares) in JAX.

:func:`solve_positions` puts the ``ee_link`` origin at target positions, with the remaining
freedom (orientation and redundancy) pulled toward a reference configuration (the home pose
by default) through the Jacobian's null space; :func:`solve_poses` reaches full poses
(position and orientation). The Jacobian is the geometric one, read off the
forward-kinematics frames, so an iteration costs one FK.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from mjx_multiarm.geometry.kinematics import forward_kinematics
from mjx_multiarm.geometry.robot import ArmModel
from mjx_multiarm.geometry.transforms import (
    quat_angle,
    quat_conjugate,
    quat_mul,
    quat_to_mat,
)


def _joint_bodies(arm: ArmModel) -> np.ndarray:
    """Body index of each joint."""
    return np.array([arm.body_joint.index(j) for j in range(len(arm.joint_names))])


def _joint_axes(arm: ArmModel, frames) -> jnp.ndarray:
    """[..., 6, 3] world-frame joint axes."""
    rot = quat_to_mat(frames.body_quat[..., _joint_bodies(arm), :])  # [..., 6, 3, 3]
    return jnp.einsum("...jab,jb->...ja", rot, jnp.asarray(arm.joint_axis, rot.dtype))


def position_jacobian(arm: ArmModel, frames) -> jnp.ndarray:
    """[..., 3, 6] d(ee position)/d(joints) from world-frame FK ``frames``."""
    lever = frames.ee_pos[..., None, :] - frames.body_pos[..., _joint_bodies(arm), :]
    return jnp.swapaxes(jnp.cross(_joint_axes(arm, frames), lever), -1, -2)


def rotation_error(target_quat, quat) -> jnp.ndarray:
    """[..., 3] rotation vector (world frame) that turns ``quat`` into ``target_quat`` (wxyz)."""
    relative = quat_mul(target_quat, quat_conjugate(quat))
    relative = relative * jnp.where(relative[..., :1] < 0, -1.0, 1.0)
    sin_half = jnp.linalg.norm(relative[..., 1:], axis=-1, keepdims=True)
    angle = 2.0 * jnp.arctan2(sin_half, relative[..., :1])
    return relative[..., 1:] * angle / jnp.maximum(sin_half, 1e-9)


def solve_poses(arm: ArmModel, target_pos, target_quat, initial, iterations: int = 100, damping: float = 0.05,
                max_step: float = 0.2, radians_per_metre: float = 0.2):
    """Joint angles [..., 6] reaching full ``ee_link`` poses, from ``initial`` [..., 6].

    Args:
      target_pos: [..., 3] positions and target_quat: [..., 4] orientations (wxyz), both in
        each arm's base frame.
      iterations: fixed number of damped-least-squares steps (jit-friendly).
      radians_per_metre: weight of the orientation error against the position error.

    Returns:
      (joints [..., 6], position error [...] in m, orientation error [...] in rad). Joint
      limits are not enforced here; which solution (elbow, wrist) is found depends on
      ``initial``.
    """
    dtype = jnp.result_type(initial)
    target_pos = jnp.asarray(target_pos, dtype)
    target_quat = jnp.asarray(target_quat, dtype)
    base_pos = jnp.zeros(3, dtype)
    base_quat = jnp.array([1.0, 0.0, 0.0, 0.0], dtype)
    weight = jnp.array([1.0] * 3 + [radians_per_metre] * 3, dtype)

    def step(joints, _):
        frames = forward_kinematics(arm, base_pos, base_quat, joints)
        jac = jnp.concatenate([position_jacobian(arm, frames), jnp.swapaxes(_joint_axes(arm, frames), -1, -2)], -2)
        jac = jac * weight[:, None]
        error = jnp.concatenate([target_pos - frames.ee_pos, rotation_error(target_quat, frames.ee_quat)], -1) * weight
        gram = jac @ jnp.swapaxes(jac, -1, -2) + damping**2 * jnp.eye(6, dtype=dtype)
        delta = jnp.einsum("...ji,...j->...i", jac, jnp.linalg.solve(gram, error[..., None])[..., 0])
        return joints + jnp.clip(delta, -max_step, max_step), None

    joints, _ = jax.lax.scan(step, jnp.asarray(initial, dtype), None, length=iterations)
    final = forward_kinematics(arm, base_pos, base_quat, joints)
    return joints, jnp.linalg.norm(target_pos - final.ee_pos, axis=-1), quat_angle(final.ee_quat, target_quat)


def solve_positions(
    arm: ArmModel,
    targets,
    initial,
    reference=None,
    iterations: int = 40,
    damping: float = 0.05,
    max_step: float = 0.3,
    reference_gain: float = 0.2,
):
    """Joint angles [..., 6] reaching ``targets`` [..., 3] (in each arm's base frame).

    Args:
      targets: [..., 3] end-effector positions, base frame of the arm.
      initial: [..., 6] starting joint angles.
      reference: [..., 6] configuration the null-space motion pulls toward (default home).
      iterations: fixed number of damped-least-squares steps (jit-friendly).
      damping: lambda of (J J^T + lambda^2 I).
      max_step: largest joint change per iteration (rad).
      reference_gain: fraction of the offset to ``reference`` removed per iteration at
        the start; it decays linearly to 0 so the last iterations are pure least squares.

    Returns:
      (joints [..., 6], position error [...] in m). Joint limits are not enforced here.
    """
    dtype = jnp.result_type(initial)
    reference = jnp.asarray(arm.home if reference is None else reference, dtype)
    base_pos = jnp.zeros(3, dtype)
    base_quat = jnp.array([1.0, 0.0, 0.0, 0.0], dtype)
    eye3 = jnp.eye(3, dtype=dtype)

    def step(joints, fraction_left):
        frames = forward_kinematics(arm, base_pos, base_quat, joints)
        jac = position_jacobian(arm, frames)
        error = targets - frames.ee_pos
        gram = jac @ jnp.swapaxes(jac, -1, -2) + damping**2 * eye3
        pinv = jnp.swapaxes(jac, -1, -2) @ jnp.linalg.inv(gram)  # [..., 6, 3]
        task = jnp.einsum("...ij,...j->...i", pinv, error)
        pull = reference_gain * fraction_left * (reference - joints)
        null = pull - jnp.einsum("...ij,...jk,...k->...i", pinv, jac, pull)
        return joints + jnp.clip(task + null, -max_step, max_step), None

    schedule = jnp.linspace(1.0, 0.0, iterations, dtype=dtype)
    joints, _ = jax.lax.scan(step, jnp.asarray(initial, dtype), schedule)
    final = forward_kinematics(arm, base_pos, base_quat, joints).ee_pos
    return joints, jnp.linalg.norm(targets - final, axis=-1)
