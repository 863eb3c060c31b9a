"""Physics backends of the pick-and-place runs: MuJoCo C (CPU, runs in lockstep in one
process) and MJX (runs batched under ``jit``/``vmap``). Both drive the same controller
(:func:`mjx_multiarm.pickplace.protocol.make_controller`) with the same scene and plans.

A run starts with every arm at its initial configuration and the objects placed, then
settles for :data:`SETTLE_STEPS` physics steps with the arms held, on MuJoCo C for both
backends (MJX takes over the settled states: the same start); each control step then
applies the controller's commands over :data:`~mjx_multiarm.pickplace.protocol.SUBSTEPS`
physics steps (servo targets interpolated linearly) and reports the joints, the objects'
positions and every arm's contacts during the step.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import time

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from mjx_multiarm.pickplace.plans import RunPlan
from mjx_multiarm.pickplace.protocol import (
    CAUSES,
    MAX_CONTROL_STEPS,
    PHASES,
    SUBSTEPS,
    TOUCH_KINDS,
    ControllerState,
    Sensors,
    arm_contacts,
    initial_state,
    make_controller,
    relative_pose,
)
from mjx_multiarm.pickplace.scene import NUM_ARMS, PickPlaceScene

SETTLE_STEPS = 120  # 0.5 s


@dataclasses.dataclass
class RunResult:
    """One run's outcome (see :data:`~mjx_multiarm.pickplace.protocol.CAUSES` and ``PHASES``)."""

    success: bool
    cause: str
    cause_phase: str | None  # phase of the arm that collided
    strict_cause: str  # first violation under the stricter accounting ("none" if none)
    strict_success: bool
    kernel_cause: str  # the run's first collision with arm-arm and arm-floor from the collision model ("none" if none)
    control_steps: int
    physics_steps: int
    phases: list[str]  # every arm's phase at the end
    object_pos: list[list[float]]  # final object positions
    seconds: float  # wall time of its batch, per run

    @classmethod
    def collect(cls, state: ControllerState, object_pos: np.ndarray, seconds: float) -> list[RunResult]:
        """Results of a batch from its final controller states (numpy, leading dim = runs)."""
        state = jax.tree.map(np.asarray, state)
        results = []
        for r in range(len(state.success)):
            strict = CAUSES[int(state.strict_cause[r])]
            success = bool(state.success[r])
            phase = int(state.cause_phase[r])
            results.append(cls(
                success=success, cause=CAUSES[int(state.cause[r])], cause_phase=PHASES[phase] if phase >= 0 else None,
                strict_cause=strict, strict_success=success and strict == "none",
                kernel_cause=CAUSES[int(state.kernel_cause[r])],
                control_steps=int(state.step[r]), physics_steps=int(state.step[r]) * SUBSTEPS,
                phases=[PHASES[int(p)] for p in state.phase[r]], object_pos=np.round(object_pos[r], 4).tolist(),
                seconds=seconds))
        return results


@functools.cache
def _controller(scene: PickPlaceScene, policy_step, max_steps: int):
    """The jitted controller of a batch of runs (one per scene, policy and step limit)."""
    return jax.jit(jax.vmap(make_controller(policy_step, scene, max_steps)))


def _lerp(a, b, k: int):
    return a + (b - a) * ((k + 1) / SUBSTEPS)


# ----------------------------------------------------------------------------------------
# MuJoCo C


def _reset_mujoco(scene: PickPlaceScene, m: mujoco.MjModel, d: mujoco.MjData, plan: RunPlan) -> None:
    mujoco.mj_resetData(m, d)
    for a in range(NUM_ARMS):
        d.qpos[scene.arm_qpos[a]] = plan.init_joints[a]
        d.ctrl[scene.arm_actuators[a]] = plan.init_joints[a]
        d.qpos[scene.object_qpos[a]:scene.object_qpos[a] + 7] = plan.object_pose[a]
    mujoco.mj_forward(m, d)
    for _ in range(SETTLE_STEPS):
        mujoco.mj_step(m, d)


def held_pose_mujoco(scene: PickPlaceScene, d: mujoco.MjData, arm: int) -> np.ndarray:
    """[7] arm ``arm``'s object in its ee_link frame now (position, wxyz)."""
    pos, quat = relative_pose(d.xpos[scene.ee_body[arm]], d.xquat[scene.ee_body[arm]], d.xpos[scene.object_body[arm]],
                              d.xquat[scene.object_body[arm]])
    return np.concatenate([np.asarray(pos), np.asarray(quat)])


def attach_mujoco(scene: PickPlaceScene, m: mujoco.MjModel, d: mujoco.MjData, arm: int) -> None:
    """Weld arm ``arm``'s object to its ee_link at their current relative pose."""
    m.eq_data[scene.welds[arm], 3:10] = held_pose_mujoco(scene, d, arm)
    d.eq_active[scene.welds[arm]] = 1


def _sense_mujoco(scene: PickPlaceScene, d: mujoco.MjData, contacts: np.ndarray) -> np.ndarray:
    n = d.ncon
    if n:
        c = d.contact
        contacts |= arm_contacts(scene, c.geom1[:n], c.geom2[:n], c.dist[:n], xp=np)
    return contacts


def _settled(scene: PickPlaceScene, plans: RunPlan) -> tuple[list, list]:
    """Each run's model copy (its object selection; later its weld poses) and its data after
    the settling steps, on MuJoCo C: both backends start every run from this state."""
    plans_np = jax.tree.map(np.asarray, plans)
    models, datas = [], []
    for r in range(len(plans_np.objects)):
        m = copy.deepcopy(scene.model)
        m.geom_pos[:] = scene.geom_pos(plans_np.objects[r])
        d = mujoco.MjData(m)
        _reset_mujoco(scene, m, d, jax.tree.map(lambda x, r=r: x[r], plans_np))
        models.append(m)
        datas.append(d)
    return models, datas


def run_mujoco(scene: PickPlaceScene, policy_step, plans: RunPlan, max_control_steps: int = MAX_CONTROL_STEPS,
               on_step=None) -> list[RunResult]:
    """Run every plan of ``plans`` (leading dim = runs) on MuJoCo C, in lockstep.

    ``on_step(step, datas, state)`` is called after every control step (rendering). Each run
    has its own model copy (its object selection and weld poses).
    """
    runs = len(plans.objects)
    start = time.perf_counter()
    models, datas = _settled(scene, plans)
    control = _controller(scene, policy_step, max_control_steps)
    state = jax.vmap(initial_state)(plans)
    sensors = _sensors_mujoco(scene, datas, np.zeros((runs, NUM_ARMS, TOUCH_KINDS), bool))
    for step in range(max_control_steps + 1):  # the controller ends every run by then
        previous = np.asarray(state.command.arm_target), np.asarray(state.command.gripper)
        state, commands = control(plans, state, sensors)
        ended = np.asarray(state.ended)
        if ended.all():
            break
        commands = jax.tree.map(np.asarray, commands)
        touched = np.zeros((runs, NUM_ARMS, TOUCH_KINDS), bool)
        for r in np.flatnonzero(~ended):
            m, d = models[r], datas[r]
            for a in np.flatnonzero(commands.attach[r]):
                attach_mujoco(scene, m, d, a)
            for a in np.flatnonzero(commands.release[r]):
                d.eq_active[scene.welds[a]] = 0
            for k in range(SUBSTEPS):
                d.ctrl[scene.arm_actuators] = _lerp(previous[0][r], commands.arm_target[r], k)
                d.ctrl[scene.finger_actuators] = _lerp(previous[1][r], commands.gripper[r], k)[:, None]
                mujoco.mj_step(m, d)
                _sense_mujoco(scene, d, touched[r])
        sensors = _sensors_mujoco(scene, datas, touched)
        if on_step is not None:
            on_step(step, datas, state)
    seconds = (time.perf_counter() - start) / runs
    return RunResult.collect(state, np.stack([d.xpos[scene.object_body] for d in datas]), seconds)


def _sensors_mujoco(scene: PickPlaceScene, datas, touched: np.ndarray) -> Sensors:
    return Sensors(joints=jnp.asarray(np.stack([d.qpos[scene.arm_qpos] for d in datas]), jnp.float32),
                   object_pos=jnp.asarray(np.stack([d.xpos[scene.object_body] for d in datas]), jnp.float32),
                   contacts=jnp.asarray(touched))


# ----------------------------------------------------------------------------------------
# MJX


@functools.cache
def _mjx_advance(scene: PickPlaceScene, policy_step, chunk: int, max_steps: int):
    """The jitted step of a batch of runs: ``chunk`` control steps (one per scene, policy,
    chunk and step limit: later batches of the same size reuse its compilation)."""
    model = mjx.put_model(scene.model)
    control = make_controller(policy_step, scene, max_steps)
    arm_act = jnp.asarray(scene.arm_actuators)
    finger_act = jnp.asarray(scene.finger_actuators)
    welds = jnp.asarray(scene.welds)

    def physics(geom_pos, eq_data):
        return model.tree_replace({"geom_pos": geom_pos, "eq_data": eq_data})

    def one_step(plan, geom_pos, eq_data, d, state, sensors):
        previous = state.command
        state, cmd = control(plan, state, sensors)
        pos, quat = relative_pose(d.xpos[scene.ee_body], d.xquat[scene.ee_body], d.xpos[scene.object_body],
                                  d.xquat[scene.object_body])
        relpose = jnp.concatenate([pos, quat], axis=-1)
        eq_data = eq_data.at[welds, 3:10].set(jnp.where(cmd.attach[:, None], relpose, eq_data[welds, 3:10]))
        eq_active = d.eq_active.at[welds].set(jnp.where(cmd.attach, True, jnp.where(cmd.release, False, d.eq_active[welds])))
        d = d.replace(eq_active=eq_active)
        m = physics(geom_pos, eq_data)

        def substep(k, carry):
            d, touched = carry
            ctrl = d.ctrl.at[arm_act].set(_lerp(previous.arm_target, cmd.arm_target, k))
            ctrl = ctrl.at[finger_act].set(_lerp(previous.gripper, cmd.gripper, k)[:, None])
            d = mjx.step(m, d.replace(ctrl=ctrl))
            return d, touched | _contacts_mjx(scene, d)

        new_d, touched = jax.lax.fori_loop(0, SUBSTEPS, substep, (d, jnp.zeros((NUM_ARMS, TOUCH_KINDS), bool)))
        new_d = jax.tree.map(lambda old, new: jnp.where(state.ended, old, new), d, new_d)
        return eq_data, new_d, state, _sense_mjx(scene, new_d, touched)

    def advance(plan, geom_pos, eq_data, d, state, sensors):
        def body(_, carry):
            return one_step(plan, geom_pos, *carry)
        return jax.lax.fori_loop(0, chunk, body, (eq_data, d, state, sensors))

    return jax.jit(jax.vmap(advance))


def _contacts_mjx(scene: PickPlaceScene, d) -> jnp.ndarray:
    c = d._impl.contact
    return arm_contacts(scene, c.geom[:, 0], c.geom[:, 1], c.dist, xp=jnp)


def _sense_mjx(scene: PickPlaceScene, d, touched) -> Sensors:
    return Sensors(joints=d.qpos[jnp.asarray(scene.arm_qpos)].astype(jnp.float32),
                   object_pos=d.xpos[jnp.asarray(scene.object_body)].astype(jnp.float32), contacts=touched)


#: Runs per jitted MJX call on the CPU backend: with jaxlib 0.10.2, batches of 8 runs hang
#: after compiling (every XLA CPU worker waits for work; benchmarks/RESULTS.md), 1-4 run.
MJX_CPU_BATCH = 4


def run_mjx(scene: PickPlaceScene, policy_step, plans: RunPlan, max_control_steps: int = MAX_CONTROL_STEPS,
            chunk: int = 20) -> list[RunResult]:
    """Run every plan of ``plans`` (leading dim = runs) on MJX from the settled MuJoCo C
    states, as one batch (on the CPU backend: batches of :data:`MJX_CPU_BATCH` runs, the
    last one padded); the host checks between chunks of ``chunk`` control steps whether
    every run has ended."""
    runs = len(plans.objects)
    size = min(MJX_CPU_BATCH, runs) if jax.default_backend() == "cpu" else runs
    results = []
    for first in range(0, runs, size):
        rows = np.minimum(np.arange(first, first + size), runs - 1)  # the last batch repeats its last run
        batch = jax.tree.map(lambda x, rows=rows: x[rows], plans)
        results += _run_mjx_batch(scene, policy_step, batch, max_control_steps, chunk)[:runs - first]
    return results


def _run_mjx_batch(scene: PickPlaceScene, policy_step, plans: RunPlan, max_control_steps: int,
                   chunk: int) -> list[RunResult]:
    """One jitted MJX batch of runs."""
    runs = len(plans.objects)
    start = time.perf_counter()
    models, datas = _settled(scene, plans)
    advance = _mjx_advance(scene, policy_step, chunk, max_control_steps)
    d = jax.tree.map(lambda *xs: jnp.stack(xs), *[mjx.put_data(m, d) for m, d in zip(models, datas)])
    geom_pos = jnp.asarray(np.stack([m.geom_pos for m in models]), d.qpos.dtype)
    eq_data = jnp.asarray(np.stack([m.eq_data for m in models]), d.qpos.dtype)
    sensors = _sensors_mujoco(scene, datas, np.zeros((runs, NUM_ARMS, TOUCH_KINDS), bool))
    state = jax.vmap(initial_state)(plans)
    while not bool(np.asarray(state.ended).all()):  # the controller ends every run by max_control_steps
        eq_data, d, state, sensors = advance(plans, geom_pos, eq_data, d, state, sensors)
    seconds = (time.perf_counter() - start) / runs
    return RunResult.collect(state, np.asarray(d.xpos[:, scene.object_body]), seconds)
