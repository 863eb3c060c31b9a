"""Policy files (save/load/validation) and the Planner API against the environment."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from mjx_multiarm import Planner, evaluate_arms
from mjx_multiarm.env.observation import InputFeatures
from mjx_multiarm.env.reaching import ReachingEnv
from mjx_multiarm.env.wrappers import TaskBank
from mjx_multiarm.geometry.robot import NUM_JOINTS
from mjx_multiarm.geometry.transforms import wxyz_to_xyzw
from mjx_multiarm.planner.policy import policy_env_settings
from mjx_multiarm.planner.policy_file import load_policy, save_policy
from mjx_multiarm.tasks.types import take, with_slots
from models.networks import Actor, Critic


@pytest.fixture(scope="module")
def policy_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("policy") / "policy.npz"
    save_policy(path, nnx.state(Actor(nnx.Rngs(3), InputFeatures(), NUM_JOINTS)), False, policy_env_settings(ReachingEnv(3)), {"note": "random weights"})
    return path


def test_round_trip_gives_the_same_actor(policy_path):
    loaded = load_policy(policy_path)
    original = Actor(nnx.Rngs(3), InputFeatures(), NUM_JOINTS)
    obs = np.random.default_rng(0).normal(size=(5, 3, 107)).astype(np.float32)
    mask = np.array([[False, True, True]] * 5)
    np.testing.assert_array_equal(np.asarray(loaded.actor(obs, mask)[0]), np.asarray(original(obs, mask)[0]))
    assert loaded.meta["provenance"] == {"note": "random weights"} and not loaded.squash


@pytest.mark.parametrize("inputs", [InputFeatures(rotations=True), InputFeatures(goal=True), InputFeatures(True, True),
                                    InputFeatures(goal=True, nearness=True), InputFeatures(goal=True, clearance=True)])
def test_round_trip_of_actors_with_input_features(tmp_path, inputs):
    """An actor with input features comes back with them (they are in the file), and a
    plain actor's file is not read as one."""
    path = tmp_path / "features.npz"
    original = Actor(nnx.Rngs(4), inputs, NUM_JOINTS)
    save_policy(path, nnx.state(original), False, policy_env_settings(ReachingEnv(2)), inputs=inputs)
    loaded = load_policy(path)
    obs = np.random.default_rng(1).normal(size=(4, 2, 107)).astype(np.float32)
    mask = np.ones((4, 2), bool)
    assert loaded.actor.encoder.inputs == inputs
    np.testing.assert_array_equal(np.asarray(loaded.actor(obs, mask)[0]), np.asarray(original(obs, mask)[0]))
    save_policy(tmp_path / "mislabelled.npz", nnx.state(Actor(nnx.Rngs(4), InputFeatures(), NUM_JOINTS)), False, {}, inputs=inputs)
    with pytest.raises(ValueError, match="another architecture"):
        load_policy(tmp_path / "mislabelled.npz")


def test_round_trip_of_a_mixture_actor(tmp_path):
    """A mixture actor's file says how many components it has; a file that says otherwise
    is refused; files without the entry hold one Gaussian."""
    original = Actor(nnx.Rngs(5), InputFeatures(goal=True), NUM_JOINTS, components=3)
    save_policy(tmp_path / "mixture.npz", nnx.state(original), False, {}, inputs=InputFeatures(goal=True), components=3)
    loaded = load_policy(tmp_path / "mixture.npz")
    assert loaded.components == loaded.meta["components"] == 3
    obs = np.random.default_rng(1).normal(size=(4, 2, 107)).astype(np.float32)
    mask = np.ones((4, 2), bool)
    np.testing.assert_array_equal(np.asarray(loaded.actor(obs, mask)[0]), np.asarray(original(obs, mask)[0]))
    save_policy(tmp_path / "mislabelled.npz", nnx.state(original), False, {}, inputs=InputFeatures(goal=True))
    with pytest.raises(ValueError, match=r"head/layers/2/bias has shape \[36\], this actor expects \[12\]"):
        load_policy(tmp_path / "mislabelled.npz")
    save_policy(tmp_path / "zero.npz", nnx.state(original), False, {}, inputs=InputFeatures(goal=True), components=0)
    with pytest.raises(ValueError, match="mixture components 0, expected an integer >= 1"):
        load_policy(tmp_path / "zero.npz")


def test_bad_policy_files_fail_clearly(policy_path, tmp_path):
    with pytest.raises(FileNotFoundError, match="no such policy file"):
        load_policy(tmp_path / "missing.npz")
    data = bytearray(policy_path.read_bytes())
    (tmp_path / "truncated.npz").write_bytes(bytes(data[: len(data) // 2]))
    with pytest.raises(ValueError, match="not a readable policy file"):
        load_policy(tmp_path / "truncated.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip file at all")
    with pytest.raises(ValueError, match="not a readable policy file"):
        load_policy(tmp_path / "junk.npz")
    np.savez(tmp_path / "plain.npz", weights=np.zeros(3))
    with pytest.raises(ValueError, match="not a policy file"):
        load_policy(tmp_path / "plain.npz")
    # altered weights: the checksum no longer matches
    with np.load(policy_path) as archive:
        arrays = {k: archive[k] for k in archive.files}
    arrays["head/layers/0/bias"] = arrays["head/layers/0/bias"] + 1.0
    np.savez(tmp_path / "altered.npz", **arrays)
    with pytest.raises(ValueError, match="checksum mismatch"):
        load_policy(tmp_path / "altered.npz")
    # another architecture (a critic's parameters under a valid header)
    save_policy(tmp_path / "critic.npz", nnx.state(Critic(nnx.Rngs(0), InputFeatures(), NUM_JOINTS)), False, {})
    with pytest.raises(ValueError, match=r"head/layers/0/kernel has shape \[262, 128\], this actor expects \[256, 128\]"):
        load_policy(tmp_path / "critic.npz")


def test_planner_step_matches_the_environment(policy_path, generated):
    """The planner builds exactly the observation the environment gives the policy, so its
    next joints equal one environment step under the policy's mean action."""
    loaded = load_policy(policy_path)
    planner = Planner(loaded)
    rows = np.flatnonzero(generated.num_arms == 3)[:2]
    env = ReachingEnv(3)
    bank = TaskBank.from_tasks(with_slots(take(generated, rows), 3), 3)
    reset = jax.jit(lambda task: env.reset(None, task))
    policy_step = jax.jit(lambda state: env.step(state, loaded.actor(state.obs, state.obs_mask)[0]))  # one compile for all steps
    for row in range(2):
        task = bank.take(np.array([row]))
        state = reset(jax.tree.map(lambda x: x[0], task))
        for _ in range(2):  # the second step observes a real history frame
            previous = state
            state = policy_step(state)
        bases = np.concatenate([np.asarray(state.task.base_pos), wxyz_to_xyzw(np.asarray(state.task.base_quat))], axis=-1)
        targets = np.concatenate([np.asarray(state.task.target_pos), wxyz_to_xyzw(np.asarray(state.task.target_quat))], axis=-1)
        expected = np.asarray(policy_step(state).joints)
        got = planner.step(np.asarray(state.joints), bases, targets, previous_joints=np.asarray(previous.joints))
        np.testing.assert_allclose(got, expected, atol=2e-5)


def test_planner_rollout_and_bad_input(policy_path):
    planner = Planner.load(policy_path)
    joints = np.array([[0.0, -1.2, 1.0, -1.4, -1.57, 0.0], [0.3, -1.0, 0.8, -1.2, -1.57, 0.0]])
    bases = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, np.pi]])
    here = evaluate_arms(bases, joints)
    at_start = np.concatenate([here.ee_pos, here.ee_quat], axis=-1)
    path = planner.rollout(joints, bases, at_start, steps=5)
    assert path.reached and path.waypoints.shape == (1, 2, 6)  # already there: no motion
    away = at_start + np.array([0.3, 0.0, 0.0, 0, 0, 0, 0])
    path = planner.rollout(joints, bases, away, steps=5)
    assert path.waypoints.shape == (6, 2, 6) and not path.reached  # random weights never get there
    assert np.all(np.abs(np.diff(path.waypoints, axis=0)) <= ReachingEnv(2).max_step + 1e-6)
    batched = planner.batched(2)
    many = jnp.broadcast_to(jnp.asarray(joints, jnp.float32), (4, 2, 6))
    assert batched(*(jnp.broadcast_to(jnp.asarray(x, jnp.float32), (4, *np.shape(x))) for x in (
        np.zeros((2, 3)), [[1, 0, 0, 0]] * 2)), many, many, *(jnp.zeros((4, 2, k)) for k in (3, 4, 3, 4))).shape == (4, 2, 6)
    assert not path.collided and path.min_distance.shape == (2,) and (path.min_distance > 0).all()
    overlapping = joints[[0, 0]]  # the grippers of arms 1 m apart, facing, interpenetrate by 7 cm
    assert evaluate_arms(bases, overlapping).collided.all()
    path = planner.rollout(overlapping, bases, away, steps=5)  # every rollout here is 5 steps: one compilation per planner
    assert path.collided and (path.min_distance < 0).all()
    safe = Planner.load(policy_path, safe=True)  # shielded: the random policy's free-start path stays free
    path = safe.rollout(joints, bases, away, steps=5)
    assert not path.collided and path.waypoints.shape == (6, 2, 6)
    goal = joints + np.array([0.4, 0.0, 0.0, 0.0, 0.0, 0.0])
    there = evaluate_arms(bases, goal)
    assert not there.collided.any()
    hybrid = safe.rollout(joints, bases, np.concatenate([there.ee_pos, there.ee_quat], axis=-1), steps=5, goal_joints=goal)
    assert hybrid.reached and not hybrid.collided and hybrid.handed_over > 0  # BiRRT finished what the policy did not
    assert len(hybrid.waypoints) == 6 + hybrid.handed_over and (hybrid.min_distance > 0).all()
    np.testing.assert_allclose(hybrid.waypoints[-1], goal, atol=1e-4)
    assert np.all(np.abs(np.diff(hybrid.waypoints, axis=0)) <= ReachingEnv(2).max_step + 1e-6)
    with pytest.raises(ValueError, match=r"goal_joints: expected shape \(2, 6\)"):
        safe.rollout(joints, bases, away, goal_joints=goal[:1])
    pos = jnp.broadcast_to(jnp.asarray([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]), (3, 2, 3))  # the bases above, wxyz
    quat = jnp.broadcast_to(jnp.asarray([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]), (3, 2, 4))
    targets = (jnp.zeros((3, 2, 3)), jnp.broadcast_to(quat, (3, 2, 4))) * 2
    assert safe.batched(2)(pos, quat, many[:3], many[:3], *targets).shape == (3, 2, 6)
    with pytest.raises(ValueError, match=r"joints: expected shape \(n_arms, 6\), got \(2, 5\)"):
        planner.step(joints[:, :5], bases, away)
    with pytest.raises(ValueError, match=r"targets: expected shape \(2, 7\) for 2 arms, got \(3, 7\)"):
        planner.step(joints, bases, np.zeros((3, 7)))
    with pytest.raises(ValueError, match="non-finite"):
        planner.step(np.where(np.eye(2, 6) > 0, np.nan, joints), bases, away)
    with pytest.raises(ValueError, match="unit norm"):
        planner.step(joints, bases, away * np.array([1, 1, 1, 0, 0, 0, 0]))
