"""Plan the BiRRT expert of every task of a dataset (resumable, parallel).

    python -m mjx_multiarm.expert --tasks tasks.npz --out experts.bin
    python -m mjx_multiarm.expert --tasks tasks.npz --out experts.bin --workers 16 --json
    python -m mjx_multiarm.expert --tasks train.npz --out train.experts --backend ray --ray-address auto
    python -m mjx_multiarm.expert info experts.bin

Re-running the same command after an interruption plans only what is missing (finished
chunks are kept in ``OUT.partial/``) and writes the same file. Failures are recorded per
task with their reason (start or goal in collision, iteration or time limit, ...).
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import sys

import numpy as np

from mjx_multiarm.cli import Progress
from mjx_multiarm.expert.planner import PlannerConfig
from mjx_multiarm.expert.precompute import BACKENDS, CHUNK_SIZE, precompute
from mjx_multiarm.expert.store import ExpertStore


def report(store: ExpertStore) -> dict:
    """The store's summary plus, per team size, solved rate, planning time and path length
    (environment steps of solved tasks)."""
    summary = store.summary()
    arms, solved, times, steps = store.index["arms"], store.solved, store.index["plan_s"], store.index["steps"]

    def team_row(k):
        done = solved & (arms == k)
        return {"tasks": int((arms == k).sum()), "solved": int(done.sum()),
                "median_plan_s": float(np.median(times[done])) if done.any() else float("nan"),
                "mean_steps": float(steps[done].mean()) if done.any() else float("nan")}

    summary["by_team_size"] = {int(k): team_row(k) for k in np.unique(arms)}
    return summary


def _print_report(summary: dict) -> None:
    print(f"{summary['solved']}/{summary['tasks']} tasks solved; median plan {summary['median_plan_s']:.3f} s, "
          f"95th percentile {summary['p95_plan_s']:.3f} s; outcomes {summary['status']}")
    for k, row in summary["by_team_size"].items():
        print(f"  {k:2d} arms: {row['solved']}/{row['tasks']} solved, median plan {1e3 * row['median_plan_s']:.1f} ms, "
              f"mean path {row['mean_steps']:.1f} steps")


def main(argv=None) -> None:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["info"]:
        info = argparse.ArgumentParser(prog="python -m mjx_multiarm.expert info", description="summarize an expert file")
        info.add_argument("path", type=pathlib.Path)
        info.add_argument("--verify", action="store_true", help="check every task's checksum")
        info.add_argument("--json", action="store_true", help="end with one JSON line")
        args = info.parse_args(argv[1:])
        try:
            store = ExpertStore(args.path)
            if args.verify:
                store.verify()
        except (ValueError, FileNotFoundError) as error:
            sys.exit(f"error: {error}")
        summary = report(store)
        _print_report(summary)
        if args.json:
            print(json.dumps(summary))
        return

    defaults = PlannerConfig()
    parser = argparse.ArgumentParser(prog="python -m mjx_multiarm.expert", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tasks", type=pathlib.Path, required=True, help="task dataset (.npz)")
    parser.add_argument("--out", type=pathlib.Path, required=True, help="expert file to write")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="local processes (default: all cores)")
    parser.add_argument("--backend", choices=BACKENDS, default="local")
    parser.add_argument("--ray-address", default=None, help="Ray cluster address (default: start a local one)")
    parser.add_argument("--iterations", type=int, default=defaults.iterations, help=f"RRT-Connect iteration cap (default {defaults.iterations})")
    parser.add_argument("--time-limit", type=float, default=defaults.time_limit, help=f"seconds per task (default {defaults.time_limit:g})")
    parser.add_argument("--range", type=float, default=defaults.range, help=f"tree extension length, rad (default {defaults.range:g})")
    parser.add_argument("--attempts", type=int, default=defaults.attempts, help=f"plans per task until the replay check passes (default {defaults.attempts})")
    parser.add_argument("--no-simplify", action="store_true", help="keep the raw RRT-Connect path")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--chunk-size", type=int, default=CHUNK_SIZE, help=f"tasks per resumable chunk (default {CHUNK_SIZE})")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.add_argument("--json", action="store_true", help="end with one JSON line")
    args = parser.parse_args(argv)
    try:
        config = PlannerConfig(iterations=args.iterations, time_limit=args.time_limit, range=args.range,
                               attempts=args.attempts, simplify=not args.no_simplify)
        progress = None
        if not args.quiet:
            from mjx_multiarm.tasks.dataset import load_tasks

            progress = Progress(load_tasks(args.tasks)[0].num_tasks, "tasks")

        def on_progress(done, new, solved):
            progress.update(done, new, f"solved {solved}/{done} ({solved / max(done, 1):.1%})")

        store = precompute(args.tasks, args.out, config, args.seed, args.workers, args.backend, args.chunk_size,
                           args.ray_address, on_progress if progress else None)
        if progress:
            progress.close()
    except (ValueError, FileNotFoundError, RuntimeError) as error:
        sys.exit(f"error: {error}")
    summary = report(store)
    print(f"wrote {args.out}")
    _print_report(summary)
    if args.json:
        print(json.dumps(summary))


if __name__ == "__main__":
    main()
