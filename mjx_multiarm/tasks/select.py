"""Training sets that weight the tasks needing coordination: a per-team-size subset of a
dataset with a chosen share of *detour* tasks, those whose straight joint-space motion from
start to goal collides (:func:`straight_motion_free`).

In the paper's difficulty bins about one 2-4-arm task in six is a detour task, and a policy
trained on them as they come solves most straight tasks and few detour tasks
(benchmarks/RESULTS.md, "Detour tasks").
"""

from __future__ import annotations

import numpy as np

from mjx_multiarm.geometry.checker import team_checker
from mjx_multiarm.geometry.collision import SWEEP_RESOLUTION
from mjx_multiarm.tasks.types import Tasks


def straight_motion_free(tasks: Tasks, resolution: float = SWEEP_RESOLUTION) -> np.ndarray:
    """[N] bool: whether each task's straight joint-space motion from its start to its goal
    configuration is collision-free (checked every ``resolution`` rad, the expert's checker).
    A task where it is not needs a detour: some arm has to go around another, or wait for it."""
    free = np.empty(tasks.num_tasks, bool)
    for i in range(tasks.num_tasks):
        active = np.asarray(tasks.active[i])
        checker = team_checker(tasks.base_pos[i][active], tasks.base_quat[i][active], resolution)
        free[i] = checker.motion_free(np.ravel(tasks.start_joints[i][active]), np.ravel(tasks.goal_joints[i][active]))
    return free


def detour_rows(num_arms, free, per_team: int, detour_share: float, seed: int = 0) -> np.ndarray:
    """Sorted rows of a subset with ``per_team`` tasks of every team size in ``num_arms`` [N]:
    ``detour_share`` of them detour tasks (``free`` [N] False) where the dataset holds that
    many (else all its detour tasks of that size), the rest drawn from its straight tasks.

    Raises ValueError when a team size has fewer than ``per_team`` tasks or ``detour_share``
    is outside [0, 1].
    """
    num_arms, free = np.asarray(num_arms), np.asarray(free, bool)
    if num_arms.shape != free.shape:
        raise ValueError(f"num_arms {num_arms.shape} and free {free.shape} must have the same shape")
    if per_team < 1:
        raise ValueError(f"per_team={per_team}: a subset takes at least one task of every team size")
    if not 0.0 <= detour_share <= 1.0:
        raise ValueError(f"detour_share={detour_share} must lie in [0, 1]")
    rng = np.random.default_rng(seed)
    rows = []
    for team in np.unique(num_arms):
        detours = np.flatnonzero((num_arms == team) & ~free)
        straight = np.flatnonzero((num_arms == team) & free)
        if len(detours) + len(straight) < per_team:
            raise ValueError(f"{team}-arm tasks: {len(detours) + len(straight)} in the dataset, fewer than per_team={per_team}")
        take_detours = min(round(detour_share * per_team), len(detours))
        take_straight = per_team - take_detours
        if take_straight > len(straight):  # not enough straight tasks: fill with detour tasks
            take_straight, take_detours = len(straight), per_team - len(straight)
        rows += [rng.choice(detours, take_detours, replace=False), rng.choice(straight, take_straight, replace=False)]
    return np.sort(np.concatenate(rows))
