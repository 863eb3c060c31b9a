"""Handing a stuck policy over to BiRRT (beyond the paper): a hybrid planner.

With safe execution (:mod:`mjx_multiarm.env.shield`) the policy never collides, and the
tasks it fails end where its team got stuck (a deadlock: arms giving way to each other
until the episode runs out). From there the BiRRT expert plans the whole team to its goal
configuration (:func:`mjx_multiarm.expert.solve.solve_team`, its steps certified free with
the environment's rules before they count); the task succeeds when that plan does and the
trajectory, the policy's steps followed by the plan's, stays within the episode's limit. :func:`birrt_handover` does this
for evaluated tasks; ``Planner.rollout(..., goal_joints=...)`` for one team.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from mjx_multiarm.env.reaching import EnvConfig
from mjx_multiarm.env.wrappers import Outcomes
from mjx_multiarm.expert.planner import SOLVED, PlannerConfig
from mjx_multiarm.expert.solve import solve_team
from mjx_multiarm.tasks.types import Tasks


def birrt_handover(tasks: Tasks, outcomes: Outcomes, final_joints: np.ndarray, config: PlannerConfig = PlannerConfig(),
                   seed: int = 0, max_steps: int = EnvConfig.max_steps) -> tuple[Outcomes, np.ndarray]:
    """The outcomes once every timed-out task is handed to BiRRT from where its episode ended.

    Args:
      tasks: numpy tasks, in ``outcomes`` order; outcomes: the policy's episodes;
      final_joints: [N, slots, 6] the joints each episode ended at (a task's arms occupy
        its first slots).
      max_steps: the episode's limit (control steps), for the policy's steps plus the plan's.

    Returns:
      (outcomes: a handed-over task that the plan solves within the limit is a success whose
      steps are the policy's plus the plan's; planning seconds per task, NaN where nothing
      was handed over).
    """
    if not len(final_joints) == len(outcomes.team) == tasks.num_tasks:
        raise ValueError(f"birrt_handover: {tasks.num_tasks} tasks, {len(outcomes.team)} outcomes and "
                         f"{len(final_joints)} final joints must match")
    success, timeout, steps, reached = (x.copy() for x in (outcomes.success, outcomes.timeout, outcomes.steps, outcomes.reached))
    plan_s = np.full(tasks.num_tasks, np.nan)
    for i in np.flatnonzero(outcomes.timeout):
        arms = int(outcomes.team[i])
        result = solve_team(tasks.base_pos[i][:arms], tasks.base_quat[i][:arms], final_joints[i][:arms],
                            tasks.goal_joints[i][:arms], config, seed, int(tasks.task_id[i]))
        plan_s[i] = result.plan_s
        if result.status == SOLVED and steps[i] + len(result.deltas) <= max_steps:
            success[i], timeout[i], steps[i], reached[i] = True, False, steps[i] + len(result.deltas), outcomes.team[i]
    return dataclasses.replace(outcomes, success=success, timeout=timeout, steps=steps, reached=reached), plan_s
