"""Where a policy's failed episodes end: each arm's final error to its target, by team size.

Runs the policy (mean actions, 500 steps, evaluation rules: 2 cm / 0.1 rad, a collision
ends the episode) on every task of ``--tasks`` and, per team size and outcome (timeout,
collision, and the solved tasks for comparison), prints the arms' final position errors
(median, shares within 2 / 5 / 10 cm and beyond 20 cm), rotation errors (median, share
within 0.1 rad), the step the episodes ended at (median, share by step 3), and how close
the task's arms stand to each other at its start and goal configurations (median of each
task's smallest distance between arms), and how many are detour tasks (the straight
joint-space motion from start to goal collides). Timeouts that end within a few cm are a
precision problem; collisions at the first steps, or timeouts far from the targets, are a
coordination problem.

    python benchmarks/failure_modes.py --checkpoint RUN_DIR/policy.npz --tasks held512.npz --json
    python benchmarks/failure_modes.py --checkpoint RUN_DIR/policy.npz --tasks crowd1to10.npz --arms 1-4
"""

from __future__ import annotations

import argparse
import json

import jax
import numpy as np

from mjx_multiarm.cli import parse_arms
from mjx_multiarm.env.reaching import EVAL_TOLERANCE
from mjx_multiarm.env.wrappers import TaskBank, make_episodes
from mjx_multiarm.geometry.collision import scene_contacts
from mjx_multiarm.geometry.transforms import quat_angle
from mjx_multiarm.planner.policy import Planner
from mjx_multiarm.tasks.dataset import load_tasks
from mjx_multiarm.tasks.select import straight_motion_free
from mjx_multiarm.tasks.types import take


def clearances(env, tasks) -> tuple[np.ndarray, np.ndarray]:
    """[N] smallest distance (m) between the arms of each task at its start and at its goal
    configuration (inf for one arm); one compiled check serves both."""
    @jax.jit
    @jax.vmap
    def check(base_pos, base_quat, joints, active):
        return scene_contacts(env.scene, base_pos, base_quat, joints, active).between_arms.min(-1)

    return tuple(np.asarray(check(tasks.base_pos, tasks.base_quat, joints, tasks.active))
                 for joints in (tasks.start_joints, tasks.goal_joints))


def final_errors(planner: Planner, tasks, steps: int) -> dict:
    """Per outcome (timeout, collision, solved): final position / rotation errors of the
    active arms, end steps, and the arms' clearance at the start and goal configurations."""
    env = planner.environment(tasks.max_arms, tolerance=EVAL_TOLERANCE, max_steps=steps)
    bank = TaskBank.from_tasks(tasks, tasks.max_arms)
    final = jax.device_get(make_episodes(env, planner.policy_fn(), steps)(bank.take(np.arange(bank.size)), planner.params))
    position = np.linalg.norm(final.arms.ee_pos - final.arms.target_pos, axis=-1)
    rotation = np.asarray(quat_angle(final.arms.ee_quat, final.arms.target_quat))
    collision = final.collided.any(axis=-1) & ~final.success
    start, goal = clearances(env, bank.tasks)
    detour = ~straight_motion_free(tasks)
    kinds = {"timeout": ~final.success & ~collision, "collision": collision, "solved": final.success}
    report = {}
    for kind, rows in kinds.items():
        arms = rows[:, None] & np.asarray(final.task.active)
        if not arms.any():
            continue
        p, r = position[arms], rotation[arms]
        report[kind] = {"tasks": int(rows.sum()), "arms": int(arms.sum()), "position_median_cm": 100 * float(np.median(p)),
                        "within_2cm": float(np.mean(p < 0.02)), "within_5cm": float(np.mean(p < 0.05)),
                        "within_10cm": float(np.mean(p < 0.10)), "beyond_20cm": float(np.mean(p > 0.20)),
                        "rotation_median_rad": float(np.median(r)), "within_0.1rad": float(np.mean(r < 0.1)),
                        "end_step_median": float(np.median(final.step[rows])), "ended_by_step_3": float(np.mean(final.step[rows] <= 3)),
                        "start_clearance_median_cm": 100 * float(np.median(start[rows])),
                        "goal_clearance_median_cm": 100 * float(np.median(goal[rows])), "detour_tasks": int(detour[rows].sum())}
    return report


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", required=True, help="policy file (RUN_DIR/policy.npz)")
    parser.add_argument("--tasks", required=True, help="task dataset .npz")
    parser.add_argument("--arms", type=parse_arms, default=None, help="team sizes to run, e.g. 1-4 (default: all in --tasks)")
    parser.add_argument("--episode-steps", type=int, default=500)
    parser.add_argument("--json", action="store_true", help="end with one JSON line")
    args = parser.parse_args()
    planner = Planner.load(args.checkpoint)
    tasks = load_tasks(args.tasks)[0]
    result = {}
    for team in sorted(set(tasks.num_arms.tolist()) & set(args.arms or tasks.num_arms.tolist())):
        result[team] = final_errors(planner, take(tasks, tasks.num_arms == team), args.episode_steps)
        for kind, row in result[team].items():
            print(f"{team} arm(s), {kind}: {row['tasks']} tasks; final position error median {row['position_median_cm']:.1f} cm "
                  f"(<2 cm {row['within_2cm']:.0%}, <5 cm {row['within_5cm']:.0%}, <10 cm {row['within_10cm']:.0%}, "
                  f">20 cm {row['beyond_20cm']:.0%}); rotation median {row['rotation_median_rad']:.2f} rad "
                  f"(<0.1 {row['within_0.1rad']:.0%}); ended at step {row['end_step_median']:.0f} (median; by step 3: "
                  f"{row['ended_by_step_3']:.0%}); arms apart at start / goal {row['start_clearance_median_cm']:.1f} / "
                  f"{row['goal_clearance_median_cm']:.1f} cm (median); detour tasks {row['detour_tasks']}")
    if args.json:
        print(json.dumps(result))


if __name__ == "__main__":
    main()
