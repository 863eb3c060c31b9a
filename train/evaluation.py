"""Deterministic evaluation of a policy on a task bank: success, collisions, timeouts."""

from __future__ import annotations

from collections.abc import Callable

import jax
from flax import nnx

from mjx_multiarm.env.reaching import ReachingEnv
from mjx_multiarm.env.wrappers import TaskBank, episode_outcomes, make_episodes
from train.agent import Agent


def policy_evaluator(actor_def: nnx.GraphDef, env: ReachingEnv, bank: TaskBank, sample_key=None,
                     std_scale: float = 1.0) -> Callable[[nnx.State], dict]:
    """``evaluate(actor_params) -> summary``: every task of ``bank`` run once for ``env``'s
    episode length with the actor's mean actions, or its sampled actions (noise bound
    scaled by ``std_scale``) when ``sample_key`` is given; the summary is
    :meth:`~mjx_multiarm.env.wrappers.EpisodeStats.summary`. Compiled once: call it as
    often as needed (e.g. during training)."""

    def policy(states, actor):
        key = None if sample_key is None else jax.random.fold_in(sample_key, states.step[0])
        return nnx.merge(actor_def, actor)(states.obs, states.obs_mask, key, std_scale)[0]

    episodes = make_episodes(env, policy, env.config.max_steps)
    return lambda actor: episode_outcomes(episodes, actor, bank).stats(env.max_arms).summary()


def evaluate_policy(agent: Agent, env: ReachingEnv, bank: TaskBank, sample_key=None, std_scale: float = 1.0) -> dict:
    """One evaluation (:func:`policy_evaluator`) of the deployed policy
    (``agent.average_actor``, mean actions), or of the training policy (``agent.actor``)
    with sampled actions when ``sample_key`` is given."""
    params = agent.actor if sample_key is not None else agent.average_actor
    return policy_evaluator(agent.actor_def, env, bank, sample_key, std_scale)(params)
