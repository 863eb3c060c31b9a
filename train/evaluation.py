"""Deterministic evaluation of a policy on a task bank: success, collisions, timeouts."""

from __future__ import annotations

import jax
from flax import nnx

from mjx_multiarm.env.reaching import ReachingEnv
from mjx_multiarm.env.wrappers import TaskBank, run_episodes
from train.agent import Agent


def evaluate_policy(agent: Agent, env: ReachingEnv, bank: TaskBank, sample_key=None, std_scale: float = 1.0) -> dict:
    """Run every task of ``bank`` once for ``env``'s episode length with the mean actions of
    the deployed policy (``agent.average_actor``), or with sampled actions of the training
    policy (``agent.actor``, its noise bound scaled by ``std_scale``) when ``sample_key`` is
    given; returns
    :meth:`~mjx_multiarm.env.wrappers.EpisodeStats.summary`."""
    actor_def = agent.actor_def

    def policy(states, actor):
        key = None if sample_key is None else jax.random.fold_in(sample_key, states.step[0])
        return nnx.merge(actor_def, actor)(states.obs, states.obs_mask, key, std_scale)[0]

    params = agent.actor if sample_key is not None else agent.average_actor
    return run_episodes(env, policy, params, bank).stats(env.max_arms).summary()
