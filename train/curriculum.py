"""The tolerance curriculum of the paper's appendix (Table: Training Curriculum).

Training starts at (10 cm, 0.2 rad) and tightens the reach tolerances over 22 levels down
to (1 cm, 0.05 rad); the policy graduates to the next level once at least 70% of the
latest 100 episodes (all of them at the current level) succeeded. The state lives on
device, so the graduation test runs inside the jitted training loop.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from train.replay import ring_write

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
    """Current level and the outcomes of the latest episodes at that level (a ring)."""

    level: jnp.ndarray
    outcomes: jnp.ndarray  # [WINDOW] bool, success of recent episodes
    count: jnp.ndarray  # episodes recorded at this level (saturates at WINDOW)
    position: jnp.ndarray

    @classmethod
    def start(cls, level: int = 0) -> Curriculum:
        if not 0 <= level < len(LEVELS):
            raise ValueError(f"curriculum level must be in [0, {len(LEVELS) - 1}], got {level}")
        zero = jnp.zeros((), jnp.int32)
        return cls(jnp.asarray(level, jnp.int32), jnp.zeros(WINDOW, bool), zero, zero)

    @property
    def tolerance(self) -> jnp.ndarray:
        """[2] (eps_p, eps_r) of the current level."""
        return jnp.asarray(LEVELS)[self.level]

    @property
    def success_rate(self) -> jnp.ndarray:
        return jnp.where(self.count > 0, jnp.sum(self.outcomes) / jnp.maximum(self.count, 1), 0.0)

    def record(self, ended, success) -> Curriculum:
        """Add the episodes flagged in ``ended`` [B] (their ``success`` [B]); graduate if due."""
        outcomes, new = ring_write(self.outcomes, success, ended, self.position)
        state = Curriculum(self.level, outcomes, jnp.minimum(self.count + new, WINDOW), (self.position + new) % WINDOW)
        graduate = (state.count >= WINDOW) & (state.success_rate >= GRADUATION_RATE) & (self.level < len(LEVELS) - 1)
        promoted = Curriculum.start().replace(level=self.level + 1)
        return jax.tree.map(lambda up, stay: jnp.where(graduate, up, stay), promoted, state)
