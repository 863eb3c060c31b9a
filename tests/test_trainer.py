"""The jitted training iteration: rollouts, expert replays on failure only, updates."""

from __future__ import annotations

import dataclasses
import os
import pathlib
import subprocess
import sys
import tempfile

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mjx_multiarm.env.observation import EE_POSE, TARGET_POSE, TARGET_POSE_PREV
from mjx_multiarm.env.reaching import EnvConfig, ReachingEnv
from mjx_multiarm.env.wrappers import TaskBank
from mjx_multiarm.expert.solve import solve_task
from mjx_multiarm.expert.store import ExpertStore, ExpertTable, save_experts
from mjx_multiarm.tasks.types import take, with_slots
from train.agent import SACConfig
from train.curriculum import LEVELS
from train.relabel import CollisionRelabeller
from train.trainer import (
    Demonstrations,
    Queue,
    TrainConfig,
    Trainer,
    hindsight_transitions,
)


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


@pytest.fixture(scope="module")
def sharing(one_arm):
    """The trainer whose compiled iteration the expert and hindsight tests share: experts in
    their own buffer (expert_share 0.25), 3 hindsight copies of every transition, 8-step
    rollouts of 4-step episodes, and a tolerance so tight that every episode fails."""
    tasks, store = one_arm
    return _trainer(tasks, store, (1e-4, 1e-4), expert_share=0.25, expert_buffer=512, hindsight=3, rollout_steps=8)


@pytest.mark.xdist_group("trainer")  # one worker compiles the shared trainer for all of them
def test_expert_experience_enters_only_for_failed_episodes(sharing):
    # Tight tolerance, 4-step episodes: every episode fails by timeout and queues its expert.
    state, metrics = sharing.iteration(sharing.init(jax.random.key(0)))
    assert int(metrics["ended"]) == 8 and int(metrics["successes"]) == 0
    assert int(state.expert_steps) > 0  # two queued failures were replayed
    assert int(state.buffer.inserted) == 4 * 8 * 4  # 4 envs x 8 steps x (1 + 3 hindsight); experts in their own buffer
    assert int(state.expert_buffer.inserted) == int(state.expert_steps)
    assert int(state.failed.count) == 6  # the other six wait for the next iterations
    assert np.isfinite(float(metrics["critic_loss"]))  # past warm-up: updates ran
    # The same environments reset at a loose tolerance: every episode succeeds at its first
    # step, nothing is queued or replayed (the same compiled iteration: the tolerance is state).
    state = sharing.init(jax.random.key(0))
    state = state.replace(envs=jax.jit(sharing.autoreset.reset, static_argnums=1)(jax.random.key(1), 4, jnp.asarray([10.0, 4.0])))
    state, metrics = sharing.iteration(state)
    assert int(metrics["successes"]) == int(metrics["ended"]) == 32
    assert int(state.expert_steps) == 0 and int(state.failed.count) == 0


@pytest.mark.slow
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


@pytest.mark.xdist_group("trainer")
def test_hindsight_goals_come_from_the_same_episode(sharing):
    """Every relabelled transition's goal is the pose its arm reached at that step or a later
    one of the same episode within the rollout (the iteration's relabelled copies: the test above)."""
    trainer = sharing

    envs, step = trainer.autoreset.reset(jax.random.key(1), 4), jax.jit(trainer.autoreset.step)
    steps = []
    for t in range(8):
        actions = jax.random.uniform(jax.random.key(t), (4, 1, 6), minval=-1, maxval=1)
        after_reset, stepped = step(envs, actions)
        steps.append((envs.env, actions, stepped))
        envs = after_reset
    before, actions, stepped = jax.tree.map(lambda *x: jnp.stack(x), *steps)
    relabel = jax.jit(lambda *args: hindsight_transitions(trainer.env, *args, 5, jax.random.key(2)))
    transitions, valid = relabel(before, actions, stepped)
    assert np.asarray(valid).all() and np.asarray(stepped.done).any()  # episodes of 4 steps end inside the rollout
    reached = np.asarray(stepped.obs)[..., 0, -1, EE_POSE]  # [T, B, 7]: each step's end-effector pose
    goals = np.asarray(transitions.next_obs)[:, -1, TARGET_POSE].reshape(5, 8, 4, 7)
    episode = np.cumsum(np.concatenate([np.zeros((1, 4)), np.asarray(stepped.done)[:-1]]), 0)  # [T, B] episode index
    later_steps = set()
    for c, t, b in np.ndindex(5, 8, 4):
        matches = np.flatnonzero(np.abs(reached[:, b] - goals[c, t, b]).max(-1) < 1e-6)
        assert matches.size and all(k >= t and episode[k, b] == episode[t, b] for k in matches), (c, t, b, matches)
        later_steps.update(int(k) - t for k in matches)
    np.testing.assert_array_equal(np.asarray(transitions.obs)[:, -1, TARGET_POSE], np.asarray(transitions.obs)[:, -1, TARGET_POSE_PREV])
    assert 0 in later_steps and max(later_steps) >= 2
    own_pose = np.abs(goals - reached[None]).max(-1).reshape(-1) < 1e-6  # goal = the pose this step reached
    own_reward = np.asarray(transitions.reward)[own_pose]  # reached (0.01) + team (1), or reached and collided (-0.05)
    assert np.asarray(transitions.terminal)[own_pose].all() and np.isclose(own_reward[:, None], [1.01, -0.04]).any(-1).all() and (own_reward > 1).any()


@pytest.mark.parametrize("overrides, message", [
    ({"num_envs": 0}, "num_envs must be >= 1"),
    ({"bc": True, "expert": False}, "needs expert=True"),
    ({"noise_decay": -1.0}, "noise_decay must be >= 0"),
    ({"hindsight": -1}, "hindsight must be >= 0"),
    ({"hindsight": 2, "bc": True}, "behaviour cloning"),
    ({"sac": {"expert_bc": -1.0}}, "expert_bc must be >= 0"),
    ({"sac": {"policy_average": 1.5}}, r"policy_average must be in \[0, 1\]"),
    ({"sac": {"gamma": 1.5}}, r"gamma must be in \(0, 1\]"),
    ({"sac": {"expert_bc": 1.0}, "expert": False}, "expert_bc adds behaviour cloning"),
    ({"sac": {"expert_bc": 1.0}, "bc": True}, "expert_bc adds behaviour cloning"),
    ({"expert_prefill": 8, "expert": False}, "expert_prefill replays expert demonstrations"),
])
def test_inconsistent_train_configs_are_rejected(overrides, message):
    """Each class checks its own fields (SACConfig's when it is built), TrainConfig the combinations."""
    with pytest.raises(ValueError, match=message):
        TrainConfig(**{k: SACConfig(**v) if k == "sac" else v for k, v in overrides.items()})


def test_queue_is_a_bounded_fifo_of_pytrees():
    queue = Queue.create(4)
    queue = queue.push(np.array([True, False, True]), np.array([7, 8, 9]))
    queue, rows, valid = queue.pop(3)
    assert rows[valid].tolist() == [7, 9] and int(queue.count) == 0
    queue = queue.push(np.ones(6, bool), np.arange(6))  # overflow keeps the newest four
    queue, rows, valid = queue.pop(4)
    assert rows[valid].tolist() == [2, 3, 4, 5]
    pairs = Queue.create(3, (jnp.zeros((), jnp.int32), jnp.zeros((2, 6))))
    pairs = pairs.push(np.array([False, True]), (np.array([1, 2]), np.stack([np.zeros((2, 6)), np.ones((2, 6))])))
    _, (rows, joints), valid = pairs.pop(2)
    assert valid.tolist() == [True, False] and int(rows[0]) == 2 and np.all(joints[0] == 1)


@pytest.mark.slow
def test_collision_states_are_queued_and_relabelled_with_plans(generated):
    """Every step where a team collides queues its joints before the step; the relabeller plans
    BiRRT from a queued state to the goal configuration, and the next iteration replays the
    plan from that state as expert transitions."""
    rows = np.flatnonzero(generated.num_arms == 2)[:2]
    tasks = with_slots(take(generated, rows), 2)
    base_pos = tasks.base_pos.copy()
    base_pos[0, 1] = base_pos[0, 0] + 0.05  # task 0: the arms stand inside each other, every step collides
    tasks = dataclasses.replace(tasks, base_pos=base_pos)
    env = ReachingEnv(2, EnvConfig(max_steps=50, end_on_collision=False))
    bank = TaskBank.from_tasks(tasks, 2)
    path = pathlib.Path(tempfile.mkdtemp()) / "two.experts"
    save_experts(path, ExpertTable.from_results([solve_task(tasks, i) for i in range(2)]))
    config = TrainConfig(num_envs=2, rollout_steps=3, updates_per_iteration=1, batch_size=8, buffer_size=2048, warmup=10**6,
                         expert_replays=1, curriculum=False, relabel=2, relabel_queue=8, expert_share=0.25, expert_buffer=2048)
    trainer = Trainer(env, bank, Demonstrations.from_store(ExpertStore(path), bank, env, 48), config)
    relabeller = CollisionRelabeller(trainer)
    state = trainer.init(jax.random.key(0))
    state, metrics = trainer.iteration(state, relabeller.empty())  # one compiled iteration for both calls
    rows_queued, joints_queued = jax.device_get(state.collisions.items)
    count = int(state.collisions.count)
    assert count >= 3 and int(metrics["queued_collisions"]) == count  # task 0's env: three colliding steps
    assert np.all(rows_queued[:count] == 0)
    np.testing.assert_allclose(joints_queued[:count], np.broadcast_to(tasks.start_joints[0], (count, 2, 6)), atol=1e-6)

    start = np.asarray(tasks.start_joints[1], np.float32)
    state = state.replace(collisions=Queue.create(8, (jnp.zeros((), jnp.int32), jnp.zeros((2, 6))))
                          .push(np.ones(2, bool), (np.array([1, 0]), np.stack([start, tasks.start_joints[0]]))))
    state, batch, stats = relabeller(state, iteration=1)
    assert stats["relabel_planned"] == 2 and stats["relabel_solved"] == 1  # task 0's state collides: no plan
    assert int(state.collisions.count) == 0 and batch.rows[0] == 1 and batch.lengths[0] > 0 and batch.lengths[1] == 0
    before = int(state.expert_buffer.inserted)
    state, _ = trainer.iteration(state, batch)
    replayed = int(state.expert_buffer.inserted) - before
    assert replayed >= 2 * int(batch.lengths[0])  # both arms of every planned step (plus any failed-task replay)
    first = jax.tree.map(lambda x: x[before : before + 2], state.expert_buffer.data)
    reset = env.reset(None, bank.take(1).replace(start_joints=jnp.asarray(start)))
    np.testing.assert_allclose(first.obs, reset.obs, atol=1e-5)
    np.testing.assert_allclose(first.action, batch.actions[0, 0], atol=1e-6)


SHARDED = """
import jax, numpy as np
from mjx_multiarm.env.reaching import EnvConfig, ReachingEnv
from mjx_multiarm.tasks.generate import GenerationSpec, generate_chunk
from mjx_multiarm.tasks.types import with_slots
from mjx_multiarm.env.wrappers import TaskBank
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


@pytest.mark.slow
def test_data_parallel_over_two_host_devices(tmp_path):
    """The training iteration splits environments and batches across 2 (forced host) devices."""
    script = tmp_path / "sharded.py"
    script.write_text(SHARDED)
    env = {**os.environ, "XLA_FLAGS": "--xla_force_host_platform_device_count=2", "JAX_PLATFORMS": "cpu"}
    result = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, env=env, timeout=900)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "sharded ok 24" in result.stdout


@pytest.mark.xdist_group("trainer")
def test_expert_share_keeps_demonstrations_in_their_own_buffer(one_arm, sharing):
    """expert_share = 0.25: expert replays fill the expert buffer (not the main one) and every
    batch holds exactly a quarter of expert transitions, however many policy rows arrive."""
    tasks, store = one_arm
    trainer = sharing
    state, _ = trainer.iteration(trainer.init(jax.random.key(0)))
    assert int(state.buffer.inserted) == 128 and not np.asarray(state.buffer.data.expert[:128]).any()
    assert int(state.expert_buffer.inserted) == int(state.expert_steps) > 0
    batch = trainer._sample(state, jax.random.key(3), state.agent.updates)
    assert int(np.asarray(batch.expert).sum()) == 4  # round(0.25 x 16)
    cloning = _trainer(tasks, store, (1e-4, 1e-4), expert_share=0.25, expert_buffer=512, sac=SACConfig(bc_start=5))
    for updates, experts in ((4, 16), (5, 4)):  # a behaviour-cloned start draws whole batches of expert transitions
        assert int(np.asarray(cloning._sample(state, jax.random.key(3), jnp.asarray(updates)).expert).sum()) == experts
    with pytest.raises(ValueError, match="expert_share"):
        TrainConfig(expert_share=0.25, expert=False)
    with pytest.raises(ValueError, match="expert_buffer"):
        _trainer(tasks, store, (1e-4, 1e-4), expert_share=0.25, expert_buffer=8)


def test_curriculum_by_team_resets_each_team_size_at_its_own_level(generated):
    """With one curriculum per team size, a reset 2-arm task gets the 2-arm level's tolerance
    and a 1-arm task the 1-arm level's; the run's level is the lowest of the bank's teams."""
    tasks = take(generated, np.flatnonzero(generated.num_arms <= 2)[:8])
    env = ReachingEnv(2, EnvConfig(max_steps=4))
    trainer = Trainer(env, TaskBank.from_tasks(tasks, 2), None,
                      TrainConfig(num_envs=16, rollout_steps=2, updates_per_iteration=1, batch_size=8, buffer_size=512, warmup=10**6,
                                  expert=False, curriculum_by_team=True))
    state = trainer.init(jax.random.key(0))
    curriculum = state.curriculum.replace(groups=state.curriculum.groups.replace(level=jnp.asarray([5, 2])))
    table = trainer._tolerances(curriculum)
    np.testing.assert_allclose(np.asarray(table), LEVELS[[5, 2]])
    envs = trainer.autoreset.reset(jax.random.key(1), 16, table)
    teams = np.asarray(envs.env.task.active.sum(-1))
    assert set(teams.tolist()) == {1, 2}
    np.testing.assert_allclose(np.asarray(envs.env.tolerance), LEVELS[np.where(teams == 1, 5, 2)])
    assert int(trainer.level(curriculum)) == 2


@pytest.mark.xdist_group("trainer")
def test_prefill_replays_distinct_experts_into_the_expert_buffer(one_arm, sharing):
    """prefill(3) replays the experts of 3 different tasks: their steps (one arm each) enter
    the expert buffer of expert_share (the main buffer without it); more than the bank's
    experts fail clearly."""
    tasks, store = one_arm
    for trainer, buffer in ((sharing, "expert_buffer"), (_trainer(tasks, store, (1e-4, 1e-4)), "buffer")):
        state = trainer.prefill(trainer.init(jax.random.key(0)), 3, seed=1, chunk=2)
        filled = getattr(state, buffer)
        assert int(filled.inserted) == int(state.expert_steps) and np.asarray(filled.data.expert[: int(filled.size)]).all()
        assert np.asarray(trainer.demos.lengths).min() >= 4 and int(state.expert_steps) == 3 * 4  # cut at the 4-step episodes
    with pytest.raises(ValueError, match="cannot prefill 5"):
        trainer.prefill(trainer.init(jax.random.key(0)), 5)


@pytest.mark.slow
def test_shield_teacher_replaces_colliding_motions_in_its_share_of_the_environments(generated):
    """shield_teacher=0.5: in the first half of the environments, every arm whose motion the
    shield replaced executes the replacement (as an action) and is flagged; the other half
    and the arms it let pass keep the policy's actions. An iteration stores the flagged arm
    steps as expert transitions in the expert buffer of expert_share."""
    from mjx_multiarm.env.shield import PROPOSED

    tasks = take(generated, np.flatnonzero((generated.num_arms >= 2) & (generated.num_arms <= 4))[:48])
    env = ReachingEnv(4, EnvConfig(max_steps=8, end_on_collision=False))
    bank = TaskBank.from_tasks(tasks, 4)
    config = TrainConfig(num_envs=48, rollout_steps=2, updates_per_iteration=1, batch_size=8, buffer_size=4096, warmup=10**6,
                         expert=False, curriculum=False, shield_teacher=0.5)
    trainer = Trainer(env, bank, None, config)
    t = bank.tasks.replace(start_joints=bank.tasks.start_joints + 0.5 * (bank.tasks.goal_joints - bank.tasks.start_joints))
    states = jax.jit(jax.vmap(lambda task: env.reset(None, task)))(t)
    drive = env.joint_deltas_to_actions(t.goal_joints - states.joints)  # full speed to the goal: some teams collide
    actions, replaced = (np.asarray(x) for x in jax.jit(trainer._shielded)(states, drive))
    executed, motion, _ = jax.jit(jax.vmap(env.shield))(t.base_pos, t.base_quat, states.joints,
                                               env.next_joints(states.joints, drive, t.active), t.active)
    teacher, active = slice(0, 24), np.asarray(t.active)
    expected = (np.asarray(motion) != PROPOSED) & active
    np.testing.assert_array_equal(replaced[teacher], expected[teacher])
    assert replaced[teacher].any() and not replaced[24:].any()
    np.testing.assert_array_equal(actions[~replaced], np.asarray(drive)[~replaced])
    np.testing.assert_allclose(np.asarray(env.next_joints(states.joints, actions, t.active))[teacher][expected[teacher]],
                               np.asarray(executed)[teacher][expected[teacher]], atol=1e-5)

    none_planned = Demonstrations(jnp.zeros((1, 4, 6)), jnp.zeros(bank.size, jnp.int32), jnp.zeros(bank.size, jnp.int32), 2)
    shared = Trainer(env, bank, none_planned, dataclasses.replace(config, expert=True, expert_share=0.25, expert_buffer=4096,
                                                                  expert_replays=1))
    state, metrics = jax.jit(lambda s: shared._rollout(s, jax.random.key(3)))(shared.init(jax.random.key(0)))
    stored = int(state.expert_buffer.inserted)
    assert stored == int(metrics["shielded_arm_steps"]) and np.asarray(state.expert_buffer.data.expert[:stored]).all()
