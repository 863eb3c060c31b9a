"""The paper's application: four UR5 arms pick objects off the floor into a central bin.

    python -m eval.pickplace --runs 500 --seed 1000 --out results/pickplace --json
    python -m eval.pickplace --runs 64 --backend mjx-warp --batch 64 # MJX on MuJoCo Warp: jitted batches, CPU or GPU
    python -m eval.pickplace --runs 64 --backend mjx --batch 64      # MJX on XLA: jitted batches
    python -m eval.pickplace --runs 20 --render 2                    # PNG frames (+ MP4) of 2 runs
    python -m eval.pickplace --runs 500 --seed 1000 --safe           # the policy's team steps shielded
    python -m eval.pickplace --runs 500 --approach-height 0 --start-height 0   # the original protocol
    python -m eval.pickplace --write-scene scene.xml                 # the scene's MJCF, for MuJoCo's viewer

Every arm runs the protocol of :mod:`mjx_multiarm.pickplace.protocol` with the shared
reaching policy (default: the shipped one) under MuJoCo physics: MuJoCo C (default; runs in
lockstep batches spread over ``--workers`` processes) or MJX (``--batch`` runs per jitted
call) on MuJoCo Warp (``mjx-warp``; the ``warp`` extra) or on XLA (``mjx``; with
:data:`~mjx_multiarm.pickplace.backends.XLA_CPU_SCHEDULER_FIX`, set before JAX starts).
Run r of seed S draws its objects and initial configuration from ``(S, r)``, so a seed picks
the same runs on either backend. With ``--safe`` a run whose scripted rise is not certified
free in the shield's collision model (1 cm to spare) draws its initial configuration again
from the same stream (:func:`~mjx_multiarm.pickplace.plans.redraw_uncertified_starts`):
the shield certifies nothing from a start in contact in its model, where the arms could
only hold.

Outcomes. ``success``: every arm finished its sequence with no collision under the
original's rule (an arm in a policy phase touching another arm, the floor, the bin or an
object it does not hold; every touch a MuJoCo contact at any physics step) and every
object's x, y lies inside the bin. ``success_rate`` counts
all runs. ``paper_success_rate`` is the published figure's definition (the original's
``demo.py``): successes over *valid* runs, where a run is valid if it succeeded, ended in an
arm-arm or arm-floor collision, or finished its sequences (objects outside the bin included);
runs ending in a bin or object collision, or a timeout, are discarded. ``strict_success``
adds the project's stricter accounting (:mod:`~mjx_multiarm.pickplace.protocol`). Beside
the physics' verdict each run keeps the collision model's (``kernel_cause``: arm-arm and
arm-floor from the reaching kernel at the end of each control step, the gripper as the
original's stand-in box).

Writes ``runs.csv`` (one row per run), ``summary.json`` and ``summary.md`` (beside the
paper's figures) and, with ``--render N``, ``render/run_<r>/frame_*.png`` and ``run_<r>.mp4``
(MP4 needs imageio and imageio-ffmpeg). ``--json`` ends the output with one JSON line holding
``runs``, ``success_rate``, ``paper_success_rate``, ``valid_runs``, ``failures`` (counts by
cause, from the physics' contacts), ``kernel_failures`` (counts by the collision model's
cause), ``kernel_missed`` (runs ended by a physics collision that the collision model's
accounting does not flag), ``kernel_only`` (runs it flags that no physics collision
ended), ``strict_success_rate``, ``mean_physics_steps_success``, ``runs_per_minute`` and
``physics_steps_per_second``.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import csv
import dataclasses
import functools
import io
import json
import multiprocessing
import os
import pathlib
import sys
import time

import jax
import numpy as np

from mjx_multiarm.files import atomic_write
from mjx_multiarm.pickplace.plans import (
    APPROACH_HEIGHT,
    START_HEIGHT,
    RunPlan,
    plan_runs,
)
from mjx_multiarm.pickplace.protocol import CAUSES, MAX_CONTROL_STEPS

#: The paper's application figures (section "Application"; the original demo's count).
PAPER = {"runs": 500, "valid_runs": 298, "paper_success_rate": 0.783, "mean_physics_steps_success": 6206}
#: Causes that keep a failed run valid under the paper's definition.
VALID_FAILURES = ("arm-arm", "arm-floor", "outside-bin")
#: Causes that are collisions.
COLLISIONS = ("arm-arm", "arm-floor", "arm-bin", "arm-object")


@functools.cache
def _policy_step(checkpoint: pathlib.Path | None, safe: bool = False):
    """The team step of the policy (once per process: the backends' compilations are reused
    by every batch); ``safe`` shields it (:mod:`mjx_multiarm.env.shield`) with the scene's
    collision model: the gripper as simulated, the bin and the floor
    (:func:`mjx_multiarm.pickplace.scene.collision_model`)."""
    from mjx_multiarm.pickplace.scene import collision_model
    from mjx_multiarm.planner.policy import Planner

    arm_xml, obstacles = collision_model()
    return Planner.load(checkpoint, safe=safe, arm_xml=arm_xml, obstacles=obstacles).batched(4)


def _run_mujoco_chunk(checkpoint, safe: bool, plans: RunPlan, max_steps: int) -> list[dict]:
    """One worker's share: its runs in lockstep on MuJoCo C."""
    from mjx_multiarm.pickplace.backends import run_mujoco
    from mjx_multiarm.pickplace.scene import build_scene

    results = run_mujoco(build_scene(), _policy_step(checkpoint, safe), plans, max_steps)
    return [dataclasses.asdict(r) for r in results]


def _chunks(plans: RunPlan, size: int) -> list[tuple[int, RunPlan]]:
    n = len(plans.objects)
    return [(start, jax.tree.map(lambda x, s=start: x[s:s + size], plans)) for start in range(0, n, size)]


#: The MJX backends and their implementation (:data:`mjx_multiarm.pickplace.backends.MJX_IMPLS`).
MJX_BACKENDS = {"mjx-warp": "warp", "mjx": "jax"}


def run_all(plans: RunPlan, backend: str, checkpoint, workers: int, batch: int, max_steps: int,
            safe: bool = False) -> list[dict]:
    """Every run's result dict, in run order."""
    chunks = _chunks(plans, batch)
    if backend in MJX_BACKENDS:
        from mjx_multiarm.pickplace.backends import run_mjx
        from mjx_multiarm.pickplace.scene import build_scene

        step, impl = _policy_step(checkpoint, safe), MJX_BACKENDS[backend]
        return [dataclasses.asdict(r) for _, chunk in chunks for r in run_mjx(build_scene(), step, chunk, max_steps, impl=impl)]
    if workers <= 1:
        return [r for _, chunk in chunks for r in _run_mujoco_chunk(checkpoint, safe, chunk, max_steps)]
    context = multiprocessing.get_context("spawn")  # JAX does not survive fork
    with concurrent.futures.ProcessPoolExecutor(workers, mp_context=context) as pool:
        futures = [pool.submit(_run_mujoco_chunk, checkpoint, safe, chunk, max_steps) for _, chunk in chunks]
        return [r for f in futures for r in f.result()]


def summarize(results: list[dict], wall_seconds: float) -> dict:
    """The run counts and rates of the module docstring."""
    runs = len(results)
    success = np.array([r["success"] for r in results], bool)
    causes = [r["cause"] for r in results]
    valid = success | np.isin(causes, VALID_FAILURES)
    steps = np.array([r["physics_steps"] for r in results])
    kernel = [r["kernel_cause"] for r in results]
    collided, kernel_collided = np.isin(causes, COLLISIONS), np.isin(kernel, COLLISIONS)
    return {
        "runs": runs,
        "success_rate": float(success.mean()) if runs else 0.0,
        "paper_success_rate": float(success.sum() / valid.sum()) if valid.any() else 0.0,
        "valid_runs": int(valid.sum()),
        "strict_success_rate": float(np.mean([r["strict_success"] for r in results])) if runs else 0.0,
        "failures": {c: causes.count(c) for c in CAUSES if c != "none" and c in causes},
        "kernel_failures": {c: kernel.count(c) for c in CAUSES if c != "none" and c in kernel},
        "kernel_missed": int((collided & ~kernel_collided).sum()),
        "kernel_only": int((~collided & kernel_collided).sum()),
        "strict_violations": {c: n for c in CAUSES if c != "none"
                              and (n := sum(r["strict_cause"] == c for r in results))},
        "failure_phases": {p: n for p in sorted({r["cause_phase"] for r in results if r["cause_phase"]})
                           if (n := sum(r["cause_phase"] == p for r in results))},
        "mean_physics_steps_success": float(steps[success].mean()) if success.any() else None,
        "mean_simulated_seconds_success": float(steps[success].mean() / 240) if success.any() else None,
        "wall_seconds": wall_seconds,
        "runs_per_minute": 60 * runs / wall_seconds if wall_seconds else None,
        "physics_steps_per_second": float(steps.sum() / wall_seconds) if wall_seconds else None,
    }


def summary_markdown(summary: dict, settings: dict) -> str:
    rows = [
        "| | runs | valid runs | success, paper's definition | success, all runs | strict success | physics steps per success |",
        "|---|---|---|---|---|---|---|",
        (f"| this run ({settings['backend']}, seed {settings['seed']}) | {summary['runs']} | {summary['valid_runs']} | "
        f"{summary['paper_success_rate']:.1%} | {summary['success_rate']:.1%} | {summary['strict_success_rate']:.1%} | "
        f"{summary['mean_physics_steps_success'] or 0:.0f} |"),
        (f"| paper (Ha et al. 2020) | {PAPER['runs']} | {PAPER['valid_runs']} | {PAPER['paper_success_rate']:.1%} | - | - | "
        f"{PAPER['mean_physics_steps_success']} |"),
        "",
        "| failure cause | runs (physics) | runs (collision model) |",
        "|---|---|---|",
        *[f"| {cause} | {summary['failures'].get(cause, 0)} | {summary['kernel_failures'].get(cause, 0)} |"
          for cause in CAUSES if cause in summary["failures"] or cause in summary["kernel_failures"]],
        "",
        f"Physics collisions the collision model's accounting misses: {summary['kernel_missed']} runs; "
        f"collisions only it sees: {summary['kernel_only']} runs.",
    ]
    return "\n".join(rows) + "\n"


def _write_runs_csv(path: pathlib.Path, results: list[dict]) -> None:
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(["run", "objects", "success", "cause", "cause_phase", "strict_cause", "kernel_cause", "phases",
                     "phase_starts", "control_steps", "physics_steps", "seconds"])
    for r in results:
        starts = " ".join("/".join(str(step) for step in arm.values()) for arm in r["phase_steps"])
        writer.writerow([r["run"], " ".join(r["objects"]), int(r["success"]), r["cause"], r["cause_phase"] or "",
                         r["strict_cause"], r["kernel_cause"], " ".join(r["phases"]), starts, r["control_steps"],
                         r["physics_steps"], f"{r['seconds']:.3f}"])
    atomic_write(path, lambda f: f.write(buffer.getvalue().encode()))


def render_runs(plans: RunPlan, count: int, checkpoint, out: pathlib.Path, max_steps: int,
                safe: bool = False) -> list[pathlib.Path]:
    """Frames (and an MP4 where imageio is installed) of the first ``count`` runs, on MuJoCo C."""
    from mjx_multiarm.pickplace.backends import run_mujoco
    from mjx_multiarm.pickplace.render import RunRecorder
    from mjx_multiarm.pickplace.scene import build_scene
    from mjx_multiarm.render import save_frames, save_video

    scene = build_scene()
    subset = jax.tree.map(lambda x: x[:count], plans)
    recorder = RunRecorder(scene.model, range(count), subset)
    run_mujoco(scene, _policy_step(checkpoint, safe), subset, max_steps, on_step=recorder.on_step)
    recorder.close()
    written = []
    for r, frames in recorder.frames.items():
        frames = np.stack(frames)
        written += save_frames(frames, out / f"run_{r}")[:1]
        try:
            written.append(save_video(frames, out / f"run_{r}.mp4", fps=10))
        except ImportError as error:
            print(f"render: {error}", file=sys.stderr)
    return written


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=500, help="runs (default 500, the paper's)")
    parser.add_argument("--backend", choices=["mujoco", *MJX_BACKENDS], default="mujoco",
                        help="MuJoCo C (default), MJX on MuJoCo Warp, or MJX on XLA")
    parser.add_argument("--seed", type=int, default=0, help="picks the runs: run r draws from (seed, r)")
    parser.add_argument("--objects", help="comma-separated object per arm for every run (default: drawn)")
    parser.add_argument("--checkpoint", type=pathlib.Path, help="policy file or run directory (default: the shipped policy)")
    parser.add_argument("--approach-height", type=float, default=APPROACH_HEIGHT, metavar="M",
                        help=f"the policy's waypoint above each pregrasp (default {APPROACH_HEIGHT}; 0: none, as the original)")
    parser.add_argument("--start-height", type=float, default=START_HEIGHT, metavar="M",
                        help=f"arms starting lower first rise straight up to this ee height (default {START_HEIGHT}; "
                             "0: no rise, as the original; with --approach-height 0: the original protocol)")
    parser.add_argument("--safe", action="store_true",
                        help="shield the policy's team steps (beyond the paper): a step that would collide between arms is replaced; "
                             "a run whose scripted rise is not certified free in the shield's model draws its start again")
    parser.add_argument("--workers", type=int, default=os.cpu_count(), help="MuJoCo C processes (default: one per core)")
    parser.add_argument("--batch", type=int, default=25, help="runs per lockstep batch (MuJoCo C) or per jitted call (MJX)")
    parser.add_argument("--max-steps", type=int, default=MAX_CONTROL_STEPS,
                        help=f"control steps before a timeout (default {MAX_CONTROL_STEPS}: the original's 100,000 physics steps)")
    parser.add_argument("--out", type=pathlib.Path, help="output directory (default runs/pickplace-<time>)")
    parser.add_argument("--render", type=int, default=0, metavar="N", help="render the first N runs (MuJoCo C)")
    parser.add_argument("--json", action="store_true", help="end with one JSON line")
    parser.add_argument("--write-scene", type=pathlib.Path, metavar="FILE",
                        help="write the scene's MJCF (every object slot with all its pieces) to FILE and exit")
    args = parser.parse_args(argv)
    if args.write_scene is not None:
        from mjx_multiarm.pickplace.scene import write_scene

        write_scene(args.write_scene)
        print(f"wrote {args.write_scene} (open it with: python -m mujoco.viewer --mjcf {args.write_scene})")
        return
    for name in ("runs", "batch", "workers", "max_steps"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be >= 1")
    if args.render < 0 or args.render > args.runs:
        parser.error(f"--render must be in [0, --runs], got {args.render}")
    if args.checkpoint is not None and not args.checkpoint.exists():
        parser.error(f"--checkpoint {args.checkpoint}: no such policy file or run directory")
    if args.backend == "mjx":  # before JAX starts its backend: batches of any size on the CPU
        from mjx_multiarm.pickplace.backends import fix_xla_cpu_scheduler

        fix_xla_cpu_scheduler()
    from mjx_multiarm.pickplace.scene import build_scene

    scene = build_scene()
    objects = None
    if args.objects:
        objects = args.objects.split(",")
        try:
            [scene.object_index(o) for o in objects]
        except ValueError as error:
            parser.error(f"--objects: {error}")
        if len(objects) != 4:
            parser.error(f"--objects: the layout has 4 arms, one object each; got {len(objects)}")
    out = args.out or pathlib.Path("runs") / f"pickplace-{time.strftime('%Y%m%d-%H%M%S')}"
    start = time.perf_counter()
    try:
        plans = plan_runs(scene, args.seed, args.runs, objects, args.approach_height, args.start_height, args.safe)
    except ValueError as error:
        parser.error(str(error))
    planning = time.perf_counter() - start
    start = time.perf_counter()
    results = run_all(plans, args.backend, args.checkpoint, args.workers, args.batch, args.max_steps, args.safe)
    wall = time.perf_counter() - start
    for r, result in enumerate(results):
        result["run"] = r
        result["objects"] = [scene.object_names[o] for o in np.asarray(plans.objects[r])]
    summary = summarize(results, wall)
    settings = {"backend": args.backend, "seed": args.seed, "runs": args.runs, "workers": args.workers,
                "batch": args.batch, "max_steps": args.max_steps, "approach_height": args.approach_height,
                "start_height": args.start_height, "safe": args.safe, "checkpoint": str(args.checkpoint or "shipped"),
                "planning_seconds": planning}
    _write_runs_csv(out / "runs.csv", results)
    text = json.dumps({"settings": settings, "summary": summary, "paper": PAPER}, indent=1)
    atomic_write(out / "summary.json", lambda f: f.write(text.encode()))
    table = summary_markdown(summary, settings)
    atomic_write(out / "summary.md", lambda f: f.write(table.encode()))
    print(table)
    print(f"{args.runs} runs in {wall:.0f} s ({summary['runs_per_minute']:.1f} runs/min, "
          f"{summary['physics_steps_per_second']:.0f} physics steps/s; run plans {planning:.0f} s); wrote {out}")
    if args.render:
        from mjx_multiarm.render import RenderingUnavailable

        try:
            for path in render_runs(plans, args.render, args.checkpoint, out / "render", args.max_steps, args.safe):
                print(f"render: {path}")
        except RenderingUnavailable as error:
            print(f"render: skipped ({error})", file=sys.stderr)
    if args.json:
        print(json.dumps(summary))


if __name__ == "__main__":
    main()
