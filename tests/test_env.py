"""The reaching environment: dynamics, rewards, invariances, padding, wrappers, bad input."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import facing_pair, make_tasks, random_joints, rollout

from mjx_multiarm.env.reaching import CONTROL_PERIOD, EnvConfig, ReachingEnv
from mjx_multiarm.env.scripted import ik_actions
from mjx_multiarm.env.wrappers import AutoReset, TaskBank, make_episodes, replay_actions
from mjx_multiarm.geometry.collision import scene_contacts
from mjx_multiarm.geometry.evaluate import base_pose_arrays
from mjx_multiarm.geometry.kinematics import forward_kinematics
from mjx_multiarm.geometry.robot import load_arm
from mjx_multiarm.geometry.transforms import quat_mul, yaw_quat
from mjx_multiarm.tasks.types import Tasks, take, with_slots


def teams_of(tasks: Tasks, arms: int, slots: int) -> TaskBank:
    """The generated tasks with ``arms`` arms, in a bank of ``slots`` slots."""
    return TaskBank.from_tasks(take(tasks, tasks.num_arms == arms), slots)




@pytest.fixture(scope="module")
def env1():
    return ReachingEnv(1, EnvConfig(max_steps=150))


@pytest.fixture(scope="module")
def scripted(generated, env1):
    """The scripted IK controller on the generated 1-arm tasks: (bank, final, states, actions)."""
    bank = teams_of(generated, 1, 1)
    return bank, *rollout(env1, 150)(bank.tasks, jnp.asarray([0.02, 0.1]))


def test_scripted_ik_solves_most_one_arm_tasks(scripted):
    bank, final, states, _ = scripted
    success = np.asarray(final.success)
    assert success.mean() >= 0.7, success.mean()
    assert np.all(np.asarray(final.done))
    # Success means both tolerances hold at that step; the team reward is paid once.
    ee = np.asarray(final.arms.ee_pos - final.arms.target_pos)[success, 0]
    assert np.all(np.linalg.norm(ee, axis=-1) < 0.02)
    returns = np.asarray(states.reward).sum(axis=0)[:, 0]
    np.testing.assert_allclose(returns[success], 1.01, atol=1e-6)  # the final step only (no prior reach)
    assert np.all(returns[~success] <= 0.0)  # failures end in a collision, never a success
    # Per-step joint motion never exceeds the velocity limit times the control period.
    joints = np.concatenate([np.asarray(bank.tasks.start_joints)[None], np.asarray(states.joints)])
    limit = load_arm().velocity_limit * CONTROL_PERIOD
    assert np.all(np.abs(np.diff(joints, axis=0)) <= limit + 1e-6)


def _pose_errors(states) -> np.ndarray:
    """Position error + 0.2 m/rad x orientation error [..., A], in numpy (independent of the env)."""
    position = np.linalg.norm(np.asarray(states.arms.ee_pos - states.arms.target_pos, np.float64), axis=-1)
    q1, q2 = (np.asarray(q, np.float64) for q in (states.arms.ee_quat, states.arms.target_quat))
    q1, q2 = (q / np.linalg.norm(q, axis=-1, keepdims=True) for q in (q1, q2))
    cos_half = np.abs(np.sum(q1 * q2, axis=-1))
    sin_half = np.linalg.norm(q1[..., :1] * q2[..., 1:] - q2[..., :1] * q1[..., 1:] - np.cross(q1[..., 1:], q2[..., 1:]), axis=-1)
    return position + 0.2 * 2 * np.arctan2(sin_half, cos_half)


def test_potential_shaping_pays_for_progress_and_telescopes(generated, scripted):
    """With shaping k each step's reward gains k (e_t - e_t+1), e = position error + 0.2 x
    orientation error; an episode's shaped return is the paper's plus k (e_0 - e_T)."""
    bank, final, states, _ = scripted
    k = 0.5
    env = ReachingEnv(1, EnvConfig(max_steps=150, shaping=k))
    shaped_final, shaped, _ = rollout(env, 150)(bank.tasks, jnp.asarray([0.02, 0.1]))
    np.testing.assert_array_equal(shaped.joints, states.joints)  # shaping changes rewards only
    start = jax.jit(jax.vmap(lambda task: env.reset(None, task)))(bank.tasks)
    errors = np.concatenate([_pose_errors(start)[None], _pose_errors(states)])[..., 0]  # [T + 1, B]
    running = np.arange(150)[:, None] < np.asarray(final.step)[None]
    extra = np.asarray(shaped.reward - states.reward)[..., 0]
    np.testing.assert_allclose(extra[running], (k * (errors[:-1] - errors[1:]))[running], atol=2e-5)
    assert not extra[~running].any()  # finished episodes pay nothing
    last = errors[np.asarray(final.step), np.arange(bank.size)]
    np.testing.assert_allclose(extra.sum(0), k * (errors[0] - last), atol=1e-4)
    with pytest.raises(ValueError, match="shaping must be >= 0"):
        EnvConfig(shaping=-0.1)


def test_dynamic_targets_move_at_task_speed_and_can_be_tracked(generated):
    env = ReachingEnv(1, EnvConfig(max_steps=300, dynamic_targets=True))
    bank = teams_of(generated, 1, 1)
    final, states, _ = rollout(env, 300)(bank.tasks, jnp.asarray([0.02, 0.1]))
    arm, tasks = load_arm(), bank.tasks
    start = forward_kinematics(arm, tasks.base_pos, tasks.base_quat, tasks.dynamic_start_joints).ee_pos
    reset = jax.jit(jax.vmap(lambda task: env.reset(None, task)))(tasks)
    np.testing.assert_allclose(reset.arms.target_pos, start, atol=1e-5)
    running = ~np.asarray(states.done[4])  # episodes still going after 5 steps
    moved = np.linalg.norm(np.asarray(states.arms.target_pos[4] - start), axis=-1)[running, 0]
    expected = np.asarray(tasks.speed)[running] * 5 * CONTROL_PERIOD
    assert running.sum() >= 10
    np.testing.assert_allclose(moved, expected, rtol=0.1)
    assert np.asarray(final.success).mean() >= 0.6
    static = ReachingEnv(1, EnvConfig(max_steps=300))
    np.testing.assert_array_equal(static.reset(None, take_row(tasks, 0)).arms.target_pos, tasks.target_pos[0])


def take_row(tasks: Tasks, i: int) -> Tasks:
    return jax.tree.map(lambda x: x[i], tasks)


def _moved_tasks(tasks: Tasks, yaw: float, shift) -> Tasks:
    """Every base and target rotated by ``yaw`` about the world z axis, then shifted."""
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    turn = np.asarray(yaw_quat(np.float64(yaw)), np.float64)

    def pose(pos, quat):
        return pos @ rot.T + np.array([*shift, 0.0]), np.asarray(quat_mul(jnp.asarray(turn), jnp.asarray(quat)), np.float64)

    base_pos, base_quat = pose(tasks.base_pos, tasks.base_quat)
    target_pos, target_quat = pose(tasks.target_pos, tasks.target_quat)
    return tasks.replace(base_pos=base_pos, base_quat=base_quat, target_pos=target_pos, target_quat=target_quat)


def random_policy(seed: int):
    """Actions drawn from a fixed sequence (the state's step counter picks the draw)."""

    def policy(state):
        return jax.random.uniform(jax.random.fold_in(jax.random.key(seed), state.step), state.joints.shape, minval=-1, maxval=1)

    return policy


def test_moving_the_whole_scene_changes_no_observation_or_reward(generated):
    tasks = take(generated, np.flatnonzero(generated.num_arms == 3)[:4])
    tasks = with_slots(tasks, 3)
    env = ReachingEnv(3, EnvConfig(max_steps=40))
    run = rollout(env, 25, random_policy(3))
    tolerance = jnp.asarray([0.3, 1.5])  # loose, so that reach rewards occur
    _, here, _ = run(TaskBank.from_tasks(tasks, 3).tasks, tolerance)
    _, there, _ = run(TaskBank.from_tasks(_moved_tasks(tasks, 2.1, (3.0, -1.5)), 3).tasks, tolerance)
    np.testing.assert_allclose(here.obs, there.obs, atol=2e-4)
    np.testing.assert_array_equal(here.obs_mask, there.obs_mask)
    np.testing.assert_array_equal(here.reward, there.reward)
    np.testing.assert_array_equal(here.collided, there.collided)
    assert np.asarray(here.reward).any()


@pytest.mark.parametrize("shaping", [0.0, pytest.param(0.5, marks=pytest.mark.slow)])
def test_hindsight_targets_equal_an_episode_run_with_those_targets(generated, shaping):
    """Relabelling step t with the poses reached at step k gives exactly what the environment
    returns when the same actions are run on the task whose targets are those poses."""
    tasks = with_slots(take(generated, np.flatnonzero(generated.num_arms == 3)[:4]), 3)
    env = ReachingEnv(3, EnvConfig(max_steps=12, shaping=shaping))
    run = rollout(env, 10, lambda state: 0.3 * random_policy(7)(state))  # slow: few collisions
    tolerance = jnp.asarray([0.05, 0.3])
    _, states, _ = run(TaskBank.from_tasks(tasks, 3).tasks, tolerance)
    goal_step = 5
    goal = jax.tree.map(lambda x: x[goal_step], states)
    retargeted = tasks.replace(target_pos=np.asarray(goal.arms.ee_pos, np.float64), target_quat=np.asarray(goal.arms.ee_quat, np.float64))
    _, truth, _ = run(TaskBank.from_tasks(retargeted, 3).tasks, tolerance)
    start = jax.jit(jax.vmap(lambda task: env.reset(None, task, tolerance)))(TaskBank.from_tasks(tasks, 3).tasks)
    before = jax.tree.map(lambda first, rest: jnp.concatenate([first[None], rest[:-1]]), start, states)
    relabelled = jax.jit(jax.vmap(jax.vmap(env.with_achieved_targets), in_axes=(0, 0, None)))(before, states, goal)
    def running(done):  # [T, B]: the episode had not ended before this step (afterwards it is frozen)
        return ~np.concatenate([np.zeros((1, 4), bool), np.cumsum(np.asarray(done), 0)[:-1] > 0])

    live = running(states.done) & running(truth.done)
    assert live[: goal_step + 1].sum() >= 8
    np.testing.assert_allclose(np.asarray(relabelled.obs)[live], np.asarray(truth.obs)[live], atol=2e-5)
    np.testing.assert_allclose(np.asarray(relabelled.reward)[live], np.asarray(truth.reward)[live], atol=1e-6)
    assert shaping == 0 or np.asarray(relabelled.reward)[live].all()  # the shaping term pays on every step
    for name in ("reached", "success", "done", "truncated"):
        np.testing.assert_array_equal(np.asarray(getattr(relabelled, name))[live], np.asarray(getattr(truth, name))[live], err_msg=name)
    at_goal = running(states.done)[goal_step] & ~np.asarray(states.collided[goal_step]).any(-1)
    assert at_goal.any() and np.asarray(relabelled.success[goal_step])[at_goal].all()  # a pose reaches itself
    with pytest.raises(ValueError, match="static targets"):
        ReachingEnv(3, EnvConfig(dynamic_targets=True)).with_achieved_targets(goal, goal, goal)


@pytest.mark.slow
def test_three_arm_task_is_identical_in_three_and_ten_slots(generated):
    tasks = take(generated, np.flatnonzero(generated.num_arms == 3)[:4])
    small, large = ReachingEnv(3, EnvConfig(max_steps=40)), ReachingEnv(10, EnvConfig(max_steps=40))
    tolerance = jnp.asarray([0.3, 1.5])

    def padded_policy(state):  # the same actions for the 3 arms, NaN garbage in empty slots
        actions = random_policy(5)(state)[:3]
        return jnp.concatenate([actions, jnp.full((7, 6), jnp.nan)])

    _, s3, _ = rollout(small, 25, lambda state: random_policy(5)(state)[:3])(TaskBank.from_tasks(tasks, 3).tasks, tolerance)
    _, s10, _ = rollout(large, 25, padded_policy)(TaskBank.from_tasks(tasks, 10).tasks, tolerance)
    np.testing.assert_allclose(s10.obs[:, :, :3, -3:], s3.obs, atol=1e-5)
    np.testing.assert_array_equal(s10.obs_mask[:, :, :3, -3:], s3.obs_mask)
    assert not np.asarray(s10.obs_mask[:, :, :3, :-3]).any() and not np.asarray(s10.obs_mask[:, :, 3:]).any()
    np.testing.assert_array_equal(s10.reward[..., :3], s3.reward)
    assert not np.asarray(s10.reward[..., 3:]).any()
    np.testing.assert_array_equal(s10.done, s3.done)
    np.testing.assert_allclose(s10.joints[..., :3, :], s3.joints, atol=1e-6)
    assert not np.asarray(s10.metrics["nonfinite_action"]).any()  # empty slots' actions are ignored


def test_observation_self_last_and_radius(generated):
    tasks = take(generated, np.flatnonzero(generated.num_arms >= 5)[:6])
    bank = TaskBank.from_tasks(tasks, 10)
    for radius in (1.7, 0.85, 0.0):
        env = ReachingEnv(10, EnvConfig(neighbour_radius=radius))
        state = jax.jit(jax.vmap(lambda task: env.reset(None, task)))(bank.tasks)
        mask, obs, active = np.asarray(state.obs_mask), np.asarray(state.obs), np.asarray(bank.tasks.active)
        base = np.asarray(bank.tasks.base_pos)
        dist = np.linalg.norm(base[:, :, None] - base[:, None], axis=-1)
        within = ((dist <= radius) | np.eye(10, dtype=bool)) & active[:, :, None] & active[:, None, :]
        np.testing.assert_array_equal(mask.sum(-1), within.sum(-1))  # nothing beyond the radius
        assert np.all(mask[active][:, -1])  # the observing arm is the last element
        np.testing.assert_allclose(obs[active][:, -1, 100:107], np.tile([0, 0, 0, 1.0, 0, 0, 0], (active.sum(), 1)), atol=1e-6)
        np.testing.assert_allclose(obs[active][:, -1, 6:12], np.asarray(bank.tasks.start_joints)[active], atol=1e-6)
        assert not mask[~active].any()


def test_arms_driven_into_each_other_collide():
    env = ReachingEnv(2, EnvConfig(max_steps=120))
    bank = TaskBank.from_tasks(facing_pair(), 2)
    final, states, _ = rollout(env, 120)(bank.tasks, jnp.asarray([0.02, 0.1]))
    assert bool(final.done[0]) and not bool(final.success[0]) and not bool(final.truncated[0])
    hit = int(np.argmax(np.asarray(states.collided).any(-1)[:, 0]))
    collided = np.asarray(states.collided[hit, 0])
    assert collided.any()
    assert np.asarray(states.metrics["min_distance"][hit, 0])[collided].max() < 0
    np.testing.assert_allclose(np.asarray(states.reward[hit, 0])[collided], -0.05, atol=1e-6)
    # The episode is over: later steps change nothing and pay nothing.
    assert not np.asarray(states.reward[hit + 1 :]).any()
    np.testing.assert_array_equal(states.joints[-1], states.joints[hit])
    assert int(final.step[0]) == hit + 1
    harsh = ReachingEnv(2, EnvConfig(max_steps=120, collision_penalty=-1.0))  # the same drive, a larger penalty
    states = rollout(harsh, 120)(bank.tasks, jnp.asarray([0.02, 0.1]))[1]
    np.testing.assert_allclose(np.asarray(states.reward[hit, 0])[collided], -1.0, atol=1e-6)
    with pytest.raises(ValueError, match="collision_penalty must be <= 0"):
        EnvConfig(collision_penalty=0.5)


def test_restoring_colliding_arms_keeps_the_episode_going():
    """end_on_collision=False (training option): the same drive into each other goes on to the
    step limit; every colliding step puts the colliding arms back where they were, pays the
    penalty, never counts as a success, and the arms never rest in contact."""
    env = ReachingEnv(2, EnvConfig(max_steps=120, end_on_collision=False))
    bank = TaskBank.from_tasks(facing_pair(), 2)
    final, states, _ = rollout(env, 120)(bank.tasks, jnp.asarray([0.02, 0.1]))
    collided = np.asarray(states.collided[:, 0])  # [T, 2]
    assert collided.any(-1).sum() >= 2  # they keep pushing into each other
    assert bool(final.done[0]) and bool(final.truncated[0]) and int(final.step[0]) == 120
    joints = np.concatenate([np.asarray(bank.tasks.start_joints), np.asarray(states.joints[:, 0])])
    np.testing.assert_array_equal(joints[1:][collided], joints[:-1][collided])  # restored
    assert np.all(np.asarray(states.reward[:, 0])[collided] <= -0.05 + 0.01 + 1e-6)
    assert not np.asarray(states.success[:, 0])[collided.any(-1)].any()
    contacts = jax.jit(jax.vmap(lambda q: scene_contacts(env.scene, bank.tasks.base_pos[0], bank.tasks.base_quat[0], q,
                                                          bank.tasks.active[0]).min_distance.min()))
    assert float(contacts(jnp.asarray(joints, jnp.float32)).min()) >= 0


@pytest.mark.slow
def test_collisions_end_once_the_tolerance_reaches_the_threshold():
    """collisions_end_at: restored collisions become the paper's rule (the episode ends at the
    first colliding step, arms not put back) for episodes whose position tolerance is at most
    the threshold, and stay restored for looser ones."""
    bank = TaskBank.from_tasks(facing_pair(), 2)
    env = ReachingEnv(2, EnvConfig(max_steps=120, end_on_collision=False, collisions_end_at=0.02))
    ending = ReachingEnv(2, EnvConfig(max_steps=120))
    final, states, _ = rollout(env, 120)(bank.tasks, jnp.asarray([0.02, 0.1]))
    expected, expected_states, _ = rollout(ending, 120)(bank.tasks, jnp.asarray([0.02, 0.1]))
    assert bool(final.done[0]) and not bool(final.truncated[0]) and not bool(final.success[0])
    assert int(final.step[0]) == int(expected.step[0]) < 120
    np.testing.assert_array_equal(states.joints, expected_states.joints)
    loose = rollout(env, 120)(bank.tasks, jnp.asarray([0.021, 0.1]))[0]
    assert bool(loose.truncated[0]) and int(loose.step[0]) == 120  # restored: goes on to the step limit
    with pytest.raises(ValueError, match="collisions_end_at must be >= 0 and needs end_on_collision=False"):
        EnvConfig(collisions_end_at=0.02)


@pytest.mark.slow
def test_thin_obstacle_is_not_tunnelled_through_in_one_step():
    """Full-speed steps whose end points are both free but which pass through the other arm.

    Checking only where a step ends would miss all of them; the swept check (no joint moving
    more than 0.05 rad between checks) must flag every one of these samples that dips 5 mm
    or more into the other arm. Grazes up to about 1 cm deep can fall between checks
    elsewhere (rate and depths in benchmarks/RESULTS.md).
    """
    env, rng, n = ReachingEnv(2), np.random.default_rng(0), 24_576
    angle, gap = rng.uniform(-np.pi, np.pi, n), rng.uniform(0.5, 0.9, n)
    bases = np.zeros((n, 2, 3))
    bases[:, 1, :2] = gap[:, None] * np.stack([np.cos(angle), np.sin(angle)], -1)
    bases[..., 2] = rng.uniform(-np.pi, np.pi, (n, 2))
    pos, quat = (jnp.asarray(x, jnp.float32) for x in base_pose_arrays(bases))
    q0 = random_joints(rng, (n, 2)).astype(np.float32)
    q1 = (q0 + rng.choice([-1.0, 1.0], (n, 2, 6)) * env.max_step).astype(np.float32)

    distance = jax.jit(lambda pos, quat, q: scene_contacts(env.scene, pos, quat, q, jnp.ones(q.shape[:-1], bool)).min_distance.min(-1))
    rows = np.flatnonzero(np.asarray((distance(pos, quat, q0) >= 0) & (distance(pos, quat, q1) >= 0)))
    fractions = np.linspace(0.0, 1.0, 33)[1:-1, None, None, None]
    path = (q0[rows] + fractions * (q1[rows] - q0[rows])).reshape(-1, 2, 6).astype(np.float32)
    dense = distance(jnp.tile(pos[rows], (31, 1, 1)), jnp.tile(quat[rows], (31, 1, 1)), path).reshape(31, -1)
    deep = rows[np.asarray(dense.min(0)) <= -0.005]
    assert len(deep) >= 3  # the search finds pass-through steps
    tasks = make_tasks(bases[deep], q0[deep].astype(np.float64), q0[deep].astype(np.float64))
    state = jax.jit(jax.vmap(lambda task: env.reset(None, task)))(TaskBank.from_tasks(tasks, 2).tasks)
    stepped = jax.jit(jax.vmap(env.step))(state, env.joint_deltas_to_actions(q1[deep] - q0[deep]))
    assert np.asarray(stepped.collided).any(-1).all()
    assert np.asarray(stepped.done).all() and not np.asarray(stepped.success).any()
    np.testing.assert_allclose(stepped.joints, q1[deep], atol=1e-5)


def test_tolerance_is_state_and_reward_variants(generated):
    tasks = TaskBank.from_tasks(take(generated, np.flatnonzero(generated.num_arms == 2)[:3]), 2).tasks
    rewards = {}
    for reward in ("team", "selfish"):
        env = ReachingEnv(2, EnvConfig(reward=reward, max_steps=3))
        step = jax.jit(jax.vmap(env.step))
        reset = jax.jit(jax.vmap(lambda task, tolerance: env.reset(None, task, tolerance), in_axes=(0, None)))
        zero = jnp.zeros((3, 2, 6))
        tight = step(reset(tasks, jnp.asarray(env.config.tolerance)), zero)
        loose = step(reset(tasks, jnp.asarray((10.0, 4.0))), zero)
        assert step._cache_size() == 1  # a new tolerance is data, not a new compilation
        assert not np.asarray(tight.success).any() and np.asarray(loose.success).all()
        rewards[reward] = np.asarray(loose.reward)
        # Timeout: tight tolerance, no motion, max_steps = 3.
        state = tight
        for _ in range(3):
            state = step(state, zero)
        assert np.asarray(state.done).all() and np.asarray(state.truncated).all() and int(state.step[0]) == 3
        assert not np.asarray(state.reward).any()  # the frozen episode pays nothing
    np.testing.assert_allclose(rewards["team"], 1.01)
    np.testing.assert_allclose(rewards["selfish"], 0.1)


def test_auto_reset_walks_the_bank_and_counts_episodes(generated):
    env = ReachingEnv(2, EnvConfig(max_steps=2))
    bank = TaskBank.from_tasks(take(generated, np.flatnonzero(generated.num_arms <= 2)[:5]), 2)
    wrapper = AutoReset(env, bank, order="sequential")
    state = jax.jit(wrapper.reset, static_argnums=1)(jax.random.key(0), 3)
    np.testing.assert_array_equal(state.env.task.task_id, [0, 1, 2])
    step = jax.jit(wrapper.step)
    zero = jnp.zeros((3, 2, 6))
    state, stepped = step(state, zero)
    assert not np.asarray(stepped.done).any() and int(state.stats.episodes.sum()) == 0
    state, stepped = step(state, zero)
    assert np.asarray(stepped.done).all() and np.asarray(stepped.step).tolist() == [2, 2, 2]
    np.testing.assert_array_equal(state.env.task.task_id, [3, 4, 0])
    np.testing.assert_array_equal(state.env.step, 0)
    np.testing.assert_array_equal(state.env.joints, bank.tasks.start_joints[np.array([3, 4, 0])])
    summary = state.stats.summary()
    teams = np.asarray(bank.tasks.active).sum(-1)[:3]
    assert summary["all"]["episodes"] == 3 and summary["all"]["timeout_rate"] == 1.0
    assert {k: v["episodes"] for k, v in summary["by_team_size"].items()} == {int(t): int((teams == t).sum()) for t in set(teams)}
    uniform = jax.jit(AutoReset(env, bank).reset, static_argnums=1)(jax.random.key(1), 64)
    assert set(np.asarray(uniform.env.task.task_id).tolist()) == set(range(5))


@pytest.mark.slow
def test_episodes_of_stalled_teams_end_early_as_timeouts(generated):
    """``make_episodes(stall_steps=K)``: a team that stops getting closer to its targets ends
    after K steps, as a timeout; one that keeps closing in (IK) ends as without it."""
    env = ReachingEnv(1, EnvConfig(max_steps=60))
    bank = teams_of(generated, 1, 1)
    still = lambda states, params: jnp.zeros(states.joints.shape)  # noqa: E731
    ik = lambda states, params: jax.vmap(lambda s: ik_actions(env, s))(states)  # noqa: E731
    final = make_episodes(env, still, 60, stall_steps=5)(bank.tasks, None)
    assert np.asarray(final.truncated).all() and (np.asarray(final.step) == 5).all()
    assert (np.asarray(make_episodes(env, still, 60)(bank.tasks, None).step) == 60).all()
    plain, stalled = (jax.device_get(make_episodes(env, ik, 60, k)(bank.tasks, None)) for k in (0, 10))
    assert np.asarray(plain.success).any()
    np.testing.assert_array_equal(stalled.success, plain.success)
    np.testing.assert_array_equal(np.where(plain.success, stalled.step, 0), np.where(plain.success, plain.step, 0))


def test_replaying_recorded_actions_reproduces_the_episode(scripted, env1):
    bank, final, _, actions = scripted
    length = jnp.full(bank.size, 150)
    start = jax.jit(jax.vmap(lambda task: env1.reset(None, task)))(bank.tasks)
    replay = jax.jit(jax.vmap(lambda s, a, n: replay_actions(env1, s, a, n), in_axes=(0, 1, 0)))
    replayed, valid = replay(start, actions, length)
    np.testing.assert_array_equal(replayed.success[:, -1], final.success)
    np.testing.assert_allclose(replayed.joints[:, -1], final.joints, atol=1e-6)
    done_at = np.asarray(final.step)
    np.testing.assert_array_equal(np.asarray(valid).sum(-1), done_at)  # valid up to the end of the episode
    # A sequence cut short holds the arms still after its last action.
    short, short_valid = replay(start, actions, jnp.full(bank.size, 2))
    np.testing.assert_array_equal(np.asarray(short_valid).sum(-1), np.minimum(2, done_at))
    np.testing.assert_allclose(short.joints[:, -1], short.joints[:, 1], atol=1e-7)


def test_bad_input_is_rejected_with_clear_errors(generated, env1):
    bank = teams_of(generated, 1, 1)
    state = env1.reset(None, take_row(bank.tasks, 0))
    step = jax.jit(env1.step)
    with pytest.raises(ValueError, match=r"expected \(1, 6\)"):
        step(state, jnp.zeros((1, 5)))
    with pytest.raises(ValueError, match="4 arms, more than the 3 slots"):
        TaskBank.from_tasks(take(generated, np.flatnonzero(generated.num_arms == 4)[:2]), 3)
    with pytest.raises(ValueError, match="expects one task of 1 slots"):
        env1.reset(None, take_row(TaskBank.from_tasks(take(generated, np.arange(2)), 10).tasks, 0))
    with pytest.raises(ValueError, match="reward must be one of"):
        EnvConfig(reward="greedy")
    with pytest.raises(ValueError, match="target_quat"):
        TaskBank.from_tasks(take(generated, np.arange(2)).replace(target_quat=np.zeros((2, 10, 4))), 10)
    # NaN components hold their joint still and are flagged; the rest of the action applies.
    action = jnp.array([[0.5, jnp.nan, 0.5, 0.5, jnp.inf, 0.5]])
    stepped = step(state, action)
    moved = np.asarray(stepped.joints - state.joints)[0]
    assert moved[1] == 0 and moved[4] == 0 and np.all(moved[[0, 2, 3, 5]] != 0)
    assert bool(stepped.metrics["nonfinite_action"][0])
