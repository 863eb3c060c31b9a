"""The pick-and-place application: assets, scene, grasping under physics, protocol, CLI."""

from __future__ import annotations

import copy
import csv
import json
import os
import pathlib

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from conftest import random_joints

from mjx_multiarm.geometry.collision import scene_contacts
from mjx_multiarm.geometry.ik import solve_poses
from mjx_multiarm.geometry.kinematics import forward_kinematics
from mjx_multiarm.geometry.robot import load_arm
from mjx_multiarm.geometry.scene import build_scene as build_arm_scene
from mjx_multiarm.geometry.transforms import quat_angle
from mjx_multiarm.pickplace import backends, plans, protocol
from mjx_multiarm.pickplace.scene import (
    ARM,
    ASSETS,
    BASE_POS,
    BASE_QUAT,
    GRIPPER_ARM_XML,
    GRIPPER_STROKE,
    NUM_ARMS,
    OBJECT,
    PARKED_OFFSET,
    build_scene,
    collision_model,
    gripper_arm_xml,
)
from mjx_multiarm.planner.policy import Planner

PICKPLACE_REFERENCE = pathlib.Path(__file__).resolve().parents[2] / "shared" / "reference" / "pickplace"


@pytest.fixture(scope="module")
def scene():
    return build_scene()


def test_scene_compiles_with_every_object_in_every_slot(scene):
    m = scene.model
    assert m.nu == NUM_ARMS * 8 and m.neq == NUM_ARMS  # 6 joint servos + 2 fingers per arm; one grasp weld each
    assert not m.eq_active0.any()
    assert set(scene.piece_geoms) == set(scene.object_names) and len(scene.object_names) == 6
    pos = scene.geom_pos(["cube", "sugar_box", "power_drill", "bleach_cleanser"])
    for name, geoms in scene.piece_geoms.items():
        for slot, chosen in enumerate(["cube", "sugar_box", "power_drill", "bleach_cleanser"]):
            moved = pos[geoms[slot]] - m.geom_pos[geoms[slot]]
            np.testing.assert_allclose(moved, 0 if name == chosen else np.broadcast_to(PARKED_OFFSET, moved.shape))
    assert (scene.geom_kind >= 0).all()


def test_bad_object_draws_are_named(scene):
    with pytest.raises(ValueError, match="unknown object 'anvil'"):
        scene.geom_pos(["cube", "anvil", "cube", "cube"])
    with pytest.raises(ValueError, match="one object per arm"):
        scene.geom_pos(["cube"] * 3)
    with pytest.raises(ValueError, match="one object per arm"):
        plans.plan_runs(scene, 0, 1, objects=["cube"] * 5)


def test_derived_assets_are_the_derivation_of_the_reference():
    """The committed assets are what the project's script makes of ../shared/reference."""
    pytest.importorskip("trimesh")
    if not PICKPLACE_REFERENCE.is_dir():
        pytest.skip(f"reference data not found at {PICKPLACE_REFERENCE}")
    from mjx_multiarm.pickplace.derive import derive

    fresh = json.loads(json.dumps(derive(PICKPLACE_REFERENCE)))
    committed = json.loads(ASSETS.read_text())
    assert fresh["bin"]["boxes"] == committed["bin"]["boxes"]
    for name, obj in committed["objects"].items():
        assert fresh["objects"][name]["hulls"] == obj["hulls"]
        assert fresh["objects"][name]["grasps"] == obj["grasps"]


def test_pose_ik_reaches_reachable_poses():
    arm = load_arm()
    rng = np.random.default_rng(0)
    joints = arm.home + rng.uniform(-1.0, 1.0, (64, 6))
    frames = forward_kinematics(arm, jnp.zeros(3), jnp.array([1.0, 0.0, 0.0, 0.0]), jnp.asarray(joints, jnp.float32))
    start = jnp.asarray(joints + rng.uniform(-0.4, 0.4, joints.shape), jnp.float32)
    _, position_error, angle_error = jax.jit(lambda p, q, s: solve_poses(arm, p, q, s))(frames.ee_pos, frames.ee_quat, start)
    assert float(jnp.max(position_error)) < 1e-3 and float(jnp.max(angle_error)) < 1e-2


def test_the_stored_grasp_table_is_the_packaged_scenes(scene, tmp_path, monkeypatch):
    """``grasp_table`` reads the stored table of the packaged scene (regenerate it with
    ``python -m mjx_multiarm.pickplace.plans`` when the scene changes); a table stored for
    another scene (another fingerprint) is not used."""
    with np.load(plans.GRASP_TABLE) as stored:
        assert str(stored["fingerprint"]) == plans.scene_fingerprint(scene), "stale grasp table"
        other = dict(stored)
    other["fingerprint"] = "another scene"
    np.savez(tmp_path / "table.npz", **other)
    monkeypatch.setattr(plans, "GRASP_TABLE", tmp_path / "table.npz")
    monkeypatch.setattr(plans, "compute_grasp_table", lambda scene: "computed")
    assert plans.grasp_table.__wrapped__(scene) == "computed"


@pytest.mark.slow
def test_the_stored_grasp_table_equals_a_fresh_computation(scene):
    """The stored table is what :func:`plans.compute_grasp_table` makes of the packaged scene
    (the same grasps; configurations within 1e-4 rad: float32 IK on another CPU)."""
    fresh = plans.compute_grasp_table(scene)
    stored = plans.grasp_table(scene)
    assert sorted(fresh) == sorted(stored)
    np.testing.assert_array_equal(fresh["grasp_index"], stored["grasp_index"])
    for key in fresh:
        np.testing.assert_allclose(fresh[key], stored[key], atol=1e-4, err_msg=key)


@pytest.mark.slow
def test_scripted_grasp_lifts_and_holds_every_object(scene):
    """Each arm at its grasp configuration closes the gripper, welds its object and lifts it
    0.3 m under MuJoCo physics; the object follows and stays where it was held."""
    table = plans.grasp_table(scene)
    for obj in range(len(scene.object_names)):
        m = copy.deepcopy(scene.model)
        m.geom_pos[:] = scene.geom_pos([obj] * NUM_ARMS)
        d = mujoco.MjData(m)
        grasp = table["grasp_joints"][:, obj]
        for a in range(NUM_ARMS):
            d.qpos[scene.arm_qpos[a]] = d.ctrl[scene.arm_actuators[a]] = grasp[a]
            d.qpos[scene.object_qpos[a]:scene.object_qpos[a] + 7] = table["spawn"][a, obj]
        mujoco.mj_forward(m, d)
        for _ in range(120):  # settle, gripper open
            mujoco.mj_step(m, d)
        d.ctrl[scene.finger_actuators] = GRIPPER_STROKE / 2
        for _ in range(120):
            mujoco.mj_step(m, d)
        start = d.xpos[scene.object_body].copy()
        for a in range(NUM_ARMS):
            backends.attach_mujoco(scene, m, d, a)
        held = [backends.held_pose_mujoco(scene, d, a) for a in range(NUM_ARMS)]
        lifted = np.asarray(protocol.lifted_joints(jnp.asarray(grasp, jnp.float32), 0.3))
        for k in range(240):  # 1 s up, then 0.5 s holding
            d.ctrl[scene.arm_actuators] = grasp + (lifted - grasp) * min(1.0, (k + 1) / 120)
            mujoco.mj_step(m, d)
        rise = d.xpos[scene.object_body][:, 2] - start[:, 2]
        name = scene.object_names[obj]
        assert np.all(rise > 0.27), f"{name}: rose {rise}"
        for a in range(NUM_ARMS):
            now = backends.held_pose_mujoco(scene, d, a)
            assert np.abs(now[:3] - held[a][:3]).max() < 0.005, f"{name}, arm {a}: slipped"


def test_arm_contacts_classify_touches(scene):
    m = scene.model
    arm0 = m.geom("arm0/ee_link_0").id
    arm1 = m.geom("arm1/pad_left").id
    floor, own, other = m.geom("floor").id, m.geom("object0/cube_0").id, m.geom("object2/cube_0").id
    bin_wall = m.geom("bin_wall_+x").id
    arm3 = m.geom("arm3/finger_right").id
    geom1 = np.array([arm0, own, arm0, arm1, floor, arm3])
    geom2 = np.array([own, arm1, other, bin_wall, arm1, arm1])
    dist = np.array([-0.001, -0.002, 0.01, -0.001, -0.003, -0.0005])  # the third is no touch
    flags = protocol.arm_contacts(scene, geom1, geom2, dist)
    expected = np.zeros((4, protocol.TOUCH_KINDS), bool)
    expected[0, protocol.TOUCH_OWN_OBJECT] = True
    expected[1, protocol.TOUCH_OTHER_OBJECT] = True  # arm 1 touched object 0
    expected[1, protocol.TOUCH_BIN] = True
    expected[1, protocol.TOUCH_FLOOR] = True
    expected[[1, 3], protocol.TOUCH_ARM] = True  # arm 3's finger met arm 1's pad
    np.testing.assert_array_equal(flags, expected)
    np.testing.assert_array_equal(np.asarray(protocol.arm_contacts(scene, jnp.asarray(geom1), jnp.asarray(geom2),
                                                                   jnp.asarray(dist), xp=jnp)), expected)


def test_arms_collide_with_each_other_in_the_physics_not_with_themselves(scene):
    """Every arm geom (capsules, gripper box, fingers, pads) can touch every other arm's and
    the static scene, and no geom of its own arm; a finger pushed into another arm's
    gripper is a MuJoCo contact."""
    m = scene.model
    kind, slot = scene.geom_kind, scene.geom_slot
    for g1 in np.flatnonzero(kind == ARM):
        for g2 in np.flatnonzero(kind == ARM):
            meets = bool(m.geom_contype[g1] & m.geom_conaffinity[g2] or m.geom_contype[g2] & m.geom_conaffinity[g1])
            assert meets == (slot[g1] != slot[g2]), (m.geom(g1).name, m.geom(g2).name)
        for g2 in np.flatnonzero(kind != ARM):
            assert m.geom_contype[g1] & m.geom_conaffinity[g2], (m.geom(g1).name, m.geom(g2).name)
    # Arm 1 moved (its base) so that its right pad sits on arm 0's left pad: MuJoCo reports
    # the pads' contact, and it counts as arm-arm for both.
    data = mujoco.MjData(m)
    mujoco.mj_kinematics(m, data)
    pad0, pad1 = m.geom("arm0/pad_left").id, m.geom("arm1/pad_right").id
    moved = copy.deepcopy(m)
    moved.body_pos[m.body("arm1/base_link").id] += data.geom_xpos[pad0] - data.geom_xpos[pad1]
    data = mujoco.MjData(moved)
    mujoco.mj_forward(moved, data)
    c, n = data.contact, data.ncon
    assert any({c.geom1[i], c.geom2[i]} == {pad0, pad1} and c.dist[i] < 0 for i in range(n))
    flags = protocol.arm_contacts(scene, c.geom1[:n], c.geom2[:n], c.dist[:n])
    assert flags[0, protocol.TOUCH_ARM] and flags[1, protocol.TOUCH_ARM]


def test_initial_configurations_touch_nothing_and_low_arms_rise(scene):
    """Initial configurations are free in the whole scene (grippers against the bin, floor
    and objects, as the original checks them), and ``rise`` lifts every arm that starts
    below the start height straight up to it, orientation kept; higher arms stay."""
    runs = plans.plan_runs(scene, 4000, 12)  # run 9 of seed 4000 first drew a gripper inside the bin wall
    data = mujoco.MjData(copy.deepcopy(scene.model))
    for r in range(12):
        assert not plans._arms_touch_scene(scene, data, runs.objects[r], runs.object_pose[r], runs.init_joints[r])
    start = forward_kinematics(load_arm(), jnp.asarray(BASE_POS), jnp.asarray(BASE_QUAT), jnp.asarray(runs.init_joints))
    end = forward_kinematics(load_arm(), jnp.asarray(BASE_POS), jnp.asarray(BASE_QUAT), jnp.asarray(runs.rise_joints))
    start_z, end_z = np.asarray(start.ee_pos[..., 2]), np.asarray(end.ee_pos[..., 2])
    low = start_z < plans.START_HEIGHT
    assert low.any() and (~low).any()
    np.testing.assert_allclose(end_z[low], plans.START_HEIGHT, atol=0.01)
    np.testing.assert_allclose(np.asarray(end.ee_pos[..., :2]), np.asarray(start.ee_pos[..., :2]), atol=0.01)
    assert (np.asarray(quat_angle(end.ee_quat, start.ee_quat)) < 0.02).all()
    np.testing.assert_array_equal(runs.rise_joints[~low], runs.init_joints[~low])
    # The team leaves ``rise`` together; without a rise, straight to the first policy phase.
    state = protocol.initial_state(jax.tree.map(lambda x: x[0], runs))
    assert (np.asarray(state.phase) == protocol.RISE).all() and len(set(np.asarray(state.duration).tolist())) == 1
    flat = plans.plan_runs(scene, 4000, 1, start_height=0.0)
    np.testing.assert_array_equal(flat.rise_joints, flat.init_joints)
    assert (np.asarray(protocol.initial_state(jax.tree.map(lambda x: x[0], flat)).duration) == 0).all()
    with pytest.raises(ValueError, match="start_height"):
        plans.plan_runs(scene, 0, 1, start_height=-0.1)


def test_shielded_runs_start_with_a_rise_certified_free_in_the_shields_model(scene):
    """``safe``: a run whose rise is not certified free in the shield's collision model (run
    77 of seed 7000 starts 7.7 mm into a neighbour there, run 17 rises 19.6 mm into one;
    both deadlocked or collided under the shield) draws its start again from its own stream,
    keeping its objects; a run whose rise is certified keeps its plan. A subset of run indices
    plans exactly those runs."""
    model = build_arm_scene(NUM_ARMS, *collision_model())
    plain = plans.plan_runs(scene, 7000, [16, 17, 77])
    safe = plans.plan_runs(scene, 7000, [16, 17, 77], safe=True)
    np.testing.assert_array_equal(plans.rise_certified(model, plain.init_joints, plain.rise_joints), [True, False, False])
    assert plans.rise_certified(model, safe.init_joints, safe.rise_joints).all()
    for field in ("init_joints", "rise_joints"):
        np.testing.assert_array_equal(getattr(safe, field)[0], getattr(plain, field)[0])
        assert (getattr(safe, field)[1:] != getattr(plain, field)[1:]).any(axis=(1, 2)).all()
    np.testing.assert_array_equal(safe.objects, plain.objects)
    data = mujoco.MjData(copy.deepcopy(scene.model))
    for r in range(3):
        assert not plans._arms_touch_scene(scene, data, safe.objects[r], safe.object_pose[r], safe.init_joints[r])
    one = plans.plan_runs(scene, 7000, [77])
    jax.tree.map(lambda a, b: np.testing.assert_array_equal(a[0], b[2]), one, plain)
    with pytest.raises(ValueError, match="run indices"):
        plans.plan_runs(scene, 7000, [-1])


@pytest.mark.slow
def test_a_full_run_on_mujoco_puts_every_object_in_the_bin(scene):
    run = jax.tree.map(lambda x: x[1:2], plans.plan_runs(scene, 1000, 2))  # run 1 of seed 1000
    [result] = backends.run_mujoco(scene, Planner.load().batched(4), run, max_control_steps=600)
    assert result.success and result.cause == "none" and result.strict_success, result
    assert result.phases == ["done"] * NUM_ARMS
    assert all(abs(x) < 0.34 and abs(y) < 0.37 for x, y, _ in result.object_pos)
    assert 0 < result.control_steps < 600


def test_the_gripper_asset_encloses_the_simulated_fingers(scene):
    """``assets/ur5_gripper.xml`` is the current derivation, and its second ee_link box holds
    every corner of the simulated fingers and pads at 11 openings (read off the physics
    scene), which the original's stand-in box alone does not."""
    assert GRIPPER_ARM_XML.read_text() == gripper_arm_xml()
    arm = load_arm(str(GRIPPER_ARM_XML))
    assert arm.box_names == ("ee_link_0", "ee_link_1")
    m, data = scene.model, mujoco.MjData(scene.model)
    ee = scene.ee_body[0]
    fingers = [g for g in range(m.ngeom) if m.geom(g).name.startswith(("arm0/pad_", "arm0/finger_"))]
    signs = np.array(np.meshgrid(*[[-1.0, 1.0]] * 3, indexing="ij")).reshape(3, -1).T
    outside_stand_in = 0
    for travel in np.linspace(0.0, GRIPPER_STROKE / 2, 11):
        data.qpos[scene.finger_qpos[0]] = travel
        mujoco.mj_kinematics(m, data)
        for g in fingers:
            world = data.geom_xpos[g] + (signs * m.geom_size[g]) @ data.geom_xmat[g].reshape(3, 3).T
            local = (world - data.xpos[ee]) @ data.xmat[ee].reshape(3, 3)
            for box, inside in zip(range(2), (False, True)):
                offset = np.abs((local - arm.box_frame[box, 0]) @ arm.box_frame[box, 1:].T) - arm.box_half[box]
                if inside:
                    assert offset.max() <= 1e-9, (m.geom(g).name, travel, offset.max())
                else:
                    outside_stand_in += (offset.max(axis=1) > 0).sum()
    assert outside_stand_in > 0


def test_the_collision_model_flags_every_physics_contact_of_the_arms(scene):
    """On random configurations of the four arms (fingers open), every arm that touches the
    bin, the floor or another arm in MuJoCo's physics scene is in collision in the pick-and-place
    collision model (the gripper as simulated, the bin as obstacles); the reaching model (the
    stand-in box, no bin) misses some of those arms."""
    arm_xml, obstacles = collision_model()
    rng = np.random.default_rng(4)
    joints = random_joints(rng, (300, NUM_ARMS), spread=0.6)
    pos, quat = (jnp.broadcast_to(jnp.asarray(x, jnp.float32), (300, *x.shape)) for x in (BASE_POS, BASE_QUAT))
    active = jnp.ones((300, NUM_ARMS), bool)
    verdict = {name: np.asarray(jax.jit(lambda *a, s=s: scene_contacts(s, *a).collided)(pos, quat, jnp.asarray(joints, jnp.float32), active))
               for name, s in (("cell", build_arm_scene(NUM_ARMS, arm_xml, obstacles)), ("reaching", build_arm_scene(NUM_ARMS)))}
    m, data = scene.model, mujoco.MjData(scene.model)
    touched = np.zeros((300, NUM_ARMS), bool)
    for k in range(300):
        data.qpos[scene.arm_qpos] = joints[k]
        data.qpos[scene.finger_qpos] = 0.0  # open
        mujoco.mj_kinematics(m, data)
        mujoco.mj_collision(m, data)
        for g1, g2 in data.contact.geom[: data.ncon][data.contact.dist[: data.ncon] < 0]:
            kinds = scene.geom_kind[[g1, g2]]
            if ARM in kinds and OBJECT not in kinds:
                touched[k, scene.geom_slot[[g1, g2]][kinds == ARM]] = True
    assert touched.sum() >= 30
    assert not (touched & ~verdict["cell"]).any(), np.argwhere(touched & ~verdict["cell"])[:5]
    assert (touched & ~verdict["reaching"]).any()


def test_timeouts_and_collisions_end_runs(scene):
    """A step limit too short to finish ends the run as a timeout; run 0 of seed 1000 starts
    with arm 1's gripper beside its object and ends in an arm-object collision while reaching
    (with the original protocol: no rise, no waypoint above the pregrasp)."""
    two = plans.plan_runs(scene, 1000, 2, approach_height=0.0, start_height=0.0)
    results = backends.run_mujoco(scene, Planner.load().batched(4), two, max_control_steps=20)
    assert results[0].cause == "arm-object" and results[0].cause_phase in ("reach_above", "reach_pregrasp")
    assert not results[0].success
    assert results[1].cause == "timeout" and results[1].control_steps == 20
    for result in results:  # every arm's phases in order, from rise at step 0, ending in its final phase
        assert [list(arm)[-1] for arm in result.phase_steps] == result.phases
        for arm in result.phase_steps:
            assert list(arm) == list(protocol.PHASES[:len(arm)]) and arm["rise"] == 0
            assert list(arm.values()) == sorted(arm.values()) and max(arm.values()) < result.control_steps


def test_mjx_runs_in_batches_of_at_most_four_on_cpu_without_the_scheduler_fix(scene, monkeypatch):
    """On the CPU backend XLA's MJX batches of 8 runs hang in XLA's runtime (jaxlib 0.10.2)
    unless it started with ``XLA_CPU_SCHEDULER_FIX``; without it ``run_mjx`` splits the runs
    into batches of 4, padding the last with its last run, and with it takes them all;
    MuJoCo Warp takes them all at once, or in batches of the size asked for."""
    assert jax.default_backend() == "cpu"
    monkeypatch.setattr(backends, "_scheduler_fixed", lambda: False)
    batches = []

    def fake_batch(scene, policy_step, plans, max_control_steps, chunk, impl):
        batches.append(np.asarray(plans.objects)[:, 0].tolist())
        return [int(o) for o in np.asarray(plans.objects)[:, 0]]

    monkeypatch.setattr(backends, "_run_mjx_batch", fake_batch)
    six = plans.plan_runs(scene, 1000, 6, objects=["cube"] * NUM_ARMS)
    six = six.replace(objects=np.arange(6, dtype=np.int32)[:, None].repeat(NUM_ARMS, axis=1))  # run r holds object r
    assert backends.run_mjx(scene, None, six, max_control_steps=5) == [0, 1, 2, 3, 4, 5]
    assert batches == [[0, 1, 2, 3], [4, 5, 5, 5]]
    batches.clear()
    assert backends.run_mjx(scene, None, jax.tree.map(lambda x: x[:2], six), max_control_steps=5) == [0, 1]
    assert batches == [[0, 1]]
    batches.clear()
    assert backends.run_mjx(scene, None, six, max_control_steps=5, impl="warp") == [0, 1, 2, 3, 4, 5]
    assert batches == [[0, 1, 2, 3, 4, 5]]
    batches.clear()
    assert backends.run_mjx(scene, None, six, max_control_steps=5, impl="warp", batch=4) == [0, 1, 2, 3, 4, 5]
    assert batches == [[0, 1, 2, 3], [4, 5, 5, 5]]
    with pytest.raises(ValueError, match="impl must be one of"):
        backends.run_mjx(scene, None, six, impl="c")
    batches.clear()
    monkeypatch.setattr(backends, "_scheduler_fixed", lambda: True)
    assert backends.run_mjx(scene, None, six, max_control_steps=5) == [0, 1, 2, 3, 4, 5]
    assert batches == [[0, 1, 2, 3, 4, 5]]


def test_the_scheduler_fix_takes_effect_only_before_jax_starts():
    """``fix_xla_cpu_scheduler`` puts the option in ``XLA_FLAGS`` in a process whose JAX has not
    started its backend, and says so; once the backend has started without it, it says it is
    not in effect and leaves ``XLA_FLAGS`` as it was."""
    import subprocess
    import sys

    script = ("import os, sys, jax\n"
              "from mjx_multiarm.pickplace.backends import fix_xla_cpu_scheduler, XLA_CPU_SCHEDULER_FIX\n"
              "if sys.argv[1] == 'late': jax.numpy.zeros(1).block_until_ready()\n"
              "print(fix_xla_cpu_scheduler(), XLA_CPU_SCHEDULER_FIX in os.environ.get('XLA_FLAGS', ''))\n")
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    for when, expected in (("early", "True True"), ("late", "False False")):
        out = subprocess.run([sys.executable, "-c", script, when], env=env, capture_output=True, text=True, check=True)
        assert out.stdout.split("\n")[-2] == expected, (when, out.stdout, out.stderr)


@pytest.mark.slow
def test_the_minimal_xla_reproduction_runs_a_batch_of_eight_with_the_fix():
    """``benchmarks/mjx_xla_hang.py``: eight convex meshes, one ``jit(vmap(mjx.step))`` call at
    batch 8, in a child process started with ``XLA_CPU_SCHEDULER_FIX``: it returns."""
    import importlib.util

    path = pathlib.Path(__file__).resolve().parents[1] / "benchmarks" / "mjx_xla_hang.py"
    spec = importlib.util.spec_from_file_location("mjx_xla_hang", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert module.probe(8, fix=True, timeout=300)["outcome"] == "ran"


def test_xla_collision_sizes_flag_every_dropped_contact(scene, monkeypatch):
    """MJX (XLA) culls each collision function's candidate pairs and the run's contacts to
    fixed sizes; the backend's check flags a state where a pair that can touch (bounding
    spheres overlapping, as in MuJoCo C's contacts) or an active contact may have been cut."""
    from mujoco import mjx

    plan = plans.plan_runs(scene, 1000, 1)
    models, datas = backends._settled(scene, plan)
    m, d = models[0], datas[0]
    mujoco.mj_forward(m, d)
    x = mjx.put_data(m, d)
    assert not backends._xla_collision_dropped(m)(x)
    groups = [np.asarray(g)[:, :2] for g in backends.collision_driver._geom_groups(m).values()]
    gaps = [np.linalg.norm(d.geom_xpos[g[:, 1]] - d.geom_xpos[g[:, 0]], axis=1) - m.geom_rbound[g].sum(1) for g in groups]
    most = max(int((gap <= 0).sum()) for gap in gaps)
    assert most > 1
    for g1, g2 in zip(d.contact.geom1[:d.ncon], d.contact.geom2[:d.ncon]):  # MuJoCo C's contacts overlap
        rows = [np.flatnonzero((g == [g1, g2]).all(1) | (g == [g2, g1]).all(1)) for g in groups]
        i = next(i for i, r in enumerate(rows) if r.size)
        row = rows[i][0]
        assert gaps[i][row] <= 0
    monkeypatch.setattr(backends, "MJX_MAX_GEOM_PAIRS", most - 1)
    assert backends._xla_collision_dropped(m)(x)
    monkeypatch.setattr(backends, "MJX_MAX_GEOM_PAIRS", most)
    assert not backends._xla_collision_dropped(m)(x)
    active = x.replace(_impl=x._impl.replace(contact=x._impl.contact.replace(dist=jnp.full_like(x._impl.contact.dist, -1e-3))))
    assert backends._xla_collision_dropped(m)(active)


@pytest.mark.slow
def test_mjx_backend_agrees_with_mujoco(scene):
    """The same two runs on both backends: the same outcomes, objects within 5 mm."""
    two = plans.plan_runs(scene, 1000, 2)
    step = Planner.load().batched(4)
    c = backends.run_mujoco(scene, step, two, max_control_steps=40)
    x = backends.run_mjx(scene, step, two, max_control_steps=40, chunk=20)
    for a, b in zip(c, x):
        assert (a.cause, a.cause_phase, a.phases, a.control_steps) == (b.cause, b.cause_phase, b.phases, b.control_steps)
        np.testing.assert_allclose(a.object_pos, b.object_pos, atol=5e-3)


@pytest.mark.slow
def test_mjx_warp_backend_agrees_with_mujoco_over_whole_runs(scene):
    """Four whole runs (every phase, to the end) in one batch on MJX's MuJoCo Warp and on
    MuJoCo C: the same outcome, every arm's phase sequence with each phase begun within 2
    control steps, the same control steps, every object in the bin on both (where the
    objects land in the bin differs, by up to 22 cm: a drop is chaotic)."""
    four = plans.plan_runs(scene, 1000, 4)
    step = Planner.load().batched(4)
    c = backends.run_mujoco(scene, step, four)
    x = backends.run_mjx(scene, step, four, impl="warp")
    for a, b in zip(c, x):
        assert a.success and b.success
        assert (a.cause, a.phases, a.control_steps) == (b.cause, b.phases, b.control_steps)
        assert list(a.phase_steps[0]) == list(protocol.PHASES)
        assert backends.phase_timing_difference(a, b) <= 2, (a.phase_steps, b.phase_steps)
        for objects in (a.object_pos, b.object_pos):  # in the bin, wherever the drop put them
            assert (np.abs(np.asarray(objects)[:, :2]) < protocol.bin_interior(scene)).all()


def test_cli_rejects_bad_input(tmp_path, capsys):
    from eval import pickplace

    for argv, message in ((["--objects", "cube,anvil,cube,cube"], "unknown object 'anvil'"),
                          (["--objects", "cube,cube,cube"], "4 arms"),
                          (["--checkpoint", str(tmp_path / "none.npz")], "no such policy file"),
                          (["--runs", "0"], "--runs must be >= 1"),
                          (["--approach-height", "-1"], "approach_height must be in [0, 0.5]"),
                          (["--start-height", "2"], "start_height must be in [0, 0.8]")):
        with pytest.raises(SystemExit):
            pickplace.main([*argv, "--out", str(tmp_path)])
        assert message in capsys.readouterr().err


@pytest.mark.slow
def test_cli_writes_outcomes_and_renders(tmp_path, capsys):
    """One short run end to end: the per-run table, the summary, the JSON line, and a
    rendered run (PNG frames and an MP4)."""
    from eval import pickplace

    pickplace.main(["--runs", "2", "--seed", "1000", "--max-steps", "4", "--workers", "1", "--render", "1",
                    "--out", str(tmp_path), "--json"])
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["runs"] == 2 and set(summary) >= {"success_rate", "paper_success_rate", "valid_runs", "failures",
                                                     "kernel_failures", "kernel_missed", "kernel_only"}
    assert (tmp_path / "runs.csv").read_text().count("\n") == 3 and (tmp_path / "summary.md").exists()
    for row in csv.DictReader((tmp_path / "runs.csv").open()):  # per arm: the step each phase began, rise at 0
        starts = [arm.split("/") for arm in row["phase_starts"].split()]
        assert len(starts) == NUM_ARMS and all(arm[0] == "0" for arm in starts)
    frames = sorted((tmp_path / "render" / "run_0").glob("*.png"))
    if not frames:
        pytest.skip("rendering unavailable on this machine")
    video = tmp_path / "render" / "run_0.mp4"
    assert video.stat().st_size > 1000
    import imageio.v3 as iio

    assert iio.imread(video).shape[0] >= 2  # a frame every other control step


def test_physics_fidelity_runs_reaching_tasks_under_servos():
    from eval.physics import physics_outcomes
    from mjx_multiarm.tasks.generate import GenerationSpec, generate_chunk

    tasks = generate_chunk(GenerationSpec(count=2, arm_counts=(2,), max_arms=2, seed=3, chunk_size=2), 0)
    out = physics_outcomes(Planner.load(), tasks, episode_steps=30)
    assert out["tasks"] == 2 and abs(out["success_rate"] + out["collision_rate"] + out["timeout_rate"] - 1) < 1e-9
    assert 0 <= out["tracking_error_rad"]["mean"] <= out["tracking_error_rad"]["max"] < 0.5
    with pytest.raises(ValueError, match="every slot is active"):
        physics_outcomes(Planner.load(), generate_chunk(GenerationSpec(count=2, arm_counts=(1,), max_arms=2, seed=3,
                                                                      chunk_size=2), 0))


def test_write_scene_writes_the_compiled_scene(scene, tmp_path):
    """``eval.pickplace --write-scene`` writes an MJCF that MuJoCo loads into the same scene."""
    from eval.pickplace import main

    main(["--write-scene", str(tmp_path / "scene.xml")])
    written = mujoco.MjModel.from_xml_path(str(tmp_path / "scene.xml"))
    for field in ("ngeom", "nbody", "njnt", "nu", "neq"):
        assert getattr(written, field) == getattr(scene.model, field), field
    for field in ("geom_contype", "geom_conaffinity", "geom_size", "geom_pos", "body_mass", "body_ipos", "body_inertia",
                  "dof_armature", "actuator_gainprm", "actuator_biasprm"):
        # MJCF text keeps 6 significant digits
        np.testing.assert_allclose(getattr(written, field), getattr(scene.model, field), rtol=1e-5, atol=1e-7, err_msg=field)


def test_summary_counts_physics_failures_beside_the_collision_models():
    """``failures`` are the physics' causes; ``kernel_failures`` the collision model's, and the
    runs each accounting alone flags are counted both ways."""
    from eval.pickplace import summarize

    def run(cause, kernel):
        return {"success": cause == "none", "cause": cause, "kernel_cause": kernel, "cause_phase": None,
                "strict_cause": cause, "strict_success": cause == "none", "physics_steps": 1200}

    results = [run("arm-arm", "none"), run("arm-arm", "arm-arm"), run("none", "arm-arm"), run("arm-bin", "arm-bin"),
               run("none", "none"), run("timeout", "none")]
    summary = summarize(results, wall_seconds=1.0)
    assert summary["failures"] == {"arm-arm": 2, "arm-bin": 1, "timeout": 1}
    assert summary["kernel_failures"] == {"arm-arm": 2, "arm-bin": 1}
    assert summary["kernel_missed"] == 1 and summary["kernel_only"] == 1
    assert summary["success_rate"] == 2 / 6
