"""The GPU recipe: fine-tune the shipped policy with the team recipe at GPU batch sizes,
then evaluate it on the validation and test sets, all in one command (issue 50).

    python benchmarks/gpu_finetune.py --out gpu_finetune            # an NVIDIA GPU: ~9 minutes in all
    python benchmarks/gpu_finetune.py --size tiny --out /tmp/gpu    # the same steps on a CPU in ~2 minutes

Steps (each a project command line, printed before it runs): generate the training tasks
(1-4 arms, the training seed 0) and plan their experts on the host's cores; generate the
validation sets (``held512.npz``, seed 7, and ``crowdval2048.npz``, seed 43, the crowded
layout) and the test sets (``test1to10.npz``, seed 8, and ``crowd1to10.npz``, seed 9)
where ``--data`` does not already hold them; fine-tune (``python -m train.sac --preset team
--init POLICY``) with 1,024 environments, batch 4,096 and a 1 M-transition buffer; evaluate
the fine-tuned policy (plain, mean actions, 500 steps, 2 cm / 0.1 rad) on every set, and
with ``--with-parent`` the parent too. ``OUT/figures.json`` holds every evaluation's per-team-size success, collision
and timeout rates; ``OUT/figures.md`` the tables for benchmarks/RESULTS.md;
``OUT/run/policy.npz`` the fine-tuned policy with its parent in its provenance. Choose
on the validation sets (commit the policy only if it is better there), report the test sets.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import subprocess
import sys
import time

from mjx_multiarm.cli import parse_arms

ROOT = pathlib.Path(__file__).resolve().parents[1]
SHIPPED = ROOT / "mjx_multiarm" / "assets" / "policy.npz"
#: The subprocesses share compiled programs (evaluations of equal shapes compile once).
ENV = {**os.environ, "JAX_COMPILATION_CACHE_DIR": os.environ.get("JAX_COMPILATION_CACHE_DIR", str(ROOT / ".jax_cache")),
       "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0.5"}

#: name -> (role, generate flags). Validation sets choose; test sets only report.
SETS = {
    "held512": ("validation", ["--arms", "1-4", "--count", "512", "--seed", "7", "--max-arms", "4"]),
    "crowdval2048": ("validation", ["--arms", "1-4", "--count", "2048", "--seed", "43", "--layout", "original", "--max-arms", "4"]),
    "test1to10": ("test", ["--arms", "1-10", "--count", "1280", "--mode", "dynamic", "--seed", "8", "--max-arms", "10"]),
    "crowd1to10": ("test", ["--arms", "1-10", "--count", "1280", "--seed", "9", "--layout", "original", "--max-arms", "10"]),
}

#: size -> training tasks, fine-tune minutes, the flags that set the GPU batch sizes, tasks kept per set.
SIZES = {
    "full": dict(train_tasks=20_000, minutes=3.5, per_set=None,
                 flags=["--num-envs", "1024", "--batch-size", "4096", "--updates-per-iteration", "32", "--warmup", "20000",
                        "--buffer-size", "1000000", "--expert-buffer-size", "1000000", "--expert-replays", "64",
                        "--no-buffer-checkpoint", "--checkpoint-minutes", "1", "--eval-minutes", "1"]),
    "tiny": dict(train_tasks=16, minutes=0.2, per_set=2,
                 flags=["--num-envs", "4", "--rollout-steps", "4", "--batch-size", "16", "--updates-per-iteration", "2",
                        "--warmup", "8", "--buffer-size", "4096", "--expert-buffer-size", "4096", "--expert-replays", "2",
                        "--no-buffer-checkpoint", "--eval-minutes", "0", "--steps", "64"]),
}


def _run(command: list[str], log) -> str:
    """Run a project command line (printed first), return its stdout; stop on failure."""
    log("$ " + " ".join(command))
    started = time.perf_counter()
    done = subprocess.run([sys.executable, *command], cwd=ROOT, capture_output=True, text=True, env=ENV)
    if done.returncode:
        sys.exit(f"failed ({done.returncode}) after {time.perf_counter() - started:.0f} s: {' '.join(command)}\n{done.stderr[-3000:]}")
    log(f"  ({time.perf_counter() - started:.0f} s)")
    return done.stdout


def _evaluate(policy: pathlib.Path, tasks: pathlib.Path, log) -> dict:
    command = ["-m", "eval.benchmark", "--checkpoint", str(policy), "--tasks", str(tasks), "--mode", "static", "--json"]
    result = json.loads(_run(command, log).strip().splitlines()[-1])
    return {arms: {k: row[k] for k in ("tasks", "success_rate", "collision_rate", "timeout_rate")}
            for arms, row in result["by_team_size"].items()}


def _table(name: str, role: str, tuned: dict, parent: dict | None) -> str:
    lines = [f"{name} ({role}): success (collisions / timeouts), %", "", "| arms | tasks | fine-tuned | parent |", "|---|---|---|---|"]
    cell = lambda r: f"{100 * r['success_rate']:.1f} ({100 * r['collision_rate']:.1f} / {100 * r['timeout_rate']:.1f})"  # noqa: E731
    for arms in sorted(tuned, key=int):
        lines.append(f"| {arms} | {tuned[arms]['tasks']} | {cell(tuned[arms])} | {cell(parent[arms]) if parent else 'not run'} |")
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=pathlib.Path, required=True, help="output directory (the run, figures)")
    parser.add_argument("--size", choices=sorted(SIZES), default="full")
    parser.add_argument("--init", type=pathlib.Path, default=SHIPPED, help="policy to fine-tune (default: the shipped one)")
    parser.add_argument("--data", type=pathlib.Path, default=None, help="folder of task sets to reuse / write (default OUT/data)")
    parser.add_argument("--minutes", type=float, default=None, help="fine-tuning minutes (default: the size's)")
    parser.add_argument("--with-parent", action="store_true", help="evaluate the parent policy on every set too")
    args = parser.parse_args(argv)
    size = SIZES[args.size]
    out = args.out.absolute()
    data = (args.data or out / "data").absolute()
    data.mkdir(parents=True, exist_ok=True)
    log = lambda message: print(message, file=sys.stderr, flush=True)  # noqa: E731
    workers = str(os.cpu_count() or 1)
    started = time.perf_counter()

    train_tasks = data / f"train{size['train_tasks']}.npz"
    if not train_tasks.exists():
        _run(["-m", "mjx_multiarm.tasks", "generate", "--arms", "1-4", "--count", str(size["train_tasks"]), "--seed", "0",
              "--max-arms", "4", "--workers", workers, "--out", str(train_tasks)], log)
    experts = train_tasks.with_suffix(".experts")
    if not experts.exists():
        _run(["-m", "mjx_multiarm.expert", "--tasks", str(train_tasks), "--out", str(experts), "--workers", workers], log)
    sets = {}
    for name, (role, flags) in SETS.items():
        path = data / (f"{name}.npz" if size["per_set"] is None else f"{name}_tiny.npz")
        if not path.exists():
            if size["per_set"] is not None:  # a few tasks of each set's team sizes and layout
                count = size["per_set"] * len(parse_arms(flags[flags.index("--arms") + 1]))
                flags = [*flags[: flags.index("--count")], "--count", str(count), *flags[flags.index("--count") + 2 :]]
            _run(["-m", "mjx_multiarm.tasks", "generate", *flags, "--workers", workers, "--out", str(path)], log)
        sets[name] = (role, path)

    run = out / "run"
    minutes = args.minutes if args.minutes is not None else size["minutes"]
    if not (run / "summary.json").exists():
        _run(["-m", "train.sac", "--preset", "team", "--init", str(args.init.absolute()), "--tasks", str(train_tasks),
              "--experts", str(experts), "--eval-tasks", str(sets["held512"][1]), "--minutes", str(minutes), *size["flags"],
              "--run-dir", str(run), "--json"], log)
    summary = json.loads((run / "summary.json").read_text())

    figures = {"device": _device(), "train_seconds": summary["train_seconds"], "env_steps": summary["env_steps"],
               "env_steps_per_s": summary["env_steps_per_s"], "updates": summary["updates"], "sets": {}}
    tables = []
    for name, (role, path) in sets.items():
        tuned = _evaluate(run / "policy.npz", path, log)
        parent = _evaluate(args.init.absolute(), path, log) if args.with_parent else None
        figures["sets"][name] = {"role": role, "file": str(path), "fine_tuned": tuned, "parent": parent}
        tables.append(_table(name, role, tuned, parent))
    figures["total_seconds"] = time.perf_counter() - started
    (out / "figures.json").write_text(json.dumps(figures, indent=2))
    header = (f"{figures['device']}: {summary['env_steps']:,} env steps in {summary['train_seconds'] / 60:.1f} min of fine-tuning "
              f"({summary['env_steps_per_s']:,.0f}/s), {figures['total_seconds'] / 60:.1f} min in all")
    (out / "figures.md").write_text(header + "\n\n" + "\n\n".join(tables) + "\n")
    print(header)
    print("\n\n".join(tables))


def _device() -> str:
    import jax  # after the subprocesses: the figures name the device the runs saw

    device = jax.devices()[0]
    return f"{device.platform}: {device.device_kind}"


if __name__ == "__main__":
    main()
