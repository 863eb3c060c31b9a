"""The certified motion check: its motion bounds hold, nothing it certifies touches in a dense
re-check, and it flags the pass-throughs that the sampled sweep misses."""

from __future__ import annotations

import importlib.util
import json
import pathlib
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import random_joints

from mjx_multiarm.env.reaching import ReachingEnv
from mjx_multiarm.env.wrappers import TaskBank
from mjx_multiarm.geometry.certified import certified_contacts, geom_reach
from mjx_multiarm.geometry.checker import team_checker
from mjx_multiarm.geometry.collision import (
    CONTACTS_ONLY,
    scene_contacts,
    swept_contacts,
)
from mjx_multiarm.geometry.kinematics import forward_kinematics
from mjx_multiarm.geometry.robot import load_arm
from mjx_multiarm.tasks.dataset import save_tasks
from mjx_multiarm.tasks.types import take

_spec = importlib.util.spec_from_file_location("common", pathlib.Path(__file__).parents[1] / "benchmarks" / "common.py")
COMMON = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(COMMON)

#: Configurations of the dense reference check per motion.
DENSE = 256

# A two-arm full-speed step whose 4 evenly spaced checks are all free while the motion
# passes 3.3 mm deep into contact (found by benchmarks/swept_collision.py's sampler).
PASS_THROUGH = dict(
    base_pos=np.array([[0.0, 0.0, 0.0], [-0.43702042, -0.39976576, 0.0]], np.float32),
    base_quat=np.array([[0.7626506, 0.0, 0.0, 0.6468107], [0.7886666, 0.0, 0.0, 0.61482114]], np.float32),
    start=np.array([[-3.424077, -1.2740806, 0.9467317, -1.6047561, -1.773134, -1.16416],
                    [-2.5572677, -1.5391283, 0.9409775, -0.3819861, -0.0845928, 0.9462252]], np.float32),
    end=np.array([[-3.581577, -1.1165806, 0.78923166, -1.4447562, -1.613134, -1.00416],
                  [-2.3997676, -1.6966283, 0.78347754, -0.22198611, -0.24459279, 1.1062253]], np.float32),
)


def _geom_points(frames) -> np.ndarray:
    """[..., P, 3] the capsule segment ends and the box corners of posed arms."""
    arm = load_arm()
    boxes = np.asarray(frames.boxes)  # [..., nbox, 4, 3]: centre, then unit axes
    signs = np.array(np.meshgrid(*[[-1.0, 1.0]] * 3, indexing="ij")).reshape(3, -1).T  # [8, 3]
    corners = boxes[..., :1, :] + np.einsum("ck,bk,...bkx->...bcx", signs, arm.box_half, boxes[..., 1:, :])
    capsules = np.asarray(frames.capsules)
    return np.concatenate([capsules.reshape(*capsules.shape[:-3], -1, 3), corners.reshape(*corners.shape[:-3], -1, 3)], -2)


def test_no_point_of_a_geom_moves_further_than_its_bound():
    """Turning one joint by a small angle moves every capsule end and box corner by at most the
    angle times the geom's reach from that joint's axis (zero for geoms before the joint);
    for a geom fixed to the joint's body the bound is met."""
    arm, reach = load_arm(), geom_reach(load_arm())
    rng = np.random.default_rng(0)
    joints = rng.uniform(*arm.joint_range.T, size=(512, 6)).astype(np.float32)
    zero = jnp.zeros(3)
    per_point = np.concatenate([np.repeat(np.arange(arm.num_capsules), 2), np.repeat(arm.num_capsules + np.arange(arm.num_boxes), 8)])
    before = _geom_points(forward_kinematics(arm, zero, jnp.array([1.0, 0, 0, 0]), joints))
    for j in range(6):
        angle = 0.02
        turned = joints.copy()
        turned[:, j] += angle
        after = _geom_points(forward_kinematics(arm, zero, jnp.array([1.0, 0, 0, 0]), turned))
        moved = np.linalg.norm(after - before, axis=-1)  # [n, P]
        assert np.all(moved <= angle * reach[j, per_point] + 1e-5), j
    gripper = per_point == arm.num_capsules + arm.num_boxes - 1  # a box on the last joint's body: its bound is exact
    assert moved[:, gripper].max() > 0.99 * angle * reach[5, -1]


def test_the_pass_through_the_sampled_sweep_misses_is_flagged():
    env = ReachingEnv(2)
    p = PASS_THROUGH
    active = jnp.ones(2, bool)
    sampled = swept_contacts(env.scene, p["base_pos"], p["base_quat"], p["start"], p["end"], active, env.substeps)
    dense = swept_contacts(env.scene, p["base_pos"], p["base_quat"], p["start"], p["end"], active, DENSE)
    assert not np.asarray(sampled.collided).any() and np.asarray(dense.min_distance).min() < -0.003
    verdict = certified_contacts(env.scene, p["base_pos"], p["base_quat"], p["start"], p["end"], active)
    assert np.asarray(verdict.collided).any()


def _random_two_arm_steps(n: int, seed: int):
    """benchmarks/common.py's two-arm full-speed steps, all arms active."""
    env, pos, quat, q0, q1 = COMMON.random_two_arm_steps(n, np.random.default_rng(seed))
    return env, pos, quat, q0, q1, np.ones((n, 2), bool)


@pytest.fixture(scope="module")
def crowded_steps(generated):
    """The generated 2-6-arm teams 30 % and 60 % along their straight start-goal paths, and a
    full-speed step toward the goal."""
    tasks = take(generated, (generated.num_arms >= 2) & (generated.num_arms <= 6))
    env = ReachingEnv(6)
    t = TaskBank.from_tasks(tasks, 6).tasks
    t = jax.tree.map(lambda x: jnp.concatenate([x] * 2), t)
    fraction = jnp.repeat(jnp.array([0.3, 0.6]), tasks.num_tasks)[:, None, None]
    q0 = t.start_joints + fraction * (t.goal_joints - t.start_joints)
    q1 = env.next_joints(q0, env.joint_deltas_to_actions(t.goal_joints - q0), t.active)
    return env, t.base_pos, t.base_quat, q0, q1, t.active


def _pickplace_steps(n: int, seed: int):
    """Full-speed steps of the four pick-and-place arms in their cell's collision model (the
    gripper as simulated, the bin as obstacles), from home-centred configurations toward others."""
    from mjx_multiarm.pickplace.scene import (
        BASE_POS,
        BASE_QUAT,
        NUM_ARMS,
        collision_model,
    )

    arm_xml, obstacles = collision_model()
    env = ReachingEnv(NUM_ARMS, arm_xml=arm_xml, obstacles=obstacles)
    rng = np.random.default_rng(seed)
    q0, goal = (jnp.asarray(random_joints(rng, (n, NUM_ARMS), spread=0.5), jnp.float32) for _ in range(2))
    active = jnp.ones((n, NUM_ARMS), bool)
    q1 = env.next_joints(q0, env.joint_deltas_to_actions(goal - q0), active)
    pos, quat = (jnp.broadcast_to(jnp.asarray(x, jnp.float32), (n, *x.shape)) for x in (BASE_POS, BASE_QUAT))
    return env, pos, quat, q0, q1, active


@pytest.mark.parametrize("steps", ["random two-arm", pytest.param("crowded teams", marks=pytest.mark.slow),
                                   pytest.param("pick-and-place cell", marks=pytest.mark.slow)])
def test_nothing_certified_free_touches_in_a_dense_recheck(steps, request):
    """Team by team: a step certified free has no contact at 256 configurations along it; every
    step the dense or the sampled check finds in contact is flagged; and the check is not
    much more cautious than the dense one. The pick-and-place cell's collision model has a
    second gripper box and the bin's boxes as obstacles."""
    if steps == "random two-arm":
        env, pos, quat, q0, q1, active = _random_two_arm_steps(512, 1)
    else:
        env, pos, quat, q0, q1, active = request.getfixturevalue("crowded_steps") if steps == "crowded teams" else _pickplace_steps(512, 2)
    start_free = ~np.asarray(scene_contacts(env.scene, pos, quat, q0, active).collided.any(-1))
    check = jax.jit(lambda *a: certified_contacts(env.scene, *a))
    verdict = check(pos, quat, q0, q1, active)
    flagged = np.asarray(verdict.collided.any(-1))[start_free]
    dense = np.asarray(swept_contacts(env.scene, pos, quat, q0, q1, active, DENSE, max_distance=CONTACTS_ONLY).collided.any(-1))[start_free]
    sampled = np.asarray(swept_contacts(env.scene, pos, quat, q0, q1, active, env.substeps).collided.any(-1))[start_free]
    assert dense.sum() >= 5 and start_free.sum() >= 100  # the sample has contacts to find
    assert not (dense & ~flagged).any() and not (sampled & ~flagged).any()
    assert (flagged & ~dense).sum() <= 0.05 * (~dense).sum()
    evaluations = np.asarray(verdict.evaluations)[start_free]
    assert evaluations.min() >= 1 and np.median(evaluations) <= 16


def test_a_team_that_holds_still_is_certified_at_its_start():
    env, pos, quat, q0, _, active = _random_two_arm_steps(64, 2)
    free = ~np.asarray(scene_contacts(env.scene, pos, quat, q0, active).collided.any(-1))
    verdict = certified_contacts(env.scene, pos[free], quat[free], q0[free], q0[free], active[free])
    assert not np.asarray(verdict.collided).any() and (np.asarray(verdict.evaluations) == 1).all()


def test_the_planners_certified_check_agrees_with_the_dense_recheck():
    """The expert's replay check (numba, pair by pair) certifies no motion that the dense check
    finds in contact, flags the sampled sweep's miss, and certifies most free motions."""
    env, pos, quat, q0, q1, active = _random_two_arm_steps(1024, 3)
    dense = np.asarray(swept_contacts(env.scene, pos, quat, q0, q1, active, DENSE, max_distance=CONTACTS_ONLY).collided.any(-1))
    start_free = ~np.asarray(scene_contacts(env.scene, pos, quat, q0, active).collided.any(-1))
    certified = np.array([team_checker(p, q, 0.05).steps_certified(np.stack([a, b]), 0.0)
                          for p, q, a, b in zip(pos, quat, q0, q1)])
    assert not (certified & dense).any() and dense[start_free].sum() >= 3
    assert (~certified & ~dense & start_free).sum() <= 0.05 * (~dense & start_free).sum()
    p = PASS_THROUGH
    assert not team_checker(p["base_pos"], p["base_quat"], 0.05).steps_certified(np.stack([p["start"], p["end"]]), 0.0)


@pytest.mark.slow
def test_the_certified_check_benchmark_finds_no_contact(tmp_path, generated):
    """benchmarks/certified_check.py at a small size: nothing certified is in contact, and no
    executed step of the safe policy is."""
    save_tasks(tmp_path / "tasks.npz", take(generated, generated.num_arms <= 3))
    script = pathlib.Path(__file__).resolve().parents[1] / "benchmarks" / "certified_check.py"
    out = subprocess.run([sys.executable, str(script), "--random", "256", "--dense", "32", "--tasks", str(tmp_path / "tasks.npz"),
                          "--per-size", "2", "--json"], check=True, capture_output=True, text=True).stdout
    report = json.loads(out.strip().splitlines()[-1])
    assert report["random"]["motions_with_free_ends"] == 256 < report["random"]["samples"]
    assert all(c["certified_in_contact"] == 0 and c["certified"] > 0 for c in report["random"]["checks"].values())
    rows = report["rollouts"]["by_team_size"].values()
    assert all(row["steps_in_contact"] == 0 and row["steps_checked"] > 0 for row in rows)
