"""Trajectory computation time: the policy vs. BiRRT by team size (the paper's runtime figure).

    python -m eval.runtime                                  # shipped policy, generated tasks, 1-10 arms
    python -m eval.runtime --per-team 20 --out benchmarks/ --json

For every static task the policy runs closed loop in the environment, and the time of its
forward passes (all arms of the team in one batch per control step, jitted, on pinned
threads) is summed until the episode ends: the policy's total computation for that
trajectory. BiRRT plans the same task (start -> goal; planning time only, as the paper).
Writes ``runtime.md`` / ``runtime.csv`` (medians per team size: policy total, BiRRT plan,
speed-up, success of each; the policy's median over its successful episodes) and ``runtime.png`` (log-scale
plot; hollow markers where the policy solved none of the tasks) to ``--out``.
"""

from __future__ import annotations

import argparse
import io
import json
import pathlib
import sys
import time


def policy_times(planner, tasks, episode_steps: int):
    """Per task: (summed forward-pass seconds until the episode ended, success)."""
    import jax
    import numpy as np

    from mjx_multiarm.env.reaching import EVAL_TOLERANCE
    from mjx_multiarm.env.wrappers import TaskBank
    from mjx_multiarm.tasks.types import take

    seconds, success = np.zeros(tasks.num_tasks), np.zeros(tasks.num_tasks, bool)
    for size in sorted(set(tasks.num_arms.tolist())):
        env = planner.environment(size, max_steps=episode_steps, tolerance=EVAL_TOLERANCE)
        reset, step = jax.jit(env.reset), jax.jit(env.step)
        forward = jax.jit(planner.policy_fn())
        rows = np.flatnonzero(tasks.num_arms == size)
        bank = TaskBank.from_tasks(take(tasks, rows), size)
        for i, row in enumerate(rows):
            state = reset(None, jax.tree.map(lambda x, i=i: x[i], bank.tasks))
            jax.block_until_ready(forward(state, planner.params))  # compile / warm up
            total = 0.0
            while not bool(state.done):
                clock = time.perf_counter()
                actions = jax.block_until_ready(forward(state, planner.params))
                total += time.perf_counter() - clock
                state = step(state, actions)
            seconds[row], success[row] = total, bool(state.success)
    return seconds, success


def plot(table: dict, path: pathlib.Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mjx_multiarm.files import atomic_write

    sizes = sorted(table)
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(sizes, [table[k]["policy_s"] for k in sizes], "o-", label="policy (sum of forward passes until done)")
    failed = [k for k in sizes if table[k]["policy_success"] == 0]
    if failed:  # those medians are over failed episodes: not a like-for-like comparison
        ax.plot(failed, [table[k]["policy_s"] for k in failed], "o", color="white", markeredgecolor="tab:blue",
                label="policy solved none of these tasks")
    ax.plot(sizes, [table[k]["birrt_s"] for k in sizes], "s-", label="BiRRT (planning time)")
    ax.set_yscale("log")
    ax.set_xlabel("arms")
    ax.set_ylabel("trajectory computation time (s), median")
    ax.set_xticks(sizes)
    ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=100))
    plt.close(fig)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog="python -m eval.runtime", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", type=pathlib.Path, help="policy file or run directory (default: the shipped policy)")
    parser.add_argument("--tasks", type=pathlib.Path, help="task dataset .npz (default: generated static tasks)")
    parser.add_argument("--per-team", type=int, default=10, help="generated tasks per team size (default 10)")
    parser.add_argument("--arms", default="1-10", help="team sizes of generated tasks (default 1-10)")
    parser.add_argument("--episode-steps", type=int, default=500)
    parser.add_argument("--threads", type=int, default=1, help="CPU cores for both planners (default 1)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("."), help="output directory (default .)")
    parser.add_argument("--json", action="store_true", help="end with one JSON line")
    args = parser.parse_args(argv)
    from eval.latency import pin_threads

    try:
        pin_threads(args.threads)
        import numpy as np

        from eval.benchmark import birrt_outcomes, generated_test_tasks
        from mjx_multiarm.cli import parse_arms
        from mjx_multiarm.expert.planner import PlannerConfig
        from mjx_multiarm.files import atomic_write
        from mjx_multiarm.planner.policy import Planner
        from mjx_multiarm.tasks.dataset import load_tasks

        tasks = load_tasks(args.tasks)[0] if args.tasks else generated_test_tasks(args.per_team, parse_arms(args.arms), args.seed + 30_000)
        planner = Planner.load(args.checkpoint)
    except (ValueError, FileNotFoundError, argparse.ArgumentTypeError) as error:
        sys.exit(f"error: {error}")
    print(f"{tasks.num_tasks} tasks: policy rollouts...", file=sys.stderr)
    policy_s, policy_ok = policy_times(planner, tasks, args.episode_steps)
    print("BiRRT plans...", file=sys.stderr)
    birrt, birrt_s = birrt_outcomes(tasks, False, args.episode_steps, PlannerConfig(), args.seed)
    table = {}
    for size in sorted(set(tasks.num_arms.tolist())):
        mine = tasks.num_arms == size
        timed = mine & policy_ok if (mine & policy_ok).any() else mine  # until success; all episodes if none succeeded
        table[int(size)] = {"policy_s": float(np.median(policy_s[timed])), "birrt_s": float(np.median(birrt_s[mine])),
                            "policy_success": float(policy_ok[mine].mean()), "birrt_success": float(birrt.success[mine].mean()),
                            "tasks": int(mine.sum())}
        table[int(size)]["speedup"] = table[int(size)]["birrt_s"] / max(table[int(size)]["policy_s"], 1e-12)
    lines = ["| arms | policy total (ms) | BiRRT plan (ms) | BiRRT / policy | policy success | BiRRT success | tasks |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    lines += [f"| {k} | {r['policy_s'] * 1e3:.1f} | {r['birrt_s'] * 1e3:.1f} | {r['speedup']:.1f}x | {r['policy_success']:.2f} | "
              f"{r['birrt_success']:.2f} | {r['tasks']} |" for k, r in table.items()]
    text = "\n".join(lines) + f"\n\nmedians per team size; {args.threads} CPU thread(s)\n"
    print(text)
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write(args.out / "runtime.md", lambda f: f.write(text.encode()))
    csv_text = io.StringIO()
    csv_text.write("arms,policy_s,birrt_s,speedup,policy_success,birrt_success,tasks\n")
    for k, r in table.items():
        csv_text.write(f"{k},{r['policy_s']:.6f},{r['birrt_s']:.6f},{r['speedup']:.3f},{r['policy_success']:.4f},{r['birrt_success']:.4f},{r['tasks']}\n")
    atomic_write(args.out / "runtime.csv", lambda f: f.write(csv_text.getvalue().encode()))
    plot(table, args.out / "runtime.png")
    if args.json:
        print(json.dumps({"threads": args.threads, "by_team_size": table}))


if __name__ == "__main__":
    main()
