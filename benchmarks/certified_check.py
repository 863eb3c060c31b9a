"""The certified motion check, checked independently: a dense re-check finds no contact in
anything it certifies (issue 51).

Two parts, each re-checking motions at ``--dense`` evenly spaced configurations (the start
and end included) with the collision kernel (``swept_contacts``):

- ``--random N``: N two-arm full-speed steps (benchmarks/swept_collision.py's sampler) whose
  ends are free. Reports, for the environment's certified check (JAX,
  ``mjx_multiarm.geometry.certified``) and the expert's (numba, pair by pair,
  ``CollisionChecker.steps_certified``): the motions it certifies, how many of those the
  dense check finds in contact (must be 0), how many it flags that the dense check finds
  free (its caution), and the evaluations the JAX march took.
- ``--tasks FILE``: the safe policy (``Planner(safe=True)``, the shipped policy unless
  ``--checkpoint``) run on the first ``--per-size`` tasks of each team size for 500 steps;
  every executed step before its episode ended is re-checked densely (must find no contact).
  With ``--handover K`` the hybrid planner's rollouts instead: the safe policy for K steps,
  then the executed steps of BiRRT's plan from where each unfinished task stopped.

    python benchmarks/certified_check.py --random 100000 --json
    python benchmarks/certified_check.py --tasks test1to10.npz --per-size 32 --json
    python benchmarks/certified_check.py --tasks crowd1to10.npz --per-size 8 --handover 100 --json
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time

import jax
import numpy as np
from common import cpu_name, random_two_arm_steps

from mjx_multiarm.env.reaching import ReachingEnv
from mjx_multiarm.env.wrappers import TaskBank, batched_step
from mjx_multiarm.expert.planner import SOLVED, PlannerConfig
from mjx_multiarm.expert.solve import executed_joints, solve_team
from mjx_multiarm.geometry.certified import certified_contacts
from mjx_multiarm.geometry.checker import team_checker
from mjx_multiarm.geometry.collision import (
    CONTACTS_ONLY,
    scene_contacts,
    swept_contacts,
)
from mjx_multiarm.geometry.robot import load_arm
from mjx_multiarm.planner.policy import SHIPPED_POLICY, Planner
from mjx_multiarm.tasks.dataset import load_tasks
from mjx_multiarm.tasks.types import take


def _dense_check(scene, dense: int):
    """A jitted ``(pos, quat, q0, q1, active) -> [n]``: some configuration among ``dense`` + 1
    evenly spaced along q0 -> q1 is in contact."""

    @jax.jit
    def collided(pos, quat, q0, q1, active):
        start = scene_contacts(scene, pos, quat, q0, active, CONTACTS_ONLY).collided.any(-1)
        return start | swept_contacts(scene, pos, quat, q0, q1, active, dense, max_distance=CONTACTS_ONLY).collided.any(-1)

    return collided


def _free_end_motions(motions: int, chunk: int, rng: np.random.Generator, free_at):
    """Yield ``(steps drawn so far, [pos, quat, q0, q1])``: ``motions`` random two-arm steps
    whose ends are free, in parts of at most ``chunk`` (the others are drawn and dropped)."""
    pool, samples, left = None, 0, motions
    while left > 0:
        _, *drawn = random_two_arm_steps(chunk, rng)
        samples += chunk
        active = np.ones(drawn[2].shape[:-1], bool)
        free = np.asarray(free_at(drawn[0], drawn[1], drawn[2], active) & free_at(drawn[0], drawn[1], drawn[3], active))
        pool = [x[free] if pool is None else np.concatenate([old, x[free]]) for old, x in zip(pool or drawn, drawn)]
        while left > 0 and len(pool[0]) >= min(chunk, left):
            size = min(chunk, left)
            yield samples, [x[:size] for x in pool]
            pool, left = [x[size:] for x in pool], left - size


def check_random(motions: int, dense: int, seed: int = 0, chunk: int = 2048) -> dict:
    """Part one of the module doc, on ``motions`` random steps with free ends."""
    scene, chunk = ReachingEnv(2).scene, min(chunk, motions)
    dense_collided = _dense_check(scene, dense)
    certify = jax.jit(lambda *a: certified_contacts(scene, *a))
    free_at = jax.jit(lambda pos, quat, q, active: ~scene_contacts(scene, pos, quat, q, active).collided.any(-1))
    counts = {name: {"certified": 0, "certified_in_contact": 0, "flagged_free": 0} for name in ("jax", "numba")}
    samples, in_contact, evaluations = 0, 0, []
    active = np.ones((chunk, 2), bool)
    for samples, part in _free_end_motions(motions, chunk, np.random.default_rng(seed), free_at):
        size = len(part[0])
        padded = [np.concatenate([x, np.repeat(x[:1], chunk - size, axis=0)]) for x in part]  # one compiled shape
        touches = np.asarray(dense_collided(*padded, active))[:size]
        verdict = certify(*padded, active)
        free = {"jax": ~np.asarray(verdict.collided.any(-1))[:size],
                "numba": np.array([team_checker(p, q, 0.05).steps_certified(np.stack([a, b]), 0.0)
                                   for p, q, a, b in zip(*part)])}
        for name, ok in free.items():
            counts[name]["certified"] += int(ok.sum())
            counts[name]["certified_in_contact"] += int((ok & touches).sum())
            counts[name]["flagged_free"] += int((~ok & ~touches).sum())
        in_contact += int(touches.sum())
        evaluations.append(np.asarray(verdict.evaluations)[:size])
        print(f"  {sum(map(len, evaluations)):,} of {motions:,} motions re-checked", flush=True)
    evaluations = np.concatenate(evaluations)
    return {"samples": samples, "motions_with_free_ends": motions, "dense": dense, "dense_in_contact": in_contact,
            "checks": counts, "jax_evaluations_mean": float(evaluations.mean()),
            "jax_evaluations_p99": float(np.percentile(evaluations, 99)), "jax_evaluations_max": int(evaluations.max())}


def _handed_over_steps(subset, size: int, final_joints: np.ndarray, unfinished: np.ndarray):
    """The executed plan steps of the hybrid (``birrt_handover``'s BiRRT call) for the
    ``unfinished`` tasks of ``subset``, from where their episodes ended: [n, 2, size, 6] motions
    with the index of their task."""
    joint_range = load_arm().joint_range
    motions, owners = [], []
    for i in np.flatnonzero(unfinished):
        result = solve_team(subset.base_pos[i][:size], subset.base_quat[i][:size], final_joints[i][:size],
                            subset.goal_joints[i][:size], PlannerConfig(), 0, int(subset.task_id[i]))
        if result.status == SOLVED:
            path = executed_joints(final_joints[i][:size], result.deltas, joint_range)
            motions.append(np.stack([path[:-1], path[1:]], axis=1))
            owners.append(np.full(len(path) - 1, i))
    if not motions:
        return np.zeros((0, 2, size, 6), np.float32), np.zeros(0, int)
    return np.concatenate(motions), np.concatenate(owners)


def check_rollouts(tasks_path: pathlib.Path, checkpoint: pathlib.Path | None, per_size: int, dense: int,
                   steps: int = 500, handover: int = 0) -> dict:
    """Part two of the module doc; with ``handover`` the hybrid's rollouts: the safe policy for
    that many steps, then BiRRT from where each unfinished task stopped."""
    steps = handover or steps
    tasks, _ = load_tasks(tasks_path)
    planner = Planner.load(checkpoint, safe=True)
    result = {"tasks": str(tasks_path), "policy": str(checkpoint or SHIPPED_POLICY), "dense": dense, "by_team_size": {}}
    for size in sorted(set(tasks.num_arms.tolist())):
        subset = take(tasks, np.flatnonzero(tasks.num_arms == size)[:per_size])
        env = planner.environment(size, max_steps=steps)
        bank = TaskBank.from_tasks(subset, size)
        policy = planner.policy_fn()

        @jax.jit
        def run(tasks, params, env=env, policy=policy):
            start = jax.vmap(lambda task: env.reset(None, task))(tasks)

            def body(states, _):
                following = batched_step(env)(states, policy(states, params))
                return following, (following.joints, states.done)

            final, trace = jax.lax.scan(body, start, None, length=steps)
            return trace, final.success

        (joints, done_before), success = jax.device_get(run(bank.tasks, planner.params))  # [T, N, A, 6], [T, N], [N]
        before = np.concatenate([np.asarray(bank.tasks.start_joints)[None], joints[:-1]])
        t, n = np.nonzero(~done_before)  # the steps executed before each episode ended
        q0, q1 = before[t, n], joints[t, n]
        row = {"tasks": bank.size, "policy_steps": int(len(t)), "policy_successes": int(success.sum())}
        if handover:
            plan, owner = _handed_over_steps(subset, size, joints[-1], ~success)
            q0, q1, n = np.concatenate([q0, plan[:, 0]]), np.concatenate([q1, plan[:, 1]]), np.concatenate([n, owner])
            row.update(handed_over=int((~success).sum()), plans=int(len(np.unique(owner))), plan_steps=int(len(plan)))
        t0 = time.perf_counter()
        check, chunk = _dense_check(env.scene, dense), 512
        rows = np.concatenate([np.arange(len(n)), np.zeros(-len(n) % chunk, int)])  # padded to whole chunks
        touched = np.concatenate([np.asarray(check(*(np.asarray(x)[part] for x in (
            np.asarray(bank.tasks.base_pos)[n], np.asarray(bank.tasks.base_quat)[n], q0, q1,
            np.asarray(bank.tasks.active)[n])))) for part in rows.reshape(-1, chunk)])[: len(n)]
        row.update(steps_checked=int(len(n)), steps_in_contact=int(touched.sum()), recheck_s=time.perf_counter() - t0)
        result["by_team_size"][str(size)] = row
        planned = f" ({row['plan_steps']:,} of them BiRRT's)" if handover else ""
        print(f"  {size:>2} arms: {bank.size} tasks, {row['policy_successes']} reached by the safe policy, "
              f"{len(n):,} executed steps re-checked{planned}, "
              f"{int(touched.sum())} in contact", flush=True)
    return result


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--random", type=int, default=0, help="random two-arm full-speed steps with free ends to re-check")
    parser.add_argument("--tasks", type=pathlib.Path, help="a task file: re-check the safe policy's executed steps")
    parser.add_argument("--checkpoint", type=pathlib.Path, help="policy file (default: the shipped policy)")
    parser.add_argument("--per-size", type=int, default=32, help="tasks per team size of --tasks")
    parser.add_argument("--handover", type=int, default=0, metavar="K",
                        help="re-check the hybrid instead: the safe policy for K steps, then BiRRT's plan from where each "
                             "unfinished task stopped (as eval.benchmark --handover --episode-steps K)")
    parser.add_argument("--dense", type=int, default=256, help="configurations per motion of the re-check")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", action="store_true", help="end with one JSON line")
    args = parser.parse_args(argv)
    if not args.random and args.tasks is None:
        parser.error("give --random N and/or --tasks FILE")
    print(f"# {cpu_name()}, jax {jax.__version__}")
    report = {}
    if args.random:
        r = report["random"] = check_random(args.random, args.dense, args.seed)
        print(f"{r['motions_with_free_ends']:,} of {r['samples']:,} two-arm full-speed steps have free ends; the dense check "
              f"({r['dense']} configurations) finds {r['dense_in_contact']} of them in contact")
        for name, c in r["checks"].items():
            print(f"  {name} certified check: certifies {c['certified']:,}, of which in contact {c['certified_in_contact']}; "
                  f"flags {c['flagged_free']} free motions")
        print(f"  JAX march: {r['jax_evaluations_mean']:.1f} evaluations on average, p99 {r['jax_evaluations_p99']:.0f}, "
              f"max {r['jax_evaluations_max']}")
    if args.tasks is not None:
        report["rollouts"] = check_rollouts(args.tasks, args.checkpoint, args.per_size, args.dense, handover=args.handover)
    if args.json:
        print(json.dumps(report))


if __name__ == "__main__":
    main()
