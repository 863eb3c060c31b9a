"""Replay stored experts in the JAX environment: do their steps reach the goals without collision?

Every solved task's delta-joint steps are executed from the task's start in
:class:`mjx_multiarm.env.reaching.ReachingEnv` (static targets, 2 cm / 0.1 rad, swept collision
checks); a replay succeeds when the episode ends in success. Batches of tasks run under one
``jit`` / ``vmap``.

    python benchmarks/expert_replay.py --tasks tasks.npz --experts tasks.experts --json

With ``--json`` the last line is one JSON object: replayed, replay_success_rate, collisions,
failures (task ids), by_team_size.
"""

from __future__ import annotations

import argparse
import json

import jax
import jax.numpy as jnp
import numpy as np

from mjx_multiarm.env.reaching import EnvConfig, ReachingEnv
from mjx_multiarm.env.wrappers import TaskBank, replay_actions
from mjx_multiarm.expert.store import ExpertStore
from mjx_multiarm.tasks.dataset import load_tasks
from mjx_multiarm.tasks.types import take

BATCH = 128
#: Replay lengths are padded to a multiple of this (few compiled shapes).
LENGTH_QUANTUM = 64


def replay_experts(tasks, store: ExpertStore, max_steps: int = 500, batch_size: int = BATCH) -> dict:
    """Replay every solved expert of ``store`` on its task of ``tasks``, ``batch_size`` at a time."""
    row_of = {int(t): i for i, t in enumerate(tasks.task_id)}
    ids = [int(t) for t in store.task_ids[store.solved] if int(t) in row_of]
    env = ReachingEnv(tasks.max_arms, EnvConfig(max_steps=max_steps))
    replay = jax.jit(jax.vmap(lambda s, a, n: replay_actions(env, s, a, n)))
    reset = jax.jit(jax.vmap(lambda task: env.reset(None, task)))
    success, collided, teams = [], [], []
    for start in range(0, len(ids), batch_size):
        batch = ids[start : start + batch_size]
        length = max(len(store.deltas(t)) for t in batch)
        deltas, lengths = store.padded(batch, -(-length // LENGTH_QUANTUM) * LENGTH_QUANTUM, tasks.max_arms)
        bank = TaskBank.from_tasks(take(tasks, np.array([row_of[t] for t in batch])), tasks.max_arms)
        states, _ = replay(reset(bank.tasks), jnp.asarray(env.joint_deltas_to_actions(deltas)), jnp.asarray(lengths))
        success += np.asarray(states.success.any(axis=1)).tolist()
        collided += np.asarray(states.collided.any(axis=(1, 2))).tolist()
        teams += np.asarray(bank.tasks.active.sum(-1)).tolist()
    success, collided, teams = np.array(success, bool), np.array(collided, bool), np.array(teams, int)
    return {
        "replayed": len(ids),
        "replay_success_rate": float(success.mean()) if len(ids) else float("nan"),
        "collisions": int(collided.sum()),
        "failures": [ids[i] for i in np.flatnonzero(~success)],
        "by_team_size": {int(k): {"replayed": int((teams == k).sum()), "success_rate": float(success[teams == k].mean())} for k in np.unique(teams)},
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tasks", required=True, help="task dataset (.npz)")
    parser.add_argument("--experts", required=True, help="expert file of those tasks")
    parser.add_argument("--max-steps", type=int, default=500, help="episode length (default 500)")
    parser.add_argument("--batch", type=int, default=BATCH, help=f"tasks replayed at once (default {BATCH})")
    parser.add_argument("--json", action="store_true", help="end with one JSON line")
    args = parser.parse_args(argv)
    result = replay_experts(load_tasks(args.tasks)[0], ExpertStore(args.experts), args.max_steps, args.batch)
    print(f"replayed {result['replayed']} experts: {result['replay_success_rate']:.2%} succeed, {result['collisions']} collide")
    for k, row in result["by_team_size"].items():
        print(f"  {k:2d} arms: {row['replayed']} replayed, {row['success_rate']:.2%} succeed")
    if args.json:
        print(json.dumps(result))


if __name__ == "__main__":
    main()
