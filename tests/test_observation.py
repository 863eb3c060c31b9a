"""Observations: shapes, ordering, masking, frame invariance, padding."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import random_bases, random_joints

from mjx_multiarm.env import observation
from mjx_multiarm.env.observation import ELEMENT_SIZE, ArmSnapshot
from mjx_multiarm.geometry.evaluate import base_pose_arrays
from mjx_multiarm.geometry.kinematics import forward_kinematics
from mjx_multiarm.geometry.robot import load_arm
from mjx_multiarm.geometry.transforms import quat_conjugate, quat_mul

# Compiled once per input shape, as the environment runs them (eagerly, every operation
# would compile on its own).
observe = jax.jit(observation.observe, static_argnames="radius")
nearness_features = jax.jit(observation.nearness_features)
clearance_features = jax.jit(observation.clearance_features)


def _snapshot(bases, joints, targets_joints):
    arm = load_arm()
    pos, quat = (jnp.asarray(x, jnp.float32) for x in base_pose_arrays(bases))
    now = forward_kinematics(arm, pos, quat, jnp.asarray(joints, jnp.float32))
    target = forward_kinematics(arm, pos, quat, jnp.asarray(targets_joints, jnp.float32))
    return pos, quat, ArmSnapshot(jnp.asarray(joints, jnp.float32), now.ee_pos, now.ee_quat, target.ee_pos, target.ee_quat, now.points)


@pytest.fixture
def scene():
    rng = np.random.default_rng(0)
    bases = random_bases(rng, 5)
    return bases, random_joints(rng, (5,)), random_joints(rng, (5,)), random_joints(rng, (5,))


def test_shapes_self_last_and_radius(scene):
    bases, q_prev, q_now, q_goal = scene
    pos, quat, prev = _snapshot(bases, q_prev, q_goal)
    _, _, now = _snapshot(bases, q_now, q_goal)
    active = jnp.ones(5, bool)
    obs, mask = observe(pos, quat, active, prev, now)
    assert obs.shape == (5, 5, ELEMENT_SIZE) and mask.shape == (5, 5)
    mask, obs = np.asarray(mask), np.asarray(obs)
    dist = np.linalg.norm(bases[:, None, :2] - bases[None, :, :2], axis=-1)
    np.testing.assert_array_equal(mask.sum(1), (dist <= 1.7).sum(1))
    for i in range(5):
        assert mask[i, -1]  # self is the last element, and unmasked
        np.testing.assert_allclose(obs[i, -1, 100:107], [0, 0, 0, 1, 0, 0, 0], atol=1e-6)  # own base
        np.testing.assert_allclose(obs[i, -1, 6:12], q_now[i], atol=1e-6)
        assert not mask[i, : 5 - mask[i].sum()].any()  # masked elements come first
        seen = np.linalg.norm(obs[i, mask[i], 100:103], axis=-1)
        assert np.all(np.diff(seen) <= 1e-6)  # decreasing base distance
    assert not obs[~mask].any()
    solo, solo_mask = observe(pos, quat, active, prev, now, radius=0.0)
    np.testing.assert_array_equal(np.asarray(solo_mask).sum(1), 1)
    np.testing.assert_allclose(np.asarray(solo)[:, -1], obs[:, -1], atol=1e-6)


def test_moving_the_whole_scene_changes_no_observation(scene):
    bases, q_prev, q_now, q_goal = scene
    yaw, shift = 0.7, np.array([1.5, -2.0])
    c, s = np.cos(yaw), np.sin(yaw)
    moved = bases.copy()
    moved[:, :2] = bases[:, :2] @ np.array([[c, s], [-s, c]]) + shift
    moved[:, 2] += yaw
    results = []
    for b in (bases, moved):
        pos, quat, prev = _snapshot(b, q_prev, q_goal)
        _, _, now = _snapshot(b, q_now, q_goal)
        results.append(observe(pos, quat, jnp.ones(5, bool), prev, now))
    np.testing.assert_array_equal(np.asarray(results[0][1]), np.asarray(results[1][1]))
    np.testing.assert_allclose(np.asarray(results[0][0]), np.asarray(results[1][0]), atol=2e-5)


def test_padding_slots_do_not_change_observations(scene):
    bases, q_prev, q_now, q_goal = scene
    small = [_snapshot(bases[:3], q[:3], q_goal[:3]) for q in (q_prev, q_now)]
    obs3, mask3 = observe(small[0][0], small[0][1], jnp.ones(3, bool), small[0][2], small[1][2])
    big = [_snapshot(bases, q, q_goal) for q in (q_prev, q_now)]
    active = jnp.arange(5) < 3
    obs5, mask5 = observe(big[0][0], big[0][1], active, big[0][2], big[1][2])
    np.testing.assert_allclose(np.asarray(obs5)[:3, -3:], np.asarray(obs3), atol=1e-6)
    np.testing.assert_array_equal(np.asarray(mask5)[:3, -3:], np.asarray(mask3))
    assert not np.asarray(mask5)[:3, :2].any() and not np.asarray(mask5)[3:].any()


def test_quaternions_are_expressed_in_the_observer_frame(scene):
    bases, q_prev, q_now, q_goal = scene
    pos, quat, snap = _snapshot(bases, q_now, q_goal)
    obs, mask = observe(pos, quat, jnp.ones(5, bool), snap, snap)
    own = np.asarray(obs)[:, -1, 19:26]
    expected = quat_mul(quat_conjugate(quat), snap.ee_quat)
    expected = np.where(np.asarray(expected)[:, :1] < 0, -np.asarray(expected), np.asarray(expected))
    np.testing.assert_allclose(own[:, 3:], expected, atol=1e-6)
    assert (own[:, 3] >= 0).all()


def _observed_at_two_steps(scene):
    """(base positions, quaternions, snapshots at t-1 and t, observations) of the scene's
    five arms, every arm seeing every other (radius 10 m)."""
    bases, joints, previous, targets = scene
    pos, quat, now = _snapshot(bases, joints, targets)
    _, _, before = _snapshot(bases, previous, targets)
    obs, mask = observe(pos, quat, jnp.ones(5, bool), before, now, radius=10.0)
    assert np.asarray(mask).all()
    return pos, quat, before, now, obs


def _seen_farthest_first(bases, i):
    """The arms observer ``i`` sees, in its sequence's order (farthest base first), itself excluded."""
    return np.argsort(-np.linalg.norm(bases[:, :2] - bases[i, :2], axis=-1), kind="stable")[:-1]


def test_nearness_features_are_the_link_point_distances_to_each_observed_arm(scene):
    """For every observer and every arm it sees: per own link point the distance to that
    arm's nearest link point (brute force in the world frame), the closing speed of the
    smallest one since t-1, and a vector as long as that smallest distance; the observer's
    own element reads as far; appended after the goal features."""
    from mjx_multiarm.env.observation import (
        CLOSING_SCALE,
        NEARNESS_CAP,
        InputFeatures,
    )

    bases = scene[0]
    _, _, before, now, obs = _observed_at_two_steps(scene)
    features = np.asarray(nearness_features(obs))
    assert features.shape == (5, 5, 14)
    own_now, own_before = np.asarray(now.points, np.float64), np.asarray(before.points, np.float64)
    dist = lambda a, b: np.linalg.norm(a[:, None] - b[None], axis=-1)
    for i in range(5):
        np.testing.assert_allclose(features[i, -1], np.r_[np.full(10, NEARNESS_CAP), np.zeros(4)])
        for slot, j in enumerate(_seen_farthest_first(bases, i)):
            d_now, d_before = dist(own_now[i], own_now[j]), dist(own_before[i], own_before[j])
            np.testing.assert_allclose(features[i, slot, :10], np.minimum(d_now.min(axis=1), NEARNESS_CAP), atol=2e-5)
            np.testing.assert_allclose(features[i, slot, 10], CLOSING_SCALE * (d_before.min() - d_now.min()), atol=3e-4)
            np.testing.assert_allclose(np.linalg.norm(features[i, slot, 11:]), d_now.min(), atol=2e-5)
    both = np.asarray(jax.jit(InputFeatures(goal=True, nearness=True))(obs))
    assert both.shape == (5, 5, 127) == (5, 5, InputFeatures(goal=True, nearness=True).size)
    np.testing.assert_array_equal(both[..., -14:], features)


def test_clearance_features_are_each_own_geoms_exact_distance_to_each_observed_arm(scene):
    """For every observer and every arm it sees: per own collision geom its signed distance
    to that arm (capped, scaled), computed in the observer's frame from the observation,
    equals the same computed in the world frame from the true joints; then how much each
    closed since t-1; the observer's own element reads as far; padding stays finite."""
    from mjx_multiarm.env.observation import (
        CLEARANCE_CAP,
        CLEARANCE_SCALE,
        CLOSING_SCALE,
        InputFeatures,
    )
    from mjx_multiarm.geometry.collision import geom_clearances
    from mjx_multiarm.geometry.scene import build_scene

    bases, joints, previous, _ = scene
    pos, quat, before, now, obs = _observed_at_two_steps(scene)
    features = np.asarray(clearance_features(obs))
    geoms = len(load_arm().geom_names)
    assert features.shape == (5, 5, 2 * geoms)
    world = build_scene(2)
    frames = {t: forward_kinematics(world.arm, pos, quat, q) for t, q in (("now", joints), ("before", previous))}

    reference = jax.jit(lambda *geoms: geom_clearances(world, *geoms))  # one compilation, not one per eager op

    def clearance(t, i, j):
        f = frames[t]
        return np.minimum(np.asarray(reference(f.capsules[i], f.boxes[i], f.capsules[j], f.boxes[j])), CLEARANCE_CAP)

    near = 0
    for i in range(5):
        np.testing.assert_allclose(features[i, -1], np.r_[np.full(geoms, CLEARANCE_SCALE * CLEARANCE_CAP), np.zeros(geoms)])
        for slot, j in enumerate(_seen_farthest_first(bases, i)):
            d_now, d_before = clearance("now", i, j), clearance("before", i, j)
            np.testing.assert_allclose(features[i, slot, :geoms], CLEARANCE_SCALE * d_now, atol=1e-4)
            np.testing.assert_allclose(features[i, slot, geoms:], CLOSING_SCALE * (d_before - d_now), atol=1e-4)
            near += (d_now < CLEARANCE_CAP).sum()
    assert near > 0  # the scene has arms within the cap
    both = np.asarray(jax.jit(InputFeatures(goal=True, clearance=True))(obs))
    assert both.shape == (5, 5, ELEMENT_SIZE + 6 + 2 * geoms) == (5, 5, InputFeatures(goal=True, clearance=True).size)
    np.testing.assert_array_equal(both[..., -2 * geoms:], features)
    padded, _ = observe(pos, quat, jnp.arange(5) < 3, before, now)  # masked (all-zero) elements
    assert np.isfinite(np.asarray(clearance_features(padded))).all()
