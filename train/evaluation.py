"""Deterministic evaluation of a policy on a task bank: success, collisions, timeouts."""

from __future__ import annotations

from flax import nnx

from mjx_multiarm.env import ReachingEnv
from mjx_multiarm.wrappers import TaskBank, run_episodes
from train.agent import Agent


def evaluate_policy(agent: Agent, env: ReachingEnv, bank: TaskBank) -> dict:
    """Run every task of ``bank`` once with the policy's mean actions for ``env``'s episode
    length; returns :meth:`~mjx_multiarm.wrappers.EpisodeStats.summary`."""
    actor_def = agent.actor_def

    def policy(states, actor):
        return nnx.merge(actor_def, actor)(states.obs, states.obs_mask)[0]

    return run_episodes(env, policy, agent.actor, bank).stats(env.max_arms).summary()
