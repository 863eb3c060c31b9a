"""Rigid-transform helpers: the project's single quaternion convention.

Inside JAX every quaternion is **scalar-first (w, x, y, z)**, MuJoCo's convention. The
original project's files and public APIs use scalar-last (x, y, z, w); convert only at
those boundaries with :func:`wxyz_to_xyzw` / :func:`xyzw_to_wxyz`.

All functions broadcast over leading dimensions and work on numpy or JAX arrays.
"""

from __future__ import annotations

import jax.numpy as jnp


def quat_mul(q1, q2):
    """Hamilton product ``q1 * q2`` of wxyz quaternions, shape [..., 4]."""
    w1, x1, y1, z1 = jnp.moveaxis(q1, -1, 0)
    w2, x2, y2, z2 = jnp.moveaxis(q2, -1, 0)
    return jnp.stack(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ],
        axis=-1,
    )


def quat_to_mat(q):
    """Rotation matrix [..., 3, 3] of unit wxyz quaternions [..., 4]."""
    w, x, y, z = jnp.moveaxis(q, -1, 0)
    return jnp.stack(
        [
            jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            jnp.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            jnp.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=-2,
    )


def axis_angle_quat(axis, angle):
    """wxyz quaternion of a rotation by ``angle`` [...] about unit ``axis`` [..., 3]."""
    half = 0.5 * jnp.asarray(angle)[..., None]
    return jnp.concatenate([jnp.cos(half), jnp.sin(half) * axis], axis=-1)


def yaw_quat(yaw):
    """wxyz quaternion of a rotation about world z by ``yaw`` [...]."""
    return axis_angle_quat(jnp.array([0.0, 0.0, 1.0]), yaw)


def canonical_quat(q):
    """The same rotation with a non-negative scalar part (a unique representative)."""
    return jnp.where(q[..., :1] < 0, -q, q)


def quat_conjugate(q):
    """Conjugate (the inverse of a unit quaternion), wxyz."""
    return q * jnp.array([1.0, -1.0, -1.0, -1.0], jnp.result_type(q))


def quat_angle(q1, q2):
    """Rotation angle between unit wxyz quaternions: the angle of ``q1^-1 q2``.

    Computed as ``2 atan2(|vector part|, |scalar part|)``: the same value as
    ``2 arccos(|<q1, q2>|)`` but well conditioned near zero (float32 arccos is not).
    """
    relative = quat_mul(quat_conjugate(q1), q2)
    return 2.0 * jnp.arctan2(jnp.linalg.norm(relative[..., 1:], axis=-1), jnp.abs(relative[..., 0]))


def wxyz_to_xyzw(q):
    """Scalar-first to scalar-last quaternion order."""
    return jnp.concatenate([q[..., 1:], q[..., :1]], axis=-1)


def xyzw_to_wxyz(q):
    """Scalar-last to scalar-first quaternion order."""
    return jnp.concatenate([q[..., 3:], q[..., :3]], axis=-1)
