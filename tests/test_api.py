"""The numpy boundary: shapes, conventions and bad input."""

from __future__ import annotations

import numpy as np
import pytest

from mjx_multiarm import evaluate_arms
from mjx_multiarm.geometry.robot import load_arm


def test_planar_and_full_base_poses_agree():
    rng = np.random.default_rng(0)
    planar = np.column_stack([rng.uniform(-1, 1, (3, 2)), rng.uniform(-np.pi, np.pi, 3)])
    half = planar[:, 2] / 2
    full = np.column_stack([planar[:, :2], np.zeros(3), np.zeros(3), np.zeros(3), np.sin(half), np.cos(half)])
    joints = rng.uniform(-1, 1, (3, 6))
    a, b = evaluate_arms(planar, joints), evaluate_arms(full, joints)
    np.testing.assert_allclose(a.ee_pos, b.ee_pos, atol=1e-6)
    np.testing.assert_allclose(a.min_distance, b.min_distance, atol=1e-6)


def test_any_batch_shape_and_xyzw_output():
    joints = np.broadcast_to(load_arm().home, (2, 5, 3, 6))
    bases = np.zeros((2, 5, 3, 3))
    bases[..., 0] = [0.0, 1.0, 2.0]
    result = evaluate_arms(bases, joints)
    assert result.ee_pos.shape == (2, 5, 3, 3) and result.ee_quat.shape == (2, 5, 3, 4)
    assert result.points.shape == (2, 5, 3, 10, 3) and result.collided.shape == (2, 5, 3)
    np.testing.assert_allclose(np.linalg.norm(result.ee_quat, axis=-1), 1.0, atol=1e-6)
    assert (result.ee_quat[..., 3] >= 0).all()  # scalar last, canonical sign
    assert not result.collided.any()  # home is collision-free


@pytest.mark.parametrize(
    ("bases", "joints", "kwargs", "message"),
    [
        (np.zeros((2, 3)), np.zeros((2, 5)), {}, r"joints: expected shape \[\.\.\., n_arms, 6\]"),
        (np.zeros((3, 3)), np.zeros((2, 6)), {}, r"base_poses: expected shape \(2, 3\)"),
        (np.zeros((2, 4)), np.zeros((2, 6)), {}, r"base_poses: expected shape"),
        (np.zeros((11, 3)), np.zeros((11, 6)), {"max_arms": 10}, r"11 arms given but the scene has only max_arms=10"),
        (np.zeros((2, 3)), np.zeros((2, 6)), {"active": np.ones(3, bool)}, r"active: expected a bool array of shape \(2,\)"),
        (np.zeros((2, 3)), np.zeros((2, 6)), {"active": np.ones(2)}, r"active: expected a bool array"),
        (np.zeros((2, 7)), np.zeros((2, 6)), {}, r"unit norm"),
    ],
)
def test_bad_shapes_are_rejected_with_a_clear_message(bases, joints, kwargs, message):
    with pytest.raises(ValueError, match=message):
        evaluate_arms(bases, joints, **kwargs)


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_non_finite_inputs_are_rejected(bad):
    joints = np.zeros((2, 6))
    joints[1, 4] = bad
    with pytest.raises(ValueError, match=r"joints: non-finite value .* at index \(1, 4\)"):
        evaluate_arms(np.zeros((2, 3)), joints)
    bases = np.zeros((2, 3))
    bases[0, 2] = bad
    with pytest.raises(ValueError, match=r"base_poses: non-finite"):
        evaluate_arms(bases, np.zeros((2, 6)))
