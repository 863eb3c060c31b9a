"""Single-step inference latency of the policy on pinned CPU threads (paper: 1.09 ms, 920 Hz).

    python -m eval.latency                      # one thread, 1-10 neighbours, shipped policy
    python -m eval.latency --threads 2 --json

Two figures per neighbour count n (1-10 arms in view, the observing arm included):

- ``forward``: one arm's policy forward pass on its sequence of n elements (jitted, numpy
  observation in, action out): the paper's per-forward-pass figure;
- ``team_step``: :meth:`mjx_multiarm.Planner.step` for a team of n arms, numpy in and out
  (kinematics, every arm's observation, all n forward passes in one batch, limits);
- ``safe_step``: the same with safe execution (``Planner(safe=True)``: the team step checked
  by the swept collision check, and given way where it would collide).

The process pins itself to ``--threads`` cores (``sched_setaffinity``) and XLA to one
intra-op thread when ``--threads 1``, before JAX starts. Latencies are per call after
warm-up (compilation excluded); p50/p99 over ``--calls`` calls.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import sys
import time


def pin_threads(threads: int) -> None:
    """Restrict this process (and the XLA thread pool created later) to ``threads`` cores."""
    if "jax" in sys.modules:
        raise RuntimeError("eval.latency must pin its threads before JAX is imported")
    cores = sorted(os.sched_getaffinity(0))
    if threads > len(cores):
        raise ValueError(f"--threads {threads}: only {len(cores)} cores available")
    os.sched_setaffinity(0, cores[:threads])
    if threads == 1:
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1").strip()


def _percentiles(seconds: list[float]) -> tuple[float, float]:
    import numpy as np

    ms = np.asarray(seconds) * 1e3
    return float(np.percentile(ms, 50)), float(np.percentile(ms, 99))


def measure(checkpoint: pathlib.Path | None, neighbours: list[int], calls: int) -> dict:
    """Latency percentiles (ms) per neighbour count (see the module docstring)."""
    import jax
    import numpy as np

    from mjx_multiarm.env.observation import ELEMENT_SIZE
    from mjx_multiarm.planner.policy import Planner

    planner, safe = Planner.load(checkpoint), Planner.load(checkpoint, safe=True)
    actor = planner.policy.actor
    forward = jax.jit(lambda obs, mask: actor(obs, mask)[0])
    rng = np.random.default_rng(0)
    result = {"neighbours": neighbours, **{f"{name}{p}_ms": [] for name in ("", "team_step_", "safe_step_") for p in ("p50", "p99")}}
    for n in neighbours:
        obs = rng.normal(size=(1, n, ELEMENT_SIZE)).astype(np.float32)
        mask = np.ones((1, n), bool)
        joints = np.tile([0.0, -1.2, 1.0, -1.4, -1.57, 0.0], (n, 1))
        bases = np.stack([np.arange(n) * 0.8, np.zeros(n), np.zeros(n)], axis=-1)
        targets = np.concatenate([bases[:, :2] + [0.4, 0.1], np.full((n, 1), 0.4), np.tile([0, 0, 0, 1.0], (n, 1))], axis=-1)
        calls_of = {"": lambda: np.asarray(forward(obs, mask)), "team_step_": lambda: planner.step(joints, bases, targets),
                    "safe_step_": lambda: safe.step(joints, bases, targets)}
        for name, call in calls_of.items():
            for _ in range(20):
                call()
            times = []
            for _ in range(calls):
                start = time.perf_counter()
                call()
                times.append(time.perf_counter() - start)
            p50, p99 = _percentiles(times)
            result[f"{name}p50_ms"].append(p50)
            result[f"{name}p99_ms"].append(p99)
    return result


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog="python -m eval.latency", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", type=pathlib.Path, help="policy file or run directory (default: the shipped policy)")
    parser.add_argument("--threads", type=int, default=1, help="CPU cores to run on (default 1)")
    parser.add_argument("--max-neighbours", type=int, default=10, help="measure 1..N neighbours (default 10)")
    parser.add_argument("--calls", type=int, default=1000, help="timed calls per figure (default 1000)")
    parser.add_argument("--json", action="store_true", help="end with one JSON line")
    args = parser.parse_args(argv)
    try:
        pin_threads(args.threads)
        result = measure(args.checkpoint, list(range(1, args.max_neighbours + 1)), args.calls)
    except (ValueError, FileNotFoundError) as error:
        sys.exit(f"error: {error}")
    result["threads"] = args.threads
    print(f"{'neighbours':>10} {'forward p50':>12} {'p99':>8} {'team step p50':>14} {'p99':>8} {'safe step p50':>14} {'p99':>8}"
          f"   (ms, {args.threads} thread(s))")
    for i, n in enumerate(result["neighbours"]):
        print(f"{n:>10} {result['p50_ms'][i]:>12.3f} {result['p99_ms'][i]:>8.3f} {result['team_step_p50_ms'][i]:>14.3f} "
              f"{result['team_step_p99_ms'][i]:>8.3f} {result['safe_step_p50_ms'][i]:>14.3f} {result['safe_step_p99_ms'][i]:>8.3f}")
    print("paper: 1.09 ms per forward pass (920 Hz), one CPU thread")
    if args.json:
        print(json.dumps(result))


if __name__ == "__main__":
    main()
