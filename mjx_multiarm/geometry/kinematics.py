"""Batched forward kinematics of UR5 arms in JAX.

Every function broadcasts over arbitrary leading dimensions (scenes, arms, substeps), so
one call evaluates every arm of every scene of a batch: no Python loop over arms or scenes.
The only Python loop runs over the arm's 8 bodies while tracing (it unrolls into the graph).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from flax import struct

from mjx_multiarm.geometry.robot import ArmModel
from mjx_multiarm.geometry.transforms import (
    axis_angle_quat,
    canonical_quat,
    quat_mul,
    quat_to_mat,
)


@struct.dataclass
class ArmFrames:
    """World-frame kinematics of arms; leading dims ``...`` are those of the inputs.

    Attributes:
      body_pos: [..., nbody, 3] body origins.
      body_quat: [..., nbody, 4] body orientations (wxyz).
      ee_pos: [..., 3] position of the ``ee_link`` frame.
      ee_quat: [..., 4] orientation of ``ee_link`` (wxyz, scalar part >= 0).
      points: [..., 10, 3] the link points observed by the policy.
      capsules: [..., ncap, 2, 3] end points of every collision capsule's segment.
      boxes: [..., nbox, 4, 3] every collision box: its centre, then its unit x, y, z axes.
    """

    body_pos: jnp.ndarray
    body_quat: jnp.ndarray
    ee_pos: jnp.ndarray
    ee_quat: jnp.ndarray
    points: jnp.ndarray
    capsules: jnp.ndarray
    boxes: jnp.ndarray


def _transform(body_pos, body_rot, body_index, local_points):
    """World coordinates of points [k, 3] (or [k, 2, 3]) attached to bodies ``body_index``."""
    rot = body_rot[..., body_index, :, :]
    pos = body_pos[..., body_index, :]
    if local_points.ndim == 3:  # capsule end point pairs
        rot, pos = rot[..., None, :, :], pos[..., None, :]
    return pos + jnp.einsum("...ij,...j->...i", rot, local_points)


@functools.partial(jax.jit, static_argnames=("arm",))
def forward_kinematics(arm: ArmModel, base_pos, base_quat, joints) -> ArmFrames:
    """Forward kinematics of arms placed at base poses.

    Args:
      arm: arm constants (:func:`mjx_multiarm.geometry.robot.load_arm`).
      base_pos: [..., 3] base positions.
      base_quat: [..., 4] base orientations (wxyz, unit).
      joints: [..., 6] joint angles (rad).
    """
    joints = jnp.asarray(joints)
    dtype = joints.dtype
    batch = jnp.broadcast_shapes(jnp.shape(base_pos)[:-1], jnp.shape(base_quat)[:-1], joints.shape[:-1])
    base_pos = jnp.broadcast_to(jnp.asarray(base_pos, dtype), (*batch, 3))
    base_quat = jnp.broadcast_to(jnp.asarray(base_quat, dtype), (*batch, 4))
    pos, quat = [base_pos], [base_quat]
    for b in range(1, len(arm.body_names)):
        parent_rot = quat_to_mat(quat[-1])
        pos.append(pos[-1] + jnp.einsum("...ij,j->...i", parent_rot, arm.body_pos[b].astype(dtype)))
        q = quat_mul(quat[-1], jnp.asarray(arm.body_quat[b], dtype))
        j = arm.body_joint[b]
        if j >= 0:
            q = quat_mul(q, axis_angle_quat(jnp.asarray(arm.joint_axis[j], dtype), joints[..., j]))
        quat.append(q)
    body_pos = jnp.stack(pos, axis=-2)
    body_quat = jnp.stack(quat, axis=-2)
    body_rot = quat_to_mat(body_quat)
    ee_quat = quat_mul(body_quat[..., arm.ee_body, :], jnp.asarray(arm.ee_quat, dtype))
    return ArmFrames(
        body_pos=body_pos,
        body_quat=body_quat,
        ee_pos=_transform(body_pos, body_rot, arm.ee_body, jnp.asarray(arm.ee_pos, dtype)),
        ee_quat=canonical_quat(ee_quat),
        points=_transform(body_pos, body_rot, arm.point_body, jnp.asarray(arm.point_pos, dtype)),
        capsules=_transform(body_pos, body_rot, arm.capsule_body, jnp.asarray(arm.capsule_ends, dtype)),
        boxes=_pose_boxes(body_pos, body_rot, arm),
    )


def _pose_boxes(body_pos, body_rot, arm: ArmModel):
    """World centres and axes [..., nbox, 4, 3] of the arm's boxes."""
    frame = jnp.asarray(arm.box_frame, body_pos.dtype)
    rot = body_rot[..., arm.box_body, :, :]
    centre = body_pos[..., arm.box_body, :] + jnp.einsum("...ij,...j->...i", rot, frame[:, 0])
    axes = jnp.einsum("...ij,...kj->...ki", rot, frame[:, 1:])
    return jnp.concatenate([centre[..., None, :], axes], axis=-2)
