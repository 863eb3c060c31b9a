"""Forward kinematics against the URDF numbers (numpy float64) and MuJoCo C."""

from __future__ import annotations

import dataclasses
import xml.etree.ElementTree as ET

import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from conftest import random_bases

from mjx_multiarm import evaluate_arms, forward_kinematics
from mjx_multiarm.geometry import compiled
from mjx_multiarm.geometry.robot import load_arm
from mjx_multiarm.geometry.scene import build_scene, set_mujoco_state
from mjx_multiarm.geometry.transforms import quat_to_mat, yaw_quat

# UR5 joint origins (xyz, rpy) and axes, parent -> child, as published for the UR5
# (DESIGN.md "Robot"); written here independently of the project's MJCF.
URDF_JOINTS = [
    ((0, 0, 0.089159), (0, 0, 0), (0, 0, 1)),
    ((0, 0.13585, 0), (0, np.pi / 2, 0), (0, 1, 0)),
    ((0, -0.1197, 0.425), (0, 0, 0), (0, 1, 0)),
    ((0, 0, 0.39225), (0, np.pi / 2, 0), (0, 1, 0)),
    ((0, 0.093, 0), (0, 0, 0), (0, 0, 1)),
    ((0, 0, 0.09465), (0, 0, 0), (0, 1, 0)),
]
EE_ORIGIN = ((0, 0.13, 0), (0, 0, np.pi / 2))
# Centres of mass of the original's 10 PyBullet links: (parent frame index, offset);
# frame 0 = base_link, 1..6 = the links after each joint, 7 = ee_link.
LINK_POINTS = [
    (0, (0, 0, 0)),
    (1, (0, 0, 0)),
    (2, (0, 0, 0.28)),
    (3, (0, 0, 0.196125)),
    (4, (0, 0.093, 0)),
    (5, (0, 0, 0.09465)),
    (6, (0, 0.06505, 0)),
    (7, (0, 0, 0)),
    (0, (0, 0, 0)),
    (6, (0, 0.0823, 0)),
]


def _rpy(r, p, y):
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return rz @ ry @ rx


def _homogeneous(rot, pos):
    t = np.eye(4)
    t[:3, :3], t[:3, 3] = rot, pos
    return t


def _axis_rotation(axis, angle):
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def urdf_fk(base_xyyaw, q):
    """Frames (base, 6 links, ee_link) as 4x4 float64 transforms."""
    frames = [_homogeneous(_rpy(0, 0, base_xyyaw[2]), (base_xyyaw[0], base_xyyaw[1], 0.0))]
    for (xyz, rpy, axis), angle in zip(URDF_JOINTS, q):
        joint = _homogeneous(_rpy(*rpy), xyz) @ _homogeneous(_axis_rotation(np.array(axis, float), angle), (0, 0, 0))
        frames.append(frames[-1] @ joint)
    frames.append(frames[-1] @ _homogeneous(_rpy(*EE_ORIGIN[1]), EE_ORIGIN[0]))
    return frames


def _rotation_angle(r1, r2):
    """Angle of r1^T r2, well conditioned near zero (atan2 of sine and cosine parts)."""
    rel = np.asarray(r1, np.float64).T @ r2
    sine = np.linalg.norm([rel[2, 1] - rel[1, 2], rel[0, 2] - rel[2, 0], rel[1, 0] - rel[0, 1]])
    return np.arctan2(sine, np.trace(rel) - 1)


def test_urdf_numbers_match_reference_file(reference_dir):
    """The numbers above are those of the URDF the original trained with."""
    root = ET.parse(reference_dir / "ur5_training.urdf").getroot()
    joints = {j.get("name"): j for j in root.iter("joint") if j.get("type")}
    names = ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint", "wrist_3_joint"]
    for name, (xyz, rpy, axis) in zip(names, URDF_JOINTS):
        origin = joints[name].find("origin")
        np.testing.assert_allclose([float(v) for v in origin.get("xyz").split()], xyz, atol=1e-9)
        np.testing.assert_allclose([float(v) for v in origin.get("rpy").split()], rpy, atol=1e-9)
        np.testing.assert_allclose([float(v) for v in joints[name].find("axis").get("xyz").split()], axis)
    ee = joints["ee_fixed_joint"].find("origin")
    np.testing.assert_allclose([float(v) for v in ee.get("xyz").split()], EE_ORIGIN[0], atol=1e-9)
    np.testing.assert_allclose([float(v) for v in ee.get("rpy").split()], EE_ORIGIN[1], atol=1e-9)


def test_fk_matches_urdf_on_1000_random_configurations():
    rng = np.random.default_rng(0)
    arm = load_arm()
    count = 1000
    q = rng.uniform(arm.joint_range[:, 0], arm.joint_range[:, 1], (count, 6))
    bases = np.column_stack([rng.uniform(-3, 3, (count, 2)), rng.uniform(-np.pi, np.pi, count)])
    result = evaluate_arms(bases[:, None], q[:, None])
    frames_jax = forward_kinematics(
        arm,
        jnp.column_stack([bases[:, :2], np.zeros(count)]).astype(jnp.float32),
        yaw_quat(jnp.asarray(bases[:, 2], jnp.float32)),
        jnp.asarray(q, jnp.float32),
    )
    body_rot = np.asarray(quat_to_mat(frames_jax.body_quat))
    worst_pos = worst_rot = worst_point = 0.0
    for k in range(count):
        frames = urdf_fk(bases[k], q[k])
        ee = frames[-1]
        worst_pos = max(worst_pos, np.abs(result.ee_pos[k, 0] - ee[:3, 3]).max())
        x, y, z, w = result.ee_quat[k, 0]
        rot = np.asarray(quat_to_mat(np.array([w, x, y, z])))
        worst_rot = max(worst_rot, _rotation_angle(rot, ee[:3, :3]))
        for b in range(7):  # every link frame's orientation, too
            worst_rot = max(worst_rot, _rotation_angle(body_rot[k, b], frames[b][:3, :3]))
        points = [frames[f] @ np.array([*offset, 1.0]) for f, offset in LINK_POINTS]
        worst_point = max(worst_point, np.abs(result.points[k, 0] - np.array(points)[:, :3]).max())
    print(f"FK vs URDF (1000 configs): ee {worst_pos:.2e} m, points {worst_point:.2e} m, rotation {worst_rot:.2e} rad")
    assert worst_pos < 1e-5, worst_pos
    assert worst_point < 1e-5, worst_point
    assert worst_rot < 1e-4, worst_rot


def test_fk_matches_mujoco_kinematics_in_padded_scene():
    rng = np.random.default_rng(1)
    scene = build_scene(4)
    data = mujoco.MjData(scene.mj_model)
    bases = random_bases(rng, 4)
    q = rng.uniform(-np.pi, np.pi, (4, 6))
    base_pos = np.column_stack([bases[:, :2], np.zeros(4)])
    base_quat = np.asarray(yaw_quat(bases[:, 2]))
    set_mujoco_state(scene, data, base_pos, base_quat, q, np.ones(4, bool))
    frames = forward_kinematics(scene.arm, base_pos, base_quat, jnp.asarray(q, jnp.float32))
    m = scene.mj_model
    for i in range(4):
        ee = m.site(f"arm{i}/ee_link").id
        np.testing.assert_allclose(frames.ee_pos[i], data.site_xpos[ee], atol=1e-5)
        ee_rot = np.asarray(quat_to_mat(frames.ee_quat[i]))
        np.testing.assert_allclose(ee_rot, data.site_xmat[ee].reshape(3, 3), atol=1e-5)
        ncap = scene.arm.num_capsules
        for c, geom in enumerate(scene.geoms[i, :ncap]):
            center = frames.capsules[i, c].mean(axis=0)
            axis = frames.capsules[i, c, 1] - frames.capsules[i, c, 0]
            np.testing.assert_allclose(center, data.geom_xpos[geom], atol=1e-5)
            np.testing.assert_allclose(
                axis, 2 * m.geom_size[geom, 1] * data.geom_xmat[geom].reshape(3, 3)[:, 2], atol=1e-5
            )
        for b, geom in enumerate(scene.geoms[i, ncap:]):
            np.testing.assert_allclose(frames.boxes[i, b, 0], data.geom_xpos[geom], atol=1e-5)
            np.testing.assert_allclose(frames.boxes[i, b, 1:].T, data.geom_xmat[geom].reshape(3, 3), atol=1e-5)


def test_compiled_fk_matches_the_jax_fk():
    """The numba kinematics the CPU collision kernel and the expert's checker pose arms with
    (float64, rotation matrices) against the JAX one (float32, quaternions), on 500 arms
    anywhere in the joint range, with tilted bases (not only yaws)."""
    rng = np.random.default_rng(7)
    arm = load_arm()
    count = 500
    pos = rng.uniform(-3, 3, (count, 3))
    quat = rng.normal(size=(count, 4))
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    q = rng.uniform(arm.joint_range[:, 0], arm.joint_range[:, 1], (count, 6))
    frames = forward_kinematics(arm, *(jnp.asarray(x, jnp.float32) for x in (pos, quat, q)))
    constants, rot = compiled.arm_constants(arm), compiled.rotations(quat)
    capsules = np.empty((count, arm.num_capsules, 2, 3))
    boxes = np.empty((count, len(arm.box_half), 4, 3))
    for i in range(count):
        compiled.pose_arm(pos, rot, q, i, constants, capsules, boxes)
    np.testing.assert_allclose(capsules, frames.capsules, atol=2e-5)
    np.testing.assert_allclose(boxes, frames.boxes, atol=2e-5)


def test_compiled_constants_need_geoms_in_body_order():
    """The compiled kinematics places each body's geoms as its chain reaches the body."""
    arm = load_arm()
    shuffled = dataclasses.replace(arm, capsule_body=arm.capsule_body[::-1].copy())
    with pytest.raises(ValueError, match="body order"):
        compiled.arm_constants(shuffled)


@pytest.mark.parametrize("shape", [(6,), (2, 3, 6)])
def test_fk_broadcasts_any_batch_shape(shape):
    arm = load_arm()
    q = jnp.zeros(shape)
    frames = forward_kinematics(arm, jnp.zeros(3), jnp.array([1.0, 0, 0, 0]), q)
    assert frames.ee_pos.shape == (*shape[:-1], 3)
    assert frames.capsules.shape == (*shape[:-1], arm.num_capsules, 2, 3)
    assert frames.boxes.shape == (*shape[:-1], arm.num_boxes, 4, 3)
    assert frames.points.shape == (*shape[:-1], 10, 3)
