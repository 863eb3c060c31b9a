"""The tolerance curriculum of the paper's appendix (Table: Training Curriculum).

Training starts at (10 cm, 0.2 rad) and tightens the reach tolerances over 22 levels down
to (1 cm, 0.05 rad); the policy graduates to the next level once at least 70% of its
latest 100 episodes at the current level succeeded.

With many environments in parallel, "the latest 100 episodes to end" is a biased sample
after every level change: a success ends after a few steps and a failure only at the step
limit, so the first episodes to end at a new level are mostly successes (with 64
environments, 14-step successes and 200-step failures, a policy that succeeds on 50% of
its episodes shows ~78% in its first window of 100). The window is therefore kept per
environment: every environment contributes its latest ``ceil(100 / num_envs)`` completed
episodes, and the policy graduates once every environment has filled its share. Completed
episodes other than the one in progress are ordinary samples of the policy's episodes, so
this rate estimates the per-episode success rate without the length bias. The state lives
on device, so the graduation test runs inside the jitted training loop.

:class:`GroupedCurriculum` keeps one such curriculum per group of episodes: one group for
all (the paper), or one per team size, so that each team size graduates on its own
episodes (with 1-4 arms mixed, the success of all teams together is held below 70 % by the
hardest team size, and no team leaves the first level).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

#: (eps_p m, eps_r rad) per level, level 0 first.
LEVELS = np.array(
    [(0.10, 0.20), (0.08, 0.16), (0.06, 0.14), (0.04, 0.10), (0.036, 0.09), (0.032, 0.08), (0.028, 0.07),
     (0.026, 0.06), (0.024, 0.05)] + [(p / 1000, 0.05) for p in (22, 21, 20, 19, 18, 17, 16, 15, 14, 13, 12, 11, 10)],
    np.float32,
)
GRADUATION_RATE = 0.7
WINDOW = 100


@struct.dataclass
class Curriculum:
    """Current level and, per environment, the outcomes of its latest episodes at that level."""

    level: jnp.ndarray
    outcomes: jnp.ndarray  # [E, K] bool, a ring per environment
    count: jnp.ndarray  # [E] episodes recorded at this level (saturates at K)
    position: jnp.ndarray  # [E] next slot of each ring

    @classmethod
    def start(cls, num_envs: int, level: int = 0) -> Curriculum:
        """Level ``level`` with empty windows for ``num_envs`` environments."""
        if not 0 <= level < len(LEVELS):
            raise ValueError(f"curriculum level must be in [0, {len(LEVELS) - 1}], got {level}")
        if num_envs < 1:
            raise ValueError(f"the curriculum needs at least one environment, got {num_envs}")
        per_env = math.ceil(WINDOW / num_envs)
        zeros = jnp.zeros(num_envs, jnp.int32)
        return cls(jnp.asarray(level, jnp.int32), jnp.zeros((num_envs, per_env), bool), zeros, zeros)

    @property
    def tolerance(self) -> jnp.ndarray:
        """[2] (eps_p, eps_r) of the current level."""
        return jnp.asarray(LEVELS)[self.level]

    @property
    def success_rate(self) -> jnp.ndarray:
        """Success over the recorded episodes at this level (0 before the first)."""
        recorded = jnp.arange(self.outcomes.shape[1]) < self.count[:, None]
        return jnp.sum(self.outcomes & recorded) / jnp.maximum(jnp.sum(recorded), 1)

    def record(self, ended, success) -> Curriculum:
        """Add the episodes that ended at this step (``ended``, ``success``: [E]); graduate if due."""
        num_envs, per_env = self.outcomes.shape
        envs = jnp.arange(num_envs)
        slot = jnp.where(ended, self.position, per_env)  # out of range: not written
        outcomes = self.outcomes.at[envs, slot].set(success, mode="drop")
        state = Curriculum(self.level, outcomes, jnp.where(ended, jnp.minimum(self.count + 1, per_env), self.count),
                           jnp.where(ended, (self.position + 1) % per_env, self.position))
        full = jnp.all(state.count >= per_env)
        graduate = full & (state.success_rate >= GRADUATION_RATE) & (self.level < len(LEVELS) - 1)
        promoted = Curriculum.start(num_envs).replace(level=self.level + 1)
        return jax.tree.map(lambda up, stay: jnp.where(graduate, up, stay), promoted, state)


@struct.dataclass
class GroupedCurriculum:
    """Independent curricula, one per group of episodes; ``groups`` has a leading dim [G]."""

    groups: Curriculum

    @classmethod
    def start(cls, num_envs: int, num_groups: int = 1, level: int = 0) -> GroupedCurriculum:
        """``num_groups`` curricula at level ``level`` with empty windows."""
        if num_groups < 1:
            raise ValueError(f"a grouped curriculum needs at least one group, got {num_groups}")
        one = Curriculum.start(num_envs, level)
        return cls(jax.tree.map(lambda x: jnp.broadcast_to(x, (num_groups, *x.shape)), one))

    @property
    def level(self) -> jnp.ndarray:
        """[G] current level of each group."""
        return self.groups.level

    @property
    def tolerance(self) -> jnp.ndarray:
        """[G, 2] (eps_p, eps_r) of each group's level."""
        return jnp.asarray(LEVELS)[self.groups.level]

    @property
    def success_rate(self) -> jnp.ndarray:
        """[G] success over each group's recorded episodes at its level."""
        return jax.vmap(lambda c: c.success_rate)(self.groups)

    def record(self, ended, success, group) -> GroupedCurriculum:
        """Add the episodes that ended (``ended``, ``success``, ``group``: [E]) to their groups."""
        ids = jnp.arange(self.groups.level.shape[0])[:, None]
        mine = ended[None] & (group[None] == ids)
        return GroupedCurriculum(jax.vmap(Curriculum.record, in_axes=(0, 0, None))(self.groups, mine, success))
