"""Deterministic evaluation of a policy on a task bank: success, collisions, timeouts."""

from __future__ import annotations

import jax
import numpy as np
from flax import nnx

from mjx_multiarm.env import ReachingEnv
from mjx_multiarm.wrappers import EpisodeStats, TaskBank, make_episodes
from train.agent import Agent

#: Tasks evaluated per compiled call (the last batch is padded by repeating tasks).
EVAL_BATCH = 256


def evaluate_policy(agent: Agent, env: ReachingEnv, bank: TaskBank, batch: int = EVAL_BATCH) -> dict:
    """Run every task of ``bank`` once with the policy's mean actions for ``env``'s episode
    length; returns :meth:`~mjx_multiarm.wrappers.EpisodeStats.summary`."""
    actor_def = agent.actor_def

    def policy(states, actor):
        return nnx.merge(actor_def, actor)(states.obs, states.obs_mask)[0]

    episodes = make_episodes(env, policy, env.config.max_steps)
    stats = EpisodeStats.zeros(env.max_arms)
    size = min(batch, bank.size)
    for start in range(0, bank.size, size):
        rows = np.arange(start, start + size) % bank.size
        final = episodes(bank.take(rows), agent.actor)
        keep = np.arange(start, start + size) < bank.size
        stats = stats.add(final.replace(done=final.done & keep))
    return jax.device_get(stats).summary()
