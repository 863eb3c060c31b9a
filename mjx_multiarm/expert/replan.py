"""The BiRRT baseline for moving targets (paper section 5): plan, execute, re-plan.

From the arms' current configuration the expert plans to the goal configuration of the
targets' current position along their paths (``interp(dynamic start -> goal, s(t))``),
executes the whole plan in the environment while the targets keep moving, and repeats
until the episode ends. Planning is treated as instantaneous (the environment's clock
stands still while the planner runs); its time is reported separately. When a plan fails
(for instance the interpolated goal is itself in collision) the arms hold still for one
step and the planner tries again at the next target position.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from mjx_multiarm.env.reaching import CONTROL_PERIOD, ReachingEnv
from mjx_multiarm.env.wrappers import TaskBank
from mjx_multiarm.expert.planner import SOLVED, PlannerConfig
from mjx_multiarm.expert.solve import solve, task_checker
from mjx_multiarm.tasks.dynamic import target_at
from mjx_multiarm.tasks.types import Tasks, take


@functools.cache
def _compiled(env: ReachingEnv):
    """jitted (reset, step, target path fraction) of ``env``, compiled once per environment."""

    def fraction(task, lengths, step):
        distance = task.speed * CONTROL_PERIOD * step
        return target_at(env.scene.arm, task.base_pos, task.base_quat, task.dynamic_start_joints, task.goal_joints, lengths, distance)[2]

    return jax.jit(env.reset), jax.jit(env.step), jax.jit(fraction)


@dataclasses.dataclass
class ReplanResult:
    """Outcome of one re-planning episode."""

    success: bool
    collided: bool
    steps: int
    plans: int  # planner calls, failed ones included
    plan_s: float  # total planning time


def replan_episode(env: ReachingEnv, tasks: Tasks, index: int, config: PlannerConfig = PlannerConfig(), seed: int = 0) -> ReplanResult:
    """Run the re-planning baseline on task ``index`` of numpy ``tasks`` (``env`` should have
    ``dynamic_targets=True``; with static targets it plans once and executes)."""
    if not env.config.dynamic_targets:
        raise ValueError("replan_episode needs an environment with EnvConfig(dynamic_targets=True)")
    task = jax.tree.map(lambda x: x[0], TaskBank.from_tasks(take(tasks, np.array([index])), env.max_arms).tasks)
    reset, step, fraction = _compiled(env)
    state = reset(None, task)
    active = np.asarray(task.active)
    checker = task_checker(tasks, index, config.resolution)
    q_from, q_to = np.asarray(task.dynamic_start_joints)[active], np.asarray(task.goal_joints)[active]
    hold = jnp.zeros(env.action_shape)
    plans, plan_s = 0, 0.0
    while not bool(state.done):
        s = np.asarray(fraction(task, state.target_lengths, state.step))[active][:, None]
        goal = (q_from + s * (q_to - q_from)).ravel()
        start = np.asarray(state.joints)[active].ravel()
        result = solve(checker, start, goal, config, seed + plans, int(tasks.task_id[index]))
        plans, plan_s = plans + 1, plan_s + result.plan_s
        if result.status != SOLVED or len(result.deltas) == 0:
            state = step(state, hold)
            continue
        actions = np.zeros((len(result.deltas), *env.action_shape), np.float32)
        actions[:, : checker.num_arms] = env.joint_deltas_to_actions(result.deltas)
        for action in actions:
            state = step(state, action)
            if bool(state.done):
                break
    return ReplanResult(bool(state.success), bool(state.collided.any()), int(state.step), plans, plan_s)
