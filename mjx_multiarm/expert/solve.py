"""Expert demonstrations for tasks: plan, decimate, and verify against the environment.

A task's expert is the delta-joint step sequence of its decimated RRT-Connect plan
(:mod:`mjx_multiarm.expert.planner`, :mod:`mjx_multiarm.expert.decimate`). Before it is
accepted the sequence is executed the way the environment executes it (float32 joints,
joint limits) and every step is checked with the certified motion check
(:mod:`mjx_multiarm.geometry.certified`), keeping
:data:`~mjx_multiarm.geometry.checker.REPLAY_MARGIN` of clearance for float32 arithmetic; the
planner's edge checks sample configurations, so a sub-millimetre graze can pass them and
fail this check. On such a disagreement the task is planned again with the next seed, up to
``PlannerConfig.attempts`` times, so every stored expert is certified free: no configuration
along its steps touches (and so the environment's sampled sweep never sees a contact).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from mjx_multiarm.env.reaching import step_limits
from mjx_multiarm.expert.decimate import ANGLE_TOLERANCE, path_to_deltas
from mjx_multiarm.expert.planner import (
    REPLAY_COLLISION,
    SOLVED,
    CollisionChecker,
    PlannerConfig,
    plan,
    task_seed,
)
from mjx_multiarm.geometry.checker import REPLAY_MARGIN, team_checker
from mjx_multiarm.geometry.robot import NUM_JOINTS, load_arm
from mjx_multiarm.tasks.types import Tasks


@dataclasses.dataclass
class ExpertResult:
    """One task's expert.

    Attributes:
      task_id: the task's dataset id.
      status: index into :data:`~mjx_multiarm.expert.planner.STATUSES`.
      deltas: [T, k, 6] float32 joint steps of the task's k arms ([0, k, 6] unless solved).
      plan_s: planning time summed over attempts (s).
      iterations: RRT-Connect iterations summed over attempts.
      attempts: plans made.
    """

    task_id: int
    status: int
    deltas: np.ndarray
    plan_s: float
    iterations: int
    attempts: int


def solve(checker: CollisionChecker, start, goal, config: PlannerConfig, seed: int, task_id: int = 0,
          angle_tolerance: float = ANGLE_TOLERANCE) -> ExpertResult:
    """Expert steps from composite ``start`` to ``goal`` ([6k] each) of ``checker``'s arms."""
    max_step, _ = step_limits(load_arm())
    empty = np.zeros((0, checker.num_arms, 6), np.float32)
    total_s, total_iterations = 0.0, 0
    for attempt in range(config.attempts):
        result = plan(checker, start, goal, config, task_seed(seed + attempt, task_id))
        total_s, total_iterations = total_s + result.plan_s, total_iterations + result.iterations
        if result.status != SOLVED:
            return ExpertResult(task_id, result.status, empty, total_s, total_iterations, attempt + 1)
        deltas = path_to_deltas(result.path, max_step, angle_tolerance)
        if replay_free(checker, start, deltas):
            return ExpertResult(task_id, SOLVED, deltas, total_s, total_iterations, attempt + 1)
    return ExpertResult(task_id, REPLAY_COLLISION, empty, total_s, total_iterations, config.attempts)


def executed_joints(start, deltas, joint_range) -> np.ndarray:
    """[T + 1, k, 6] the team configurations of executing ``deltas`` [T, k, 6] from ``start``
    ([k, 6] or composite [6k]) as the environment does (float32 joints, ``joint_range`` [6, 2])."""
    lower, upper = (np.asarray(x, np.float32) for x in np.asarray(joint_range).T)
    joints = [np.asarray(start, np.float32).reshape(-1, NUM_JOINTS)]
    for delta in np.asarray(deltas, np.float32):
        joints.append(np.clip(joints[-1] + delta, lower, upper).astype(np.float32))
    return np.stack(joints)


def replay_free(checker: CollisionChecker, start, deltas) -> bool:
    """Whether executing ``deltas`` [T, k, 6] from composite ``start`` [6k] as the environment
    does is certified free (:func:`executed_joints`), keeping :data:`REPLAY_MARGIN`."""
    joint_range = np.stack([checker.lower[:NUM_JOINTS], checker.upper[:NUM_JOINTS]], axis=-1)
    return checker.steps_certified(executed_joints(start, deltas, joint_range), REPLAY_MARGIN)


def task_checker(tasks: Tasks, index: int, resolution: float) -> CollisionChecker:
    """The collision checker of the active arms of task ``index``."""
    active = np.asarray(tasks.active[index])
    return team_checker(tasks.base_pos[index][active], tasks.base_quat[index][active], resolution)


def solve_team(base_pos, base_quat, start, goal, config: PlannerConfig = PlannerConfig(), seed: int = 0, task_id: int = 0,
               angle_tolerance: float = ANGLE_TOLERANCE) -> ExpertResult:
    """The expert of a team (bases as :func:`team_checker`'s) from joints ``start`` to ``goal``
    ([k, 6] each)."""
    checker = team_checker(base_pos, base_quat, config.resolution)
    return solve(checker, np.ravel(start), np.ravel(goal), config, seed, task_id, angle_tolerance)


def solve_task(tasks: Tasks, index: int, config: PlannerConfig = PlannerConfig(), seed: int = 0,
               angle_tolerance: float = ANGLE_TOLERANCE) -> ExpertResult:
    """The expert of task ``index`` of numpy ``tasks`` (start -> goal)."""
    active = np.asarray(tasks.active[index])
    return solve_team(tasks.base_pos[index][active], tasks.base_quat[index][active], np.asarray(tasks.start_joints[index])[active],
                      np.asarray(tasks.goal_joints[index])[active], config, seed, int(tasks.task_id[index]), angle_tolerance)
