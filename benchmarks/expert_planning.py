"""Expert planner benchmark: success rate and planning time per team size.

Generates test-style static tasks (``--count`` per team size, stratified over the
difficulty bins like the ``test`` preset), plans them with the batched precompute (one CPU
thread per worker process, ``--workers`` processes), and reports per team size the solved
rate, the median / 95th-percentile planning time of solved tasks, the planning rate
(``workers`` / mean planning time: tasks/s of that team size alone) and the mean length of
the experts in environment steps; overall, tasks per second of wall time, everything
included (worker start-up, compilation, writing the experts). The tasks and the expert file
are kept in ``--dir`` for ``benchmarks/expert_replay.py``.

    python benchmarks/expert_planning.py --arms 1-4,10 --count 20 --workers 2 --dir /tmp/expert-bench --json
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time

import numpy as np
from common import cpu_name

from mjx_multiarm.cli import parse_arms
from mjx_multiarm.expert.__main__ import report
from mjx_multiarm.expert.planner import STATUSES, PlannerConfig
from mjx_multiarm.expert.precompute import precompute
from mjx_multiarm.tasks.dataset import save_tasks
from mjx_multiarm.tasks.generate import GenerationSpec, generate_chunk


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--arms", type=parse_arms, default=tuple(range(1, 11)), help="team sizes (default 1-10)")
    parser.add_argument("--count", type=int, default=20, help="tasks per team size (default 20)")
    parser.add_argument("--workers", type=int, default=2, help="planning processes, one CPU thread each (default 2)")
    parser.add_argument("--iterations", type=int, default=PlannerConfig().iterations)
    parser.add_argument("--time-limit", type=float, default=PlannerConfig().time_limit)
    parser.add_argument("--seed", type=int, default=11)
    parser.add_argument("--dir", type=pathlib.Path, default=pathlib.Path("expert-bench"), help="where tasks and experts are written")
    parser.add_argument("--chunk-size", type=int, default=1, help="tasks per precompute chunk (default 1)")
    parser.add_argument("--json", action="store_true", help="end with one JSON line")
    args = parser.parse_args(argv)

    args.dir.mkdir(parents=True, exist_ok=True)
    tasks_file, experts_file = args.dir / "tasks.npz", args.dir / "tasks.experts"
    count = args.count * len(args.arms)
    spec = GenerationSpec(count=count, arm_counts=args.arms, mode="static", seed=args.seed, chunk_size=count)
    save_tasks(tasks_file, generate_chunk(spec, 0), {"benchmark": "expert_planning"})
    config = PlannerConfig(iterations=args.iterations, time_limit=args.time_limit)
    experts_file.unlink(missing_ok=True)
    start = time.perf_counter()
    store = precompute(tasks_file, experts_file, config, seed=0, workers=args.workers, chunk_size=args.chunk_size)
    wall = time.perf_counter() - start
    summary = report(store)
    arms, times = store.index["arms"], store.index["plan_s"]
    print(f"# {cpu_name()}, {args.workers} workers x 1 thread, iterations {args.iterations}, time limit {args.time_limit:g} s")
    print(f"{'arms':>4} {'solved':>8} {'median ms':>10} {'p95 ms':>8} {'max ms':>8} {'tasks/s':>8} {'steps':>6}  failures")
    for k in sorted(summary["by_team_size"]):
        row = summary["by_team_size"][k]
        team, solved = arms == k, store.solved & (arms == k)
        p95 = float(np.percentile(times[solved], 95)) if solved.any() else float("nan")
        failures = {STATUSES[s]: int(n) for s, n in zip(*np.unique(store.index["status"][team & ~store.solved], return_counts=True))}
        row.update(p95_plan_s=p95, max_plan_s=float(times[team].max()), solved_rate=row["solved"] / row["tasks"],
                   tasks_per_s=args.workers / float(times[team].mean()))
        print(f"{k:>4} {row['solved']:>4}/{row['tasks']:<3} {1e3 * row['median_plan_s']:>10.2f} {1e3 * p95:>8.2f} "
              f"{1e3 * row['max_plan_s']:>8.1f} {row['tasks_per_s']:>8.1f} {row['mean_steps']:>6.1f}  {failures or ''}")
    print(f"wall {wall:.1f} s for {count} tasks ({count / wall:.1f} tasks/s, everything included); experts in {experts_file}")
    if args.json:
        print(json.dumps({**summary, "wall_s": wall, "tasks_per_s": count / wall, "workers": args.workers}))


if __name__ == "__main__":
    main()
