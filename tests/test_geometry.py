"""Property-based tests of the geometric kernels."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from hypothesis import example, given, settings
from hypothesis import strategies as st

from mjx_multiarm.geometry.collision import segment_distance
from mjx_multiarm.geometry.transforms import (
    axis_angle_quat,
    quat_angle,
    quat_mul,
    quat_to_mat,
    wxyz_to_xyzw,
    xyzw_to_wxyz,
)

coordinate = st.floats(-1.0, 1.0, allow_nan=False, width=32)
point = st.tuples(coordinate, coordinate, coordinate).map(np.array)


def _segments_distance(p1, q1, p2, q2):
    args = [jnp.asarray(np.asarray(x, np.float32)[:, None]) for x in (p1, q1, p2, q2)]
    return float(segment_distance(*args)[0])


def _brute_force(p1, q1, p2, q2, n=401):
    s = np.linspace(0, 1, n)[:, None]
    a, b = p1 + s * (q1 - p1), p2 + s * (q2 - p2)
    return np.min(np.linalg.norm(a[:, None] - b[None], axis=-1))


def _near_parallel_error(p1, q1, p2, q2) -> float:
    """How far the float32 kernel may overestimate for nearly parallel segments: below
    sin^2 of about 1e-6 (float32's resolution of ``a e - b^2``) the segments count as parallel
    and the kernel measures from an end of the first, off by at most the shorter length
    times the sine of their angle (e.g. 1e-5 m for 1 m segments 1e-5 rad apart)."""
    d1, d2 = q1 - p1, q2 - p2
    sine = np.linalg.norm(np.cross(d1, d2)) / (np.linalg.norm(d1) * np.linalg.norm(d2))
    return float(min(np.linalg.norm(d1), np.linalg.norm(d2)) * sine) if sine < 1e-3 else 0.0


@settings(max_examples=200)
@given(point, point, point, point)
@example(np.array([0.0, 1.0, 0.0]), np.zeros(3), np.zeros(3), np.array([0.0, 1.0, 1.0761518751678523e-05]))
def test_segment_distance_matches_dense_sampling(p1, q1, p2, q2):
    if min(np.linalg.norm(q1 - p1), np.linalg.norm(q2 - p2)) < 1e-3:
        return  # capsules always have a positive length
    ours = _segments_distance(p1, q1, p2, q2)
    brute = _brute_force(p1, q1, p2, q2)
    # The true minimum is at most the sampled one, and within the sampling step of it.
    step = (np.linalg.norm(q1 - p1) + np.linalg.norm(q2 - p2)) / 400
    assert ours <= brute + 1e-5 + _near_parallel_error(p1, q1, p2, q2)
    assert ours >= brute - step - 1e-5


@settings(max_examples=100)
@given(point, point, point, point, st.floats(-np.pi, np.pi), point)
def test_segment_distance_is_symmetric_and_rigid_invariant(p1, q1, p2, q2, angle, shift):
    if min(np.linalg.norm(q1 - p1), np.linalg.norm(q2 - p2)) < 1e-3:
        return
    # float32: nearly parallel segments that meet near an end lose up to ~4e-5 m (hypothesis
    # found p1 (0.25, 0.25, 0), q1 = q2 (-0.896, -0.875, 0), p2 at the origin: 3.5e-5).
    tolerance = 1e-4
    d = _segments_distance(p1, q1, p2, q2)
    assert abs(d - _segments_distance(p2, q2, p1, q1)) < tolerance
    assert abs(d - _segments_distance(q1, p1, q2, p2)) < tolerance
    rot = np.asarray(quat_to_mat(np.array([np.cos(angle / 2), 0.6 * np.sin(angle / 2), 0, 0.8 * np.sin(angle / 2)])))
    moved = [rot @ x + shift for x in (p1, q1, p2, q2)]
    assert abs(d - _segments_distance(*moved)) < tolerance


def test_parallel_and_touching_segments():
    x = np.array([1.0, 0, 0])
    assert abs(_segments_distance(np.zeros(3), x, np.array([0.5, 0.2, 0]), np.array([1.5, 0.2, 0])) - 0.2) < 1e-6
    assert abs(_segments_distance(np.zeros(3), x, np.array([2.0, 0, 0]), np.array([3.0, 0, 0])) - 1.0) < 1e-6
    assert _segments_distance(np.zeros(3), x, np.array([0.5, -1, 0]), np.array([0.5, 1, 0])) < 1e-6


@given(st.tuples(coordinate, coordinate, coordinate, coordinate))
def test_quaternion_conventions(q):
    q = np.array(q, np.float64)
    if np.linalg.norm(q) < 1e-3:
        return
    q /= np.linalg.norm(q)
    np.testing.assert_allclose(np.asarray(xyzw_to_wxyz(wxyz_to_xyzw(q))), q, atol=1e-7)
    rot = np.asarray(quat_to_mat(q))
    np.testing.assert_allclose(rot @ rot.T, np.eye(3), atol=1e-5)
    np.testing.assert_allclose(np.asarray(quat_to_mat(quat_mul(q, q))), rot @ rot, atol=1e-5)


@given(st.tuples(coordinate, coordinate, coordinate, coordinate), st.floats(1e-5, 3.0))
def test_quat_angle_is_accurate_for_small_and_large_angles(q, angle):
    q = np.array(q, np.float64)
    if np.linalg.norm(q) < 1e-3:
        return
    q /= np.linalg.norm(q)
    turned = quat_mul(q, axis_angle_quat(np.array([0.6, 0.0, 0.8]), angle))
    assert abs(float(quat_angle(q, turned)) - angle) < 1e-5 + 1e-6 * angle
    assert abs(float(quat_angle(q, -np.asarray(turned))) - angle) < 1e-5 + 1e-6 * angle  # sign-free
