"""The pick-and-place protocol: every arm runs its own phase sequence, asynchronously.

Per arm, as the original demo (``demo/demo.py`` of the paper's code):

0. ``rise`` (scripted; beyond the original): an arm whose end effector starts lower than
   ``start_height`` lifts it straight up, and the team starts its policy phases together
   when every rise is over (the arms start pointing at the bin, grippers near its walls,
   where the policy, which does not see the bin, would sweep through them);
1. ``reach_above`` (policy; beyond the original): the shared reaching policy drives the arm
   to a waypoint ``approach_height`` above the pregrasp position (0 skips it: the original
   protocol), then ``reach_pregrasp`` (policy) to the pregrasp position (the grasp backed
   off 0.10 m along the approach axis); each done within 5 cm / 0.2 rad. The waypoint keeps
   the gripper high while an arm turns from home (over the bin) to its object;
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
the bin or an object other than the one it holds ends the run. Every touch is a MuJoCo
contact (arms with their grippers, fingers and pads, the bin, the floor, the objects: the
scene's contact bits) at any physics step of the control step, as the original counted
PyBullet's contact points. The project's stricter accounting also records (without ending
the run) contacts in scripted phases, self collisions (the collision model's: an arm's own
geoms do not collide in the physics), and touching its own object outside the grasp
(``to_grasp`` .. ``raise``). The collision model's verdict (the reaching kernel, checked at
the end of each control step, the gripper as the original's stand-in box, no bin) is kept
beside it as ``kernel_cause``: the run's first collision under the original rule with arm-arm and
arm-floor contacts taken from the kernel instead, recorded without ending the run.

Shielded runs (``eval.pickplace --safe``) certify every team step in the cell's collision
model (:func:`mjx_multiarm.pickplace.scene.collision_model`: the arms' capsules, the stand-in
box and a box enclosing the simulated fingers and pads, the bin's boxes, the floor). It
does not hold the objects (neither one carried nor those on the floor), and the policy's
observation sees none of it beyond the arms' link points (as the paper's).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from mjx_multiarm.env.reaching import CONTROL_PERIOD
from mjx_multiarm.geometry.collision import scene_contacts
from mjx_multiarm.geometry.kinematics import forward_kinematics
from mjx_multiarm.geometry.robot import load_arm
from mjx_multiarm.geometry.scene import build_scene as build_arm_scene
from mjx_multiarm.geometry.transforms import quat_angle, quat_mul, quat_to_mat
from mjx_multiarm.pickplace.plans import RunPlan, lifted_joints
from mjx_multiarm.pickplace.scene import (
    ARM,
    BASE_POS,
    BASE_QUAT,
    BIN,
    FLOOR,
    GRIPPER_STROKE,
    NUM_ARMS,
    OBJECT,
    TIMESTEP,
    PickPlaceScene,
)

PHASES = ("rise", "reach_above", "reach_pregrasp", "to_pregrasp", "to_grasp", "close", "lift", "reach_dump", "to_dump", "lower", "release",
          "raise", "home", "done")
(RISE, REACH_ABOVE, REACH_PREGRASP, TO_PREGRASP, TO_GRASP, CLOSE, LIFT, REACH_DUMP, TO_DUMP, LOWER, RELEASE, RAISE, HOME,
 DONE) = range(len(PHASES))
#: Phases in which an arm may touch its own object.
GRASP_WINDOW = (TO_GRASP, RAISE)
#: A policy phase ends within 5 cm / 0.2 rad of its target (the original's tolerances).
PHASE_TOLERANCE = (0.05, 0.2)
LIFT_HEIGHT = 0.30
DUMP_DROP = 0.05
#: Scripted moves: at least 0.5 s (the original's duration), at most half the velocity limit.
SCRIPTED_STEPS = round(0.5 / CONTROL_PERIOD)
SCRIPTED_SPEED = 0.5
SUBSTEPS = round(CONTROL_PERIOD / TIMESTEP)
#: The original's limit: 100,000 physics steps of 1/240 s.
MAX_CONTROL_STEPS = 100_000 // SUBSTEPS

#: Why a run ended (``cause``), or the first stricter-accounting violation (``strict_cause``).
CAUSES = ("none", "arm-arm", "arm-floor", "arm-bin", "arm-object", "arm-self", "outside-bin", "timeout")
(NONE, ARM_ARM, ARM_FLOOR, ARM_BIN, ARM_OBJECT, ARM_SELF, OUTSIDE_BIN, TIMEOUT) = range(len(CAUSES))
#: Physics contact kinds per arm (the sensors' ``contacts`` [4, TOUCH_KINDS]).
TOUCH_FLOOR, TOUCH_BIN, TOUCH_OWN_OBJECT, TOUCH_OTHER_OBJECT, TOUCH_ARM = range(5)
TOUCH_KINDS = 5


@struct.dataclass
class Sensors:
    """What the physics reports after a control step."""

    joints: jnp.ndarray  # [4, 6] measured arm joint angles
    object_pos: jnp.ndarray  # [4, 3] object slot positions
    contacts: jnp.ndarray  # [4, TOUCH_KINDS] bool: touched floor / bin / own object / another object / another arm during the step


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
    entered: jnp.ndarray  # [4, len(PHASES)] control step at which each arm entered each phase (-1: not yet)
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
    kernel_cause: jnp.ndarray  # first collision with arm-arm and arm-floor from the collision model (NONE if none)


def bin_interior(scene: PickPlaceScene) -> np.ndarray:
    """[2] half extents (x, y) of the bin's walls (their centres, inside the rim): an object is
    in the bin when its x, y are inside."""
    walls = [b for b in scene.assets.bin_boxes if b["name"].startswith("wall")]
    half = np.zeros(2)
    for box in walls:
        axis = 0 if box["name"].endswith("x") else 1
        half[axis] = max(half[axis], abs(box["pos"][axis]))
    return half


def initial_state(plan: RunPlan) -> ControllerState:
    """The state at the start of a run: every arm in ``rise``, for as long as the slowest
    arm's rise takes (arms that do not rise hold; none rising: ``reach_above`` from the
    first control step)."""
    joints = jnp.asarray(plan.init_joints, jnp.float32)
    goal = jnp.asarray(plan.rise_joints, jnp.float32)
    frames = forward_kinematics(load_arm(), BASE_POS, BASE_QUAT, joints)
    zeros = jnp.zeros(NUM_ARMS, jnp.int32)
    entered = jnp.full((NUM_ARMS, len(PHASES)), -1, jnp.int32).at[:, RISE].set(0)
    duration = jnp.where(jnp.any(goal != joints, axis=-1), _move_steps(joints, goal), 0).max()
    duration = jnp.full(NUM_ARMS, duration)
    return ControllerState(
        phase=zeros + RISE, phase_step=zeros, entered=entered, duration=duration, start=joints, goal=goal,
        command=Commands(joints, jnp.zeros(NUM_ARMS, jnp.float32), jnp.zeros(NUM_ARMS, bool), jnp.zeros(NUM_ARMS, bool)),
        prev_joints=joints, prev_target_pos=frames.ee_pos, prev_target_quat=frames.ee_quat,
        step=jnp.int32(0), ended=jnp.bool_(False), success=jnp.bool_(False), cause=jnp.int32(NONE),
        cause_phase=jnp.int32(-1), strict_cause=jnp.int32(NONE), kernel_cause=jnp.int32(NONE))


def _move_steps(start, goal):
    speed = SCRIPTED_SPEED * jnp.asarray(load_arm().velocity_limit, jnp.float32) * CONTROL_PERIOD
    return jnp.maximum(SCRIPTED_STEPS, jnp.ceil(jnp.max(jnp.abs(goal - start) / speed, axis=-1))).astype(jnp.int32)


def _policy_phase(phase):
    return (phase == REACH_ABOVE) | (phase == REACH_PREGRASP) | (phase == REACH_DUMP)


def policy_target(plan: RunPlan, phase):
    """[4, 3], [4, 4] each arm's policy target in ``phase`` [4] (meaningful in policy phases)."""
    above, dump = (phase == REACH_ABOVE)[:, None], (phase == REACH_DUMP)[:, None]
    pos = jnp.where(above, plan.above_pos, jnp.where(dump, plan.dump_pos, plan.reach_pos))
    quat = jnp.where(above, plan.above_quat, jnp.where(dump, plan.dump_quat, plan.reach_quat))
    return pos, quat


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
    home = jnp.asarray(load_arm().home, jnp.float32)
    base_pos, base_quat = jnp.asarray(BASE_POS, jnp.float32), jnp.asarray(BASE_QUAT, jnp.float32)
    active = jnp.ones(NUM_ARMS, bool)

    def control(plan: RunPlan, state: ControllerState, sensors: Sensors):
        joints = sensors.joints
        phase = state.phase
        frames = forward_kinematics(load_arm(), base_pos, base_quat, joints)
        # Collisions of the configuration reached, under both rules.
        kernel = scene_contacts(arm_scene, base_pos, base_quat, joints, active)
        touch = sensors.contacts
        in_policy = _policy_phase(phase)
        attached = (phase > CLOSE) & (phase <= RELEASE)
        in_grasp = (phase >= GRASP_WINDOW[0]) & (phase <= GRASP_WINDOW[1])
        arm_arm, floor = touch[:, TOUCH_ARM], touch[:, TOUCH_FLOOR]
        bin_ = touch[:, TOUCH_BIN]
        objects = touch[:, TOUCH_OTHER_OBJECT] | (touch[:, TOUCH_OWN_OBJECT] & ~attached)
        original = [(ARM_ARM, in_policy & arm_arm), (ARM_FLOOR, in_policy & floor), (ARM_BIN, in_policy & bin_),
                    (ARM_OBJECT, in_policy & objects)]
        strict = [(ARM_ARM, arm_arm), (ARM_FLOOR, floor), (ARM_BIN, bin_),
                  (ARM_OBJECT, touch[:, TOUCH_OTHER_OBJECT] | (touch[:, TOUCH_OWN_OBJECT] & ~in_grasp)),
                  (ARM_SELF, kernel.within_arm < 0)]
        by_kernel = [(ARM_ARM, in_policy & (kernel.between_arms < 0)), (ARM_FLOOR, in_policy & (kernel.ground < 0)),
                     *original[2:]]
        collision = _first(original)
        culprit = jnp.argmax(jnp.stack([f for _, f in original]).any(axis=0))
        strict_now = _first(strict)
        kernel_now = _first(by_kernel)

        # Phase transitions.
        target_pos, target_quat = policy_target(plan, phase)
        reached = ((jnp.linalg.norm(frames.ee_pos - target_pos, axis=-1) < PHASE_TOLERANCE[0])
                   & (quat_angle(frames.ee_quat, target_quat) < PHASE_TOLERANCE[1]))
        done = jnp.where(in_policy, reached, state.phase_step >= state.duration) & (phase < DONE)
        phase = jnp.where(done, phase + 1, phase)
        dz = jnp.select([phase == LIFT, phase == LOWER, phase == RAISE], [LIFT_HEIGHT, -DUMP_DROP, DUMP_DROP], 0.0)
        cartesian = (phase == LIFT) | (phase == LOWER) | (phase == RAISE)
        goal = jnp.select(
            [(phase == p)[:, None] for p in (TO_PREGRASP, TO_GRASP, TO_DUMP, HOME)] + [cartesian[:, None]],
            [plan.pregrasp_joints, plan.grasp_joints, plan.dump_joints, jnp.broadcast_to(home, joints.shape),
             lifted_joints(joints, dz)],
            joints)
        goal = jnp.where(done[:, None], goal, state.goal)
        start = jnp.where(done[:, None], joints, state.start)
        duration = jnp.where(done, _move_steps(start, goal), state.duration)
        phase_step = jnp.where(done, 0, state.phase_step)

        # Commands for the next control step.
        use_policy = _policy_phase(phase)
        targets_pos, targets_quat = policy_target(plan, phase)
        targets_pos = jnp.where(use_policy[:, None], targets_pos, frames.ee_pos)
        targets_quat = jnp.where(use_policy[:, None], targets_quat, frames.ee_quat)
        policy = policy_step(base_pos, base_quat, state.prev_joints, joints, state.prev_target_pos,
                             state.prev_target_quat, targets_pos, targets_quat)
        fraction = jnp.minimum(1.0, (phase_step + 1) / duration)[:, None]
        scripted = start + (goal - start) * fraction
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
            phase_step=phase_step + 1,
            entered=jnp.where(~state.ended & done[:, None] & (jnp.arange(len(PHASES)) == phase[:, None]), state.step,
                              state.entered),
            duration=duration, start=start, goal=goal, command=commands,
            prev_joints=joints, prev_target_pos=targets_pos, prev_target_quat=targets_quat,
            step=state.step + jnp.where(state.ended, 0, 1),
            ended=state.ended | ends,
            success=jnp.where(ends, (collision == NONE) & all_done & in_bin, state.success),
            cause=jnp.where(ends, cause, state.cause),
            cause_phase=jnp.where(ends & (collision != NONE), state.phase[culprit], state.cause_phase),
            strict_cause=jnp.where(~state.ended & (state.strict_cause == NONE), strict_now, state.strict_cause),
            kernel_cause=jnp.where(~state.ended & (state.kernel_cause == NONE), kernel_now, state.kernel_cause),
        )
        # An ended run holds its last commands.
        held = Commands(state.command.arm_target, state.command.gripper, jnp.zeros(NUM_ARMS, bool), jnp.zeros(NUM_ARMS, bool))
        commands = jax.tree.map(lambda a, b: jnp.where(state.ended | ends, a, b), held, commands)
        return new_state.replace(command=commands), commands

    return control


def arm_contacts(scene: PickPlaceScene, geom1, geom2, dist, xp=np):
    """[4, TOUCH_KINDS] bool per arm: touching the floor / the bin / its own object / another
    object / another arm, from a contact list (``geom1``, ``geom2``, ``dist``; ``dist < 0`` is a touch). ``xp`` is
    numpy (MuJoCo C) or jax.numpy (MJX)."""
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
            (mine & (other_kind == ARM) & (other_slot != arms[None, :])).any(axis=0),
        ], axis=1))
    return flags[0] | flags[1]


def relative_pose(ee_pos, ee_quat, obj_pos, obj_quat):
    """The object's pose in the ee_link frame (position, wxyz): a weld's ``relpose``."""
    rot = quat_to_mat(ee_quat)
    pos = jnp.einsum("...ji,...j->...i", rot, obj_pos - ee_pos)
    conj = ee_quat * jnp.array([1.0, -1.0, -1.0, -1.0])
    return pos, quat_mul(conj, obj_quat)
