"""Physics backends of the pick-and-place runs: MuJoCo C (CPU, runs in lockstep in one
process) and MJX (runs batched under ``jit``/``vmap``) in either of its implementations:
MuJoCo Warp (``impl="warp"``: Warp kernels on the CPU or an NVIDIA GPU, any batch) or XLA
(``impl="jax"``). All drive the same controller
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
import os
import time

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from jax._src import xla_bridge  # the backend-start hook (jaxlib 0.10.2)
from mujoco import mjx
from mujoco.mjx._src import collision_driver  # MJX's collision groups, to check its culling

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
from mjx_multiarm.pickplace.scene import MJX_MAX_CONTACTS, MJX_MAX_GEOM_PAIRS, NUM_ARMS, PickPlaceScene

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
    phase_steps: list[dict[str, int]]  # every arm's phases in order, each with the control step it began
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
                phases=[PHASES[int(p)] for p in state.phase[r]],
                phase_steps=[{PHASES[p]: int(k) for p, k in enumerate(arm) if k >= 0} for arm in state.entered[r]],
                object_pos=np.round(object_pos[r], 4).tolist(),
                seconds=seconds))
        return results


def phase_timing_difference(a: RunResult, b: RunResult) -> int | None:
    """The largest difference, in control steps, between the steps at which the same arm
    began the same phase in two runs of one plan; ``None`` where an arm's phase sequences
    differ (one reached a phase the other did not)."""
    if [list(arm) for arm in a.phase_steps] != [list(arm) for arm in b.phase_steps]:
        return None
    return max(abs(x[p] - y[p]) for x, y in zip(a.phase_steps, b.phase_steps) for p in x)


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


#: MJX implementations of the physics: ``"jax"`` (XLA) and ``"warp"`` (MuJoCo Warp kernels
#: called from JAX; the ``warp`` extra, ``pip install ".[warp]"``; CPU or NVIDIA GPU).
MJX_IMPLS = ("jax", "warp")
#: Contacts (per run; one list for the batch) and constraint rows (per run) MuJoCo Warp
#: allocates: twice and seven times MuJoCo C's largest counts over 16 whole runs of seed
#: 5000 (31 contacts, 148 rows; benchmarks/RESULTS.md). A batch that runs out raises.
WARP_CONTACTS_PER_RUN, WARP_CONSTRAINT_ROWS = 64, 1024


@functools.cache
def _mjx_advance(scene: PickPlaceScene, policy_step, chunk: int, max_steps: int, impl: str = "jax"):
    """The jitted step of a batch of runs: ``chunk`` control steps (one per scene, policy,
    chunk, step limit and implementation: later batches of the same size reuse its
    compilation). Its arguments are batched along their first axis, ``world`` being each
    run's index in the batch (MuJoCo Warp keeps the contacts of every run in one list)."""
    model = mjx.put_model(scene.model, impl=impl)
    control = make_controller(policy_step, scene, max_steps)
    arm_act = jnp.asarray(scene.arm_actuators)
    finger_act = jnp.asarray(scene.finger_actuators)
    welds = jnp.asarray(scene.welds)
    per_run = _per_run_fields(impl)
    dropped = _xla_collision_dropped(scene.model) if impl == "jax" else lambda d: jnp.zeros((), bool)

    def physics(geom_pos, eq_data):
        return model.tree_replace({"geom_pos": geom_pos, "eq_data": eq_data})

    def one_step(world, plan, geom_pos, eq_data, d, state, sensors):
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
            d, touched, overflow = carry
            ctrl = d.ctrl.at[arm_act].set(_lerp(previous.arm_target, cmd.arm_target, k))
            ctrl = ctrl.at[finger_act].set(_lerp(previous.gripper, cmd.gripper, k)[:, None])
            d = mjx.step(m, d.replace(ctrl=ctrl))
            return d, touched | _contacts_mjx(scene, d, world, impl), overflow | dropped(d)

        new_d, touched, overflow = jax.lax.fori_loop(
            0, SUBSTEPS, substep, (d, jnp.zeros((NUM_ARMS, TOUCH_KINDS), bool), jnp.zeros((), bool)))
        new_d = per_run(lambda old, new: jnp.where(state.ended, old, new), d, new_d)  # an ended run stands still
        return eq_data, new_d, state, _sense_mjx(scene, new_d, touched), overflow & ~state.ended

    def advance(world, plan, geom_pos, eq_data, d, state, sensors):
        def body(_, carry):
            *carry, overflow = carry
            *carry, more = one_step(world, plan, geom_pos, *carry)
            return *carry, overflow | more
        return jax.lax.fori_loop(0, chunk, body, (eq_data, d, state, sensors, jnp.zeros((), bool)))

    return jax.jit(jax.vmap(advance))


def _xla_collision_dropped(model: mujoco.MjModel):
    """A function of one run's ``mjx.Data`` after an XLA step: whether its collision sizes
    (:data:`~mjx_multiarm.pickplace.scene.MJX_MAX_GEOM_PAIRS`, ``MJX_MAX_CONTACTS``) may have
    dropped a contact in that step. MJX keeps, in every collision function with more
    candidate pairs than ``max_geom_pairs``, the nearest pairs by bounding sphere: a pair can
    only touch where its spheres overlap, so none was dropped unless more pairs overlap than
    it keeps. Of the contacts it keeps the deepest ``max_contact_points``: one may have been
    dropped only if every kept contact is active. ``geom_xpos`` after the step is where its
    collision ran (the integrator moves only ``qpos``)."""
    margin = model.geom_margin
    groups = [np.asarray(pairs)[:, :2] for pairs in collision_driver._geom_groups(model).values()]
    culled = [g for g in groups if len(g) > MJX_MAX_GEOM_PAIRS]
    geom1 = jnp.asarray(np.concatenate([g[:, 0] for g in culled]))
    geom2 = jnp.asarray(np.concatenate([g[:, 1] for g in culled]))
    reach = jnp.asarray(np.concatenate([model.geom_rbound[g].sum(1) + margin[g].sum(1) for g in culled]))
    group = jnp.asarray(np.concatenate([np.full(len(g), i) for i, g in enumerate(culled)]))

    def dropped(d) -> jnp.ndarray:
        gap = jnp.linalg.norm(d.geom_xpos[geom2] - d.geom_xpos[geom1], axis=-1) - reach
        overlapping = jax.ops.segment_sum((gap <= 0).astype(jnp.int32), group, num_segments=len(culled))
        contact = d._impl.contact
        return (overlapping > MJX_MAX_GEOM_PAIRS).any() | (contact.dist < contact.includemargin).all()

    return dropped


def _per_run_fields(impl: str):
    """``fn`` mapped over the fields of two ``mjx.Data`` that hold one run's state: every
    field on XLA; on MuJoCo Warp not the contact list and buffer sizes, which the batch's
    runs share (they pass through from the newer data)."""
    if impl == "jax":
        return jax.tree.map
    from mujoco.mjx.warp.types import DATA_NON_VMAP

    def mapped(fn, old, new):
        out = jax.tree.map(fn, old, new)
        return out.replace(_impl=out._impl.replace(**{name: getattr(new._impl, name) for name in DATA_NON_VMAP}))

    return mapped


def _contacts_mjx(scene: PickPlaceScene, d, world, impl: str) -> jnp.ndarray:
    """[arms, kinds] this run's contacts after a physics step (:func:`arm_contacts`)."""
    if impl == "jax":
        c = d._impl.contact
        return arm_contacts(scene, c.geom[:, 0], c.geom[:, 1], c.dist, xp=jnp)
    c = d._impl  # MuJoCo Warp: one list for the batch, each contact tagged with its run
    mine = (jnp.arange(c.contact__dist.shape[0]) < c.nacon[0]) & (c.contact__worldid == world)
    return arm_contacts(scene, c.contact__geom[:, 0], c.contact__geom[:, 1], jnp.where(mine, c.contact__dist, jnp.inf), xp=jnp)


def _sense_mjx(scene: PickPlaceScene, d, touched) -> Sensors:
    return Sensors(joints=d.qpos[jnp.asarray(scene.arm_qpos)].astype(jnp.float32),
                   object_pos=d.xpos[jnp.asarray(scene.object_body)].astype(jnp.float32), contacts=touched)


#: The XLA CPU option that ends a wedge of batched MJX convex collisions: with jaxlib 0.10.2
#: and XLA's concurrency-optimized scheduler, a jitted ``vmap`` of ``mjx.step`` over 8 or more
#: runs of a scene with mesh geoms compiles, then never returns (every worker thread idle;
#: ``benchmarks/mjx_xla_hang.py`` reproduces it with 8 meshes). It must be in ``XLA_FLAGS``
#: before JAX starts its backend (:func:`fix_xla_cpu_scheduler`).
XLA_CPU_SCHEDULER_FIX = "--xla_cpu_enable_concurrency_optimized_scheduler=false"
#: Runs per jitted call of XLA's MJX on the CPU backend where that option is not in effect
#: (1-4 run). MuJoCo Warp (``impl="warp"``) runs any batch.
MJX_CPU_BATCH = 4


def fix_xla_cpu_scheduler() -> bool:
    """Put :data:`XLA_CPU_SCHEDULER_FIX` in ``XLA_FLAGS`` unless JAX has started its CPU
    backend (XLA reads its flags then); whether the option is in effect for this process."""
    flags = os.environ.get("XLA_FLAGS", "")
    if XLA_CPU_SCHEDULER_FIX not in flags and "cpu" not in _started_with_fix:
        os.environ["XLA_FLAGS"] = f"{flags} {XLA_CPU_SCHEDULER_FIX}".strip()
    return _scheduler_fixed()


def _scheduler_fixed() -> bool:
    """Whether the CPU backend started, or will start, with :data:`XLA_CPU_SCHEDULER_FIX`."""
    return _started_with_fix.get("cpu", XLA_CPU_SCHEDULER_FIX in os.environ.get("XLA_FLAGS", ""))


_started_with_fix: dict[str, bool] = {}  # per platform: XLA_FLAGS held the fix when its backend started


def _record_start(backend) -> None:
    _started_with_fix[backend.platform] = XLA_CPU_SCHEDULER_FIX in os.environ.get("XLA_FLAGS", "")


xla_bridge.register_backend_initialization_hook(_record_start)


def run_mjx(scene: PickPlaceScene, policy_step, plans: RunPlan, max_control_steps: int = MAX_CONTROL_STEPS,
            chunk: int = 20, impl: str = "jax", batch: int | None = None) -> list[RunResult]:
    """Run every plan of ``plans`` (leading dim = runs) on MJX (``impl``: one of
    :data:`MJX_IMPLS`) from the settled MuJoCo C states, in batches of ``batch`` runs (all
    of them by default; at most :data:`MJX_CPU_BATCH` with XLA on the CPU backend unless
    :func:`fix_xla_cpu_scheduler` took effect), the last one padded; the host checks between
    chunks of ``chunk`` control steps whether every run of a batch has ended, and raises where
    a run's XLA collision may have dropped a contact (:func:`_xla_collision_dropped`)."""
    if impl not in MJX_IMPLS:
        raise ValueError(f"impl must be one of {MJX_IMPLS}, got {impl!r}")
    runs = len(plans.objects)
    size = min(batch or runs, runs)
    if impl == "jax" and jax.default_backend() == "cpu" and not _scheduler_fixed():
        size = min(size, MJX_CPU_BATCH)
    results = []
    for first in range(0, runs, size):
        rows = np.minimum(np.arange(first, first + size), runs - 1)  # the last batch repeats its last run
        part = jax.tree.map(lambda x, rows=rows: x[rows], plans)
        results += _run_mjx_batch(scene, policy_step, part, max_control_steps, chunk, impl)[:runs - first]
    return results


#: The fields of a settled MuJoCo C run that MuJoCo Warp's batched data takes over (the rest
#: is recomputed by the first physics step; the controller reads the bodies' poses before it).
_WARP_STATE = ("time", "qpos", "qvel", "act", "ctrl", "qacc_warmstart", "eq_active", "xpos", "xquat")


def _batched_data(models, datas, impl: str):
    """The runs' settled MuJoCo C states as one batched ``mjx.Data``."""
    if impl == "jax":
        return jax.tree.map(lambda *xs: jnp.stack(xs), *[mjx.put_data(m, d) for m, d in zip(models, datas)])
    runs = len(datas)
    state = {name: jnp.asarray(np.stack([getattr(d, name) for d in datas])) for name in _WARP_STATE}

    def one(state):
        d = mjx.make_data(models[0], impl="warp", naconmax=WARP_CONTACTS_PER_RUN * runs, njmax=WARP_CONSTRAINT_ROWS)
        return d.replace(**{name: value.astype(getattr(d, name).dtype) for name, value in state.items()})

    return jax.vmap(one)(state)


def _run_mjx_batch(scene: PickPlaceScene, policy_step, plans: RunPlan, max_control_steps: int,
                   chunk: int, impl: str) -> list[RunResult]:
    """One jitted MJX batch of runs."""
    runs = len(plans.objects)
    start = time.perf_counter()
    models, datas = _settled(scene, plans)
    advance = _mjx_advance(scene, policy_step, chunk, max_control_steps, impl)
    d = _batched_data(models, datas, impl)
    geom_pos = jnp.asarray(np.stack([m.geom_pos for m in models]), d.qpos.dtype)
    eq_data = jnp.asarray(np.stack([m.eq_data for m in models]), d.qpos.dtype)
    sensors = _sensors_mujoco(scene, datas, np.zeros((runs, NUM_ARMS, TOUCH_KINDS), bool))
    state = jax.vmap(initial_state)(plans)
    world = jnp.arange(runs)
    while not bool(np.asarray(state.ended).all()):  # the controller ends every run by max_control_steps
        eq_data, d, state, sensors, dropped = advance(world, plans, geom_pos, eq_data, d, state, sensors)
        if np.asarray(dropped).any():
            raise RuntimeError(f"MJX (XLA) may have dropped a contact: more candidate pairs overlap than the "
                               f"{MJX_MAX_GEOM_PAIRS} it keeps per collision function, or every one of the "
                               f"{MJX_MAX_CONTACTS} contacts it keeps is active: raise scene.MJX_MAX_GEOM_PAIRS / "
                               f"MJX_MAX_CONTACTS")
        if impl == "warp" and np.asarray(d._impl.overflow).any():
            raise RuntimeError(f"MuJoCo Warp ran out of contacts or constraint rows ({WARP_CONTACTS_PER_RUN} contacts per "
                               f"run, {WARP_CONSTRAINT_ROWS} rows): raise WARP_CONTACTS_PER_RUN / WARP_CONSTRAINT_ROWS")
    seconds = (time.perf_counter() - start) / runs
    return RunResult.collect(state, np.asarray(d.xpos[:, scene.object_body]), seconds)
