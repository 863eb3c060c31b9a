"""Capsule-box and box-box signed distances against coal (GJK/EPA) and MuJoCo C.

coal is the exact reference. MuJoCo's ``mj_geomDistance`` agrees wherever both call the
pair apart, but it is not a reference for capsule-box: with the capsule's axis through the
box it can report a positive distance (the capsule end's distance to a face).
"""

from __future__ import annotations

import jax
import mujoco
import numpy as np
import pytest

from mjx_multiarm.geometry.collision import box_box_distance, segment_box_distance

HALF_A = np.array([0.07, 0.06, 0.04])  # the gripper stand-in box
HALF_B = np.array([0.05, 0.02, 0.09])
RADIUS = 0.04
HALF_LENGTH = 0.1

PAIR_XML = f"""
<mujoco>
  <worldbody>
    <body name="a" mocap="true"><geom name="a" type="box" size="{' '.join(map(str, HALF_A))}"/></body>
    <body name="b" mocap="true"><geom name="b" type="box" size="{' '.join(map(str, HALF_B))}"/></body>
    <body name="c" mocap="true"><geom name="c" type="capsule" size="{RADIUS} {HALF_LENGTH}"/></body>
  </worldbody>
</mujoco>
"""


def _random_poses(rng, n):
    """Positions within 0.35 m of the origin (many near contacts) and uniform rotations."""
    pos = rng.uniform(-0.15, 0.15, (n, 3))
    quat = rng.normal(size=(n, 4))
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    # Axis-aligned and face-parallel cases, where a naive closest-feature search degenerates.
    quat[: n // 8] = [1.0, 0.0, 0.0, 0.0]
    return pos, quat


def _rotation(quat):
    mat = np.empty(9)
    mujoco.mju_quat2Mat(mat, quat)
    return mat.reshape(3, 3)


def _mujoco_distances(pose_a, pose_other, other: str):
    m = mujoco.MjModel.from_xml_string(PAIR_XML)
    d = mujoco.MjData(m)
    body = {"b": 1, "c": 2}[other]
    out = []
    for (pa, qa), (po, qo) in zip(zip(*pose_a), zip(*pose_other)):
        d.mocap_pos[0], d.mocap_quat[0] = pa, qa
        d.mocap_pos[body], d.mocap_quat[body] = po, qo
        d.mocap_pos[3 - body] = [10.0, 10.0, 10.0]
        mujoco.mj_kinematics(m, d)
        out.append(mujoco.mj_geomDistance(m, d, m.geom("a").id, m.geom(other).id, 1.0, None))
    return np.array(out)


def _coal_distances(pose_a, pose_other, other: str):
    coal = pytest.importorskip("coal")
    box = coal.Box(*(2 * HALF_A))
    shape = coal.Capsule(RADIUS, 2 * HALF_LENGTH) if other == "c" else coal.Box(*(2 * HALF_B))
    request, result, out = coal.DistanceRequest(), coal.DistanceResult(), []
    for (pa, qa), (po, qo) in zip(zip(*pose_a), zip(*pose_other)):
        result.clear()
        out.append(coal.distance(box, coal.Transform3s(_rotation(qa), pa), shape, coal.Transform3s(_rotation(qo), po),
                                 request, result))
    return np.array(out)


def _coords_first(pos, quat, half):
    """Centre [3, n], axes [3, 3, n] and half sizes [3, 1] of boxes."""
    axes = np.stack([_rotation(q) for q in quat])  # [n, 3 (coord), 3 (axis)]
    return pos.T, np.transpose(axes, (2, 1, 0)), half[:, None]


@pytest.mark.parametrize("other", ["capsule", "box"])
def test_signed_distance_matches_mj_geom_distance(other):
    rng = np.random.default_rng(7)
    n = 3000
    pose_a, pose_o = _random_poses(rng, n), _random_poses(rng, n)
    centre, axes, half = _coords_first(*pose_a, HALF_A)
    if other == "capsule":
        z = np.stack([_rotation(q)[:, 2] for q in pose_o[1]])
        p, q = (pose_o[0] - HALF_LENGTH * z).T, (pose_o[0] + HALF_LENGTH * z).T
        ours = np.asarray(jax.jit(segment_box_distance)(p, q, centre, axes, half)) - RADIUS
    else:
        ours = np.asarray(jax.jit(box_box_distance)(centre, axes, half, *_coords_first(*pose_o, HALF_B)))
    name = "c" if other == "capsule" else "b"
    exact, mj = _coal_distances(pose_a, pose_o, name), _mujoco_distances(pose_a, pose_o, name)
    apart = exact > 0
    assert 0.2 < apart.mean() < 0.9, apart.mean()  # both verdicts well represented
    np.testing.assert_allclose(ours[apart], exact[apart], atol=2e-6)
    np.testing.assert_array_equal(ours < 0, exact < 0)
    both = apart & (mj > 0)
    np.testing.assert_allclose(ours[both], mj[both], atol=2e-6)
    print(f"{other}: {apart.sum()} apart, max |ours - coal| {np.abs(ours - exact)[apart].max():.1e} m; "
          f"mj_geomDistance calls {np.sum((mj > 0) != apart)} of {n} pairs apart wrongly")
