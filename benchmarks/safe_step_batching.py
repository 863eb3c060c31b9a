"""Safe execution stepped over a batch of teams: ``vmap`` against team by team (``lax.map``).

Under ``vmap`` the certified check's march (a ``while_loop``) runs until the slowest team of
the batch is done, and every team pays for every evaluation; ``lax.map`` lets each team take
its own number (``mjx_multiarm.env.wrappers.batched_step`` picks it on a CPU). Runs the
shipped policy with safe execution on the first ``--tasks`` tasks of ``--arms`` arms of a task
file for ``--steps`` control steps, both ways, and reports the second (compiled) run's time
and the largest joint difference between the two.

    python benchmarks/safe_step_batching.py --tasks crowd1to10.npz --arms 10 --count 32 --steps 20
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import numpy as np
from common import cpu_name

from mjx_multiarm.env.wrappers import TaskBank
from mjx_multiarm.planner.policy import Planner
from mjx_multiarm.tasks.dataset import load_tasks
from mjx_multiarm.tasks.types import take


def timed_rollouts(tasks_path: str, arms: int, count: int, steps: int) -> dict:
    tasks, _ = load_tasks(tasks_path)
    rows = np.flatnonzero(tasks.num_arms == arms)[:count]
    if not len(rows):
        raise SystemExit(f"error: {tasks_path} has no {arms}-arm task")
    planner = Planner.load(safe=True)
    env, policy = planner.environment(arms), planner.policy_fn()
    bank = TaskBank.from_tasks(take(tasks, rows), arms)
    steppers = {"vmap": jax.vmap(env.step), "map": lambda s, a: jax.lax.map(lambda pair: env.step(*pair), (s, a))}
    report, joints = {"tasks": int(len(rows)), "arms": arms, "steps": steps}, {}
    for name, step in steppers.items():

        @jax.jit
        def run(tasks, params, step=step):
            start = jax.vmap(lambda task: env.reset(None, task))(tasks)
            return jax.lax.scan(lambda s, _: (step(s, policy(s, params)), None), start, None, length=steps)[0]

        jax.block_until_ready(run(bank.tasks, planner.params))  # compile
        clock = time.perf_counter()
        final = jax.block_until_ready(run(bank.tasks, planner.params))
        report[f"{name}_s"] = time.perf_counter() - clock
        joints[name] = np.asarray(final.joints)
    report["max_joint_difference"] = float(np.abs(joints["vmap"] - joints["map"]).max())
    return report


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tasks", required=True, help="task file")
    parser.add_argument("--arms", type=int, default=10)
    parser.add_argument("--count", type=int, default=32, help="tasks (the first of that team size)")
    parser.add_argument("--steps", type=int, default=20, help="control steps")
    args = parser.parse_args(argv)
    print(f"# {cpu_name()}, jax {jax.__version__}")
    report = timed_rollouts(args.tasks, args.arms, args.count, args.steps)
    print(f"{report['tasks']} {args.arms}-arm teams, {args.steps} safe steps: vmap {report['vmap_s']:.2f} s, "
          f"team by team {report['map_s']:.2f} s ({report['vmap_s'] / report['map_s']:.1f}x); "
          f"largest joint difference {report['max_joint_difference']:.1e} rad")
    print(json.dumps(report))


if __name__ == "__main__":
    main()
