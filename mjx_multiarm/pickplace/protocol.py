"""The pick-and-place protocol: every arm runs its own phase sequence, asynchronously.

Per arm, as the original demo (``demo/demo.py`` of the paper's code):

1. ``reach_pregrasp`` (policy): the shared reaching policy drives the arm to the pregrasp
   position (the grasp backed off 0.10 m along the approach axis); done within 5 cm / 0.2 rad;
2. scripted: ``to_pregrasp`` (joint move to the exact pregrasp configuration), ``to_grasp``,
   ``close`` (the gripper closes; at its end the object is attached by a weld), ``lift``
   (0.30 m up, a Cartesian move by IK);
3. ``reach_dump`` (policy): to the dump pose above the bin (ee_link pointing down);
4. scripted: ``to_dump``, ``lower`` (5 cm), ``release`` (weld off, gripper opens), ``raise``
   (5 cm), ``home``; then ``done``.

One deviation from the original: the policy's target in ``reach_pregrasp`` is the pregrasp
position with the orientation the policy was trained to reach there (position IK pulled toward
home, as :mod:`mjx_multiarm.tasks.generate` makes training targets), not the grasp's
orientation; ``to_pregrasp`` turns the wrist. The GraspIt grasps' orientations are far outside
the training targets (whose last joint stays near 0), and the policy does not reach them.

The controller is one JAX function of a run's plan, its state and what the physics reports
(joint angles, object positions, contacts); both backends (:mod:`mjx_multiarm.pickplace.backends`)
call it, so the protocol exists once. The policy runs at its training control rate (20 Hz);
each control step is :data:`SUBSTEPS` physics steps of 1/240 s, over which the servo targets
are interpolated. The policy observes every arm: an arm in a scripted phase appears with its
current end-effector pose as its target, as in the original.

Collision rules. The original's: an arm in a policy phase touching another arm, the floor,
the bin or an object other than the one it holds ends the run. The project's stricter
accounting also records (without ending the run) contacts in scripted phases, self
collisions, and touching its own object outside the grasp (``to_grasp`` .. ``raise``).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from mjx_multiarm.env.reaching import CONTROL_PERIOD
from mjx_multiarm.geometry.collision import scene_contacts
from mjx_multiarm.geometry.evaluate import evaluate_arms
from mjx_multiarm.geometry.ik import solve_poses, solve_positions
from mjx_multiarm.geometry.kinematics import forward_kinematics
from mjx_multiarm.geometry.scene import build_scene as build_arm_scene
from mjx_multiarm.geometry.transforms import quat_angle, quat_mul, quat_to_mat
from mjx_multiarm.pickplace.scene import (
    ARM, ARM_BASES, BASE_HEIGHT, BIN, DUMP_POSITIONS, FLOOR, GRIPPER_STROKE, NUM_ARMS, OBJECT, OBJECT_XY, TIMESTEP,
    PickPlaceScene,
)

PHASES = ("reach_pregrasp", "to_pregrasp", "to_grasp", "close", "lift", "reach_dump", "to_dump", "lower", "release",
          "raise", "home", "done")
(REACH_PREGRASP, TO_PREGRASP, TO_GRASP, CLOSE, LIFT, REACH_DUMP, TO_DUMP, LOWER, RELEASE, RAISE, HOME,
 DONE) = range(len(PHASES))
#: Phases in which an arm may touch its own object.
GRASP_WINDOW = (TO_GRASP, RAISE)
#: A policy phase ends within 5 cm / 0.2 rad of its target (the original's tolerances).
PHASE_TOLERANCE = (0.05, 0.2)
PREGRASP_BACKOFF = 0.10
LIFT_HEIGHT = 0.30
DUMP_DROP = 0.05
#: Scripted moves: at least 0.5 s (the original's duration), at most half the velocity limit.
SCRIPTED_STEPS = round(0.5 / CONTROL_PERIOD)
SCRIPTED_SPEED = 0.5
SUBSTEPS = round(CONTROL_PERIOD / TIMESTEP)
#: The original's limit: 100,000 physics steps of 1/240 s.
MAX_CONTROL_STEPS = 100_000 // SUBSTEPS
#: Initial configurations: home + U(-0.4, 0.4) rad per joint, collision-free, ee above 0.2 m.
INIT_NOISE = 0.4
INIT_MIN_EE_HEIGHT = 0.2

#: Why a run ended (``cause``), or the first stricter-accounting violation (``strict_cause``).
CAUSES = ("none", "arm-arm", "arm-floor", "arm-bin", "arm-object", "arm-self", "outside-bin", "timeout")
(NONE, ARM_ARM, ARM_FLOOR, ARM_BIN, ARM_OBJECT, ARM_SELF, OUTSIDE_BIN, TIMEOUT) = range(len(CAUSES))
#: Physics contact kinds per arm (the sensors' ``contacts`` [4, 4]).
TOUCH_FLOOR, TOUCH_BIN, TOUCH_OWN_OBJECT, TOUCH_OTHER_OBJECT = range(4)

BASE_POS = np.concatenate([ARM_BASES[:, :2], np.full((NUM_ARMS, 1), BASE_HEIGHT)], axis=1)
BASE_QUAT = np.stack([np.cos(ARM_BASES[:, 2] / 2), 0 * ARM_BASES[:, 2], 0 * ARM_BASES[:, 2], np.sin(ARM_BASES[:, 2] / 2)], 1)


@struct.dataclass
class RunPlan:
    """One run's draws and the poses its phases head for (world frame, wxyz); leading batch
    dims allowed."""

    objects: jnp.ndarray  # [4] object index per arm
    init_joints: jnp.ndarray  # [4, 6]
    object_pose: jnp.ndarray  # [4, 7] spawn pose (position, wxyz)
    reach_pos: jnp.ndarray  # [4, 3] the policy's target in reach_pregrasp: the pregrasp position ...
    reach_quat: jnp.ndarray  # [4, 4] ... with the orientation of a training target there
    pregrasp_joints: jnp.ndarray  # [4, 6] the exact pregrasp (to_pregrasp's goal)
    grasp_joints: jnp.ndarray  # [4, 6]
    dump_pos: jnp.ndarray  # [4, 3]
    dump_quat: jnp.ndarray  # [4, 4]
    dump_joints: jnp.ndarray  # [4, 6]


@struct.dataclass
class Sensors:
    """What the physics reports after a control step."""

    joints: jnp.ndarray  # [4, 6] measured arm joint angles
    object_pos: jnp.ndarray  # [4, 3] object slot positions
    contacts: jnp.ndarray  # [4, 4] bool: touched floor / bin / own object / another object during the step


@struct.dataclass
class Commands:
    """What the backend applies over the next control step."""

    arm_target: jnp.ndarray  # [4, 6] servo targets at the end of the step
    gripper: jnp.ndarray  # [4] finger travel (0 open .. GRIPPER_STROKE / 2 closed)
    attach: jnp.ndarray  # [4] bool: weld the object to ee_link now (at its current relative pose)
    release: jnp.ndarray  # [4] bool: remove the weld now


@struct.dataclass
class ControllerState:
    phase: jnp.ndarray  # [4] int32
    phase_step: jnp.ndarray  # [4] control steps into the phase
    duration: jnp.ndarray  # [4] control steps of a scripted phase
    start: jnp.ndarray  # [4, 6] scripted move from ...
    goal: jnp.ndarray  # [4, 6] ... to
    command: Commands
    prev_joints: jnp.ndarray  # [4, 6] joints one control step ago (observed by the policy)
    prev_target_pos: jnp.ndarray  # [4, 3]
    prev_target_quat: jnp.ndarray  # [4, 4]
    step: jnp.ndarray  # control steps so far
    ended: jnp.ndarray  # bool
    success: jnp.ndarray  # bool
    cause: jnp.ndarray  # CAUSES index
    cause_phase: jnp.ndarray  # phase of the arm that caused the end (-1 if none)
    strict_cause: jnp.ndarray  # first stricter-accounting violation (NONE if none)
    strict_step: jnp.ndarray


def bin_interior(scene: PickPlaceScene) -> np.ndarray:
    """[2] half extents (x, y) of the bin's rim: an object is in the bin when its x, y are inside."""
    walls = [b for b in scene.assets.bin_boxes if b["name"].startswith("wall")]
    half = np.zeros(2)
    for box in walls:
        axis = 0 if box["name"].endswith("x") else 1
        half[axis] = max(half[axis], abs(box["pos"][axis]))
    return half


def initial_state(plan: RunPlan) -> ControllerState:
    """The state at the start of a run (every arm in ``reach_pregrasp``)."""
    joints = jnp.asarray(plan.init_joints, jnp.float32)
    frames = forward_kinematics(_arm(), BASE_POS, BASE_QUAT, joints)
    zeros = jnp.zeros(NUM_ARMS, jnp.int32)
    return ControllerState(
        phase=zeros, phase_step=zeros, duration=zeros + 1, start=joints, goal=joints,
        command=Commands(joints, jnp.zeros(NUM_ARMS, jnp.float32), jnp.zeros(NUM_ARMS, bool), jnp.zeros(NUM_ARMS, bool)),
        prev_joints=joints, prev_target_pos=frames.ee_pos, prev_target_quat=frames.ee_quat,
        step=jnp.int32(0), ended=jnp.bool_(False), success=jnp.bool_(False), cause=jnp.int32(NONE),
        cause_phase=jnp.int32(-1), strict_cause=jnp.int32(NONE), strict_step=jnp.int32(-1))


@functools.cache
def _arm():
    return build_arm_scene(NUM_ARMS).arm


def _move_steps(start, goal):
    speed = SCRIPTED_SPEED * jnp.asarray(_arm().velocity_limit, jnp.float32) * CONTROL_PERIOD
    return jnp.maximum(SCRIPTED_STEPS, jnp.ceil(jnp.max(jnp.abs(goal - start) / speed, axis=-1))).astype(jnp.int32)


def _lifted(joints, dz: float):
    """Joint angles that move each arm's ee_link by ``dz`` vertically, orientation kept."""
    frames = forward_kinematics(_arm(), jnp.zeros(3), jnp.array([1.0, 0.0, 0.0, 0.0]), joints)
    return solve_poses(_arm(), frames.ee_pos + jnp.array([0.0, 0.0, dz]), frames.ee_quat, joints, iterations=40)[0]


def _first(flags_by_cause):
    """The first cause (in CAUSES order) whose flag is set, or NONE."""
    codes = jnp.array([c for c, _ in flags_by_cause], jnp.int32)
    flags = jnp.stack([jnp.any(f) for _, f in flags_by_cause])
    return jnp.where(flags.any(), codes[jnp.argmax(flags)], NONE)


def make_controller(policy_step, scene: PickPlaceScene, max_steps: int = MAX_CONTROL_STEPS):
    """The controller ``control(plan, state, sensors) -> (state, commands)`` of one run (jit
    and vmap it). ``policy_step`` is :meth:`mjx_multiarm.planner.Planner.batched` for 4 arms;
    a run still going after ``max_steps`` control steps ends as a timeout."""
    if max_steps < 1:
        raise ValueError(f"max_steps must be >= 1, got {max_steps}")
    arm_scene = build_arm_scene(NUM_ARMS)
    interior = jnp.asarray(bin_interior(scene), jnp.float32)
    home = jnp.asarray(_arm().home, jnp.float32)
    base_pos, base_quat = jnp.asarray(BASE_POS, jnp.float32), jnp.asarray(BASE_QUAT, jnp.float32)
    active = jnp.ones(NUM_ARMS, bool)

    def control(plan: RunPlan, state: ControllerState, sensors: Sensors):
        joints = sensors.joints
        phase = state.phase
        frames = forward_kinematics(_arm(), base_pos, base_quat, joints)
        # Collisions of the configuration reached, under both rules.
        kernel = scene_contacts(arm_scene, base_pos, base_quat, joints, active)
        touch = sensors.contacts
        in_policy = (phase == REACH_PREGRASP) | (phase == REACH_DUMP)
        attached = (phase > CLOSE) & (phase <= RELEASE)
        in_grasp = (phase >= GRASP_WINDOW[0]) & (phase <= GRASP_WINDOW[1])
        arm_arm = kernel.between_arms < 0
        floor = (kernel.ground < 0) | touch[:, TOUCH_FLOOR]
        bin_ = touch[:, TOUCH_BIN]
        objects = touch[:, TOUCH_OTHER_OBJECT] | (touch[:, TOUCH_OWN_OBJECT] & ~attached)
        original = [(ARM_ARM, in_policy & arm_arm), (ARM_FLOOR, in_policy & floor), (ARM_BIN, in_policy & bin_),
                    (ARM_OBJECT, in_policy & objects)]
        strict = [(ARM_ARM, arm_arm), (ARM_FLOOR, floor), (ARM_BIN, bin_),
                  (ARM_OBJECT, touch[:, TOUCH_OTHER_OBJECT] | (touch[:, TOUCH_OWN_OBJECT] & ~in_grasp)),
                  (ARM_SELF, kernel.within_arm < 0)]
        collision = _first(original)
        culprit = jnp.argmax(jnp.stack([f for _, f in original]).any(axis=0))
        strict_now = _first(strict)

        # Phase transitions.
        target_pos = jnp.where((phase == REACH_DUMP)[:, None], plan.dump_pos, plan.reach_pos)
        target_quat = jnp.where((phase == REACH_DUMP)[:, None], plan.dump_quat, plan.reach_quat)
        reached = ((jnp.linalg.norm(frames.ee_pos - target_pos, axis=-1) < PHASE_TOLERANCE[0])
                   & (quat_angle(frames.ee_quat, target_quat) < PHASE_TOLERANCE[1]))
        done = jnp.where(in_policy, reached, state.phase_step >= state.duration) & (phase < DONE)
        phase = jnp.where(done, phase + 1, phase)
        goal = jnp.select(
            [(phase == p)[:, None] for p in (TO_PREGRASP, TO_GRASP, LIFT, TO_DUMP, LOWER, RAISE, HOME)],
            [plan.pregrasp_joints, plan.grasp_joints, _lifted(joints, LIFT_HEIGHT), plan.dump_joints,
             _lifted(joints, -DUMP_DROP), _lifted(joints, DUMP_DROP), jnp.broadcast_to(home, joints.shape)],
            joints)
        goal = jnp.where(done[:, None], goal, state.goal)
        start = jnp.where(done[:, None], joints, state.start)
        duration = jnp.where(done, _move_steps(start, goal), state.duration)
        phase_step = jnp.where(done, 0, state.phase_step)

        # Commands for the next control step.
        targets_pos = jnp.where(((phase == REACH_PREGRASP) | (phase == REACH_DUMP))[:, None],
                                jnp.where((phase == REACH_DUMP)[:, None], plan.dump_pos, plan.reach_pos), frames.ee_pos)
        targets_quat = jnp.where(((phase == REACH_PREGRASP) | (phase == REACH_DUMP))[:, None],
                                 jnp.where((phase == REACH_DUMP)[:, None], plan.dump_quat, plan.reach_quat),
                                 frames.ee_quat)
        policy = policy_step(base_pos, base_quat, state.prev_joints, joints, state.prev_target_pos,
                             state.prev_target_quat, targets_pos, targets_quat)
        fraction = jnp.minimum(1.0, (phase_step + 1) / duration)[:, None]
        scripted = start + (goal - start) * fraction
        use_policy = (phase == REACH_PREGRASP) | (phase == REACH_DUMP)
        arm_target = jnp.where(use_policy[:, None], policy, scripted)
        closed = GRIPPER_STROKE / 2
        gripper_fraction = jnp.minimum(1.0, (phase_step + 1) / SCRIPTED_STEPS)
        gripper = jnp.select([phase == CLOSE, (phase > CLOSE) & (phase < RELEASE), phase == RELEASE],
                             [closed * gripper_fraction, jnp.full(NUM_ARMS, closed), closed * (1 - gripper_fraction)],
                             jnp.zeros(NUM_ARMS))
        commands = Commands(arm_target, gripper.astype(jnp.float32), done & (phase == LIFT), done & (phase == RELEASE))

        # The run's end.
        all_done = jnp.all(phase == DONE)
        in_bin = jnp.all(jnp.abs(sensors.object_pos[:, :2]) < interior)
        timeout = state.step + 1 >= max_steps
        ends = ~state.ended & ((collision != NONE) | all_done | timeout)
        cause = jnp.where(collision != NONE, collision,
                          jnp.where(all_done, jnp.where(in_bin, NONE, OUTSIDE_BIN), TIMEOUT))
        new_state = ControllerState(
            phase=jnp.where(state.ended, state.phase, phase),
            phase_step=phase_step + 1, duration=duration, start=start, goal=goal, command=commands,
            prev_joints=joints, prev_target_pos=targets_pos, prev_target_quat=targets_quat,
            step=state.step + jnp.where(state.ended, 0, 1),
            ended=state.ended | ends,
            success=jnp.where(ends, (collision == NONE) & all_done & in_bin, state.success),
            cause=jnp.where(ends, cause, state.cause),
            cause_phase=jnp.where(ends & (collision != NONE), state.phase[culprit], state.cause_phase),
            strict_cause=jnp.where(~state.ended & (state.strict_cause == NONE), strict_now, state.strict_cause),
            strict_step=jnp.where(~state.ended & (state.strict_cause == NONE) & (strict_now != NONE), state.step,
                                  state.strict_step),
        )
        # An ended run holds its last commands.
        held = Commands(state.command.arm_target, state.command.gripper, jnp.zeros(NUM_ARMS, bool), jnp.zeros(NUM_ARMS, bool))
        commands = jax.tree.map(lambda a, b: jnp.where(state.ended | ends, a, b), held, commands)
        return new_state.replace(command=commands), commands

    return control


def arm_contacts(scene: PickPlaceScene, objects, geom1, geom2, dist, xp=np):
    """[4, 4] bool per arm: touching the floor / the bin / its own object / another object,
    from a contact list (``geom1``, ``geom2``, ``dist``; ``dist < 0`` is a touch). ``xp`` is
    numpy (MuJoCo C) or jax.numpy (MJX). ``objects`` is unused by the classification (the
    slot decides whose object it is) and kept for the backends' symmetry."""
    del objects
    kind = xp.asarray(scene.geom_kind)
    slot = xp.asarray(scene.geom_slot)
    touching = dist < 0
    arms = xp.arange(NUM_ARMS)
    flags = []
    for own, other in ((geom1, geom2), (geom2, geom1)):
        is_arm = (kind[own] == ARM) & touching
        mine = is_arm[:, None] & (slot[own][:, None] == arms[None, :])  # [ncon, 4]
        other_kind, other_slot = kind[other][:, None], slot[other][:, None]
        flags.append(xp.stack([
            (mine & (other_kind == FLOOR)).any(axis=0),
            (mine & (other_kind == BIN)).any(axis=0),
            (mine & (other_kind == OBJECT) & (other_slot == arms[None, :])).any(axis=0),
            (mine & (other_kind == OBJECT) & (other_slot != arms[None, :])).any(axis=0),
        ], axis=1))
    return flags[0] | flags[1]


def relative_pose(ee_pos, ee_quat, obj_pos, obj_quat):
    """The object's pose in the ee_link frame (position, wxyz): a weld's ``relpose``."""
    rot = quat_to_mat(ee_quat)
    pos = jnp.einsum("...ji,...j->...i", rot, obj_pos - ee_pos)
    conj = ee_quat * jnp.array([1.0, -1.0, -1.0, -1.0])
    return pos, quat_mul(conj, obj_quat)


# ----------------------------------------------------------------------------------------
# Run plans: draws from a seed, grasps and dump poses.


#: Resting orientations tried besides upright (wxyz): the cube rests on any face.
RESTING = {"cube": np.array([[1.0, 0.0, 0.0, 0.0], [np.sqrt(0.5), np.sqrt(0.5), 0.0, 0.0],
                             [np.sqrt(0.5), -np.sqrt(0.5), 0.0, 0.0], [np.sqrt(0.5), 0.0, np.sqrt(0.5), 0.0],
                             [np.sqrt(0.5), 0.0, -np.sqrt(0.5), 0.0], [0.0, 1.0, 0.0, 0.0]])}
#: Yaws tried, about the direction from the object to its arm's base.
SPAWN_YAWS = np.pi / 2 * np.arange(4)


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


def _to_base(arm: int, pos, quat):
    """World poses -> arm ``arm``'s base frame (numpy, wxyz)."""
    yaw = ARM_BASES[arm, 2]
    c, s = np.cos(yaw), np.sin(yaw)
    rel = np.asarray(pos) - BASE_POS[arm]
    pos_b = np.stack([c * rel[..., 0] + s * rel[..., 1], -s * rel[..., 0] + c * rel[..., 1], rel[..., 2]], -1)
    quat_b = np.asarray(quat_mul(jnp.asarray(BASE_QUAT[arm] * [1, -1, -1, -1]), jnp.asarray(quat)))
    return pos_b, quat_b


def _ik(arm: int, pos, quat, seeds: np.ndarray):
    """Best IK solution for world poses [N, 3], [N, 4] over ``seeds`` ([S, 6] for every pose,
    or [N, S, 6]): (joints [N, 6], ok [N]); the best is the solved one nearest home."""
    pos_b, quat_b = _to_base(arm, pos, quat)
    n = len(pos_b)
    seeds = np.broadcast_to(seeds, (n, *np.shape(seeds)[-2:]))
    s = seeds.shape[1]
    tile = lambda x: jnp.asarray(np.repeat(x, s, axis=0), jnp.float32)  # noqa: E731
    joints, pe, ae = _solve(tile(pos_b), tile(quat_b), jnp.asarray(seeds.reshape(n * s, 6), jnp.float32))
    joints, pe, ae = (np.asarray(x).reshape(n, s, *np.shape(x)[1:]) for x in (joints, pe, ae))
    ok = (pe < 1e-3) & (ae < 1e-2) & (np.abs(joints) <= 2 * np.pi).all(-1)
    cost = np.where(ok, np.abs(joints - _arm().home).sum(-1), np.inf)
    best = cost.argmin(axis=1)
    return joints[np.arange(n), best], ok[np.arange(n), best]


@jax.jit
def _solve(pos, quat, seeds):
    return solve_poses(_arm(), pos, quat, seeds, iterations=150)


def _ik_seeds() -> np.ndarray:
    home = _arm().home
    seeds = [home]
    for pan in np.linspace(-np.pi, np.pi, 8, endpoint=False):
        for wrist in (-np.pi / 2, np.pi / 2):
            seeds.append([pan, -1.2, 1.6, -1.9, wrist, 0.0])
    return np.array(seeds)


def _clear(arm: int, joints: np.ndarray) -> np.ndarray:
    """[N] the arm alone at ``joints`` [N, 6] touches neither itself nor the ground."""
    base = np.broadcast_to(np.concatenate([BASE_POS[arm], _xyzw(BASE_QUAT[arm])]), (len(joints), 1, 7))
    return ~evaluate_arms(base, joints[:, None]).collided[:, 0]


def _xyzw(q):
    return np.concatenate([q[..., 1:], q[..., :1]], -1)


def _pose_mul(pos_a, quat_a, pos_b, quat_b):
    pos = pos_a + np.einsum("...ij,...j->...i", np.asarray(quat_to_mat(jnp.asarray(quat_a))), pos_b)
    return pos, np.asarray(quat_mul(jnp.asarray(quat_a), jnp.asarray(quat_b)))


@functools.cache
def grasp_table(scene: PickPlaceScene) -> dict:
    """Per arm and object: the spawn pose, the chosen grasp and its pregrasp / grasp
    configurations; per arm: the dump pose and configuration (numpy, world frame, wxyz).
    Deterministic.

    A grasp qualifies when its pregrasp and grasp poses have IK solutions within joint limits
    (the grasp's solution seeds the pregrasp's, so both are on one branch), clear of self and
    ground collision in the collision model, with the open fingers above the floor. Over the
    spawn candidates (:func:`spawn_candidates`) the pregrasp configuration nearest to the
    policy's training distribution wins: the policy was trained on targets reached by
    position IK pulled toward home (:mod:`mjx_multiarm.tasks.generate`), so the distance to
    that configuration at the pregrasp position is the score. The dump pose is such a target:
    the dump position with the orientation that position IK gives.
    """
    seeds = _ik_seeds()
    nobj = len(scene.object_names)
    table = {k: np.zeros((NUM_ARMS, nobj, *shape)) for k, shape in
             (("spawn", (7,)), ("reach_joints", (6,)), ("pregrasp_joints", (6,)), ("grasp_joints", (6,)))}
    table["grasp_index"] = np.zeros((NUM_ARMS, nobj), int)
    for arm in range(NUM_ARMS):
        for obj in range(nobj):
            grasps = scene.assets.objects[scene.object_names[obj]].grasps
            best = (-np.inf, None)
            for k, spawn in enumerate(spawn_candidates(scene, arm, obj)):
                g_pos, g_quat = _pose_mul(spawn[:3], spawn[3:], grasps[:, :3], grasps[:, 3:])
                approach = np.asarray(quat_to_mat(jnp.asarray(g_quat)))[:, :, 0]  # ee_link x in the world
                p_pos = g_pos - PREGRASP_BACKOFF * approach
                q_grasp, ok_g = _ik(arm, g_pos, g_quat, seeds)
                q_pre, ok_p = _ik(arm, p_pos, g_quat, q_grasp[:, None])
                ok = ok_g & ok_p & _clear(arm, q_grasp) & _clear(arm, q_pre) & (_finger_bottom(g_pos, g_quat) > 0.005)
                typical = _typical_joints(arm, p_pos)
                score = np.where(ok, -np.abs(q_pre - typical).sum(-1) - 1e-3 * k, -np.inf)
                g = int(np.argmax(score))
                if score[g] > best[0]:
                    best = (score[g], (spawn, g, typical[g], q_pre[g], q_grasp[g]))
            if best[1] is None:
                raise RuntimeError(f"no feasible grasp for arm {arm}, object {scene.object_names[obj]}")
            spawn, g, *poses = best[1]
            table["grasp_index"][arm, obj] = g
            for key, value in zip(("spawn", "reach_joints", "pregrasp_joints", "grasp_joints"), (spawn, *poses)):
                table[key][arm, obj] = value
    reach = forward_kinematics(_arm(), BASE_POS[:, None], BASE_QUAT[:, None], jnp.asarray(table["reach_joints"], jnp.float32))
    table["reach_pos"], table["reach_quat"] = np.asarray(reach.ee_pos, np.float64), np.asarray(reach.ee_quat, np.float64)
    dump_joints = np.stack([_typical_joints(arm, DUMP_POSITIONS[arm][None])[0] for arm in range(NUM_ARMS)])
    frames = forward_kinematics(_arm(), BASE_POS, BASE_QUAT, jnp.asarray(dump_joints, jnp.float32))
    if np.abs(np.asarray(frames.ee_pos) - DUMP_POSITIONS).max() > 1e-3:
        raise RuntimeError("no IK solution for a dump position")
    dump_quat = np.asarray(frames.ee_quat, np.float64)
    table.update(dump_pos=DUMP_POSITIONS.copy(), dump_quat=dump_quat, dump_joints=dump_joints)
    return table


def _typical_joints(arm: int, pos) -> np.ndarray:
    """[N, 6] configurations reaching world positions [N, 3] the way training targets were
    made: position IK from home, pulled toward home."""
    pos_b, _ = _to_base(arm, pos, np.broadcast_to([1.0, 0.0, 0.0, 0.0], (len(pos), 4)))
    return np.asarray(_solve_positions(jnp.asarray(pos_b, jnp.float32)), np.float64)


@jax.jit
def _solve_positions(pos):
    home = jnp.broadcast_to(jnp.asarray(_arm().home, jnp.float32), (*pos.shape[:-1], 6))
    return solve_positions(_arm(), pos, home, iterations=100)[0]


def _finger_bottom(pos, quat) -> np.ndarray:
    """[N] lowest z of the open fingers' pads for ee_link poses [N, 3], [N, 4]."""
    from mjx_multiarm.pickplace.scene import PAD_CENTRE_X, PAD_HALF

    rot = np.asarray(quat_to_mat(jnp.asarray(quat)))
    corners = np.array([[PAD_CENTRE_X + sx * PAD_HALF[0], sy * PAD_HALF[1], sz * (GRIPPER_STROKE / 2 + 2 * PAD_HALF[2])]
                        for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    return (pos[:, None, 2] + np.einsum("nij,kj->nki", rot, corners)[..., 2]).min(axis=1)


def sample_initial_joints(rng: np.random.Generator, max_tries: int = 1000) -> np.ndarray:
    """[4, 6] home + U(-0.4, 0.4) per joint, redrawn until the team is collision-free with
    every end effector above 0.2 m (the original's rule)."""
    base = np.broadcast_to(np.concatenate([BASE_POS, _xyzw(BASE_QUAT)], 1), (NUM_ARMS, 7))
    for _ in range(max_tries):
        joints = _arm().home + rng.uniform(-INIT_NOISE, INIT_NOISE, (NUM_ARMS, 6))
        at = evaluate_arms(base, joints)
        if not at.collided.any() and (at.ee_pos[:, 2] > INIT_MIN_EE_HEIGHT).all():
            return joints
    raise RuntimeError(f"no collision-free initial configuration in {max_tries} draws")


def plan_runs(scene: PickPlaceScene, seed: int, runs: int, objects=None) -> RunPlan:
    """``runs`` run plans drawn from ``seed`` (run r uses ``np.random.default_rng([seed, r])``):
    one object per arm uniformly (or ``objects``: names or indices, [4] for every run), initial
    configurations as the original."""
    table = grasp_table(scene)
    if objects is not None:
        fixed = np.array([scene.object_index(o) if isinstance(o, str) else int(o) for o in objects])
        if fixed.shape != (NUM_ARMS,):
            raise ValueError(f"objects: the layout needs one object per arm ({NUM_ARMS}), got {len(fixed)}")
    plans = []
    arms = np.arange(NUM_ARMS)
    for r in range(runs):
        rng = np.random.default_rng([seed, r])
        objs = fixed if objects is not None else rng.integers(len(scene.object_names), size=NUM_ARMS)
        plans.append(RunPlan(
            objects=objs.astype(np.int32),
            init_joints=sample_initial_joints(rng),
            object_pose=table["spawn"][arms, objs],
            reach_pos=table["reach_pos"][arms, objs], reach_quat=table["reach_quat"][arms, objs],
            pregrasp_joints=table["pregrasp_joints"][arms, objs], grasp_joints=table["grasp_joints"][arms, objs],
            dump_pos=table["dump_pos"], dump_quat=table["dump_quat"], dump_joints=table["dump_joints"]))
    return jax.tree.map(lambda *xs: np.stack(xs).astype(np.int32 if xs[0].dtype.kind == "i" else np.float32), *plans)
