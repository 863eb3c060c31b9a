"""Certified motion check: a straight joint-space motion counts as free only if no configuration
along it can touch (beyond the paper; the sampled sweep of
:func:`mjx_multiarm.geometry.collision.swept_contacts` checks a few configurations only).

The check is conservative advancement (Schwarzer, Saha and Latombe 2005; FCL's
conservative advancement) with the exact distances of :mod:`mjx_multiarm.geometry.collision`:

- Motion bound. Along ``q(s) = q0 + s (q1 - q0)``, s in [0, 1], a point of a geom g moves at
  most ``sum_j |q1_j - q0_j| R[j, g]`` per unit of s, where ``R[j, g]`` bounds the distance of
  any point of g from joint j's axis over the rest of the motion: its distance at the
  current pose plus how far the joints beyond j can still move it, capped by a
  configuration-independent bound (:func:`geom_reach`). An arm's bound ``M`` is the largest
  over its geoms.
- Rates. The distance of an arm to another arm shrinks by at most ``M_a + M_other`` per unit
  of s (``M_other``: the largest bound of the other active arms); a self pair's by at most
  the bound of its outer geom over the joints between the two bodies (relative motion in
  the inner body's frame); a geom's height above the ground by at most the geom's bound.
  Self pairs and the ground are checked pair by pair (:func:`~mjx_multiarm.geometry.collision.self_and_ground_distances`),
  arms against each other by the collision kernel's smallest distance per arm.
- March. From s = 0 the whole team is evaluated at the current s; every arm whose distances
  cover the rest of the motion (``d >= rate (1 - s)`` for each kind) is certified free; the
  others are free on ``[s, s + d / rate]``, and the team advances by the smallest such step of
  the arms still pending. An arm whose step falls below :data:`SMALLEST_STEP` (a contact, or
  a clearance too small to certify) is reported as colliding; so is one still pending after
  :data:`MAX_EVALUATIONS` evaluations. An arm that does not move is certified by its
  distances at s = 0: its pairs with moving arms are certified by their own march.

The verdict is exact in the model: an arm reported free has no contact at any s (up to the
float32 arithmetic of the distances). Safe execution (:mod:`mjx_multiarm.env.shield`), the
safe environment's collision verdict, :meth:`mjx_multiarm.planner.policy.Planner.rollout`'s
reported collisions and the BiRRT expert's replay check use it; training and the paper's
metric use the sampled sweep (faster, and what the original measured).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct

from mjx_multiarm.geometry.collision import (
    Contacts,
    ground_geoms,
    kernel_jit,
    scene_contacts,
    self_and_ground_distances,
)
from mjx_multiarm.geometry.kinematics import forward_kinematics
from mjx_multiarm.geometry.robot import NUM_JOINTS, ArmModel
from mjx_multiarm.geometry.scene import Scene
from mjx_multiarm.geometry.transforms import quat_to_mat

#: Smallest step (a fraction of the motion) the march may take; an arm that needs a smaller
#: one is reported as colliding (with the arms' full-speed bound of about 0.5 m a step,
#: this is a clearance of about 0.5 mm).
SMALLEST_STEP = 1.0 / 8192
#: Evaluations of the team after which arms still pending are reported as colliding.
MAX_EVALUATIONS = 256
#: Distances beyond this (m) are not computed exactly (the collision kernel's
#: ``max_distance``); any value is sound, larger ones take fewer evaluations.
CERTIFY_RANGE = 1.0


def _geom_points(arm: ArmModel) -> list[tuple[int, np.ndarray, float]]:
    """Each collision geom as (body, points [k, 3] in the body frame, radius around them): a
    capsule's segment ends, a box's 8 corners."""
    signs = np.array(np.meshgrid(*[[-1.0, 1.0]] * 3, indexing="ij")).reshape(3, -1).T
    capsules = [(b, ends, r) for b, ends, r in zip(arm.capsule_body, arm.capsule_ends, arm.capsule_radius)]
    boxes = [(b, frame[0] + (signs * half) @ frame[1:], 0.0) for b, frame, half in zip(arm.box_body, arm.box_frame, arm.box_half)]
    return capsules + boxes


@functools.cache
def geom_reach(arm: ArmModel) -> np.ndarray:
    """[6, ngeom] upper bound (m) on the distance of any point of each collision geom
    (capsules, then boxes) from each joint's axis; 0 where the joint does not move the geom.

    A geom rigidly attached to the joint's body (no joint in between) gets its exact largest
    distance from the axis; one beyond another joint gets the lengths of the body offsets from
    the joint to its body plus its extent from its body origin (configuration independent)."""
    norms = np.linalg.norm(arm.body_pos, axis=-1)
    geoms = _geom_points(arm)
    reach = np.zeros((NUM_JOINTS, len(geoms)))
    for b, j in enumerate(arm.body_joint):
        if j < 0:
            continue
        axis = arm.joint_axis[j] / np.linalg.norm(arm.joint_axis[j])
        rigid = {b: (np.zeros(3), np.eye(3))}  # bodies fixed in body b's frame: origin, rotation
        for c in range(b + 1, len(arm.body_names)):
            if arm.body_joint[c] >= 0:
                break
            origin, rotation = rigid[c - 1]
            turn = np.empty(9)
            mujoco.mju_quat2Mat(turn, arm.body_quat[c])
            rigid[c] = (origin + rotation @ arm.body_pos[c], rotation @ turn.reshape(3, 3))
        for g, (body, points, radius) in enumerate(geoms):
            if body in rigid:
                origin, rotation = rigid[body]
                local = origin + points @ rotation.T
                reach[j, g] = np.linalg.norm(local - np.outer(local @ axis, axis), axis=-1).max() + radius
            elif body > b:
                reach[j, g] = norms[b + 1 : body + 1].sum() + np.linalg.norm(points, axis=-1).max() + radius
    return reach


@functools.cache
def pair_tables(scene: Scene) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The static tables of the rates: joint bodies [6], each self pair's outer geom [S] (the
    one on the later body) and the joints between its two bodies [6, S] bool (those that move
    the pair relative to each other), the ground geoms [G]."""
    arm = scene.arm
    bodies = np.concatenate([arm.capsule_body, arm.box_body])
    joint_body = np.array([arm.body_joint.index(j) for j in range(NUM_JOINTS)])
    pairs = scene.pairs.self_pairs
    inner = np.minimum(bodies[pairs[:, 0]], bodies[pairs[:, 1]])
    outer = np.where(bodies[pairs[:, 0]] > bodies[pairs[:, 1]], pairs[:, 0], pairs[:, 1])
    between = (joint_body[:, None] > inner[None]) & (joint_body[:, None] <= bodies[outer][None])
    return joint_body, outer, between, ground_geoms(scene)


def _reach_now(scene: Scene, frames, delta, remaining) -> jnp.ndarray:
    """[..., A, 6, ngeom] bounds on each geom's distance from each joint's axis over the rest of
    the motion: its distance now (posed ``frames``) plus how far the joints beyond can move it
    in the ``remaining`` fraction, capped by :func:`geom_reach`."""
    arm = scene.arm
    reach = jnp.asarray(geom_reach(arm), delta.dtype)
    joint_body = pair_tables(scene)[0]
    origin = frames.body_pos[..., joint_body, :]  # [..., A, 6, 3]
    axis = jnp.einsum("...jab,jb->...ja", quat_to_mat(frames.body_quat[..., joint_body, :]),
                      jnp.asarray(arm.joint_axis / np.linalg.norm(arm.joint_axis, axis=-1, keepdims=True), delta.dtype))
    signs = jnp.asarray(np.array(np.meshgrid(*[[-1.0, 1.0]] * 3, indexing="ij")).reshape(3, -1).T, delta.dtype)
    corners = frames.boxes[..., :1, :] + jnp.einsum("ck,bk,...bkx->...bcx", signs, jnp.asarray(arm.box_half, delta.dtype),
                                                    frames.boxes[..., 1:, :])  # [..., A, B, 8, 3]

    def farthest(points):  # [..., A, K, P, 3] -> [..., A, 6, K]
        offset = points[..., None, :, :, :] - origin[..., :, None, None, :]
        along = (offset * axis[..., :, None, None, :]).sum(-1, keepdims=True)
        return jnp.linalg.norm(offset - along * axis[..., :, None, None, :], axis=-1).max(axis=-1)

    radius = jnp.concatenate([jnp.asarray(arm.capsule_radius, delta.dtype), jnp.zeros(arm.num_boxes, delta.dtype)])
    now = jnp.concatenate([farthest(frames.capsules), farthest(corners)], axis=-1) + radius
    moved = delta[..., :, None] * reach  # [..., A, 6, G]: how far each joint can move each geom
    beyond = jnp.cumsum(moved[..., ::-1, :], axis=-2)[..., ::-1, :] - moved  # by the joints after each joint
    return jnp.where(reach > 0, jnp.minimum(reach, now + remaining[..., None, None, None] * beyond), 0.0)


@functools.partial(jax.jit, static_argnames=("scene",))
def motion_bounds(scene: Scene, joints_from, joints_to, active) -> jnp.ndarray:
    """[..., A] how far (m) any point of each arm's geoms can move along the straight motion
    (from :func:`geom_reach`; the march tightens it with the arms' poses)."""
    reach = jnp.asarray(geom_reach(scene.arm), jnp.result_type(joints_from))
    return jnp.where(active, (jnp.abs(joints_to - joints_from) @ reach).max(axis=-1), 0.0)


def _rates(scene: Scene, frames, delta, remaining, active):
    """Per unit of motion from here on: how fast each arm's distance to the other arms [..., A],
    each self pair's distance [..., A, S] and each ground geom's height [..., A, G] can shrink."""
    _, outer, between, ground = pair_tables(scene)
    reach = _reach_now(scene, frames, delta, remaining)
    speed = jnp.einsum("...j,...jg->...g", delta, reach)  # [..., A, G]
    bound = jnp.where(active, speed.max(axis=-1), 0.0)
    self_rate = jnp.einsum("...j,...js,js->...s", delta, reach[..., outer], jnp.asarray(between, delta.dtype))
    return bound + _other_max(bound, active), self_rate, speed[..., ground]


@struct.dataclass
class CertifiedMotion:
    """Per-arm verdict of :func:`certified_contacts`; fields [..., A].

    Attributes:
      contacts: the smallest distances seen at the evaluated configurations (a negative one
        is a contact found).
      uncertified: the arm was not certified free (a contact, a clearance below what
        :data:`SMALLEST_STEP` allows, or :data:`MAX_EVALUATIONS` reached).
      evaluations: [...] team evaluations the march took.
    """

    contacts: Contacts
    uncertified: jnp.ndarray
    evaluations: jnp.ndarray

    @property
    def collided(self) -> jnp.ndarray:
        return self.contacts.collided | self.uncertified

    @property
    def min_distance(self) -> jnp.ndarray:
        return self.contacts.min_distance


def _other_max(bounds, active):
    """[..., A] the largest bound of the other active arms."""
    num_arms = bounds.shape[-1]
    others = active[..., None, :] & ~jnp.eye(num_arms, dtype=bool)
    return jnp.where(others, bounds[..., None, :], 0.0).max(axis=-1)


def _fraction(distance, rate):
    """How much of the motion a clearance ``distance`` covers at ``rate`` (m per unit of motion)."""
    return jnp.where(rate > 0, distance / jnp.where(rate > 0, rate, 1.0), jnp.where(distance >= 0, jnp.inf, -jnp.inf))


@kernel_jit("scene", "margin", "max_evaluations", "smallest_step")
def certified_contacts(scene: Scene, base_pos, base_quat, joints_from, joints_to, active, margin: float = 0.0,
                       max_evaluations: int = MAX_EVALUATIONS, smallest_step: float = SMALLEST_STEP) -> CertifiedMotion:
    """Certified collision verdict of the straight motion ``joints_from -> joints_to`` (module doc).

    Args:
      base_pos: [..., A, 3]; base_quat: [..., A, 4] (wxyz); joints_from / joints_to:
        [..., A, 6]; active: [..., A] bool. Any leading batch dims; one march per team.
      margin: clearance (m) every arm must keep along the motion to be certified.
    """
    joints_from, joints_to = jnp.asarray(joints_from), jnp.asarray(joints_to)
    shape = jnp.broadcast_shapes(joints_from.shape, joints_to.shape)
    joints_from, joints_to = jnp.broadcast_to(joints_from, shape), jnp.broadcast_to(joints_to, shape)
    active = jnp.broadcast_to(active, shape[:-1])
    delta = jnp.abs(joints_to - joints_from)
    moving = motion_bounds(scene, joints_from, joints_to, active) > 0

    def evaluate(s):
        """Per arm: the distances as the kernel reports them, and the fraction of the rest of the
        motion they certify."""
        joints = joints_from + s[..., None, None] * (joints_to - joints_from)
        contacts = scene_contacts(scene, base_pos, base_quat, joints, active, CERTIFY_RANGE)
        frames = forward_kinematics(scene.arm, base_pos, base_quat, joints)
        self_dist, ground = self_and_ground_distances(scene, frames)
        between_rate, self_rate, ground_rate = _rates(scene, frames, delta, 1.0 - s, active)
        step = jnp.minimum(_fraction(contacts.between_arms - margin, between_rate),
                           jnp.minimum(_fraction(self_dist - margin, self_rate).min(axis=-1),
                                       _fraction(ground - margin, ground_rate).min(axis=-1)))
        return contacts, step

    def body(carry):
        s, done, bad, seen, count = carry
        live = (active & ~done & ~bad).any(axis=-1)  # teams still marching (the others wait, unchanged)
        contacts, step = evaluate(s)
        seen = jax.tree.map(lambda old, new: jnp.where(live[..., None], jnp.minimum(old, new), old), seen, contacts)
        certified = (step >= (1.0 - s)[..., None]) | ((count == 0)[..., None] & ~moving & (step >= 0))
        done = done | (live[..., None] & ~bad & certified)
        bad = bad | (active & ~done & (step < smallest_step))
        pending = active & ~done & ~bad
        advance = jnp.where(pending, step, jnp.inf).min(axis=-1)
        s = jnp.where(pending.any(axis=-1), jnp.minimum(s + advance, 1.0), s)
        return s, done, bad, seen, count + live

    def pending(carry):
        s, done, bad, _, count = carry
        left = active & ~done & ~bad
        return (left.any(axis=-1) & (count < max_evaluations)).any()

    batch = shape[:-2]
    no = jnp.zeros(shape[:-1], bool)
    far = jnp.full(shape[:-1], jnp.inf, joints_from.dtype)
    start = (jnp.zeros(batch, joints_from.dtype), ~active, no, Contacts(far, far, far), jnp.zeros(batch, jnp.int32))
    _, done, _, seen, count = jax.lax.while_loop(pending, body, body(start))
    return CertifiedMotion(contacts=seen, uncertified=active & ~done, evaluations=count)
