"""A scripted baseline controller: damped-least-squares IK toward each arm's target pose.

Each arm independently steps its joints along ``J^T (J J^T + lambda^2 I)^-1 e``, where ``e``
stacks the end-effector position error and rotation-vector error in the world frame and
``J`` is the arm's geometric Jacobian, scaled down (keeping its direction) to the per-step
joint limit. It sees no other arm, so it serves to check the environment's dynamics,
tolerances and success logic, and as a lower bound for multi-arm tasks.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from mjx_multiarm.env.reaching import ReachingEnv, State
from mjx_multiarm.geometry.kinematics import forward_kinematics
from mjx_multiarm.geometry.robot import ArmModel
from mjx_multiarm.geometry.transforms import (
    canonical_quat,
    quat_conjugate,
    quat_mul,
    quat_to_mat,
)


def rotation_vector(q):
    """Axis * angle [..., 3] of unit wxyz quaternions (angle in [0, pi])."""
    q = canonical_quat(q)
    sin_half = jnp.linalg.norm(q[..., 1:], axis=-1, keepdims=True)
    angle = 2.0 * jnp.arctan2(sin_half, q[..., :1])
    scale = jnp.where(sin_half > 1e-6, angle / jnp.maximum(sin_half, 1e-6), 2.0 / q[..., :1])
    return q[..., 1:] * scale


def geometric_jacobian(arm: ArmModel, base_pos, base_quat, joints):
    """World-frame end-effector Jacobian [..., 6, 6]: rows (linear xyz, angular xyz)."""
    frames = forward_kinematics(arm, base_pos, base_quat, joints)
    joint_body = np.array([arm.body_joint.index(j) for j in range(len(arm.joint_names))])
    rot = quat_to_mat(frames.body_quat[..., joint_body, :])  # [..., 6, 3, 3]
    axes = jnp.einsum("...ij,...j->...i", rot, jnp.asarray(arm.joint_axis, rot.dtype))
    lever = frames.ee_pos[..., None, :] - frames.body_pos[..., joint_body, :]
    return jnp.swapaxes(jnp.concatenate([jnp.cross(axes, lever), axes], axis=-1), -1, -2)


def ik_actions(env: ReachingEnv, state: State, damping: float = 0.05):
    """Actions [max_arms, 6] moving every arm toward its current target (one environment)."""
    arms = state.arms
    error = jnp.concatenate(
        [arms.target_pos - arms.ee_pos, rotation_vector(quat_mul(arms.target_quat, quat_conjugate(arms.ee_quat)))], axis=-1
    )
    jac = geometric_jacobian(env.scene.arm, state.task.base_pos, state.task.base_quat, state.joints)
    gram = jac @ jnp.swapaxes(jac, -1, -2) + damping**2 * jnp.eye(6, dtype=jac.dtype)
    delta = jnp.einsum("...ji,...j->...i", jac, jnp.linalg.solve(gram, error[..., None])[..., 0])
    speed = jnp.max(jnp.abs(delta) / env.max_step, axis=-1, keepdims=True)
    return env.joint_deltas_to_actions(delta / jnp.maximum(speed, 1.0))
