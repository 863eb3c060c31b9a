"""An on-device replay buffer of per-arm transitions (a ring, no copying when full).

Each transition is one arm's step: its observation sequence and mask, its action, its
reward, the next observation sequence and mask, whether the episode terminated there
(success or collision; a timeout is not a termination, so the critic bootstraps through
it) and whether the step came from an expert demonstration. Inserts take a fixed-size
batch with a validity mask (inactive arms, steps beyond a demonstration), so every shape
is static under ``jit``; valid rows are packed into the ring in order. Sampling is
uniform over the filled part.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from mjx_multiarm.env.observation import ELEMENT_SIZE
from mjx_multiarm.geometry.robot import NUM_JOINTS


def ring_write(ring, values, flags, start):
    """``ring`` [S, ...] with ``values`` [M, ...] written where ``flags`` [M], in order, at
    slots ``start``, ``start + 1``, ... (mod S); returns (ring, rows written)."""
    size = ring.shape[0]
    flags = flags.astype(bool)
    index = jnp.where(flags, (start + jnp.cumsum(flags) - 1) % size, size)  # out of range: dropped
    return ring.at[index].set(values.astype(ring.dtype), mode="drop"), flags.sum().astype(jnp.int32)


@struct.dataclass
class Transitions:
    """A batch of per-arm transitions; leading dim [N]."""

    obs: jnp.ndarray  # [N, L, 107]
    mask: jnp.ndarray  # [N, L]
    action: jnp.ndarray  # [N, 6]
    reward: jnp.ndarray  # [N]
    next_obs: jnp.ndarray  # [N, L, 107]
    next_mask: jnp.ndarray  # [N, L]
    terminal: jnp.ndarray  # [N] bool
    expert: jnp.ndarray  # [N] bool: a step of an expert demonstration


@struct.dataclass
class ReplayBuffer:
    """``data`` holds ``capacity`` rows; the newest valid row is at ``position - 1``."""

    data: Transitions
    position: jnp.ndarray  # next row to write
    size: jnp.ndarray  # filled rows
    inserted: jnp.ndarray  # valid rows ever inserted

    @property
    def capacity(self) -> int:
        return self.data.reward.shape[0]

    @classmethod
    def create(cls, capacity: int, sequence: int) -> ReplayBuffer:
        """An empty buffer for observation sequences of length ``sequence`` (= max_arms)."""
        obs = jnp.zeros((capacity, sequence, ELEMENT_SIZE), jnp.float32)
        mask = jnp.zeros((capacity, sequence), bool)
        data = Transitions(obs, mask, jnp.zeros((capacity, NUM_JOINTS), jnp.float32), jnp.zeros(capacity, jnp.float32),
                           obs, mask, jnp.zeros(capacity, bool), jnp.zeros(capacity, bool))
        zero = jnp.zeros((), jnp.int32)
        return cls(data, zero, zero, zero)

    def insert(self, batch: Transitions, valid) -> ReplayBuffer:
        """Append the rows of ``batch`` [M] where ``valid`` [M]; M must not exceed the capacity."""
        rows = valid.shape[0]
        if rows > self.capacity:
            raise ValueError(f"inserting {rows} rows at once into a buffer of {self.capacity}")
        data = jax.tree.map(lambda buf, new: ring_write(buf, new, valid, self.position)[0], self.data, batch)
        count = valid.sum().astype(jnp.int32)
        return ReplayBuffer(data, (self.position + count) % self.capacity, jnp.minimum(self.size + count, self.capacity),
                            self.inserted + count)

    def sample(self, key, batch_size: int) -> Transitions:
        """``batch_size`` rows drawn uniformly (with replacement) from the filled part."""
        index = jax.random.randint(key, (batch_size,), 0, jnp.maximum(self.size, 1))
        return jax.tree.map(lambda x: x[index], self.data)
