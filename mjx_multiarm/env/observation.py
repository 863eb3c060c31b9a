"""Decentralized observations (paper section 4.2): what each arm sees of its neighbours.

Each arm observes every active arm whose base lies within ``radius`` of its own base,
itself included. Every observed arm contributes one 107-D element, expressed in the
observing arm's base frame:

====================  ====  ===========================================================
slice                 size  content
====================  ====  ===========================================================
``[0:6]``, ``[6:12]``   12  joint angles at t-1, t
``[12:19]``             7   end-effector position + quaternion (wxyz) at t-1
``[19:26]``             7   end-effector position + quaternion at t
``[26:33]``             7   target position + quaternion at t-1
``[33:40]``             7   target position + quaternion at t
``[40:70]``             30  the 10 link points at t-1
``[70:100]``            30  the 10 link points at t
``[100:107]``           7   base position + quaternion (no history)
====================  ====  ===========================================================

Quaternions are made sign-canonical (w >= 0) after the change of frame. The sequence of an
arm has fixed length ``max_arms``: masked (absent) elements first, then the observed arms
by decreasing base distance, so the observing arm itself is always the last element. With
``radius=0`` an arm observes only itself (the paper's individualistic ablation).
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
from flax import struct

from mjx_multiarm.geometry.collision import geom_clearances
from mjx_multiarm.geometry.kinematics import forward_kinematics
from mjx_multiarm.geometry.scene import build_scene
from mjx_multiarm.geometry.transforms import (
    canonical_quat,
    quat_conjugate,
    quat_mul,
    quat_to_mat,
)
from mjx_multiarm.options import option

ELEMENT_SIZE = 107
#: Slices of an element: end-effector pose at t; target poses at t-1 and t.
EE_POSE = slice(19, 26)
TARGET_POSE_PREV, TARGET_POSE = slice(26, 33), slice(33, 40)
#: The element's five quaternions (end effector and target at t-1 and t, base).
QUATERNIONS = (slice(15, 19), slice(22, 26), slice(29, 33), slice(36, 40), slice(103, 107))
#: Their position and quaternion parts.
EE_POSITION, EE_QUAT = slice(EE_POSE.start, EE_POSE.start + 3), slice(EE_POSE.start + 3, EE_POSE.stop)
TARGET_POSITION, TARGET_QUAT = slice(TARGET_POSE.start, TARGET_POSE.start + 3), slice(TARGET_POSE.start + 3, TARGET_POSE.stop)
#: Goal-error features: 1 cm of position error -> 0.1, and the rotation error (rad, small angles).
GOAL_POSITION_SCALE = 10.0
GOAL_FEATURES = 6
#: Link points of an element at t-1 and t ([10 x 3] each).
POINTS_PREV, POINTS = slice(40, 70), slice(70, 100)
#: Nearness features: per own link point its distance to the element's nearest point (10),
#: how fast the smallest such distance closes (1), the vector between the closest pair (3).
NEARNESS_FEATURES = 14
#: Distances are capped here (m): beyond it a neighbour is simply far.
NEARNESS_CAP = 1.0
#: Closing speed scale: metres per step x this (a full-speed approach is ~0.1 m per step).
CLOSING_SCALE = 10.0
#: Clearance features: per collision geom of the observing arm its signed distance to the
#: element's arm, capped at :data:`CLEARANCE_CAP` (m) and scaled by :data:`CLEARANCE_SCALE`,
#: then how fast each closed since t-1 (x :data:`CLOSING_SCALE`).
CLEARANCE_CAP = 0.3
CLEARANCE_SCALE = 10.0
#: Slices of an element: joints at t-1 and t, base position and quaternion.
JOINTS_PREV, JOINTS = slice(0, 6), slice(6, 12)
BASE_POSITION, BASE_QUAT = slice(100, 103), slice(103, 107)
#: Default neighbour radius (m): two workspace radii, as in the original code.
NEIGHBOUR_RADIUS = 1.7


@struct.dataclass
class ArmSnapshot:
    """World-frame state of every arm slot at one step; leading dims [..., A]."""

    joints: jnp.ndarray  # [..., A, 6]
    ee_pos: jnp.ndarray  # [..., A, 3]
    ee_quat: jnp.ndarray  # [..., A, 4] wxyz
    target_pos: jnp.ndarray  # [..., A, 3]
    target_quat: jnp.ndarray  # [..., A, 4]
    points: jnp.ndarray  # [..., A, 10, 3]


def _points_in_frames(base_pos, base_rot, points):
    """World points [..., A(j), K, 3] in every arm i's base frame: [..., A(i), A(j), K * 3]."""
    offset = points[..., None, :, :, :] - base_pos[..., :, None, None, :]
    local = jnp.einsum("...iba,...ijkb->...ijka", base_rot, offset)  # R_i^T (x - p_i)
    return local.reshape(*local.shape[:-2], -1)


def _quats_in_frames(base_quat, quat):
    """World orientations [..., A(j), 4] in every arm i's base frame: [..., A(i), A(j), 4]."""
    return canonical_quat(quat_mul(quat_conjugate(base_quat)[..., :, None, :], quat[..., None, :, :]))


def _elements(base_pos, base_quat, prev: ArmSnapshot, now: ArmSnapshot):
    """[..., A(i), A(j), 107]: arm j's element in arm i's frame."""
    base_rot = quat_to_mat(base_quat)
    num_arms = base_pos.shape[-2]

    def pose(pos, quat):
        return [_points_in_frames(base_pos, base_rot, pos[..., None, :]), _quats_in_frames(base_quat, quat)]

    joints = [jnp.broadcast_to(s.joints[..., None, :, :], (*s.joints.shape[:-2], num_arms, num_arms, 6)) for s in (prev, now)]
    poses = [*pose(prev.ee_pos, prev.ee_quat), *pose(now.ee_pos, now.ee_quat)]
    poses += [*pose(prev.target_pos, prev.target_quat), *pose(now.target_pos, now.target_quat)]
    points = [_points_in_frames(base_pos, base_rot, s.points) for s in (prev, now)]
    return jnp.concatenate([*joints, *poses, *points, *pose(base_pos, base_quat)], axis=-1)


def observe(base_pos, base_quat, active, prev: ArmSnapshot, now: ArmSnapshot, radius: float = NEIGHBOUR_RADIUS):
    """Every arm's observation sequence.

    Args:
      base_pos: [..., A, 3]; base_quat: [..., A, 4] (wxyz); active: [..., A] bool.
      prev, now: the arms at t-1 and t (at reset pass the same snapshot twice).
      radius: neighbour radius (m); 0 gives the individualistic (self-only) observation.

    Returns:
      (obs [..., A, A, 107], mask [..., A, A] bool); row i is arm i's sequence, masked
      elements first and arm i itself last. Rows of inactive arms are fully masked.
    """
    elements = _elements(base_pos, base_quat, prev, now)
    dist = jnp.linalg.norm(base_pos[..., :, None, :] - base_pos[..., None, :, :], axis=-1)  # [..., A, A]
    eye = jnp.eye(base_pos.shape[-2], dtype=bool)
    seen = active[..., :, None] & active[..., None, :] & ((dist <= radius) | eye)
    key = jnp.where(seen, -dist, -jnp.inf)
    key = jnp.where(eye, 0.0, key)  # self sorts last (every other seen arm has key < 0)
    key = jnp.where(active[..., :, None], key, -jnp.inf)
    order = jnp.argsort(key, axis=-1, stable=True)
    obs = jnp.take_along_axis(elements, order[..., None], axis=-2)
    mask = jnp.take_along_axis(seen, order, axis=-1)
    return jnp.where(mask[..., None], obs, 0.0), mask


@dataclasses.dataclass(frozen=True)
class InputFeatures:
    """What the networks compute from each 107-D element before their LSTM (the stored
    observations stay 107-D, so replay and hindsight relabelling are unchanged).

    ``rotations``: quaternions replaced by two rotation-matrix columns
    (:func:`rotation_features`). ``goal``: the end effector's error to its target
    appended (:func:`goal_features`). ``nearness``: how close each element's arm is to the
    observing arm appended (:func:`nearness_features`). All off: the element as it is, as
    the original."""

    rotations: bool = option(False, "the networks see every orientation as two rotation-matrix columns (continuous) "
                                    "instead of a sign-canonical quaternion (0: the original)")
    goal: bool = option(False, "the networks see each end effector's position and rotation error to its target besides "
                               "the two poses (0: the original)", flag="goal_features")
    nearness: bool = option(False, "the networks see, for each observed arm, the distances from the observing arm's link "
                                   "points to its nearest link points, their closing speed and direction (0: the original)",
                            flag="nearness_features")
    clearance: bool = option(False, "the networks see, for each observed arm, the exact signed distance from each of the "
                                    "observing arm's collision geoms to it (the collision model's), and how fast each "
                                    "closed (0: the original)", flag="clearance_features")

    @property
    def size(self) -> int:
        """Length of a transformed element."""
        return (ELEMENT_SIZE + 2 * len(QUATERNIONS) * self.rotations + GOAL_FEATURES * self.goal
                + NEARNESS_FEATURES * self.nearness + (2 * _num_geoms() if self.clearance else 0))

    def __call__(self, obs):
        """Observation sequences [..., L, 107] (the observing arm last) -> [..., L, size]."""
        parts = [rotation_features(obs) if self.rotations else obs]
        if self.goal:
            parts.append(goal_features(obs))
        if self.nearness:
            parts.append(nearness_features(obs))
        if self.clearance:
            parts.append(clearance_features(obs))
        return jnp.concatenate(parts, axis=-1) if len(parts) > 1 else parts[0]


def goal_features(obs):
    """[..., 6] of elements [..., 107]: the target's position relative to the end effector
    (observer's frame, x ``GOAL_POSITION_SCALE``) and the rotation taking the end effector
    onto the target as a rotation vector (its small-angle form ``2 sign(w) xyz``, in the end
    effector's frame). The networks otherwise have to resolve a 2 cm goal from two poses
    given in metres; zero for masked (all-zero) elements."""
    position = GOAL_POSITION_SCALE * (obs[..., TARGET_POSITION] - obs[..., EE_POSITION])
    error = canonical_quat(quat_mul(quat_conjugate(obs[..., EE_QUAT]), obs[..., TARGET_QUAT]))
    return jnp.concatenate([position, 2.0 * error[..., 1:]], axis=-1)


def _nearest(own, other):
    """Per own point [..., 10] the distance to the nearest point of ``other``, and the index
    of that point; points [..., 30] flattened."""
    a, b = own.reshape(*own.shape[:-1], -1, 1, 3), other.reshape(*other.shape[:-1], 1, -1, 3)
    distance = jnp.linalg.norm(a - b, axis=-1)  # [..., 10, 10]
    return distance.min(axis=-1), distance.argmin(axis=-1)


def _observer_reads_far(features, cap, distances: int):
    """``features`` [..., L, F] of a sequence with the observing arm's own element (last)
    set to "far": its first ``distances`` entries at ``cap``, the rest 0."""
    far = jnp.where(jnp.arange(features.shape[-1]) < distances, cap, 0.0).astype(features.dtype)
    is_self = jnp.arange(features.shape[-2]) == features.shape[-2] - 1
    return jnp.where(is_self[:, None], far, features)


def nearness_features(obs):
    """[..., L, 14] of observation sequences [..., L, 107] whose last element is the
    observing arm: for each element's arm, the distance from each of the observer's 10 link
    points to that arm's nearest link point (capped at :data:`NEARNESS_CAP`), how fast the
    smallest of them closed since t-1 (x :data:`CLOSING_SCALE`), and the vector from the
    observer's closest point to the arm's closest point (observer's frame). Decentralized:
    computed from what the arm observes. The observer's own element reads as far (cap, 0).
    """
    own = obs[..., -1:, :]
    now, nearest = _nearest(own[..., POINTS], obs[..., POINTS])
    before, _ = _nearest(own[..., POINTS_PREV], obs[..., POINTS_PREV])
    closest = now.argmin(axis=-1)  # [..., L] the observer's point nearest this arm
    own_points = own[..., POINTS].reshape(*own.shape[:-1], -1, 3)  # [..., 1, 10, 3]
    other_points = obs[..., POINTS].reshape(*obs.shape[:-1], -1, 3)  # [..., L, 10, 3]
    start = jnp.take_along_axis(own_points, closest[..., None, None], axis=-2)[..., 0, :]
    target = jnp.take_along_axis(nearest, closest[..., None], axis=-1)
    end = jnp.take_along_axis(other_points, target[..., None], axis=-2)[..., 0, :]
    closing = CLOSING_SCALE * (before.min(axis=-1) - now.min(axis=-1))
    features = jnp.concatenate([jnp.minimum(now, NEARNESS_CAP), closing[..., None], end - start], axis=-1)
    return _observer_reads_far(features, NEARNESS_CAP, 10)


def _num_geoms() -> int:
    """Collision geoms per arm (the clearance features' G)."""
    return len(build_scene(2).arm.geom_names)


def clearance_features(obs):
    """[..., L, 2 G] of observation sequences [..., L, 107] whose last element is the
    observing arm (G = 13 collision geoms per arm): the signed distance (m, capped at
    :data:`CLEARANCE_CAP`, x :data:`CLEARANCE_SCALE`) from each of the observer's collision
    geoms to each element's arm at t, exact under the collision model
    (:func:`~mjx_multiarm.geometry.collision.geom_clearances` of both arms posed from their
    observed joints and base poses), then how much each closed since t-1 (x
    :data:`CLOSING_SCALE`). Decentralized: computed from what the arm observes. The
    observer's own element reads as far (cap, 0); masked (all-zero) elements stay finite.
    """
    scene = build_scene(2)
    quat = obs[..., BASE_QUAT]
    quat = jnp.where(jnp.any(quat != 0.0, axis=-1, keepdims=True), quat, jnp.array([1.0, 0.0, 0.0, 0.0], obs.dtype))

    def clearances(joints):  # [..., L, G]
        frames = forward_kinematics(scene.arm, obs[..., BASE_POSITION], quat, joints)
        own = frames.capsules[..., -1:, :, :, :], frames.boxes[..., -1:, :, :, :]
        return jnp.minimum(geom_clearances(scene, *own, frames.capsules, frames.boxes), CLEARANCE_CAP)

    now, before = clearances(obs[..., JOINTS]), clearances(obs[..., JOINTS_PREV])
    features = jnp.concatenate([CLEARANCE_SCALE * now, CLOSING_SCALE * (before - now)], axis=-1)
    return _observer_reads_far(features, CLEARANCE_SCALE * CLEARANCE_CAP, now.shape[-1])


def rotation_features(obs):
    """Elements [..., 107] with each quaternion replaced by the first two columns of its
    rotation matrix: [..., 117]. Unlike a sign-canonical quaternion, which flips all four
    components when an orientation crosses w = 0, these six numbers are continuous in the
    orientation (Zhou et al. 2019), and the same for q and -q."""
    parts, start = [], 0
    for quat in QUATERNIONS:
        columns = quat_to_mat(obs[..., quat])[..., :, :2]
        parts += [obs[..., start : quat.start], jnp.swapaxes(columns, -1, -2).reshape(*obs.shape[:-1], 6)]
        start = quat.stop
    return jnp.concatenate([*parts, obs[..., start:]], axis=-1)


def retarget(obs, goal_obs):
    """``obs`` [..., 107] with every observed arm's target (at t-1 and t) set to that arm's
    end-effector pose in ``goal_obs``: an observation of the same arm in the same sequence
    order at a later step of the episode (the order depends only on the fixed bases)."""
    goal = goal_obs[..., EE_POSE]
    return obs.at[..., TARGET_POSE_PREV].set(goal).at[..., TARGET_POSE].set(goal)
