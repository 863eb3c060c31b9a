"""Safe execution: a team step that never collides in the model (beyond the paper).

Before a team step is executed, every arm's motion is checked with the swept collision
check against the other arms' motions (the environment's own check, same substeps). Each
arm has three motions, tried in order: the one proposed (by the policy), its reverse (a
step back, away from whatever the proposal ran into), and holding still. While any motion
of the team collides, the colliding arms step down one option, except the one with the
highest priority (lowest slot index) among those not yet given the right of way: it keeps
its motion for one more check, so that of two arms that run into each other the lower one
backs off and the higher one passes. An arm whose motion still collides when nothing else
can give way steps down as well. Holding still is always free when the team's current
configuration is free (held arms are where they were, and every moving arm is checked
against them), so the loop ends with a collision-free step in at most 3 x arms checks.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from mjx_multiarm.geometry.collision import Contacts, swept_contacts
from mjx_multiarm.geometry.scene import Scene

#: The motions an arm may be given, in the order they are tried.
PROPOSED, REVERSED, HELD = 0, 1, 2


def shielded_joints(scene: Scene, base_pos, base_quat, joints, proposed, active, substeps: int, joint_range):
    """The executed next joints of one team and what was done to each arm.

    Args:
      joints: [A, 6] the current (collision-free) joints; proposed: [A, 6] the next joints
        asked for (within the per-step and joint limits); active: [A] bool.
      substeps, joint_range: as the environment's swept check and joint limits.

    Returns:
      (next joints [A, 6], motion [A] int: :data:`PROPOSED`, :data:`REVERSED` or
      :data:`HELD`, contacts of the executed step).
    """
    num_arms = joints.shape[-2]
    slot = jnp.arange(num_arms)
    reverse = jnp.clip(2.0 * joints - proposed, joint_range[:, 0], joint_range[:, 1])
    options = jnp.stack([proposed, reverse, joints])  # [3, A, 6]
    still = ~jnp.any(proposed != joints, axis=-1) | ~active
    level = jnp.where(still, HELD, PROPOSED)

    def motion(level):
        return jnp.take_along_axis(options, level[None, :, None], axis=0)[0]

    def check(level) -> Contacts:
        return swept_contacts(scene, base_pos, base_quat, joints, motion(level), active, substeps)

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
