"""Collision checking against MuJoCo C on the same model, hand-made cases, padding."""

from __future__ import annotations

import functools
import importlib
import json
import pathlib

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from conftest import random_padded_scenes
from hypothesis import given, settings
from hypothesis import strategies as st

from mjx_multiarm import (
    evaluate_arms,
    forward_kinematics,
    num_substeps,
    scene_contacts,
    swept_contacts,
)
from mjx_multiarm.geometry import compiled as compiled_kernel
from mjx_multiarm.geometry.collision import (
    CONTACTS_ONLY,
    KERNEL_VARIABLE,
    KERNELS,
    frame_contacts,
    geom_clearances,
)
from mjx_multiarm.geometry.evaluate import base_pose_arrays
from mjx_multiarm.geometry.scene import build_scene, set_mujoco_state

MAX_ARMS = 10


@pytest.fixture(params=KERNELS)
def kernel(request, monkeypatch):
    """Each collision kernel in turn, as the default of the functions the test traces."""
    monkeypatch.setenv(KERNEL_VARIABLE, request.param)
    return request.param


def _jax_contacts(scene, bases, joints, active):
    pos, quat = base_pose_arrays(bases)
    f = jax.jit(lambda *a: scene_contacts(scene, *a))
    contacts = f(jnp.asarray(pos, jnp.float32), jnp.asarray(quat, jnp.float32), jnp.asarray(joints, jnp.float32), active)
    return jax.tree.map(np.asarray, contacts)


def _mujoco_collided(scene, data, bases, joints, active):
    """Per-arm verdict of ``mj_collision`` (a contact with negative distance)."""
    pos, quat = base_pose_arrays(bases)
    set_mujoco_state(scene, data, pos, quat, joints, active)
    mujoco.mj_collision(scene.mj_model, data)
    touching = np.zeros(scene.mj_model.ngeom, bool)
    contact = data.contact
    hits = contact.geom[: data.ncon][contact.dist[: data.ncon] < 0]
    touching[hits.ravel()] = True
    return touching[scene.geoms].any(axis=1) & active


def _mujoco_distances(scene, data, bases, joints, active):
    """Per-arm smallest signed distance by kind from ``mj_geomDistance`` over the same pairs."""
    pos, quat = base_pose_arrays(bases)
    set_mujoco_state(scene, data, pos, quat, joints, active)
    m, geoms, pairs = scene.mj_model, scene.geoms, scene.pairs
    out = {kind: np.full(scene.max_arms, np.inf) for kind in ("between", "self", "ground")}
    arms = np.flatnonzero(active)
    for i in arms:
        for a, b in pairs.self_pairs:
            out["self"][i] = min(out["self"][i], mujoco.mj_geomDistance(m, data, geoms[i, a], geoms[i, b], 100.0, None))
        for c in pairs.ground:
            out["ground"][i] = min(out["ground"][i], mujoco.mj_geomDistance(m, data, scene.ground_geom, geoms[i, c], 100.0, None))
        for j in arms[arms > i]:
            for a, b in zip(*np.nonzero(pairs.between_arms)):
                d = mujoco.mj_geomDistance(m, data, geoms[i, a], geoms[j, b], 100.0, None)
                out["between"][i], out["between"][j] = min(out["between"][i], d), min(out["between"][j], d)
    return out


@pytest.mark.slow
def test_verdicts_agree_with_mujoco_on_10000_random_scenes(kernel):
    rng = np.random.default_rng(0)
    scene = build_scene(MAX_ARMS)
    data = mujoco.MjData(scene.mj_model)
    bases, joints, active = random_padded_scenes(rng, 10_000, MAX_ARMS)
    ours = _jax_contacts(scene, bases, joints, active).collided
    theirs = np.array([_mujoco_collided(scene, data, bases[k], joints[k], active[k]) for k in range(len(bases))])
    disagree = np.argwhere(ours != theirs)
    assert len(disagree) == 0, f"{len(disagree)} arm verdicts differ, first at (scene, arm) {disagree[:5].tolist()}"
    # A good share of both verdicts, and every kind of contact, occurs.
    share = ours[active].mean()
    print(f"10,000 scenes, {active.sum()} arms: {len(disagree)} verdicts differ from mj_collision; {share:.1%} collided")
    assert 0.2 < share < 0.8, share


def test_signed_distances_match_mj_geom_distance(kernel):
    rng = np.random.default_rng(1)
    scene = build_scene(MAX_ARMS)
    data = mujoco.MjData(scene.mj_model)
    bases, joints, active = random_padded_scenes(rng, 40, MAX_ARMS)
    ours = _jax_contacts(scene, bases, joints, active)
    worst = 0.0
    for k in range(len(bases)):
        theirs = _mujoco_distances(scene, data, bases[k], joints[k], active[k])
        for kind, mine in (("between", ours.between_arms), ("self", ours.within_arm), ("ground", ours.ground)):
            finite = np.isfinite(theirs[kind])
            np.testing.assert_array_equal(np.isfinite(mine[k]), finite, err_msg=kind)
            # Apart: the same distance. Penetrating: both negative (depths of boxes differ).
            apart = finite & (theirs[kind] >= 0)
            np.testing.assert_allclose(mine[k][apart], theirs[kind][apart], atol=1e-4, err_msg=f"scene {k} {kind}")
            np.testing.assert_array_equal(mine[k][finite] < 0, theirs[kind][finite] < 0, err_msg=f"scene {k} {kind}")
            worst = max(worst, np.abs(mine[k][apart] - theirs[kind][apart]).max(initial=0.0))
    print(f"per-arm smallest distances vs mj_geomDistance ({active.sum()} arms): max difference {worst:.2e} m")


#: Two static boxes, one turned about x and z, in the workspace of random 4-arm scenes.
OBSTACLES = (((0.4, 0.0, 0.3), (1.0, 0.0, 0.0, 0.0), (0.1, 0.2, 0.3)),
             ((-0.3, 0.3, 0.2), (0.8924, 0.3696, 0.0, 0.2588), (0.05, 0.3, 0.15)))


def test_obstacle_distances_match_mj_geom_distance(monkeypatch):
    """With static boxes in the scene, each arm's ``ground`` distance is the smallest of its
    height and its distances to the boxes, as ``mj_geomDistance`` gives them on the same
    model (the boxes are world geoms of its MJCF); the numba kernel refuses such scenes."""
    scene = build_scene(4, None, OBSTACLES)
    m, data = scene.mj_model, mujoco.MjData(scene.mj_model)
    boxes = [m.geom(f"obstacle{k}").id for k in range(len(OBSTACLES))]
    bases, joints, active = random_padded_scenes(np.random.default_rng(3), 60, 4)
    ours = _jax_contacts(scene, bases, joints, active).ground
    plain = _jax_contacts(build_scene(4), bases, joints, active).ground
    near_box = 0
    for k in range(len(bases)):
        pos, quat = base_pose_arrays(bases[k])
        set_mujoco_state(scene, data, pos, quat, joints[k], active[k])
        for i in np.flatnonzero(active[k]):
            to_box = min(mujoco.mj_geomDistance(m, data, b, scene.geoms[i, g], 100.0, None) for b in boxes for g in scene.pairs.ground)
            theirs = min(to_box, *(mujoco.mj_geomDistance(m, data, scene.ground_geom, scene.geoms[i, g], 100.0, None)
                                   for g in scene.pairs.ground))
            assert (ours[k, i] < 0) == (theirs < 0), (k, i, ours[k, i], theirs)
            if theirs >= 0:
                np.testing.assert_allclose(ours[k, i], theirs, atol=1e-4)
            near_box += to_box < plain[k, i]
    assert near_box >= 20  # the boxes decide many arms' distances
    monkeypatch.setenv(KERNEL_VARIABLE, "numba")
    with pytest.raises(ValueError, match="numba collision kernel has no static obstacles"):
        _jax_contacts(scene, bases[:1], joints[:1], active[:1])
    with pytest.raises(ValueError, match="half sizes must be positive"):
        build_scene(2, None, (((0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0), (0.1, 0.0, 0.1)),))


def test_geom_clearances_match_mj_geom_distance_per_geom():
    """Per collision geom of one arm, its signed distance to another arm is the smallest
    ``mj_geomDistance`` to that arm's geoms (apart: equal; penetrating: both negative)."""
    rng = np.random.default_rng(2)
    scene = build_scene(2)
    data = mujoco.MjData(scene.mj_model)
    bases, joints, active = random_padded_scenes(rng, 40, 2)
    active[:] = True
    pos, quat = base_pose_arrays(bases)
    frames = forward_kinematics(scene.arm, pos, quat, joints)
    ours = np.asarray(geom_clearances(scene, frames.capsules[:, 0], frames.boxes[:, 0], frames.capsules[:, 1], frames.boxes[:, 1]))
    assert ours.shape == (40, len(scene.arm.geom_names))
    m, geoms = scene.mj_model, scene.geoms
    for k in range(len(bases)):
        set_mujoco_state(scene, data, pos[k], quat[k], joints[k], active[k])
        theirs = np.array([min(mujoco.mj_geomDistance(m, data, geoms[0, a], geoms[1, b], 100.0, None)
                               for b in np.flatnonzero(scene.pairs.between_arms[a])) for a in range(geoms.shape[1])])
        apart = theirs >= 0
        np.testing.assert_allclose(ours[k][apart], theirs[apart], atol=1e-4, err_msg=f"scene {k}")
        np.testing.assert_array_equal(ours[k] < 0, theirs < 0, err_msg=f"scene {k}")
    between = np.asarray(_jax_contacts(scene, bases, joints, active).between_arms[:, 0])
    np.testing.assert_allclose(ours.min(axis=1), between, atol=1e-6)  # the kernel's per-arm figure
    assert 0 < (ours.min(axis=1) < 0).mean() < 1


def _two_arms(joints_a, joints_b, distance=0.9):
    """Two arms facing each other along x, ``distance`` apart."""
    return np.array([[0.0, 0.0, 0.0], [distance, 0.0, np.pi]]), np.array([joints_a, joints_b], float)


# At zero pan the arm stretches along +x of its base (toward the other arm, turned by pi).
REACH_OUT = [0.0, 0.0, 0.0, -np.pi / 2, 0.0, 0.0]  # horizontal, stretched out
UPRIGHT = [0.0, -np.pi / 2, 0.0, -np.pi / 2, 0.0, 0.0]


def _reference_verdict(scene, bases, joints):
    return _mujoco_collided(scene, mujoco.MjData(scene.mj_model), bases, joints, np.ones(len(joints), bool))


def test_two_arms_reaching_into_each_other():
    scene = build_scene(2)
    bases, joints = _two_arms(REACH_OUT, REACH_OUT)
    result = evaluate_arms(bases, joints)
    assert result.collided.all() and (result.distance_between_arms < 0).all()
    np.testing.assert_array_equal(result.collided, _reference_verdict(scene, bases, joints))
    far = evaluate_arms(*_two_arms(UPRIGHT, UPRIGHT, distance=1.8))
    assert not far.collided.any()


def test_arm_folded_onto_itself():
    folded = [0.0, -np.pi / 2, 3.1, 0.0, 0.0, 0.0]  # elbow fully bent: forearm onto upper arm
    result = evaluate_arms(np.zeros((1, 3)), np.array([folded]))
    assert result.collided[0] and result.distance_within_arm[0] < 0
    assert result.distance_ground[0] > 0 and np.isinf(result.distance_between_arms[0])


def test_arm_through_the_floor():
    down = [0.0, np.pi / 2, 0.0, 0.0, 0.0, 0.0]  # upper arm pointing straight down
    result = evaluate_arms(np.zeros((1, 3)), np.array([down]))
    assert result.collided[0] and result.distance_ground[0] < -0.3
    assert not evaluate_arms(np.zeros((1, 3)), np.array([UPRIGHT])).collided[0]


def test_swept_motion_collides_between_free_endpoints(kernel):
    """Arm 1 swings its pan through arm 0: both ends are free, the middle is not."""
    scene = build_scene(2)
    bases = np.array([[0.0, 0.0, 0.0], [0.75, 0.0, np.pi]])
    start = np.array([UPRIGHT, [-1.2, 0.0, 0.0, -np.pi / 2, 0.0, 0.0]])
    end = start.copy()
    end[1, 0] = 1.2
    pos, quat = base_pose_arrays(bases)
    active = np.ones(2, bool)
    endpoints = [evaluate_arms(bases, q) for q in (start, end)]
    assert not any(r.collided.any() for r in endpoints)
    steps = num_substeps(start, end)
    assert steps == 48  # 2.4 rad at 0.05 rad per check
    sweep = jax.jit(lambda *a, substeps: swept_contacts(scene, *a, substeps), static_argnames="substeps")
    args = (pos, quat, jnp.asarray(start, jnp.float32), jnp.asarray(end, jnp.float32), active)
    assert bool(sweep(*args, substeps=steps).collided.all())
    # Checking only the end point misses it (the sweep's checks include the end point).
    assert not bool(sweep(*args, substeps=1).collided.any())


def test_padding_does_not_change_results():
    """The same 3-arm task in a 3-slot and a 10-slot model, padded slots anywhere."""
    rng = np.random.default_rng(2)
    bases, joints, _ = random_padded_scenes(rng, 30, 3)
    small = evaluate_arms(bases, joints)
    padded_bases = np.zeros((30, 10, 3))
    padded_joints = rng.normal(size=(30, 10, 6))  # junk in the inactive slots
    padded_bases[:, 3:, :2] = 0.1  # inactive bases on top of the active ones
    padded_bases[:, :3], padded_joints[:, :3] = bases, joints
    active = np.zeros((30, 10), bool)
    active[:, :3] = True
    big = evaluate_arms(padded_bases, padded_joints, active, max_arms=10)
    np.testing.assert_array_equal(big.collided[:, :3], small.collided)
    # Values agree to float32 rounding (XLA vectorizes the two shapes differently).
    for field in ("ee_pos", "ee_quat", "points", "min_distance", "distance_between_arms", "distance_within_arm"):
        np.testing.assert_allclose(getattr(big, field)[:, :3], getattr(small, field), atol=1e-6, err_msg=field)
    assert np.isinf(big.min_distance[:, 3:]).all() and not big.collided[:, 3:].any()


def test_inactive_slot_between_active_ones():
    bases, joints = _two_arms(REACH_OUT, REACH_OUT)
    three = np.stack([bases[0], [0.45, 0.0, 0.0], bases[1]])
    three_joints = np.stack([joints[0], REACH_OUT, joints[1]])
    result = evaluate_arms(three, three_joints, np.array([True, False, True]))
    assert result.collided[[0, 2]].all() and not result.collided[1]
    alone = evaluate_arms(three, three_joints, np.array([True, False, False]))
    assert not alone.collided.any()


@pytest.mark.parametrize("num_arms", [1, 2, 10])
def test_every_slot_count_compiles_and_has_consistent_pairs(num_arms):
    scene = build_scene(num_arms)
    pairs = scene.pairs
    assert len(pairs.self_pairs) > 0 and 0 not in pairs.ground  # the base never meets the ground
    if num_arms > 1:
        np.testing.assert_array_equal(pairs.between_arms, pairs.between_arms.T)


@pytest.mark.slow
def test_chunked_and_whole_batch_checks_agree():
    rng = np.random.default_rng(3)
    scene = build_scene(4)
    bases, joints, active = random_padded_scenes(rng, 50, 4)
    pos, quat = base_pose_arrays(bases)
    frames = forward_kinematics(scene.arm, pos, quat, jnp.asarray(joints, jnp.float32))
    whole = frame_contacts(scene, frames, active, chunk=50, kernel="xla")
    chunked = frame_contacts(scene, frames, active, chunk=8, kernel="xla")  # 7 chunks, the last one padded
    for field in ("between_arms", "within_arm", "ground"):
        np.testing.assert_allclose(getattr(chunked, field), getattr(whole, field), atol=1e-6, err_msg=field)


def test_numba_and_xla_kernels_give_the_same_distances():
    """The two kernels on the same posed scenes (1-10 active arms, padding, some arms far
    apart), called on a [2, N] batch under vmap: the same infinities, distances equal to
    float32 rounding, hence the same verdicts away from contact."""
    rng = np.random.default_rng(4)
    scene = build_scene(MAX_ARMS)
    bases, joints, active = random_padded_scenes(rng, 300, MAX_ARMS, spread=1.5)
    bases[::7, :, :2] *= 3.0  # teams spread beyond reach of each other
    pos, quat = base_pose_arrays(bases)
    frames = forward_kinematics(scene.arm, pos, quat, jnp.asarray(joints, jnp.float32))
    split = jax.tree.map(lambda x: x.reshape(2, -1, *x.shape[1:]), (frames, jnp.asarray(active)))

    def contacts(kernel):
        one = jax.jit(jax.vmap(lambda f, a: frame_contacts(scene, f, a, kernel=kernel)))
        return jax.tree.map(lambda x: np.asarray(x).reshape(-1, MAX_ARMS), one(*split))

    xla, compiled = contacts("xla"), contacts("numba")
    for field in ("between_arms", "within_arm", "ground"):
        a, b = getattr(compiled, field), getattr(xla, field)
        np.testing.assert_array_equal(np.isinf(a), np.isinf(b), err_msg=field)
        finite = np.isfinite(b)
        np.testing.assert_allclose(a[finite], b[finite], atol=2e-6, err_msg=field)
    clear = np.abs(xla.min_distance) > 1e-5
    np.testing.assert_array_equal(compiled.collided[clear], xla.collided[clear])
    assert 0.1 < xla.collided[active].mean() < 0.9 and np.isinf(xla.between_arms[~active]).all()


def test_numba_kernel_checks_only_the_masked_pairs():
    """With a between-arms mask that leaves pairs out (none, or capsules only), the numba
    kernel's distance between arms is the brute-force minimum over the pairs left in."""
    rng = np.random.default_rng(8)
    scene = build_scene(3)
    bases, joints, active = random_padded_scenes(rng, 30, 3)
    frames = forward_kinematics(scene.arm, *base_pose_arrays(bases), jnp.asarray(joints, jnp.float32))
    capsules, boxes = np.asarray(frames.capsules), np.asarray(frames.boxes)
    arm, ncap = scene.arm, scene.arm.num_capsules
    radius, half = arm.capsule_radius.astype(np.float64), arm.box_half.astype(np.float64)
    capsules_only = np.zeros_like(scene.pairs.between_arms)
    capsules_only[:ncap, :ncap] = True
    for mask in (np.zeros_like(capsules_only), capsules_only):
        between = compiled_kernel.batch_contacts(radius, half, np.zeros((0, 2), np.int64), mask, scene.pairs.ground.astype(np.int64),
                                                 capsules[:, None], boxes[:, None], active)[0]
        expected = np.full(active.shape, np.inf)
        for n, i, j, a, b in np.argwhere(np.ones((len(active), 3, 3, *mask.shape), bool) & mask):
            if i != j and active[n, i] and active[n, j]:
                d = compiled_kernel.geom_distance(capsules[n].astype(np.float64), boxes[n].astype(np.float64), i, a, j, b,
                                                  radius, half)
                expected[n, i] = min(expected[n, i], d)
        np.testing.assert_allclose(between, expected, atol=1e-6)
    assert np.isfinite(expected[active.sum(axis=1) > 1]).any()


def _random_motions(seed: int, count: int, num_arms: int):
    """(scene, base_pos, base_quat, start, end, active): random padded scenes and joint
    motions of up to 0.3 rad per joint, float32."""
    rng = np.random.default_rng(seed)
    scene = build_scene(num_arms)
    bases, start, active = random_padded_scenes(rng, count, num_arms)
    end = start + rng.uniform(-0.3, 0.3, start.shape)
    pos, quat = base_pose_arrays(bases)
    return scene, pos, quat, jnp.asarray(start, jnp.float32), jnp.asarray(end, jnp.float32), active


@pytest.mark.parametrize("with_end_frames", [False, True])
def test_swept_checks_agree_between_kernels(monkeypatch, with_end_frames):
    """The numba kernel's swept check (one call over the substeps, each substep's distances
    bounding the next's) gives each arm the XLA kernel's smallest distance over them."""
    scene, pos, quat, start, end, active = _random_motions(5, 64, 4)
    end_frames = forward_kinematics(scene.arm, pos, quat, end) if with_end_frames else None

    def swept(kernel):
        monkeypatch.setenv(KERNEL_VARIABLE, kernel)
        check = jax.jit(lambda *a: swept_contacts(scene, *a, substeps=6, end_frames=end_frames))
        return jax.tree.map(np.asarray, check(pos, quat, start, end, active))

    xla, compiled = swept("xla"), swept("numba")
    for field in ("between_arms", "within_arm", "ground"):
        a, b = getattr(compiled, field), getattr(xla, field)
        np.testing.assert_array_equal(np.isinf(a), np.isinf(b), err_msg=field)
        np.testing.assert_allclose(a[np.isfinite(b)], b[np.isfinite(b)], atol=2e-6, err_msg=field)
    assert 0.1 < xla.collided[active].mean() < 0.9


# The XLA kernel clips its exact distances at the end; the numba kernel skips pairs, the risk the fast tier checks.
@pytest.mark.parametrize("kernel", ["numba", pytest.param("xla", marks=pytest.mark.slow)], indirect=True)
def test_max_distance_clips_the_distances_and_keeps_the_verdicts(kernel):
    """With ``max_distance`` (0: contacts only, and 5 cm) every distance is the exact one
    clipped at it (the numba kernel skips the pairs that cannot come within it), for one
    configuration and for a swept motion, so the verdicts are those of the exact query."""
    scene, pos, quat, start, end, active = _random_motions(9, 200, 5)

    @functools.partial(jax.jit, static_argnums=0)
    def queries(limit):
        return (scene_contacts(scene, pos, quat, start, active, limit),
                swept_contacts(scene, pos, quat, start, end, active, substeps=4, max_distance=limit))

    exact_queries = queries(np.inf)
    for max_distance in (CONTACTS_ONLY, 0.05):
        for exact, clipped in zip(exact_queries, queries(max_distance)):
            for field in ("between_arms", "within_arm", "ground"):
                np.testing.assert_allclose(getattr(clipped, field), np.minimum(getattr(exact, field), max_distance),
                                           atol=2e-6, err_msg=f"{field} at {max_distance}")
            np.testing.assert_array_equal(clipped.collided, exact.collided)
            assert 0.1 < exact.collided[active].mean() < 0.9


@settings(max_examples=10)
@given(st.floats(-5, 5), st.floats(-5, 5), st.floats(-np.pi, np.pi), st.integers(0, 2**31 - 1))
def test_planar_rigid_motion_of_the_whole_scene_changes_nothing(dx, dy, yaw, seed):
    rng = np.random.default_rng(seed)
    bases, joints, _ = random_padded_scenes(rng, 4, 4)
    c, s = np.cos(yaw), np.sin(yaw)
    moved = bases.copy()
    moved[..., 0] = c * bases[..., 0] - s * bases[..., 1] + dx
    moved[..., 1] = s * bases[..., 0] + c * bases[..., 1] + dy
    moved[..., 2] = bases[..., 2] + yaw
    a, b = evaluate_arms(bases, joints), evaluate_arms(moved, joints)
    np.testing.assert_array_equal(a.collided, b.collided)
    for field in ("distance_between_arms", "distance_within_arm", "distance_ground"):
        np.testing.assert_allclose(getattr(b, field), getattr(a, field), atol=1e-5, err_msg=field)


@pytest.mark.parametrize("contacts_only", [False, True])
def test_verdicts_match_the_recorded_reference(kernel, contacts_only, monkeypatch, capsys):
    """The first 2,000 of the 100,000 random scenes recorded by benchmarks/collision_verdicts.py
    give the recorded verdicts, arm by arm, and the numba checker's: a kernel change that
    keeps the collision model changes no verdict. Asking for contacts only changes none either."""
    benchmarks = pathlib.Path(__file__).parents[1] / "benchmarks"
    monkeypatch.syspath_prepend(str(benchmarks))
    verdicts = importlib.import_module("collision_verdicts")
    query = ["--max-distance", str(CONTACTS_ONLY), "--no-checker"] if contacts_only else []
    verdicts.main(["--scenes", "2000", "--reference", str(benchmarks / "collision_verdicts_100k.npz"), "--json", *query])
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert result["differ_from_reference"] == 0 and result.get("differ_from_checker", 0) == 0, result
    assert 0.2 < result["collided_arms"] / result["arms"] < 0.8


def test_self_pairs_nearest_first_is_an_ordering_by_mean_distance():
    """The numba kernel's self pairs: the same pairs, nearest first over the sampled configurations."""
    scene = build_scene(1)
    arm, pairs = scene.arm, scene.pairs.self_pairs.astype(np.int64)
    radius, box_half = arm.capsule_radius.astype(np.float64), arm.box_half.astype(np.float64)
    joints = np.random.default_rng(3).uniform(arm.joint_range[:, 0], arm.joint_range[:, 1], (16, 6))
    ordered = compiled_kernel.nearest_first(compiled_kernel.arm_constants(arm), radius, box_half, pairs, joints)
    assert sorted(map(tuple, ordered)) == sorted(map(tuple, pairs))
    frames = forward_kinematics(arm, np.zeros(3), np.array([1.0, 0, 0, 0]), joints)
    capsules, boxes = np.asarray(frames.capsules, np.float64), np.asarray(frames.boxes, np.float64)
    mean = [np.mean([compiled_kernel.geom_distance(capsules, boxes, i, a, i, b, radius, box_half) for i in range(16)])
            for a, b in ordered]
    assert np.all(np.diff(mean) >= -1e-5)  # the kernel's own float64 poses against float32 ones
