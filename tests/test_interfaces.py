"""The standard interfaces: Brax ``Env`` (with Brax's wrappers and a Brax trainer) and JaxMARL."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax.envs.wrappers.training import wrap

from mjx_multiarm.env.brax_env import BraxReaching
from mjx_multiarm.env.jaxmarl_env import MultiArmReaching
from mjx_multiarm.env.reaching import EnvConfig
from mjx_multiarm.env.wrappers import TaskBank
from mjx_multiarm.tasks.generate import GenerationSpec, generate_chunk
from mjx_multiarm.tasks.types import take


@pytest.fixture(scope="module")
def mixed_tasks():
    """1- and 2-arm tasks in 2 slots."""
    return generate_chunk(GenerationSpec(count=16, arm_counts=(1, 2), mode="static", seed=11, max_arms=2), 0)


@pytest.fixture(scope="module")
def two_arm_bank(mixed_tasks):
    return TaskBank.from_tasks(take(mixed_tasks, mixed_tasks.num_arms == 2), 2)


def test_brax_env_reset_step_and_wrappers(two_arm_bank):
    env = BraxReaching(two_arm_bank, EnvConfig(max_steps=5))
    assert (env.observation_size, env.action_size) == (2 * 2 * 108, 12)
    starts = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(0), 12))
    assert starts.obs.shape == (12, env.observation_size) and not np.any(starts.done)
    assert len(set(np.asarray(starts.pipeline_state.task.task_id).tolist())) > 1  # reset draws the task with its rng

    wrapped = wrap(env, episode_length=3)  # Brax's vmap, episode and auto-reset wrappers
    batch = jax.jit(wrapped.reset)(jax.random.split(jax.random.PRNGKey(1), 4))
    step = jax.jit(wrapped.step)
    actions = 0.1 * jax.random.normal(jax.random.PRNGKey(2), (4, env.action_size))
    first = step(batch, actions)
    # the Brax step is the environment's step: its joint motion, the team's summed reward
    moved = jax.vmap(env.env.next_joints)(batch.pipeline_state.joints, actions.reshape(4, 2, 6), batch.pipeline_state.task.active)
    ended = np.asarray(first.pipeline_state.collided.any(-1))
    np.testing.assert_allclose(np.asarray(first.pipeline_state.joints)[~ended], np.asarray(moved)[~ended], atol=1e-6)
    np.testing.assert_allclose(first.reward, first.pipeline_state.reward.sum(-1), rtol=1e-6)
    batch = first
    for _ in range(2):
        batch = step(batch, jnp.zeros((4, env.action_size)))
    assert np.all(np.asarray(batch.done) == 1) and np.all(np.asarray(batch.info["steps"]) == 3)
    batch = step(batch, jnp.zeros((4, env.action_size)))  # auto-reset: back to each first state, then one step
    np.testing.assert_array_equal(batch.info["steps"], 1)


@pytest.mark.slow
def test_a_brax_trainer_runs_on_the_environment(mixed_tasks):
    """Brax's evolution-strategies trainer for a few iterations on 1-arm tasks (the README's
    example; Brax 0.14's PPO and SAC need an API jax 0.10 removed)."""
    from brax.training.agents.es.train import train as es

    env = BraxReaching(TaskBank.from_tasks(take(mixed_tasks, mixed_tasks.num_arms == 1), 1), EnvConfig(max_steps=10), tolerance=(0.1, 0.5))
    make_policy, params, metrics = es(env, num_timesteps=400, episode_length=10, population_size=8, num_eval_envs=4, num_evals=2,
                                      seed=0)
    assert np.isfinite(metrics["eval/episode_reward"]) and 0 <= metrics["eval/episode_success"] <= 1
    action, _ = make_policy(params, deterministic=True)(env.reset(jax.random.PRNGKey(0)).obs, jax.random.PRNGKey(1))
    assert action.shape == (env.action_size,)


def test_jaxmarl_view_one_agent_per_arm(two_arm_bank):
    env = MultiArmReaching(two_arm_bank, EnvConfig(max_steps=4))
    assert env.agents == ["arm_0", "arm_1"] and env.num_agents == 2
    assert env.observation_space("arm_0").shape == (2 * 108,) and env.action_space("arm_1").shape == (6,)
    obs, state = env.reset(jax.random.PRNGKey(0))
    assert set(obs) == {"arm_0", "arm_1"} and obs["arm_0"].shape == (216,)
    # each arm's observation is its own decentralized one: itself last in its sequence
    np.testing.assert_array_equal(obs["arm_1"][:214].reshape(2, 107)[-1], state.obs[1, -1])
    actions = {"arm_0": jnp.full(6, 0.02), "arm_1": jnp.full(6, -0.02)}
    step, ended = jax.jit(env.step), False
    for i in range(4):  # the episode ends by step 4 (timeout at the latest), and step() restarts it
        before = state
        obs, state, rewards, dones, infos = step(jax.random.PRNGKey(1 + i), state, actions)
        assert set(dones) == {"arm_0", "arm_1", "__all__"} and set(rewards) == {"arm_0", "arm_1"}
        if bool(dones["__all__"]):
            ended = True
            break
        moved = env.env.next_joints(before.joints, jnp.stack([actions["arm_0"], actions["arm_1"]]), before.task.active)
        np.testing.assert_allclose(state.joints, moved, atol=1e-6)
        assert [float(rewards[a]) for a in env.agents] == pytest.approx(np.asarray(state.reward).tolist())
    assert ended and int(state.step) == 0 and obs["arm_0"].shape == (216,)


def test_jaxmarl_view_needs_one_team_size(mixed_tasks):
    with pytest.raises(ValueError, match="one team size"):
        MultiArmReaching(TaskBank.from_tasks(mixed_tasks, 2))
    with pytest.raises(ValueError, match="one team size"):
        MultiArmReaching(TaskBank.from_tasks(take(mixed_tasks, mixed_tasks.num_arms == 1), 2))
