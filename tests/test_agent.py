"""Replay buffer and SAC / behaviour-cloning updates."""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from mjx_multiarm.env.observation import InputFeatures
from models.networks import Actor, Mixture
from train.agent import (
    LOSER_SHARE,
    SACConfig,
    bc_update,
    cloning_error,
    create_agent,
    critic_loss,
    expert_bc_loss,
    sac_update,
    td_target,
)
from train.replay import ReplayBuffer, Transitions


#: The update every test jits: one compilation per config (static) and batch shape, so the
#: tests that use the default config and 64-row batches share theirs.
update = jax.jit(sac_update, static_argnums=3)


def _batch(key, n, length=3):
    keys = jax.random.split(key, 4)
    obs = jax.random.normal(keys[0], (n, length, 107))
    mask = jnp.broadcast_to(jnp.arange(length) >= 1, (n, length))
    return Transitions(obs, mask, jax.random.uniform(keys[1], (n, 6), minval=-1, maxval=1),
                       jax.random.normal(keys[2], (n,)), jax.random.normal(keys[3], (n, length, 107)), mask,
                       jnp.arange(n) % 5 == 0, jnp.arange(n) % 2 == 0)


def test_replay_buffer_packs_valid_rows_into_a_ring():
    buffer = ReplayBuffer.create(capacity=8, sequence=3)
    batch = _batch(jax.random.key(0), 6)
    valid = jnp.array([True, False, True, True, False, True])
    buffer = buffer.insert(batch, valid)
    assert int(buffer.size) == 4 and int(buffer.position) == 4 and int(buffer.inserted) == 4
    np.testing.assert_array_equal(buffer.data.reward[:4], batch.reward[valid])
    buffer = buffer.insert(batch, jnp.ones(6, bool))  # wraps: rows 4..7 then 0..1
    assert int(buffer.size) == 8 and int(buffer.position) == 2 and int(buffer.inserted) == 10
    np.testing.assert_array_equal(buffer.data.reward[4:], batch.reward[:4])
    np.testing.assert_array_equal(buffer.data.reward[:2], batch.reward[4:])
    sample = buffer.sample(jax.random.key(1), 32)
    assert sample.obs.shape == (32, 3, 107)
    assert set(np.asarray(sample.reward).tolist()) <= set(np.asarray(buffer.data.reward).tolist())


def test_one_sac_update_lowers_the_critic_loss_on_a_fixed_batch():
    agent = create_agent(jax.random.key(0))
    batch = _batch(jax.random.key(1), 64)
    key = jax.random.key(2)
    target = td_target(agent, batch, jax.random.split(key)[0])
    before = critic_loss(agent, agent.critic, batch, target)[0]
    updated, metrics = update(agent, batch, key, SACConfig())
    after = critic_loss(updated, updated.critic, batch, target)[0]
    assert float(after) < float(before)
    np.testing.assert_allclose(metrics["critic_loss"], before, rtol=1e-5)
    assert int(updated.updates) == 1 and float(metrics["alpha"]) == pytest.approx(1e-3)
    # Target critics move by tau toward the critics.
    expected = jax.tree.map(lambda c, t0: t0 + 1e-3 * (c - t0), updated.critic, agent.target_critic)
    for got, want in zip(jax.tree.leaves(updated.target_critic), jax.tree.leaves(expected)):
        np.testing.assert_allclose(got, want, atol=1e-6)


def _assert_same_step(before, after, step):
    """``after`` - ``before`` is the optimizer ``step`` up to float32 rounding (Adam's first
    step divides each gradient by its own magnitude, so near-zero gradients round freely:
    compared over all parameters at once)."""
    flat = lambda tree: np.concatenate([np.ravel(x) for x in jax.tree.leaves(tree)])  # noqa: E731
    taken, wanted = flat(after) - flat(before), flat(step)
    assert np.linalg.norm(taken - wanted) < 1e-3 * np.linalg.norm(wanted)


@pytest.mark.parametrize("components", [1, 3])
def test_actor_update_reusing_the_critic_encodings_equals_the_full_actor_loss(components):
    """The actor loss values its actions with the critics' encodings of the batch from the
    critic loss: the loss and the actor's step equal those of the textbook actor loss that
    runs the critics again on the observations. A mixture's loss is the expectation over its
    components: each component's reparameterized sample, weighted by the mixture weight."""
    import optax

    config = SACConfig(components=components)
    agent = create_agent(jax.random.key(0), config)
    batch = _batch(jax.random.key(1), 64)
    key = jax.random.key(2)
    updated, metrics = update(agent, batch, key, config)
    actor_key = jax.random.split(key)[1]

    def textbook(params):
        actor = nnx.merge(agent.actor_def, params)
        dist = actor.distribution(batch.obs, batch.mask)
        actions, log_probs = actor.component_samples(dist, actor_key)
        loss = 0.0
        for k in range(components):
            q = jnp.minimum(*agent.critics()(batch.obs, batch.mask, actions[:, k]))
            loss = loss + jnp.exp(dist.log_weights[:, k]) * (jnp.exp(agent.log_alpha) * log_probs[:, k] - q)
        return jnp.mean(loss)

    loss, grads = jax.jit(jax.value_and_grad(textbook))(agent.actor)
    np.testing.assert_allclose(metrics["actor_loss"], loss, rtol=1e-6)
    step, _ = optax.adam(config.actor_lr).update(grads, agent.actor_opt, agent.actor)
    _assert_same_step(agent.actor, updated.actor, step)
    if components == 1:  # one component: the sample the policy acts with
        actor = agent.policy()
        action, log_prob = actor.sample(actor.distribution(batch.obs, batch.mask), actor_key)
        sampled, sampled_log_prob = actor.component_samples(actor.distribution(batch.obs, batch.mask), actor_key)
        np.testing.assert_allclose(sampled[:, 0], action, rtol=1e-6)
        np.testing.assert_allclose(sampled_log_prob[:, 0], log_prob, rtol=1e-5)


def test_cloning_a_mixture_trains_the_nearest_component_and_makes_it_the_heaviest():
    """Relaxed winner-takes-all: the error is mostly the nearest component's, plus the
    cross-entropy of the weights toward it; one component: the plain squared error of the
    mean."""
    actor = Actor(nnx.Rngs(0), InputFeatures(), 6, components=2)
    mean = jnp.array([[[-0.5] * 6, [0.5] * 6]])
    dist = Mixture(mean, jnp.zeros((1, 2, 6)), jnp.log(jnp.array([[0.75, 0.25]])))
    target = jnp.full((1, 6), 0.4)
    expected = (1 - LOSER_SHARE) * 6 * 0.1**2 + LOSER_SHARE * 6 * 0.9**2 - math.log(0.25)
    np.testing.assert_allclose(cloning_error(actor, dist, target), [expected], rtol=1e-6)
    single = Actor(nnx.Rngs(0), InputFeatures(), 6)
    one = Mixture(mean[:, 1:], jnp.zeros((1, 1, 6)), jnp.zeros((1, 1)))
    np.testing.assert_allclose(cloning_error(single, one, target), [6 * 0.1**2], rtol=1e-6)


def test_behaviour_cloned_start_then_sac():
    """bc_start = 1: the first update's actor step is a behaviour-cloning step on the batch's
    expert rows (the critics take their usual step); the second is SAC's."""
    import optax

    config = SACConfig(bc_start=1)
    agent = create_agent(jax.random.key(0), config)
    batch = _batch(jax.random.key(1), 64)

    def cloning(params):
        actor = nnx.merge(agent.actor_def, params)
        mean = actor.mode(actor.distribution(batch.obs, batch.mask))
        error = jnp.sum((mean - batch.action) ** 2, axis=-1)
        return jnp.sum(jnp.where(batch.expert, error, 0.0)) / batch.expert.sum()

    first, metrics = update(agent, batch, jax.random.key(2), config)
    loss, grads = jax.value_and_grad(cloning)(agent.actor)
    np.testing.assert_allclose(metrics["actor_loss"], loss, rtol=1e-6)
    step, _ = optax.adam(config.actor_lr).update(grads, agent.actor_opt, agent.actor)
    _assert_same_step(agent.actor, first.actor, step)
    plain, _ = update(agent, batch, jax.random.key(2), SACConfig())
    for got, want in zip(jax.tree.leaves(first.critic), jax.tree.leaves(plain.critic)):
        np.testing.assert_allclose(got, want, atol=1e-6)  # the critics' step is SAC's
    _, later = update(first, batch, jax.random.key(3), config)
    _, reference = update(first, batch, jax.random.key(3), SACConfig())
    np.testing.assert_allclose(later["actor_loss"], reference["actor_loss"], rtol=1e-6)


def test_learned_temperature_and_behaviour_cloning():
    config = SACConfig(squash=True, learn_alpha=True)
    agent = create_agent(jax.random.key(0), config)
    batch = _batch(jax.random.key(1), 64)
    updated, _ = update(agent, batch, jax.random.key(2), config)
    assert float(updated.log_alpha) != float(agent.log_alpha)
    bc = jax.jit(bc_update)
    first, metrics = bc(agent, batch)
    for _ in range(20):
        first, later = bc(first, batch)
    assert float(later["bc_loss"]) < float(metrics["bc_loss"])


def test_expert_bc_loss_counts_expert_rows_the_critic_prefers():
    batch = _batch(jax.random.key(0), 8)  # rows 0, 2, 4, 6 are expert steps
    error = jnp.sum(batch.action**2, axis=-1)  # a policy whose action is 0 everywhere
    q_data = jnp.array([1.0, 1.0, 1.0, 1.0, -1.0, 1.0, -1.0, 1.0])  # the expert's action is better on rows 0 and 2 only
    loss, share = expert_bc_loss(error, batch, q_data, jnp.zeros(8))
    expected = np.mean(np.sum(np.asarray(batch.action)[[0, 2]] ** 2, axis=-1))
    np.testing.assert_allclose(loss, expected, rtol=1e-6)
    assert float(share) == pytest.approx(2 / 8)
    loss, share = expert_bc_loss(error, batch, -q_data - 2, jnp.zeros(8))  # the critic prefers the policy everywhere
    assert float(loss) == 0.0 and float(share) == 0.0
    loss, share = expert_bc_loss(error, batch, -q_data - 2, jnp.zeros(8), filtered=False)  # every expert row
    expected = np.mean(np.sum(np.asarray(batch.action)[[0, 2, 4, 6]] ** 2, axis=-1))
    np.testing.assert_allclose(loss, expected, rtol=1e-6)
    assert float(share) == pytest.approx(4 / 8)


@pytest.mark.parametrize("components", [1, 2])
def test_expert_bc_pulls_the_mean_action_toward_the_expert_actions(components):
    batch = _batch(jax.random.key(1), 64)

    def expert_error(config):
        config = dataclasses.replace(config, components=components)
        agent = create_agent(jax.random.key(0), config)
        for key in jax.random.split(jax.random.key(2), 30):
            agent, metrics = update(agent, batch, key, config)
        mean = agent.policy()(batch.obs, batch.mask)[0]
        return float(jnp.mean(jnp.sum((mean - batch.action) ** 2, -1)[batch.expert])), metrics

    pure, metrics = expert_error(SACConfig())
    assert "expert_bc_loss" not in metrics
    cloned, metrics = expert_error(SACConfig(expert_bc=1.0))
    assert 0.0 < float(metrics["expert_bc_share"]) <= 0.5  # only expert rows (half the batch) count
    assert cloned < 0.7 * pure


@pytest.mark.parametrize("kind", ["sac", "bc"])
def test_deployed_actor_is_a_polyak_average_of_the_actor(kind):
    """With policy_average = r the deployed parameters follow a_k = a_k-1 + r (actor_k - a_k-1);
    with 0 they are the latest actor."""
    batch = _batch(jax.random.key(1), 64)
    for rate in (0.0, 0.3):
        config = SACConfig(policy_average=rate)
        cloning = jax.jit(lambda a: bc_update(a, batch, config))
        step = (lambda a, k: update(a, batch, k, config)) if kind == "sac" else (lambda a, k: cloning(a))
        agent = create_agent(jax.random.key(0), config)
        expected = agent.actor
        for key in jax.random.split(jax.random.key(2), 3):
            agent = step(agent, key)[0]
            expected = jax.tree.map(lambda e, a: e + rate * (a - e) if rate else a, expected, agent.actor)
        for got, want in zip(jax.tree.leaves(agent.average_actor), jax.tree.leaves(expected)):
            np.testing.assert_allclose(got, want, atol=1e-6)
        moved = any(not np.allclose(a, b) for a, b in zip(jax.tree.leaves(agent.average_actor), jax.tree.leaves(agent.actor)))
        assert moved == bool(rate)
