"""Safe execution: shielded team steps never collide, and change nothing that is free."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from conftest import facing_pair, rollout

from mjx_multiarm.env.reaching import EnvConfig, ReachingEnv
from mjx_multiarm.env.shield import AWAY, HELD, PROPOSED, away_joints, box_distances
from mjx_multiarm.env.wrappers import TaskBank
from mjx_multiarm.geometry.certified import certified_contacts
from mjx_multiarm.geometry.collision import (
    CONTACTS_ONLY,
    scene_contacts,
    swept_contacts,
)
from mjx_multiarm.geometry.kinematics import forward_kinematics
from mjx_multiarm.tasks.types import take


@pytest.fixture(scope="module")
def crowded(generated):
    """Free configurations of the generated 2-4-arm teams in 4 slots, and proposals
    that drive every arm at full speed toward its goal (some of them collide)."""
    tasks = take(generated, (generated.num_arms >= 2) & (generated.num_arms <= 4))
    env = ReachingEnv(4)
    t = TaskBank.from_tasks(tasks, 4).tasks
    # Every team at its start and 1/4, 1/2 and 3/4 along its straight joint path to its goal, where free.
    t = jax.tree.map(lambda x: jnp.concatenate([x] * 4), t)
    fraction = jnp.repeat(jnp.arange(4) / 4, tasks.num_tasks)[:, None, None]
    t = t.replace(start_joints=t.start_joints + fraction * (t.goal_joints - t.start_joints))
    free = ~np.asarray(scene_contacts(env.scene, t.base_pos, t.base_quat, t.start_joints, t.active).collided.any(-1))
    t = jax.tree.map(lambda x: x[free], t)
    proposed = env.next_joints(t.start_joints, env.joint_deltas_to_actions(t.goal_joints - t.start_joints), t.active)
    return env, t, proposed


def test_shielded_steps_never_collide_and_free_steps_pass_unchanged(crowded):
    env, t, proposed = crowded
    limits = {"joint_range": env.joint_range, "max_step": env.max_step}
    shield = jax.jit(jax.vmap(env.shield))
    executed, motion, contacts = shield(t.base_pos, t.base_quat, t.start_joints, proposed, t.active)
    certify = jax.jit(lambda p, q, a, b, active: certified_contacts(env.scene, p, q, a, b, active))
    asked = np.asarray(certify(t.base_pos, t.base_quat, t.start_joints, proposed, t.active).collided.any(-1))
    assert 5 <= asked.sum() < len(asked)  # the proposals are not certified free in some teams, not all
    # The independent check: 256 configurations along every executed step, none in contact.
    dense = swept_contacts(env.scene, t.base_pos, t.base_quat, t.start_joints, executed, t.active, 256, max_distance=CONTACTS_ONLY)
    assert not np.asarray(dense.collided).any()
    np.testing.assert_array_equal(np.asarray(contacts.min_distance),
                                  np.asarray(certify(t.base_pos, t.base_quat, t.start_joints, executed, t.active).min_distance))
    executed, motion, proposed = (np.asarray(x) for x in (executed, motion, proposed))
    start, active = np.asarray(t.start_joints), np.asarray(t.active)
    np.testing.assert_array_equal(executed[~asked], proposed[~asked])  # free team steps are left alone
    assert (motion[~asked][active[~asked]] == PROPOSED).all()
    away = np.asarray(jax.jit(jax.vmap(functools.partial(away_joints, env.scene, **limits)))(t.base_pos, t.base_quat, t.start_joints,
                                                                                    t.active))
    for level, expected in ((PROPOSED, proposed), (AWAY, away), (HELD, start)):
        np.testing.assert_allclose(executed[motion == level], expected[motion == level], atol=1e-6)
    assert (motion[asked] == PROPOSED).any() and (motion[asked] != PROPOSED).any()  # some pass, some give way
    assert (motion[~active] == HELD).all()
    ratio = (np.abs(away - start) / env.max_step).max(-1)[active]  # a full step away, or none (no arm near)
    assert np.all(np.isclose(ratio, 1.0, atol=1e-4) | (ratio < 1e-6)) and (ratio > 0.5).mean() > 0.5


def test_arms_driven_into_each_other_never_collide_when_shielded():
    """Two arms driven into each other (the plain environment ends that episode in a
    collision, test_env): shielded, the drive goes on to the step limit without one."""
    bank = TaskBank.from_tasks(facing_pair(), 2)
    final, states, _ = rollout(ReachingEnv(2, EnvConfig(max_steps=80, safe=True)), 80)(bank.tasks, jnp.asarray([0.02, 0.1]))
    assert not np.asarray(states.collided).any() and np.asarray(states.metrics["min_distance"]).min() >= 0
    task = jax.tree.map(lambda x: x[0], bank.tasks)  # its executed steps, re-checked densely
    joints = np.concatenate([np.asarray(task.start_joints)[None], np.asarray(states.joints[:, 0])])
    dense = swept_contacts(ReachingEnv(2).scene, task.base_pos, task.base_quat, joints[:-1], joints[1:], task.active, 256)
    assert not np.asarray(dense.collided).any()
    assert np.asarray(states.metrics["shielded"][:, 0]).any(axis=0).all()  # both arms had to give way
    assert bool(final.truncated[0]) and int(final.step[0]) == 80


def test_the_step_away_leaves_static_obstacles():
    """An arm alone beside a box (a bin wall the policy does not see) steps away from it,
    where without the box it would stay; the box distances are MuJoCo's (a point is a
    sphere of radius 0)."""
    bare = ReachingEnv(1)
    base_pos, base_quat, active = jnp.zeros((1, 3)), jnp.array([[1.0, 0.0, 0.0, 0.0]]), jnp.ones(1, bool)
    joints = jnp.asarray(bare.scene.arm.home, jnp.float32)[None]
    ee = np.asarray(forward_kinematics(bare.scene.arm, base_pos, base_quat, joints).points)[0, -1]
    box = ((float(ee[0]), float(ee[1]) + 0.15, float(ee[2])), (0.9238795, 0.0, 0.0, 0.3826834), (0.05, 0.08, 0.2))
    walled = ReachingEnv(1, EnvConfig(), None, (box,))
    limits = {"joint_range": bare.joint_range, "max_step": bare.max_step}
    np.testing.assert_array_equal(np.asarray(away_joints(bare.scene, base_pos, base_quat, joints, active, **limits)),
                                  np.asarray(joints))

    def nearest(q):
        points = forward_kinematics(walled.scene.arm, base_pos, base_quat, q).points
        return float(box_distances(walled.scene, points).min())

    away = away_joints(walled.scene, base_pos, base_quat, joints, active, **limits)
    assert nearest(away) > nearest(joints) + 0.005
    assert np.isclose(np.abs(np.asarray(away - joints)) / np.asarray(bare.max_step), 1.0, atol=1e-4).any()
    # The signed distances against MuJoCo's, outside and inside the box.
    m = mujoco.MjModel.from_xml_string(
        f"""<mujoco><worldbody><geom name="box" type="box" pos="{' '.join(map(str, box[0]))}"
        quat="{' '.join(map(str, box[1]))}" size="{' '.join(map(str, box[2]))}"/>
        <body name="probe" mocap="true"><geom name="point" type="sphere" size="1e-6" contype="0" conaffinity="0"/></body>
        </worldbody></mujoco>""")
    d = mujoco.MjData(m)
    points = np.asarray(box[0]) + np.random.default_rng(0).uniform(-0.3, 0.3, (64, 3))
    ours = np.asarray(box_distances(walled.scene, jnp.asarray(points, jnp.float32)))[:, 0]
    for point, distance in zip(points, ours):
        d.mocap_pos[0] = point
        mujoco.mj_kinematics(m, d)
        np.testing.assert_allclose(distance, mujoco.mj_geomDistance(m, d, 0, 1, 1.0, None) + 1e-6, atol=2e-5)
