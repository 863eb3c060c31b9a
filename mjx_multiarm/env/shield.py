"""Safe execution: a team step that never collides in the model (beyond the paper).

Before a team step is executed, every arm's motion is checked against the other arms'
motions with the certified motion check (:mod:`mjx_multiarm.geometry.certified`: no
configuration along the step can touch, not only the sampled ones). Each
arm has three motions, tried in order: the one proposed (by the policy), a step away from
the other arms and the static obstacles (:func:`away_joints`: up the gradient of its
distance to their link points and boxes), and holding still. While any motion of the team collides, the colliding arms step
down one option, except the one with the highest priority (lowest slot index) among those
not yet given the right of way: it keeps its motion for one more check, so that of two
arms that run into each other the lower one makes room and the higher one passes. An arm
whose motion still collides when nothing else can give way steps down as well. Holding
still is always free when the team's current configuration is free (held arms are where
they were, certified by their distances at the start, and every moving arm is checked
against them), so the loop ends with a certified collision-free step in at most 3 x arms
checks. Stepping away (rather than holding, or
reversing the proposal) is what gets blocked arms unstuck: measured in
benchmarks/RESULTS.md, "Safe execution".
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from mjx_multiarm.geometry.certified import CertifiedMotion, certified_contacts
from mjx_multiarm.geometry.kinematics import forward_kinematics
from mjx_multiarm.geometry.scene import Scene

#: The motions an arm may be given, in the order they are tried.
PROPOSED, AWAY, HELD = 0, 1, 2
#: Evaluations the certified check may take per team check; an arm still pending counts as
#: colliding and steps down (sound: a lower cap only makes the shield more cautious). Kept at
#: the check's own cap: batches of teams step one team at a time on a CPU
#: (:func:`mjx_multiarm.env.wrappers.batched_step`), so a slow team no longer holds up the others.
SHIELD_EVALUATIONS = 256


def shielded_joints(scene: Scene, base_pos, base_quat, joints, proposed, active, joint_range, max_step):
    """The executed next joints of one team and what was done to each arm.

    Args:
      joints: [A, 6] the current (collision-free) joints; proposed: [A, 6] the next joints
        asked for (within the per-step and joint limits); active: [A] bool.
      joint_range, max_step: the environment's joint limits [6, 2] and largest joint motion
        per step [6].

    Returns:
      (next joints [A, 6], motion [A] int: :data:`PROPOSED`, :data:`AWAY` or :data:`HELD`,
      the executed step's :class:`~mjx_multiarm.geometry.certified.CertifiedMotion`).
    """
    num_arms = joints.shape[-2]
    slot = jnp.arange(num_arms)
    away = away_joints(scene, base_pos, base_quat, joints, active, max_step, joint_range)
    options = jnp.stack([proposed, away, joints])  # [3, A, 6]
    still = ~jnp.any(proposed != joints, axis=-1) | ~active
    level = jnp.where(still, HELD, PROPOSED)

    def motion(level):
        return jnp.take_along_axis(options, level[None, :, None], axis=0)[0]

    def check(level) -> CertifiedMotion:
        return certified_contacts(scene, base_pos, base_quat, joints, motion(level), active,
                                  max_evaluations=SHIELD_EVALUATIONS)

    def colliding(level, contacts):
        return contacts.collided & active & (level < HELD)

    def body(carry):
        level, passed, contacts = carry
        bad = colliding(level, contacts)
        waiting = bad & ~passed
        first = jnp.argmin(jnp.where(waiting, slot, num_arms))
        excused = waiting.any() & (slot == first) & (bad.sum() > 1)  # keeps its motion for one more check
        level = jnp.where(bad & ~excused, level + 1, level)
        return level, passed | excused, check(level)

    def cond(carry):
        return colliding(carry[0], carry[2]).any()

    level, _, contacts = jax.lax.while_loop(cond, body, (level, jnp.zeros(num_arms, bool), check(level)))
    return motion(level), level, contacts


#: Softness (m) of the smallest link-point distance whose gradient points away from the others.
AWAY_SOFTNESS = 0.05
#: Beyond this distance (m) of its link points to every other arm's and every obstacle an arm
#: feels no push.
AWAY_RANGE = 0.5


def away_joints(scene: Scene, base_pos, base_quat, joints, active, max_step, joint_range):
    """[A, 6] every arm's joints one full step up the gradient of its smooth smallest
    distance from its link points (the 10 points the policy observes) to the other arms'
    and to the scene's static obstacle boxes (a bin: a policy that does not see it would
    otherwise push into it, held, forever); arms with nothing within :data:`AWAY_RANGE`
    stay where they are."""
    num_arms = joints.shape[-2]
    other = active[:, None] & active[None, :] & ~jnp.eye(num_arms, dtype=bool)

    def clearance(q):
        points = forward_kinematics(scene.arm, base_pos, base_quat, q).points  # [A, 10, 3]
        gap = points[:, None, :, None, :] - points[None, :, None, :, :]  # [A, A, 10, 10, 3]
        distance = jnp.sqrt((gap * gap).sum(-1) + 1e-9)
        distance = jnp.where(other[:, :, None, None], distance, AWAY_RANGE).reshape(num_arms, -1)
        if len(scene.obstacle_half):
            distance = jnp.concatenate([distance, box_distances(scene, points).reshape(num_arms, -1)], axis=-1)
        soft = -AWAY_SOFTNESS * jax.nn.logsumexp(-distance / AWAY_SOFTNESS, axis=-1)
        return jnp.where(active, jnp.minimum(soft, AWAY_RANGE), 0.0).sum()

    gradient = jax.grad(clearance)(joints)
    scale = jnp.max(jnp.abs(gradient) / max_step, axis=-1, keepdims=True)
    step = jnp.where(scale > 1e-9, gradient / jnp.maximum(scale, 1e-9), 0.0)
    return jnp.clip(joints + step, joint_range[:, 0], joint_range[:, 1])


def box_distances(scene: Scene, points) -> jnp.ndarray:
    """[..., P, K] signed distance of each point [..., P, 3] to each static obstacle box."""
    frames = jnp.asarray(scene.obstacle_frames, points.dtype)  # [K, 4, 3]: centre, then axes
    offset = points[..., :, None, :] - frames[:, 0]  # [..., P, K, 3]
    local = jnp.einsum("...kj,kij->...ki", offset, frames[:, 1:])
    excess = jnp.abs(local) - jnp.asarray(scene.obstacle_half, points.dtype)
    outside = jnp.sqrt((jnp.maximum(excess, 0.0) ** 2).sum(-1) + 1e-12)
    return outside + jnp.minimum(excess.max(-1), 0.0)
