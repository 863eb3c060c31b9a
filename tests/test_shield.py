"""Safe execution: shielded team steps never collide, and change nothing that is free."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import facing_pair, rollout

from mjx_multiarm.env.reaching import EnvConfig, ReachingEnv
from mjx_multiarm.env.shield import AWAY, HELD, PROPOSED, away_joints
from mjx_multiarm.env.wrappers import TaskBank
from mjx_multiarm.geometry.certified import certified_contacts
from mjx_multiarm.geometry.collision import (
    CONTACTS_ONLY,
    scene_contacts,
    swept_contacts,
)
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
