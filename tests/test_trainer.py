"""The jitted training iteration: rollouts, expert replays on failure only, updates."""

from __future__ import annotations

import os
import subprocess
import sys

import jax
import numpy as np
import pytest

from mjx_multiarm.env import EnvConfig, ReachingEnv
from mjx_multiarm.expert.solve import solve_task
from mjx_multiarm.expert.store import ExpertStore, ExpertTable, save_experts
from mjx_multiarm.tasks.types import take, with_slots
from mjx_multiarm.wrappers import TaskBank
from train.agent import SACConfig
from train.trainer import Demonstrations, FailedQueue, TrainConfig, Trainer


@pytest.fixture(scope="module")
def one_arm(generated, tmp_path_factory):
    """Four 1-arm tasks in one slot and their expert file."""
    tasks = with_slots(take(generated, np.flatnonzero(generated.num_arms == 1)[:4]), 1)
    path = tmp_path_factory.mktemp("experts") / "one_arm.experts"
    save_experts(path, ExpertTable.from_results([solve_task(tasks, i) for i in range(4)]))
    return tasks, ExpertStore(path)


def _trainer(tasks, store, tolerance, expert=True, **overrides):
    env = ReachingEnv(1, EnvConfig(max_steps=4, tolerance=tolerance))
    bank = TaskBank.from_tasks(tasks, 1)
    config = TrainConfig(**{"num_envs": 4, "rollout_steps": 4, "updates_per_iteration": 2, "batch_size": 16, "buffer_size": 2048,
                            "warmup": 8, "expert": expert, "expert_replays": 2, "curriculum": False, **overrides})
    return Trainer(env, bank, Demonstrations.from_store(store, bank, env, 48), config)


def test_expert_experience_enters_only_for_failed_episodes(one_arm):
    tasks, store = one_arm
    # Tight tolerance, 4-step episodes: every episode fails by timeout and queues its expert.
    failing = _trainer(tasks, store, (1e-4, 1e-4))
    state = failing.init(jax.random.key(0))
    state, metrics = failing.iteration(state)
    assert int(metrics["ended"]) == 4 and int(metrics["successes"]) == 0
    assert int(state.expert_steps) > 0  # two queued failures were replayed
    assert int(state.buffer.inserted) == 16 + int(state.expert_steps)  # 4 envs x 4 steps + expert steps
    assert int(state.failed.count) == 2  # the other two wait for the next iteration
    assert np.isfinite(float(metrics["critic_loss"]))  # past warm-up: updates ran
    # Loose tolerance: every episode succeeds at its first step, nothing is queued or replayed.
    succeeding = _trainer(tasks, store, (10.0, 4.0))
    state = succeeding.init(jax.random.key(0))
    state, metrics = succeeding.iteration(state)
    assert int(metrics["successes"]) == int(metrics["ended"]) == 16
    assert int(state.expert_steps) == 0 and int(state.failed.count) == 0
    # Without experts, failures are not queued.
    plain = _trainer(tasks, store, (1e-4, 1e-4), expert=False)
    state, _ = plain.iteration(plain.init(jax.random.key(0)))
    assert int(state.expert_steps) == 0 and int(state.failed.count) == 0


def test_noise_schedule_narrows_exploration_at_tight_levels(one_arm):
    """With noise_decay 1 at the last level (1 cm, a tenth of the first level's 10 cm) the
    rollout actions stay within a tenth of the fixed standard-deviation bound of the mean
    (and, the bound moving in log space, an untrained policy's noise shrinks ~sqrt(10)x)."""
    tasks, store = one_arm

    def deviations(noise_decay):
        trainer = _trainer(tasks, store, (1e-4, 1e-4), expert=False, warmup=10**6, curriculum=True, start_level=21,
                           noise_decay=noise_decay)
        state, _ = trainer.iteration(trainer.init(jax.random.key(0)))
        data = jax.tree.map(lambda x: x[: int(state.buffer.size)], state.buffer.data)
        mean, _ = state.agent.policy()(data.obs, data.mask)
        return np.abs(np.asarray(data.action - mean))

    fixed, scheduled = deviations(0.0), deviations(1.0)
    assert scheduled.max() <= 0.1 * np.sqrt(0.1) * 6  # six standard deviations of the narrowed bound
    assert scheduled.mean() < 0.5 * fixed.mean()


@pytest.mark.parametrize("overrides, message", [
    ({"num_envs": 0}, "num_envs must be >= 1"),
    ({"bc": True, "expert": False}, "needs expert=True"),
    ({"noise_decay": -1.0}, "noise_decay must be >= 0"),
    ({"sac": SACConfig(expert_bc=-1.0)}, "expert_bc must be >= 0"),
    ({"sac": SACConfig(expert_bc=1.0), "expert": False}, "expert_bc adds behaviour cloning"),
    ({"sac": SACConfig(expert_bc=1.0), "bc": True}, "expert_bc adds behaviour cloning"),
])
def test_inconsistent_train_configs_are_rejected(overrides, message):
    with pytest.raises(ValueError, match=message):
        TrainConfig(**overrides)


def test_failed_queue_is_a_bounded_fifo():
    queue = FailedQueue.create(4)
    queue = queue.push(np.array([True, False, True]), np.array([7, 8, 9]))
    queue, rows, valid = queue.pop(3)
    assert rows[valid].tolist() == [7, 9] and int(queue.count) == 0
    queue = queue.push(np.ones(6, bool), np.arange(6))  # overflow keeps the newest four
    queue, rows, valid = queue.pop(4)
    assert rows[valid].tolist() == [2, 3, 4, 5]


SHARDED = """
import jax, numpy as np
from mjx_multiarm.env import EnvConfig, ReachingEnv
from mjx_multiarm.tasks.generate import GenerationSpec, generate_chunk
from mjx_multiarm.tasks.types import with_slots
from mjx_multiarm.wrappers import TaskBank
from train.trainer import TrainConfig, Trainer

assert len(jax.devices()) == 2
tasks = with_slots(generate_chunk(GenerationSpec(count=4, arm_counts=(1,), mode="static", seed=5, chunk_size=4), 0), 1)
env = ReachingEnv(1, EnvConfig(max_steps=8))
config = TrainConfig(num_envs=4, rollout_steps=2, updates_per_iteration=2, batch_size=8, buffer_size=256, warmup=4,
                     expert=False, curriculum=False)
trainer = Trainer(env, TaskBank.from_tasks(tasks, 1), None, config, jax.devices())
state = trainer.init(jax.random.key(0))
for _ in range(3):
    state, metrics = trainer.iteration(state)
joints = state.envs.env.joints
assert len(joints.sharding.device_set) == 2 and joints.sharding.spec[0] == "data", joints.sharding
assert np.isfinite(float(metrics["critic_loss"]))
print("sharded ok", int(state.env_steps))
"""


def test_data_parallel_over_two_host_devices(tmp_path):
    """The training iteration splits environments and batches across 2 (forced host) devices."""
    script = tmp_path / "sharded.py"
    script.write_text(SHARDED)
    env = {**os.environ, "XLA_FLAGS": "--xla_force_host_platform_device_count=2", "JAX_PLATFORMS": "cpu"}
    result = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, env=env, timeout=900)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "sharded ok 24" in result.stdout
