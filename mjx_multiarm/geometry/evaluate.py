"""NumPy-in / NumPy-out entry point: end-effector poses and collision flags of arm teams.

This is the validated API boundary: shapes, team sizes and finiteness are checked here,
outside ``jit``, with errors that name the argument and the expected shape. Inside, the
batch is padded to ``max_arms`` slots and to a power-of-two batch size (so repeated calls
with varying batch sizes reuse a handful of compiled functions).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from mjx_multiarm.geometry.collision import frame_contacts
from mjx_multiarm.geometry.kinematics import forward_kinematics
from mjx_multiarm.geometry.robot import NUM_JOINTS
from mjx_multiarm.geometry.scene import Scene, build_scene
from mjx_multiarm.geometry.transforms import wxyz_to_xyzw, xyzw_to_wxyz, yaw_quat


@struct.dataclass
class ArmEvaluation:
    """Per-arm results of :func:`evaluate_arms` (numpy; leading dims ``[..., n]``).

    Attributes:
      ee_pos: [..., n, 3] end-effector (``ee_link``) positions, world frame (m).
      ee_quat: [..., n, 4] end-effector orientations, **xyzw** (the original's order).
      points: [..., n, 10, 3] the 10 observed link points.
      collided: [..., n] bool: the arm touches another arm, itself, or the ground.
      min_distance: [..., n] smallest signed distance (m) over all its checked pairs.
      distance_between_arms / distance_within_arm / distance_ground: [..., n] per kind.
    """

    ee_pos: np.ndarray
    ee_quat: np.ndarray
    points: np.ndarray
    collided: np.ndarray
    min_distance: np.ndarray
    distance_between_arms: np.ndarray
    distance_within_arm: np.ndarray
    distance_ground: np.ndarray


def base_pose_arrays(base_poses, name: str = "base_poses") -> tuple[np.ndarray, np.ndarray]:
    """Split poses into positions [..., 3] and wxyz quaternions [..., 4].

    ``base_poses`` is [..., 3] planar (x, y, yaw) or [..., 7] (x, y, z, qx, qy, qz, qw);
    ``name`` is the argument named in errors.
    """
    base_poses = np.asarray(base_poses, dtype=np.float64)
    if base_poses.shape[-1] == 3:
        pos = np.concatenate([base_poses[..., :2], np.zeros_like(base_poses[..., :1])], axis=-1)
        return pos, np.asarray(yaw_quat(base_poses[..., 2]))
    quat = np.asarray(xyzw_to_wxyz(base_poses[..., 3:]))
    norm = np.linalg.norm(quat, axis=-1, keepdims=True)
    if np.any(np.abs(norm - 1.0) > 1e-3):
        raise ValueError(f"{name}: quaternions (columns 3:7, xyzw) must have unit norm")
    return base_poses[..., :3], quat / norm


def check_finite(name: str, array: np.ndarray) -> None:
    if not np.all(np.isfinite(array)):
        bad = np.argwhere(~np.isfinite(array))[0]
        raise ValueError(f"{name}: non-finite value (NaN or inf) at index {tuple(int(i) for i in bad)}")


def _validated(base_poses, joints, active, max_arms):
    joints = np.asarray(joints, dtype=np.float64)
    base_poses = np.asarray(base_poses, dtype=np.float64)
    if joints.ndim < 2 or joints.shape[-1] != NUM_JOINTS:
        raise ValueError(f"joints: expected shape [..., n_arms, {NUM_JOINTS}], got {joints.shape}")
    batch, n = joints.shape[:-2], joints.shape[-2]
    if base_poses.shape not in ((*batch, n, 3), (*batch, n, 7)):
        raise ValueError(
            f"base_poses: expected shape {(*batch, n, 3)} (x, y, yaw) or {(*batch, n, 7)} "
            f"(x, y, z, qx, qy, qz, qw) to match joints {joints.shape}, got {base_poses.shape}"
        )
    active = np.ones((*batch, n), bool) if active is None else np.asarray(active)
    if active.shape != (*batch, n) or active.dtype != bool:
        raise ValueError(f"active: expected a bool array of shape {(*batch, n)}, got {active.dtype} {active.shape}")
    max_arms = n if max_arms is None else max_arms
    if n > max_arms:
        raise ValueError(f"{n} arms given but the scene has only max_arms={max_arms} slots")
    check_finite("joints", joints)
    check_finite("base_poses", base_poses)
    return base_poses, joints, active, max_arms


@functools.cache
def _evaluator(scene: Scene):
    @jax.jit
    def evaluate(base_pos, base_quat, joints, active):
        frames = forward_kinematics(scene.arm, base_pos, base_quat, joints)
        return frames, frame_contacts(scene, frames, active)

    return evaluate


def _pad(array: np.ndarray, size: int, axis: int, value) -> np.ndarray:
    widths = [(0, 0)] * array.ndim
    widths[axis] = (0, size - array.shape[axis])
    return np.pad(array, widths, constant_values=value)


def evaluate_arms(base_poses, joints, active=None, *, max_arms: int | None = None) -> ArmEvaluation:
    """End-effector poses and per-arm collision flags of teams of UR5 arms.

    Args:
      base_poses: [..., n, 3] planar (x, y, yaw) or [..., n, 7] (x, y, z, qx, qy, qz, qw).
      joints: [..., n, 6] joint angles (rad); any batch shape ``...``.
      active: optional [..., n] bool; inactive arms (padding) are ignored entirely.
      max_arms: slots of the compiled scene (default ``n``); ``n <= max_arms``.

    Returns:
      :class:`ArmEvaluation` with numpy arrays shaped like the inputs.

    Raises:
      ValueError: on a wrong shape, a team larger than ``max_arms``, or a NaN/inf input.
    """
    base_poses, joints, active, max_arms = _validated(base_poses, joints, active, max_arms)
    batch, n = joints.shape[:-2], joints.shape[-2]
    base_pos, base_quat = base_pose_arrays(base_poses)
    flat = int(np.prod(batch, dtype=int))
    padded = 1 << max(flat - 1, 0).bit_length()  # next power of two: few distinct compiles

    def prepare(x, fill):
        x = x.reshape(flat, n, *x.shape[len(batch) + 1 :])
        return _pad(_pad(x, max_arms, 1, fill), padded, 0, fill)

    frames, contacts = _evaluator(build_scene(max_arms))(
        jnp.asarray(prepare(base_pos, 0.0), jnp.float32),
        jnp.asarray(prepare(base_quat, 0.0), jnp.float32),  # zero quaternions rotate by identity
        jnp.asarray(prepare(joints, 0.0), jnp.float32),
        prepare(active, False),
    )

    def unpad(x):
        x = np.asarray(x)[:flat, :n]
        return x.reshape(*batch, n, *x.shape[2:])

    return ArmEvaluation(
        ee_pos=unpad(frames.ee_pos),
        ee_quat=unpad(wxyz_to_xyzw(frames.ee_quat)),
        points=unpad(frames.points),
        collided=unpad(contacts.collided),
        min_distance=unpad(contacts.min_distance),
        distance_between_arms=unpad(contacts.between_arms),
        distance_within_arm=unpad(contacts.within_arm),
        distance_ground=unpad(contacts.ground),
    )
