"""The planner's compiled collision checker against the JAX kernel: the same verdicts."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from mjx_multiarm.geometry.checker import CollisionChecker
from mjx_multiarm.geometry.collision import scene_contacts
from mjx_multiarm.geometry.robot import load_arm
from mjx_multiarm.geometry.scene import build_scene
from mjx_multiarm.geometry.transforms import yaw_quat

ARM = load_arm()


def _random_scenes(rng, count: int, num_arms: int):
    """Bases scattered so that arms often reach each other, joints home + N(0, 1 rad)."""
    pos = np.zeros((count, num_arms, 3))
    pos[..., :2] = rng.uniform(-0.5, 0.5, (count, num_arms, 2)) * np.sqrt(num_arms)
    quat = np.asarray(yaw_quat(rng.uniform(-np.pi, np.pi, (count, num_arms))), np.float64)
    joints = np.clip(ARM.home + rng.normal(0.0, 1.0, (count, num_arms, 6)), *ARM.joint_range.T)
    return pos, quat, joints


def _kernel_distance(num_arms, pos, quat, joints):
    contacts = scene_contacts(build_scene(num_arms), jnp.asarray(pos, jnp.float32), jnp.asarray(quat, jnp.float32),
                              jnp.asarray(joints, jnp.float32), jnp.ones(joints.shape[:2], bool))
    return np.asarray(contacts.min_distance).min(axis=-1)


@pytest.mark.parametrize("num_arms, count", [(1, 600), (2, 600), pytest.param(4, 300, marks=pytest.mark.slow),
                                              pytest.param(10, 100, marks=pytest.mark.slow)])
def test_verdicts_match_the_jax_kernel(num_arms, count):
    """Random scenes (self, ground and between-arm contacts all occur): identical verdicts,
    except within float32 rounding of contact (the kernel's precision)."""
    pos, quat, joints = _random_scenes(np.random.default_rng(num_arms), count, num_arms)
    distance = _kernel_distance(num_arms, pos, quat, joints)
    verdicts = np.array([CollisionChecker(p, q, ARM.joint_range, 0.05).collided(j.reshape(1, -1))[0]
                         for p, q, j in zip(pos, quat, joints)])
    clear = np.abs(distance) > 1e-5
    assert 0.1 < verdicts.mean() < 1.0 or num_arms == 10
    np.testing.assert_array_equal(verdicts[clear], distance[clear] < 0.0)


@pytest.mark.slow
def test_margin_counts_near_contact_as_contact():
    pos, quat, joints = _random_scenes(np.random.default_rng(7), 300, 2)
    distance = _kernel_distance(2, pos, quat, joints)
    verdicts = np.array([CollisionChecker(p, q, ARM.joint_range, 0.05, margin=0.02).collided(j.reshape(1, -1))[0]
                         for p, q, j in zip(pos, quat, joints)])
    clear = np.abs(distance - 0.02) > 1e-5
    np.testing.assert_array_equal(verdicts[clear], distance[clear] < 0.02)


def test_motion_check_finds_what_the_dense_states_find():
    """An edge collides iff one of its resolution-spaced states does (checked coarse to fine)."""
    rng = np.random.default_rng(3)
    pos, quat, joints = _random_scenes(rng, 200, 2)
    for p, q, start in zip(pos, quat, joints):
        checker = CollisionChecker(p, q, ARM.joint_range, 0.05)
        start = start.ravel()
        end = start + rng.normal(0.0, 0.3, start.shape)
        steps = max(1, int(np.ceil(np.max(np.abs(end - start)) / 0.05 - 1e-9)))
        states = start + (np.arange(1, steps + 1)[:, None] / steps) * (end - start)
        assert checker.motion_free(start, end) == (not checker.collided(states).any())


def test_bad_input_is_named():
    checker = CollisionChecker(np.zeros((2, 3)), np.tile([1.0, 0, 0, 0], (2, 1)), ARM.joint_range, 0.05)
    with pytest.raises(ValueError, match="configs"):
        checker.collided(np.zeros((1, 6)))
    with pytest.raises(ValueError, match="base_pos"):
        CollisionChecker(np.zeros((2, 3)), np.tile([1.0, 0, 0, 0], (3, 1)), ARM.joint_range, 0.05)
