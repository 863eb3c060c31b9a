"""Throughput of the pick-and-place runs on both physics backends: physics steps per second.

Each measurement runs a batch of pick-and-place runs (held-out plans of ``--seed``) for
``--steps`` control steps of 12 physics steps each (1/240 s), with the shipped policy, on
MuJoCo C (one process, the runs in lockstep) or MJX (jitted ``vmap`` over the batch) on
MuJoCo Warp (``mjx-warp``) or on XLA (``mjx``; with ``XLA_CPU_SCHEDULER_FIX``, any batch).
Each backend is timed twice on the same batch: the first call compiles (the controller and
policy; on MJX also the physics), the second is the steady state, which also includes
settling every run's start on MuJoCo C (120 physics steps, both backends). Physics steps/s
counts the steps of runs still going (a run that ended early stops counting; MJX still
computes it, masked); ``computed`` counts every slot of the batch.

    python benchmarks/pickplace_throughput.py --backend mujoco,mjx-warp --batch 1,8,64,256 --steps 40
    python benchmarks/pickplace_throughput.py --backend mjx --batch 1,8,64 --steps 20
    python benchmarks/pickplace_throughput.py --backend mjx-warp,mjx --batch 500 --steps 100 --json   # GPU

With ``--json`` every measurement also prints one JSON line.
"""

from __future__ import annotations

import argparse
import functools
import json
import time

import jax
from common import cpu_name

from eval.pickplace import MJX_BACKENDS
from mjx_multiarm.pickplace.backends import fix_xla_cpu_scheduler, run_mjx, run_mujoco
from mjx_multiarm.pickplace.plans import plan_runs
from mjx_multiarm.pickplace.protocol import SUBSTEPS
from mjx_multiarm.pickplace.scene import build_scene
from mjx_multiarm.planner.policy import Planner


def _timed(fn):
    start = time.perf_counter()
    results = fn()
    return results, time.perf_counter() - start


def measure(backend: str, batch: int, steps: int, seed: int) -> dict:
    """One backend at one batch size: wall times and physics steps per second."""
    scene = build_scene()
    plans = plan_runs(scene, seed, batch)
    policy_step = Planner.load().batched(4)
    if backend == "mujoco":
        run = run_mujoco
    else:
        run = functools.partial(run_mjx, impl=MJX_BACKENDS[backend])
    _, first = _timed(lambda: run(scene, policy_step, plans, steps))
    results, seconds = _timed(lambda: run(scene, policy_step, plans, steps))
    simulated = sum(r.physics_steps for r in results)
    return {
        "backend": backend, "batch": batch, "control_steps": steps, "device": str(jax.devices()[0]),
        "cpu": cpu_name(), "first_call_s": round(first, 2), "seconds": round(seconds, 3),
        "physics_steps_per_s": round(simulated / seconds, 1),
        "computed_physics_steps_per_s": round(batch * steps * SUBSTEPS / seconds, 1),
        "outcomes": {c: n for c in sorted({r.cause for r in results}) if (n := sum(r.cause == c for r in results))},
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--backend", default="mujoco,mjx-warp", help="comma-separated: mujoco, mjx-warp, mjx")
    parser.add_argument("--batch", default="1,4,16", help="comma-separated runs per batch")
    parser.add_argument("--steps", type=int, default=40, help="control steps per run (12 physics steps each)")
    parser.add_argument("--seed", type=int, default=5000, help="picks the runs")
    parser.add_argument("--json", action="store_true", help="print one JSON line per measurement")
    args = parser.parse_args()
    backends = args.backend.split(",")
    if unknown := set(backends) - {"mujoco", *MJX_BACKENDS}:
        parser.error(f"--backend: unknown {', '.join(sorted(unknown))}; choose mujoco, mjx-warp, mjx")
    batches = [int(b) for b in args.batch.split(",")]
    if min(batches) < 1 or args.steps < 1:
        parser.error("--batch and --steps must be >= 1")
    if "mjx" in backends:
        fix_xla_cpu_scheduler()  # before JAX starts: XLA's MJX in batches of any size on the CPU
    print(f"{cpu_name()}, JAX devices {jax.devices()}")
    for backend in backends:
        for batch in batches:
            row = measure(backend, batch, args.steps, args.seed)
            print(f"{backend:8s} batch {batch:5d}: {row['physics_steps_per_s']:10.0f} physics steps/s "
                  f"({row['seconds']:.1f} s; first call {row['first_call_s']:.1f} s; {row['outcomes']})")
            if args.json:
                print(json.dumps(row))


if __name__ == "__main__":
    main()
