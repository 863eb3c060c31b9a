"""Benchmark a trained policy or the BiRRT baseline on test tasks: the paper's tables.

    python -m eval.benchmark                                    # shipped policy, generated test set
    python -m eval.benchmark --checkpoint runs/x --tasks test.npz --out results/
    python -m eval.benchmark --planner birrt --tasks test.npz   # the baseline on the same tasks

The policy runs deterministically (mean actions) in the JAX environment, vectorized over
the tasks of each team size (a scene of exactly that many slots). Static episodes start at
the task's start and chase fixed targets; dynamic episodes (tasks with a dynamic mode)
chase targets moving at the task's speed. An episode succeeds when every arm is within
2 cm / 0.1 rad at the same step before ``--episode-steps`` (default 500, the paper's) and
without any collision. BiRRT static: plan start -> goal, then execute the plan (its steps
are replayed with the environment's rules before it counts); dynamic: the re-planning loop
of :mod:`mjx_multiarm.expert.replan`. ``--safe`` runs the policy with safe execution
(:mod:`mjx_multiarm.env.shield`: every team step certified before it is executed, arms whose
motions are not certified free step away from the others or hold), beyond the paper: no
collisions, and its failures are timeouts (deadlocks). ``--handover`` hands every task the
policy leaves unfinished to BiRRT from where its episode ended
(:mod:`mjx_multiarm.planner.handover`: a hybrid planner; its steps are the policy's plus the
plan's, at most 500 in all, and ``planned`` / ``mean_plan_s`` / ``max_plan_s`` report the
handed-over plans); ``--stall-steps K`` hands a team over as soon as it stops making
progress (a deadlock detector) rather than after ``--episode-steps``. BiRRT's plans, alone
or handed over, count only within the episode's 500 steps. ``longest_success_steps`` is the
longest successful trajectory, ``mean_task_s`` the wall time per task (compilation
included); ``--time-limit`` with a raised ``--iterations`` runs BiRRT at another planner's
time per task.

Writes ``static.md`` / ``static.csv`` (success by team size x difficulty bin, with the
paper's numbers), ``dynamic.md`` / ``dynamic.csv`` (by target speed), and
``outcomes.csv`` (one row per task and mode) to ``--out``. ``--json`` ends the output with
one JSON line: ``success[arms][bin]``, ``collision_rate``, ``timeout_rate``,
``steps_to_success``, ``by_team_size[arms]`` (success, collision, timeout and arm reach
rates) and the same under ``dynamic``.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import pathlib
import sys
import time

import jax
import numpy as np

from mjx_multiarm.cli import Progress, parse_arms
from mjx_multiarm.env.reaching import EVAL_TOLERANCE, EnvConfig, ReachingEnv
from mjx_multiarm.env.wrappers import Outcomes, TaskBank, final_states, make_episodes
from mjx_multiarm.expert.planner import SOLVED, PlannerConfig
from mjx_multiarm.expert.replan import replan_episode
from mjx_multiarm.expert.solve import solve_task
from mjx_multiarm.files import atomic_write
from mjx_multiarm.planner.handover import birrt_handover
from mjx_multiarm.planner.policy import Planner
from mjx_multiarm.render import (
    RenderingUnavailable,
    make_renderer,
    record_episode,
    render_episode,
    save_frames,
    save_video,
)
from mjx_multiarm.tasks.dataset import load_tasks
from mjx_multiarm.tasks.generate import GenerationSpec, generate_chunk
from mjx_multiarm.tasks.types import (
    DIFFICULTY_BINS,
    SPEED_BINS,
    Tasks,
    bin_index,
    concatenate,
    take,
)

#: The paper's static success rates (2 cm / 0.1 rad) by team size, all difficulties.
PAPER_STATIC = {1: 0.988, 2: 0.943, 3: 0.960, 4: 0.951, 5: 0.943, 6: 0.938, 7: 0.918, 8: 0.909, 9: 0.910, 10: 0.905}


def generated_test_tasks(per_team: int, arms: tuple[int, ...], seed: int) -> Tasks:
    """``per_team`` tasks of every team size in ``arms`` with a dynamic mode (so both
    tables can be made), spread over the difficulty bins by the generator."""
    spec = GenerationSpec(count=per_team * len(arms), arm_counts=tuple(arms), mode="dynamic", seed=seed, max_arms=max(arms),
                          chunk_size=256)
    return concatenate([generate_chunk(spec, c) for c in range(spec.num_chunks)])


def policy_outcomes(planner: Planner, tasks: Tasks, dynamic: bool, episode_steps: int, batch: int = 256,
                    handover: PlannerConfig | None = None, seed: int = 0, stall_steps: int = 0,
                    max_steps: int = 500) -> tuple[Outcomes, np.ndarray]:
    """Deterministic episodes of every task (in ``tasks`` order), bucketed by team size:
    (outcomes, seconds of BiRRT planning per task, NaN where none). With ``handover`` the tasks that time
    out are handed to BiRRT from where they ended (:mod:`mjx_multiarm.planner.handover`), the
    policy's steps plus the plan's within ``max_steps``; ``stall_steps`` ends an episode whose
    team stopped making progress (:func:`~mjx_multiarm.env.wrappers.make_episodes`)."""
    team = tasks.num_arms
    parts, seconds, order = [], [], []
    for size in sorted(set(team.tolist())):
        rows = np.flatnonzero(team == size)
        env = planner.environment(size, max_steps=episode_steps, dynamic_targets=dynamic, tolerance=EVAL_TOLERANCE)
        subset = take(tasks, rows)
        final = final_states(make_episodes(env, planner.policy_fn(), episode_steps, stall_steps), planner.params,
                             TaskBank.from_tasks(subset, size), batch)
        outcomes, plan_s = Outcomes.of(final), np.full(len(rows), np.nan)
        if handover is not None:
            outcomes, plan_s = birrt_handover(subset, outcomes, final.joints, handover, seed, max_steps)
        parts.append(outcomes)
        seconds.append(plan_s)
        order.append(rows)
    back = np.argsort(np.concatenate(order))
    return Outcomes.concatenate(parts).select(back), np.concatenate(seconds)[back]


def birrt_outcomes(tasks: Tasks, dynamic: bool, episode_steps: int, config: PlannerConfig, seed: int = 0,
                   progress: Progress | None = None) -> tuple[Outcomes, np.ndarray]:
    """The BiRRT baseline on every task: (outcomes, planning seconds per task)."""
    team = tasks.num_arms
    success, collision, steps, plan_s = (np.zeros(tasks.num_tasks, t) for t in (bool, bool, np.int64, np.float64))
    envs = {}
    for i in range(tasks.num_tasks):
        if dynamic:
            size = int(team[i])
            if size not in envs:
                envs[size] = ReachingEnv(size, EnvConfig(max_steps=episode_steps, dynamic_targets=True))
            result = replan_episode(envs[size], tasks, i, config, seed)
            success[i], collision[i], steps[i], plan_s[i] = result.success, result.collided, result.steps, result.plan_s
        else:
            result = solve_task(tasks, i, config, seed)
            success[i] = result.status == SOLVED and len(result.deltas) <= episode_steps  # the episode's limit holds for plans too
            steps[i], plan_s[i] = len(result.deltas), result.plan_s
        if progress:
            progress.update(i + 1, i + 1, f"{int(success[: i + 1].sum())} succeeded")
    return Outcomes(team, success, collision, ~success & ~collision, steps, np.where(success, team, 0)), plan_s


def success_table(outcomes: Outcomes, bins: np.ndarray, names: list[str]) -> dict[int, dict[str, float | None]]:
    """Success rate per team size and bin (None where a bin has no task), plus 'average'."""
    table = {}
    for size in sorted(set(outcomes.team.tolist())):
        mine = outcomes.team == size
        row = {}
        for b, name in enumerate(names):
            sel = mine & (bins == b)
            row[name] = float(outcomes.success[sel].mean()) if sel.any() else None
        row["average"] = float(outcomes.success[mine].mean())
        table[int(size)] = row
    return table


def team_rates(outcomes: Outcomes) -> dict[int, dict[str, float]]:
    """Per team size: tasks, success, collision and timeout rates, and the share of arms
    within tolerance when their episode ended (``arm_reach_rate``), as
    :meth:`~mjx_multiarm.env.wrappers.EpisodeStats.summary` counts them."""
    by_team = outcomes.stats(int(outcomes.team.max())).summary()["by_team_size"]
    names = ("success_rate", "collision_rate", "timeout_rate", "arm_reach_rate")
    return {size: {"tasks": row["episodes"], **{name: row[name] for name in names}} for size, row in by_team.items()}


def summary(outcomes: Outcomes, bins: np.ndarray, names: list[str]) -> dict:
    won = outcomes.success
    return {
        "success": success_table(outcomes, bins, names),
        "by_team_size": team_rates(outcomes),
        "tasks": int(len(won)),
        "collision_rate": float(outcomes.collision.mean()),
        "timeout_rate": float(outcomes.timeout.mean()),
        "steps_to_success": float(outcomes.steps[won].mean()) if won.any() else None,
        "longest_success_steps": int(outcomes.steps[won].max()) if won.any() else None,
    }


def markdown(title: str, result: dict, names: list[str], paper: dict | None) -> str:
    """A markdown table of ``result['success']`` (rows: team sizes)."""
    columns = [*names, "average"] + (["paper"] if paper else [])
    lines = [f"### {title}", "", "| arms | " + " | ".join(columns) + " |", "|---" * (len(columns) + 1) + "|"]
    for size, row in result["success"].items():
        cells = ["-" if row[c] is None else f"{row[c]:.3f}" for c in [*names, "average"]]
        if paper:
            cells.append(f"{paper[size]:.3f}" if size in paper else "-")
        lines.append(f"| {size} | " + " | ".join(cells) + " |")
    steps = result["steps_to_success"]
    lines += ["", f"{result['tasks']} tasks; collision rate {result['collision_rate']:.3f}, timeout rate "
              f"{result['timeout_rate']:.3f}, mean steps to success {'-' if steps is None else f'{steps:.1f}'}", "",
              "| arms | tasks | success | collisions | timeouts | arms reached |", "|---|---|---|---|---|---|"]
    lines += [f"| {size} | {r['tasks']} | {r['success_rate']:.3f} | {r['collision_rate']:.3f} | {r['timeout_rate']:.3f} | "
              f"{r['arm_reach_rate']:.3f} |" for size, r in result["by_team_size"].items()]
    lines.append("")
    return "\n".join(lines)


def _csv(result: dict, names: list[str]) -> bytes:
    out = io.StringIO()
    writer = csv.writer(out)
    writer.writerow(["arms", *names, "average"])
    for size, row in result["success"].items():
        writer.writerow([size, *("" if row[c] is None else f"{row[c]:.6f}" for c in [*names, "average"])])
    return out.getvalue().encode()


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m eval.benchmark", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", type=pathlib.Path, help="policy file or run directory (default: the shipped policy)")
    parser.add_argument("--tasks", type=pathlib.Path, help="task dataset .npz (default: a generated test set)")
    parser.add_argument("--planner", choices=["policy", "birrt"], default="policy")
    parser.add_argument("--per-team", type=int, default=20, help="generated test set: tasks per team size (default 20)")
    parser.add_argument("--arms", help="team sizes: of the generated test set (default 1-10), or the tasks of --tasks to run "
                                       "(default all)")
    parser.add_argument("--mode", choices=["static", "dynamic", "both"], default="both", help="which tables (default both)")
    parser.add_argument("--neighbour-radius", type=float, metavar="M",
                        help="observe neighbour bases within M metres instead of the radius the policy file records "
                             "(0: the policy sees only its own arm, as the individualistic ablation)")
    parser.add_argument("--safe", action="store_true",
                        help="safe execution: every team step is checked before it is executed; arms whose motions would "
                             "collide step away from the others or hold (no collisions; failures are deadlocks, counted "
                             "as timeouts)")
    parser.add_argument("--handover", action="store_true",
                        help="hand every task the policy does not finish (timeout) to BiRRT from where its episode ended, "
                             "static targets only (a hybrid planner; use with --safe, whose failures are deadlocks)")
    parser.add_argument("--episode-steps", type=int, default=500, help="control steps per episode (default 500, the paper's)")
    parser.add_argument("--stall-steps", type=int, default=0, metavar="K",
                        help="with --handover: hand a team over as soon as its summed end-effector distance to its targets "
                             "has not shrunk by 1 cm in K steps (a deadlock detector; 0: after --episode-steps)")
    parser.add_argument("--iterations", type=int, default=PlannerConfig.iterations, help="BiRRT iteration cap per plan")
    parser.add_argument("--time-limit", type=float, default=PlannerConfig.time_limit,
                        help="BiRRT wall-clock cap per task (s; with a raised --iterations: BiRRT at a hybrid's time per task)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=pathlib.Path, help="output directory (default runs/benchmark-<planner>-<time>)")
    parser.add_argument("--render", type=int, default=0, metavar="N",
                        help="save the policy's first N static episodes as PNG frames (and MP4 with imageio) under OUT/render/")
    parser.add_argument("--json", action="store_true", help="end with one JSON line")
    return parser


def render_episodes(planner: Planner, tasks: Tasks, count: int, episode_steps: int, out: pathlib.Path) -> None:
    """Frames (and an MP4 where imageio is installed) of the policy on the first ``count`` tasks."""
    scenes = {}  # team size -> (environment, renderer)
    for i in range(min(count, tasks.num_tasks)):
        size = int(tasks.num_arms[i])
        if size not in scenes:
            env = planner.environment(size, max_steps=episode_steps, tolerance=EVAL_TOLERANCE)
            scenes[size] = env, make_renderer(env.scene.mj_model, 480, 640)
        env, renderer = scenes[size]
        task = jax.tree.map(lambda x: x[0], TaskBank.from_tasks(take(tasks, np.array([i])), size).tasks)
        trajectory = record_episode(env, planner.policy_fn(), planner.params, task)
        frames = render_episode(env, jax.device_get(task), trajectory, renderer=renderer)
        name = f"episode{i}_{size}arms_{'success' if trajectory.success else 'collision' if trajectory.collided else 'timeout'}"
        save_frames(frames, out / "render" / name)
        try:
            save_video(frames, out / "render" / f"{name}.mp4")
        except ImportError as error:
            print(f"render: {error}", file=sys.stderr)
        print(f"render: {out / 'render' / name} ({len(frames)} frames)", file=sys.stderr)


def _check_values(args: argparse.Namespace) -> None:
    """ValueError naming the first flag whose value cannot run: counts below 1, an ``--out``
    that is a file or already holds a benchmark's results."""
    for flag, value, least in (("--episode-steps", args.episode_steps, 1), ("--iterations", args.iterations, 1),
                               ("--per-team", args.per_team, 1), ("--render", args.render, 0), ("--stall-steps", args.stall_steps, 0)):
        if value < least:
            raise ValueError(f"{flag} must be >= {least}, got {value}")
    if not args.time_limit > 0:
        raise ValueError(f"--time-limit must be > 0 s, got {args.time_limit}")
    if args.stall_steps and not args.handover:
        raise ValueError("--stall-steps hands stalled teams over: it needs --handover")
    if args.out is not None and args.out.exists():
        if not args.out.is_dir():
            raise ValueError(f"--out {args.out} is a file; give a directory for the results")
        if (args.out / "summary.json").exists():
            raise ValueError(f"--out {args.out} already holds a benchmark's results (summary.json); give another directory")


def main(argv=None) -> None:
    args = _parser().parse_args(argv)
    try:
        _check_values(args)
        team_sizes = args.arms or "1-10"
        arms = parse_arms(team_sizes)
        if args.tasks:
            tasks = load_tasks(args.tasks)[0]
            if args.arms:
                tasks = take(tasks, np.isin(tasks.num_arms, arms))
                if not tasks.num_tasks:
                    raise ValueError(f"{args.tasks}: no task of {args.arms} arms")
        else:
            print(f"generating {args.per_team} test tasks per team size {team_sizes}...", file=sys.stderr)
            tasks = generated_test_tasks(args.per_team, arms, args.seed + 20_000)
        if (args.neighbour_radius is not None or args.safe or args.handover) and args.planner != "policy":
            raise ValueError("--neighbour-radius, --safe and --handover apply to --planner policy only")
        if args.handover and args.mode != "static":
            raise ValueError("--handover plans to fixed goals: it needs --mode static")
        planner = Planner.load(args.checkpoint, args.neighbour_radius, args.safe) if args.planner == "policy" else None
    except (ValueError, FileNotFoundError, argparse.ArgumentTypeError) as error:
        sys.exit(f"error: {error}")
    out = args.out or pathlib.Path("runs") / f"benchmark-{args.planner}-{time.strftime('%Y%m%d-%H%M%S')}"
    out.mkdir(parents=True, exist_ok=True)
    if args.render and planner is not None:
        try:
            render_episodes(planner, tasks, args.render, args.episode_steps, out)
        except RenderingUnavailable as error:
            print(f"render: skipped: {error}", file=sys.stderr)
    modes = ["static", "dynamic"] if args.mode == "both" else [args.mode]
    if "dynamic" in modes and not tasks.has_dynamic_mode.any():
        if args.mode == "dynamic":
            sys.exit(f"error: {args.tasks}: no task has a dynamic mode")
        modes.remove("dynamic")
    report, rows = {"planner": args.planner}, []
    if planner is not None:
        report["neighbour_radius"] = planner.env_config.neighbour_radius
        report["safe"] = planner.env_config.safe
        report["handover"] = args.handover
        report["stall_steps"] = args.stall_steps
    for mode in modes:
        subset = tasks if mode == "static" else take(tasks, tasks.has_dynamic_mode)
        clock = time.perf_counter()
        if planner is not None:
            print(f"{mode}: {subset.num_tasks} tasks, policy rollouts...", file=sys.stderr)
            config = PlannerConfig(iterations=args.iterations, time_limit=args.time_limit) if args.handover else None
            outcomes, plan_s = policy_outcomes(planner, subset, mode == "dynamic", args.episode_steps, handover=config,
                                               seed=args.seed, stall_steps=args.stall_steps)
            if not args.handover:
                plan_s = None
        else:
            progress = Progress(subset.num_tasks, f"{mode} BiRRT")
            outcomes, plan_s = birrt_outcomes(subset, mode == "dynamic", args.episode_steps,
                                              PlannerConfig(iterations=args.iterations, time_limit=args.time_limit), args.seed,
                                              progress)
            progress.close()
        bins, names = ((bin_index(subset.difficulty, DIFFICULTY_BINS), list(DIFFICULTY_BINS)) if mode == "static"
                       else (bin_index(subset.speed, SPEED_BINS), list(SPEED_BINS)))
        result = summary(outcomes, bins, names)
        result["seconds"] = time.perf_counter() - clock
        result["mean_task_s"] = result["seconds"] / subset.num_tasks  # wall time to a trajectory, compilation included
        if plan_s is not None:
            planned = ~np.isnan(plan_s)
            result["planned"] = int(planned.sum())
            result["mean_plan_s"] = float(plan_s[planned].mean()) if planned.any() else None
            result["max_plan_s"] = float(plan_s[planned].max()) if planned.any() else None
        title = f"{mode.capitalize()} targets, {args.planner}, success by team size and {'difficulty' if mode == 'static' else 'target speed'}"
        text = markdown(title, result, names, PAPER_STATIC if mode == "static" else None)
        print(text)
        atomic_write(out / f"{mode}.md", lambda f, t=text: f.write(t.encode()))
        atomic_write(out / f"{mode}.csv", lambda f, r=result, n=names: f.write(_csv(r, n)))
        rows += [(mode, int(subset.task_id[i]), int(outcomes.team[i]), bool(outcomes.success[i]), bool(outcomes.collision[i]),
                  bool(outcomes.timeout[i]), int(outcomes.steps[i]), int(outcomes.reached[i])) for i in range(subset.num_tasks)]
        if mode == "static":
            report.update(result)
        else:
            report["dynamic"] = result
    table = io.StringIO()
    csv.writer(table).writerows([("mode", "task_id", "arms", "success", "collision", "timeout", "steps", "arms_reached"), *rows])
    atomic_write(out / "outcomes.csv", lambda f: f.write(table.getvalue().encode()))
    atomic_write(out / "summary.json", lambda f: f.write(json.dumps(report, indent=2).encode()))
    print(f"results in {out}", file=sys.stderr)
    if args.json:
        print(json.dumps(report))


if __name__ == "__main__":
    main()
