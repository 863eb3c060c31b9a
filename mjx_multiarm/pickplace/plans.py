"""Run plans of the pick-and-place protocol: draws from a seed, object placements, grasps,
and the configurations the phases head for.

A run's draws (objects, initial configuration) come from ``np.random.default_rng([seed, run])``.
Everything else is a deterministic table per arm and object (:func:`grasp_table`): where the
object stands, which GraspIt grasp the arm uses, the pregrasp / grasp configurations, and the
policy's targets. Its IK takes half a minute, so the table of the packaged scene is stored
(``assets/grasp_table.npz``, written by ``python -m mjx_multiarm.pickplace.plans``) and
used while its fingerprint (the compiled scene and the grasps) matches; any other scene
computes its own.
"""

from __future__ import annotations

import argparse
import copy
import functools
import hashlib
import pathlib

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct

from mjx_multiarm.files import atomic_write
from mjx_multiarm.geometry.certified import certified_contacts
from mjx_multiarm.geometry.evaluate import evaluate_arms
from mjx_multiarm.geometry.ik import solve_poses, solve_positions
from mjx_multiarm.geometry.kinematics import forward_kinematics
from mjx_multiarm.geometry.robot import load_arm
from mjx_multiarm.geometry.scene import Scene, build_scene as build_arm_scene
from mjx_multiarm.geometry.transforms import quat_mul, quat_to_mat, wxyz_to_xyzw
from mjx_multiarm.pickplace.scene import (
    ARM,
    ARM_BASES,
    BASE_POS,
    BASE_QUAT,
    DUMP_POSITIONS,
    GRIPPER_STROKE,
    NUM_ARMS,
    OBJECT_XY,
    PAD_CENTRE_X,
    PAD_HALF,
    PickPlaceScene,
    build_scene,
    collision_model,
)

PREGRASP_BACKOFF = 0.10
#: Height of the waypoint above the pregrasp position (``reach_above``; 0: the original protocol).
APPROACH_HEIGHT = 0.25
#: Before its first policy phase, an arm whose end effector starts lower than this (m) rises
#: straight up to it (``rise``; 0: no rise, the original protocol).
START_HEIGHT = 0.3
#: Clearance (m) the shielded protocol's rise keeps in the shield's collision model
#: (:func:`redraw_uncertified_starts`): room for the servos' lag behind the rise's commands
#: when the policy phases begin.
START_CLEARANCE = 0.01
#: Initial configurations: home + U(-0.4, 0.4) rad per joint, collision-free in the physics
#: scene (arms, grippers, bin, floor, objects) and the collision model, ee above 0.2 m.
INIT_NOISE = 0.4
INIT_MIN_EE_HEIGHT = 0.2
#: Resting orientations tried besides upright (wxyz): the cube rests on any face.
RESTING = {"cube": np.array([[1.0, 0.0, 0.0, 0.0], [np.sqrt(0.5), np.sqrt(0.5), 0.0, 0.0],
                             [np.sqrt(0.5), -np.sqrt(0.5), 0.0, 0.0], [np.sqrt(0.5), 0.0, np.sqrt(0.5), 0.0],
                             [np.sqrt(0.5), 0.0, -np.sqrt(0.5), 0.0], [0.0, 1.0, 0.0, 0.0]])}
#: Yaws tried, about the direction from the object to its arm's base.
SPAWN_YAWS = np.pi / 2 * np.arange(4)
IK_ITERATIONS = 150
ROWS = 4096  # IK and collision calls are padded to a multiple of this (one compilation)
GRASP_TABLE = pathlib.Path(__file__).resolve().parents[1] / "assets" / "grasp_table.npz"


@struct.dataclass
class RunPlan:
    """One run's draws and the poses its phases head for (world frame, wxyz); leading batch
    dims allowed."""

    objects: jnp.ndarray  # [4] object index per arm
    init_joints: jnp.ndarray  # [4, 6]
    rise_joints: jnp.ndarray  # [4, 6] the end of ``rise`` (init_joints where the arm does not rise)
    object_pose: jnp.ndarray  # [4, 7] spawn pose (position, wxyz)
    above_pos: jnp.ndarray  # [4, 3] the policy's waypoint (reach_above): above the pregrasp position ...
    above_quat: jnp.ndarray  # [4, 4] ... with the orientation of a training target there
    reach_pos: jnp.ndarray  # [4, 3] the policy's target in reach_pregrasp: the pregrasp position ...
    reach_quat: jnp.ndarray  # [4, 4] ... with the orientation of a training target there
    pregrasp_joints: jnp.ndarray  # [4, 6] the exact pregrasp (to_pregrasp's goal)
    grasp_joints: jnp.ndarray  # [4, 6]
    dump_pos: jnp.ndarray  # [4, 3]
    dump_quat: jnp.ndarray  # [4, 4]
    dump_joints: jnp.ndarray  # [4, 6]


def spawn_candidates(scene: PickPlaceScene, arm: int, obj: int) -> np.ndarray:
    """[K, 7] poses arm ``arm``'s object ``obj`` may stand in (position, wxyz): on the floor
    1 m from the centre in front of the arm, upright (or resting on a face, for the cube),
    turned about the vertical by :data:`SPAWN_YAWS` from facing the arm's base."""
    xy = OBJECT_XY[arm]
    facing = np.arctan2(*(ARM_BASES[arm, 1::-1] - xy[::-1]))
    asset = scene.assets.objects[scene.object_names[obj]]
    points = np.concatenate(asset.hulls)
    poses = []
    for rest in RESTING.get(asset.name, np.array([[1.0, 0.0, 0.0, 0.0]])):
        for yaw in facing + SPAWN_YAWS:
            quat = np.asarray(quat_mul(jnp.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)]), jnp.asarray(rest)))
            bottom = (points @ np.asarray(quat_to_mat(jnp.asarray(quat))).T)[:, 2].min()
            poses.append([*xy, -bottom + 1e-3, *quat])
    return np.array(poses)


@functools.cache
def _base_poses() -> np.ndarray:
    """[4, 7] the arms' base poses as :func:`~mjx_multiarm.geometry.evaluate.evaluate_arms`
    takes them (position, xyzw)."""
    return np.concatenate([BASE_POS, np.asarray(wxyz_to_xyzw(BASE_QUAT))], 1)


def _padded(fn, *arrays):
    """``fn`` on ``arrays`` padded (first rows repeated) to a multiple of :data:`ROWS` rows."""
    n = len(arrays[0])
    rows = -(-n // ROWS) * ROWS
    padded = [np.concatenate([a, np.repeat(a[:1], rows - n, axis=0)]) if rows > n else a for a in arrays]
    return [np.asarray(x)[:n] for x in fn(*padded)]


def _to_base(arms: np.ndarray, pos: np.ndarray, quat: np.ndarray):
    """World poses [N, 3], [N, 4] -> the base frames of ``arms`` [N] (wxyz)."""
    yaw = ARM_BASES[arms, 2]
    c, s = np.cos(yaw), np.sin(yaw)
    rel = pos - BASE_POS[arms]
    pos_b = np.stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1], rel[:, 2]], -1)
    quat_b = np.asarray(quat_mul(jnp.asarray(BASE_QUAT[arms] * [1, -1, -1, -1]), jnp.asarray(quat)))
    return pos_b, quat_b


@jax.jit
def _solve(pos, quat, seeds):
    joints, position_error, angle_error = solve_poses(load_arm(), pos, quat, seeds, iterations=IK_ITERATIONS)
    return joints, (position_error < 1e-3) & (angle_error < 1e-2) & jnp.all(jnp.abs(joints) <= 2 * np.pi, axis=-1)


@jax.jit
def _solve_positions(pos):
    home = jnp.broadcast_to(jnp.asarray(load_arm().home, jnp.float32), (*pos.shape[:-1], 6))
    return (solve_positions(load_arm(), pos, home, iterations=100)[0],)


def typical_joints(arms: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """[N, 6] configurations reaching world positions [N, 3] the way training targets are made
    (:mod:`mjx_multiarm.tasks.generate`: position IK from home, pulled toward home)."""
    pos_b, _ = _to_base(arms, pos, np.broadcast_to([1.0, 0.0, 0.0, 0.0], (len(pos), 4)))
    return _padded(_solve_positions, pos_b.astype(np.float32))[0].astype(np.float64)


def _ik(arms, pos, quat, seeds: np.ndarray):
    """IK of world poses [N] from seeds [N, S, 6]: (joints [N, 6], ok [N]), the solved seed
    nearest its own start winning (so a seed picks its branch)."""
    pos_b, quat_b = _to_base(arms, pos, quat)
    n, s = seeds.shape[:2]
    joints, ok = _padded(_solve, np.repeat(pos_b, s, 0).astype(np.float32), np.repeat(quat_b, s, 0).astype(np.float32),
                         seeds.reshape(n * s, 6).astype(np.float32))
    joints, ok = joints.reshape(n, s, 6), ok.reshape(n, s)
    cost = np.where(ok, np.abs(joints - seeds).sum(-1), np.inf)
    best = cost.argmin(axis=1)
    return joints[np.arange(n), best].astype(np.float64), ok[np.arange(n), best]


def _clear(arms: np.ndarray, joints: np.ndarray) -> np.ndarray:
    """[N] each arm alone at ``joints`` touches neither itself nor the ground."""
    return ~_padded(lambda b, q: (evaluate_arms(b, q).collided,), _base_poses()[arms][:, None], joints[:, None])[0][:, 0]


def _finger_bottom(pos, quat) -> np.ndarray:
    """[N] lowest z of the open fingers' pads for ee_link poses [N, 3], [N, 4]."""
    rot = np.asarray(quat_to_mat(jnp.asarray(quat)))
    corners = np.array([[PAD_CENTRE_X + sx * PAD_HALF[0], sy * PAD_HALF[1], sz * (GRIPPER_STROKE / 2 + 2 * PAD_HALF[2])]
                        for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    return (pos[:, None, 2] + np.einsum("nij,kj->nki", rot, corners)[..., 2]).min(axis=1)


def _pose_mul(pos_a, quat_a, pos_b, quat_b):
    pos = pos_a + np.einsum("...ij,...j->...i", np.asarray(quat_to_mat(jnp.asarray(quat_a))), pos_b)
    return pos, np.asarray(quat_mul(jnp.asarray(quat_a), jnp.asarray(quat_b)))


#: The model fields a grasp table depends on: the bodies' tree, joints and every geom.
FINGERPRINT_FIELDS = ("body_parentid", "body_pos", "body_quat", "jnt_type", "jnt_bodyid", "jnt_pos", "jnt_axis", "jnt_range",
                      "geom_type", "geom_bodyid", "geom_size", "geom_pos", "geom_quat", "geom_contype", "geom_conaffinity",
                      "mesh_vertadr", "mesh_vertnum", "mesh_vert")


def scene_fingerprint(scene: PickPlaceScene) -> str:
    """sha256 of what a grasp table is computed from: the compiled model's bodies, joints
    and geoms (:data:`FINGERPRINT_FIELDS`) and every object's grasps."""
    digest = hashlib.sha256()
    for field in FINGERPRINT_FIELDS:
        digest.update(np.ascontiguousarray(getattr(scene.model, field)).tobytes())
    for name in scene.object_names:
        digest.update(np.ascontiguousarray(scene.assets.objects[name].grasps, np.float64).tobytes())
    return digest.hexdigest()


@functools.cache
def grasp_table(scene: PickPlaceScene) -> dict:
    """:func:`compute_grasp_table` of ``scene``: the stored table where it was computed from
    this scene (same fingerprint), else computed."""
    if GRASP_TABLE.is_file():
        with np.load(GRASP_TABLE) as stored:
            if str(stored["fingerprint"]) == scene_fingerprint(scene):
                return {k: stored[k] for k in stored.files if k != "fingerprint"}
    return compute_grasp_table(scene)


def compute_grasp_table(scene: PickPlaceScene) -> dict:
    """Per arm and object: the spawn pose, the chosen grasp and its configurations, and the
    policy's reach target; per arm: the dump pose and configuration (numpy, world, wxyz).

    A grasp qualifies when its pregrasp and grasp poses have IK solutions within joint limits
    (the grasp's solution seeds the pregrasp's, so both are on one branch), clear of self and
    ground collision in the collision model, with the open fingers above the floor. Over the
    spawn candidates (:func:`spawn_candidates`) the grasp whose pregrasp configuration is
    nearest (summed joint distance) to the policy's reach configuration wins: the
    configuration of a training target at the pregrasp position (:func:`typical_joints`),
    whose pose is the policy's target. The dump pose is such a target too: the dump position
    with the orientation position IK gives.
    """
    nobj = len(scene.object_names)
    rows = {k: [] for k in ("arm", "obj", "cand", "grasp", "spawn", "pos", "quat")}
    for arm in range(NUM_ARMS):
        for obj in range(nobj):
            grasps = scene.assets.objects[scene.object_names[obj]].grasps
            for k, spawn in enumerate(spawn_candidates(scene, arm, obj)):
                pos, quat = _pose_mul(spawn[:3], spawn[3:], grasps[:, :3], grasps[:, 3:])
                n = len(grasps)
                for key, value in (("arm", [arm] * n), ("obj", [obj] * n), ("cand", [k] * n), ("grasp", range(n)),
                                   ("spawn", [spawn] * n), ("pos", pos), ("quat", quat)):
                    rows[key].append(np.asarray(value))
    # Only grasps whose open fingers clear the floor are solved, and only solved grasps' pregrasps
    # (every condition is required, so the others could not win).
    r = {k: np.concatenate(v)[_finger_bottom(np.concatenate(rows["pos"]), np.concatenate(rows["quat"])) > 0.005]
         for k, v in rows.items()}
    approach = np.asarray(quat_to_mat(jnp.asarray(r["quat"])))[:, :, 0]  # ee_link x in the world
    pregrasp_pos = r["pos"] - PREGRASP_BACKOFF * approach
    typical = typical_joints(r["arm"], pregrasp_pos)
    home = np.broadcast_to(load_arm().home, typical.shape)
    flips = [typical + [0, 0, 0, 0, 0, turn] for turn in (np.pi / 2, -np.pi / 2)]
    q_grasp, ok = _ik(r["arm"], r["pos"], r["quat"], np.stack([typical, home, *flips], axis=1))
    solved = np.flatnonzero(ok)
    q_pre = np.zeros_like(q_grasp)
    if solved.size:
        q_pre[solved], ok[solved] = _ik(r["arm"][solved], pregrasp_pos[solved], r["quat"][solved],
                                        q_grasp[solved, None])
    ok &= _clear(r["arm"], q_grasp) & _clear(r["arm"], q_pre)
    score = np.where(ok, -np.abs(q_pre - typical).sum(-1) - 1e-3 * r["cand"], -np.inf)
    table = {k: np.zeros((NUM_ARMS, nobj, *shape)) for k, shape in
             (("spawn", (7,)), ("reach_joints", (6,)), ("pregrasp_joints", (6,)), ("grasp_joints", (6,)))}
    table["grasp_index"] = np.zeros((NUM_ARMS, nobj), int)
    for arm in range(NUM_ARMS):
        for obj in range(nobj):
            mine = np.flatnonzero((r["arm"] == arm) & (r["obj"] == obj))
            if not np.isfinite(score[mine].max(initial=-np.inf)):
                raise RuntimeError(f"no feasible grasp for arm {arm}, object {scene.object_names[obj]}")
            best = mine[np.argmax(score[mine])]
            table["grasp_index"][arm, obj] = r["grasp"][best]
            for key, value in (("spawn", r["spawn"]), ("reach_joints", typical), ("pregrasp_joints", q_pre),
                               ("grasp_joints", q_grasp)):
                table[key][arm, obj] = value[best]
    reach = forward_kinematics(load_arm(), BASE_POS[:, None], BASE_QUAT[:, None], jnp.asarray(table["reach_joints"]))
    table["reach_pos"], table["reach_quat"] = np.asarray(reach.ee_pos, np.float64), np.asarray(reach.ee_quat, np.float64)
    dump_joints = typical_joints(np.arange(NUM_ARMS), DUMP_POSITIONS)
    dump = forward_kinematics(load_arm(), BASE_POS, BASE_QUAT, jnp.asarray(dump_joints))
    if np.abs(np.asarray(dump.ee_pos) - DUMP_POSITIONS).max() > 1e-3:
        raise RuntimeError("no IK solution for a dump position")
    table.update(dump_pos=DUMP_POSITIONS.copy(), dump_quat=np.asarray(dump.ee_quat, np.float64), dump_joints=dump_joints)
    return table


def lifted_joints(joints, dz):
    """[..., 4, 6] joint angles that move each arm's ee_link by ``dz`` (m; one number, or [..., 4]
    one per arm) vertically, orientation kept."""
    frames = forward_kinematics(load_arm(), jnp.zeros(3), jnp.array([1.0, 0.0, 0.0, 0.0]), joints)
    up = jnp.zeros_like(frames.ee_pos).at[..., 2].set(dz)
    return solve_poses(load_arm(), frames.ee_pos + up, frames.ee_quat, joints, iterations=40)[0]


def rise_joints(init_joints: np.ndarray, start_height: float) -> np.ndarray:
    """[R, 4, 6] where each arm's ``rise`` ends: its end effector lifted straight up to
    ``start_height`` (arms already higher stay); an arm whose lift IK misses by more than
    1 cm or collides stays where it is."""
    init = jnp.asarray(init_joints, jnp.float32)
    ee_z = np.asarray(forward_kinematics(load_arm(), BASE_POS, BASE_QUAT, init).ee_pos[..., 2])
    dz = np.maximum(start_height - ee_z, 0.0)
    lifted = np.asarray(lifted_joints(init, jnp.asarray(dz, jnp.float32)), np.float64)
    at = evaluate_arms(np.broadcast_to(_base_poses(), (*lifted.shape[:-2], NUM_ARMS, 7)), lifted)
    ok = (np.abs(at.ee_pos[..., 2] - ee_z - dz) < 0.01) & ~at.collided & (dz > 0)
    return np.where(ok[..., None], lifted, init_joints)


def _arms_touch_scene(scene: PickPlaceScene, data: mujoco.MjData, objects, object_pose, joints) -> bool:
    """Whether an arm or its gripper touches another arm, the bin, the floor or an object
    (MuJoCo C's contacts in the run's own scene) at ``joints`` [4, 6] with ``objects`` placed at ``object_pose`` [4, 7]; the
    model's geom positions are set for ``objects``."""
    m = data.model
    m.geom_pos[:] = scene.geom_pos(objects)
    mujoco.mj_resetData(m, data)
    for a in range(NUM_ARMS):
        data.qpos[scene.arm_qpos[a]] = joints[a]
        data.qpos[scene.object_qpos[a]:scene.object_qpos[a] + 7] = object_pose[a]
    mujoco.mj_forward(m, data)
    n = data.ncon
    geoms = np.stack([data.contact.geom1[:n], data.contact.geom2[:n]])
    return bool(((scene.geom_kind[geoms] == ARM).any(axis=0) & (data.contact.dist[:n] < 0)).any())


def sample_initial_joints(rng: np.random.Generator, clear=None, max_tries: int = 1000) -> np.ndarray:
    """[4, 6] home + U(-0.4, 0.4) per joint, redrawn until the team is collision-free with
    every end effector above 0.2 m (the original's rule), free in the collision model (the
    policy's: arms, self, ground) and, where ``clear(joints) -> bool`` is given, in the
    physics scene (every arm with its gripper against every other body, as the original)."""
    for _ in range(max_tries):
        joints = load_arm().home + rng.uniform(-INIT_NOISE, INIT_NOISE, (NUM_ARMS, 6))
        at = evaluate_arms(_base_poses(), joints)
        if (not at.collided.any() and (at.ee_pos[:, 2] > INIT_MIN_EE_HEIGHT).all()
                and (clear is None or clear(joints))):
            return joints
    raise RuntimeError(f"no collision-free initial configuration in {max_tries} draws")


def plan_runs(scene: PickPlaceScene, seed: int, runs, objects=None, approach_height: float = APPROACH_HEIGHT,
              start_height: float = START_HEIGHT, safe: bool = False) -> RunPlan:
    """The plans of ``runs`` (a count: runs 0 .. runs - 1; or a sequence of run indices) drawn
    from ``seed`` (run r uses ``np.random.default_rng([seed, r])``): one object per arm
    uniformly (or ``objects``: names or indices, one per arm, for every run), initial
    configurations as the original; the ``rise`` to ``start_height`` (m) and the
    ``reach_above`` waypoint ``approach_height`` (m) above each pregrasp position (0 skips
    either). ``safe`` (the shielded protocol): a run whose whole rise is not certified free
    in the shield's collision model (:func:`~mjx_multiarm.pickplace.scene.collision_model`)
    draws its initial configuration again (:func:`redraw_uncertified_starts`)."""
    indices = list(range(runs)) if isinstance(runs, (int, np.integer)) else [int(r) for r in runs]
    if not indices or min(indices) < 0:
        raise ValueError(f"runs must be a count >= 1 or non-negative run indices, got {runs}")
    if not 0 <= approach_height <= 0.5:
        raise ValueError(f"approach_height must be in [0, 0.5] m, got {approach_height}")
    if not 0 <= start_height <= 0.8:
        raise ValueError(f"start_height must be in [0, 0.8] m, got {start_height}")
    fixed = None
    if objects is not None:  # checked before the grasp table's IK compiles
        if len(objects) != NUM_ARMS:
            raise ValueError(f"objects: the layout needs one object per arm ({NUM_ARMS}), got {len(objects)}")
        fixed = np.array([scene.object_index(o) if isinstance(o, str) else int(o) for o in objects])
    table = grasp_table(scene)
    nobj = len(scene.object_names)
    above_pos = table["reach_pos"] + [0.0, 0.0, approach_height]
    arm_rows = np.repeat(np.arange(NUM_ARMS), nobj)
    above_joints = typical_joints(arm_rows, above_pos.reshape(-1, 3))
    above = forward_kinematics(load_arm(), BASE_POS[arm_rows], BASE_QUAT[arm_rows], jnp.asarray(above_joints))
    above_quat = np.asarray(above.ee_quat, np.float64).reshape(NUM_ARMS, nobj, 4)
    plans, rngs, clears = [], [], []
    arms = np.arange(NUM_ARMS)
    data = mujoco.MjData(copy.deepcopy(scene.model))
    for r in indices:
        rng = np.random.default_rng([seed, r])
        objs = fixed if fixed is not None else rng.integers(len(scene.object_names), size=NUM_ARMS)
        spawn = table["spawn"][arms, objs]
        clear = functools.partial(_physics_clear, scene, data, objs, spawn)
        init = sample_initial_joints(rng, clear)
        rngs.append(rng)
        clears.append(clear)
        plans.append(RunPlan(
            objects=objs.astype(np.int32), init_joints=init, rise_joints=init, object_pose=spawn,
            above_pos=above_pos[arms, objs], above_quat=above_quat[arms, objs], reach_pos=table["reach_pos"][arms, objs], reach_quat=table["reach_quat"][arms, objs],
            pregrasp_joints=table["pregrasp_joints"][arms, objs], grasp_joints=table["grasp_joints"][arms, objs],
            dump_pos=table["dump_pos"], dump_quat=table["dump_quat"], dump_joints=table["dump_joints"]))
    plans = jax.tree.map(lambda *xs: np.stack(xs), *plans)
    if start_height > 0:
        plans = plans.replace(rise_joints=rise_joints(plans.init_joints, start_height))
    plans = _as_executed(plans)
    if safe:
        model = build_arm_scene(NUM_ARMS, *collision_model())
        plans = redraw_uncertified_starts(plans, model, rngs, clears, start_height)
    return plans


def _as_executed(plans: RunPlan) -> RunPlan:
    """The plans in the dtypes the controller runs them (float32, int32)."""
    return jax.tree.map(lambda x: np.asarray(x).astype(np.int32 if x.dtype.kind == "i" else np.float32), plans)


def _physics_clear(scene: PickPlaceScene, data: mujoco.MjData, objects, object_pose, joints) -> bool:
    return not _arms_touch_scene(scene, data, objects, object_pose, joints)


def rise_certified(model: Scene, init_joints, rise_joints) -> np.ndarray:
    """[R] whether each run's scripted ``rise`` (the whole team's straight joint motion
    ``init_joints -> rise_joints`` [R, 4, 6], the start included) is certified free in the
    collision model ``model`` (:func:`mjx_multiarm.geometry.certified.certified_contacts`),
    with :data:`START_CLEARANCE` to spare."""
    init, rise = jnp.asarray(init_joints, jnp.float32), jnp.asarray(rise_joints, jnp.float32)
    batch = init.shape[:-2]
    motion = certified_contacts(model, jnp.broadcast_to(jnp.asarray(BASE_POS, jnp.float32), (*batch, NUM_ARMS, 3)),
                                jnp.broadcast_to(jnp.asarray(BASE_QUAT, jnp.float32), (*batch, NUM_ARMS, 4)),
                                init, rise, jnp.ones((*batch, NUM_ARMS), bool), margin=START_CLEARANCE)
    return ~np.asarray(motion.uncertified).any(axis=-1)


def redraw_uncertified_starts(plans: RunPlan, model: Scene, rngs, clears, start_height: float,
                              max_tries: int = 1000) -> RunPlan:
    """``plans`` where every run's rise is certified free in the shield's collision model
    ``model`` (:func:`rise_certified`): a run whose is not draws its initial configuration
    again from its own stream (``rngs[i]``, continued; ``clears[i]`` its physics check) until
    it is. Its objects stay; every other run keeps its plan. The shield can certify nothing
    from a configuration in contact in its model, so a run that would start its policy
    phases there could only hold (benchmarks/RESULTS.md, the deadlocks of the fifth session)."""
    ok = rise_certified(model, plans.init_joints, plans.rise_joints)
    init, rise = np.array(plans.init_joints), np.array(plans.rise_joints)
    for i in np.flatnonzero(~ok):
        for _ in range(max_tries):
            candidate = sample_initial_joints(rngs[i], clears[i])
            lifted = rise_joints(candidate[None], start_height)[0] if start_height > 0 else candidate
            candidate, lifted = candidate.astype(np.float32), lifted.astype(np.float32)
            if rise_certified(model, candidate, lifted):
                init[i], rise[i] = candidate, lifted
                break
        else:
            raise RuntimeError(f"no initial configuration of run index {i} with a rise certified free "
                               f"in the shield's model in {max_tries} draws")
    return plans.replace(init_joints=init, rise_joints=rise)


def main(argv=None) -> None:
    """Command line: compute the packaged scene's grasp table and store it (atomically)."""
    parser = argparse.ArgumentParser(description="Compute the packaged pick-and-place scene's grasp table and store it.")
    parser.add_argument("--out", type=pathlib.Path, default=GRASP_TABLE, help="output .npz (default: the packaged asset)")
    args = parser.parse_args(argv)
    scene = build_scene()
    table = compute_grasp_table(scene)
    atomic_write(args.out, lambda f: np.savez(f, fingerprint=scene_fingerprint(scene), **table))
    print(f"wrote {args.out}: {NUM_ARMS} arms x {len(scene.object_names)} objects")


if __name__ == "__main__":
    main()
