"""Expert planner benchmark: success rate and planning time per team size.

Generates test-style static tasks (``--count`` per team size, stratified over the
difficulty bins like the ``test`` preset), plans them with the batched precompute (one CPU
thread per worker process, ``--workers`` processes), and reports per team size the solved
rate and the median / 95th-percentile planning time of solved tasks. The tasks and the
expert file are kept in ``--dir`` for ``benchmarks/expert_replay.py``.

    python benchmarks/expert_planning.py --arms 1-10 --count 20 --workers 2 --dir /tmp/expert-bench --json
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time

import numpy as np
from core_throughput import cpu_name

from mjx_multiarm.expert.__main__ import report
from mjx_multiarm.expert.planner import STATUSES, PlannerConfig
from mjx_multiarm.expert.precompute import precompute
from mjx_multiarm.tasks.__main__ import parse_arms
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
    store = precompute(tasks_file, experts_file, config, seed=0, workers=args.workers, chunk_size=1)
    wall = time.perf_counter() - start
    summary = report(store)
    arms, times = store.index["arms"], store.index["plan_s"]
    print(f"# {cpu_name()}, {args.workers} workers x 1 thread, iterations {args.iterations}, time limit {args.time_limit:g} s")
    print(f"{'arms':>4} {'solved':>8} {'median s':>9} {'p95 s':>8} {'max s':>8}  failures")
    for k in sorted(summary["by_team_size"]):
        row = summary["by_team_size"][k]
        solved = store.solved & (arms == k)
        p95 = float(np.percentile(times[solved], 95)) if solved.any() else float("nan")
        worst = float(times[arms == k].max())
        failures = {STATUSES[s]: int(n) for s, n in zip(*np.unique(store.index["status"][(arms == k) & ~store.solved], return_counts=True))}
        row.update(p95_plan_s=p95, max_plan_s=worst, solved_rate=row["solved"] / row["tasks"])
        print(f"{k:>4} {row['solved']:>4}/{row['tasks']:<3} {row['median_plan_s']:>9.3f} {p95:>8.3f} {worst:>8.2f}  {failures or ''}")
    print(f"wall {wall:.0f} s for {count} tasks; experts in {experts_file}")
    if args.json:
        print(json.dumps({**summary, "wall_s": wall, "workers": args.workers}))


if __name__ == "__main__":
    main()
