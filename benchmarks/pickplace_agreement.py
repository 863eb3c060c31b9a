"""Whole-run agreement of the pick-and-place physics backends: MuJoCo C against MJX.

The same plans (runs of ``--seed``) run to the end on MuJoCo C (one process, in lockstep)
and on MJX (``--impl``: MuJoCo Warp or XLA; one jitted batch), with the shipped policy; per run: the outcome, the first cause, every arm's phase
sequence with the control step each phase began (rise, reach, grasp, close, lift, ...,
release, home, done), the control steps, and the largest difference of the objects' final
positions. Two runs agree when outcome and cause, every arm's phase sequence and the run's
length are the same and every phase began within ``--tolerance`` control steps on both.

    python benchmarks/pickplace_agreement.py --runs 20 --seed 1000 --json
    python benchmarks/pickplace_agreement.py --runs 8 --seed 1000 --impl jax --json
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import numpy as np
from common import cpu_name

from mjx_multiarm.pickplace.backends import (
    MJX_IMPLS,
    fix_xla_cpu_scheduler,
    phase_timing_difference,
    run_mjx,
    run_mujoco,
)
from mjx_multiarm.pickplace.plans import plan_runs
from mjx_multiarm.pickplace.scene import build_scene
from mjx_multiarm.planner.policy import Planner


def compare(runs: int, seed: int, impl: str, tolerance: int) -> dict:
    """Both backends on the same runs: per-run rows and the counts that agree."""
    scene = build_scene()
    plans = plan_runs(scene, seed, runs)
    step = Planner.load().batched(4)
    start = time.perf_counter()
    reference = run_mujoco(scene, step, plans)
    mujoco_s = time.perf_counter() - start
    start = time.perf_counter()
    batched = run_mjx(scene, step, plans, impl=impl)
    mjx_s = time.perf_counter() - start
    rows = []
    for r, (a, b) in enumerate(zip(reference, batched)):
        timing = phase_timing_difference(a, b)
        rows.append({
            "run": r, "mujoco": a.cause, "mjx": b.cause, "same_outcome": a.success == b.success and a.cause == b.cause,
            "same_phases": timing is not None and a.cause_phase == b.cause_phase, "phase_step_difference": timing,
            "phase_changes": sum(len(arm) - 1 for arm in a.phase_steps),
            "control_steps": [a.control_steps, b.control_steps],
            "object_diff_m": round(float(np.abs(np.subtract(a.object_pos, b.object_pos)).max()), 4)})
    agree = sum(row["same_outcome"] and row["same_phases"] and row["phase_step_difference"] <= tolerance
                and row["control_steps"][0] == row["control_steps"][1] for row in rows)
    timings = [row["phase_step_difference"] for row in rows if row["phase_step_difference"] is not None]
    return {"runs": runs, "seed": seed, "impl": impl, "tolerance_steps": tolerance, "device": str(jax.devices()[0]), "cpu": cpu_name(),
            "agree": agree, "mujoco_successes": sum(a.success for a in reference), "mjx_successes": sum(b.success for b in batched),
            "phase_changes_compared": sum(row["phase_changes"] for row in rows if row["same_phases"]),
            "largest_phase_step_difference": max(timings) if timings else None,
            "largest_step_difference": max(abs(row["control_steps"][0] - row["control_steps"][1]) for row in rows),
            "largest_object_diff_m": max(row["object_diff_m"] for row in rows),
            "mujoco_s": round(mujoco_s, 1), "mjx_s": round(mjx_s, 1), "rows": rows}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=20)
    parser.add_argument("--seed", type=int, default=1000, help="picks the runs")
    parser.add_argument("--impl", choices=MJX_IMPLS, default="warp", help="MJX's implementation")
    parser.add_argument("--tolerance", type=int, default=2, help="control steps by which a phase's start may differ")
    parser.add_argument("--json", action="store_true", help="end with one JSON line")
    args = parser.parse_args()
    if args.runs < 1 or args.tolerance < 0:
        parser.error("--runs must be >= 1 and --tolerance >= 0")
    if args.impl == "jax":
        fix_xla_cpu_scheduler()  # before JAX starts: the runs in one batch on the CPU
    report = compare(args.runs, args.seed, args.impl, args.tolerance)
    print("| run | MuJoCo C | MJX | same phase sequence | phase changes | largest start difference (control steps) "
          "| control steps (C / MJX) | object difference (m) |")
    print("|---|---|---|---|---|---|---|---|")
    for row in report["rows"]:
        steps = row["control_steps"]
        print(f"| {row['run']} | {row['mujoco']} | {row['mjx']} | {row['same_phases']} | {row['phase_changes']} | "
              f"{row['phase_step_difference']} | {steps[0]} / {steps[1]} | {row['object_diff_m']:.3f} |")
    print(f"{report['agree']} of {report['runs']} runs agree in outcome, phase sequence (each start within "
          f"{args.tolerance} control steps) and control steps; MuJoCo C {report['mujoco_s']} s, MJX ({args.impl}) {report['mjx_s']} s")
    if args.json:
        print(json.dumps(report))


if __name__ == "__main__":
    main()
