"""Minimal reproduction of the XLA CPU wedge of batched MJX convex collisions (jaxlib 0.10.2).

Eight free convex meshes (6 vertices each) over a box floor; ``jit(vmap(mjx.step))`` at batch
``--batch``, called three times in a child process. On XLA's CPU backend it compiles, then a
call never returns at batches of 8 and more (1-4 run): no thread uses the CPU. Without mesh
geoms it runs. ``--fix`` starts the child with ``XLA_CPU_SCHEDULER_FIX`` in ``XLA_FLAGS``
(XLA's concurrency-optimized scheduler off), which runs every batch
(benchmarks/RESULTS.md, "The XLA wedge at batch 8").

    python benchmarks/mjx_xla_hang.py --batch 1,4,8,64 --json          # 8 and 64: hang
    python benchmarks/mjx_xla_hang.py --batch 1,4,8,64 --fix --json    # every batch runs
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

from mjx_multiarm.pickplace.backends import XLA_CPU_SCHEDULER_FIX

MESHES = 8
CALLS = 3  # the wedge comes at the first call or a later one


def model_xml(meshes: int = MESHES) -> str:
    """The reproduction's scene: ``meshes`` free convex meshes over a box floor."""
    bodies = "".join(f'<body pos="{(i % 8) * 0.3} {(i // 8) * 0.3} 0.3"><freejoint/><geom type="mesh" mesh="m"/></body>'
                     for i in range(meshes))
    return ('<mujoco><asset><mesh name="m" vertex="0 0 0 .1 0 0 0 .1 0 0 0 .1 .1 .1 .1 .05 .12 .02"/></asset>'
            f'<worldbody><geom type="box" size="3 3 .05" pos="0 0 -.05"/>{bodies}</worldbody></mujoco>')


def step_batch(batch: int, calls: int = CALLS) -> None:
    """Compile ``jit(vmap(mjx.step))`` at ``batch`` and call it ``calls`` times, each on the
    last one's result (the child's work)."""
    import jax
    import jax.numpy as jnp
    import mujoco
    from mujoco import mjx

    m = mujoco.MjModel.from_xml_string(model_xml())
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    mx = mjx.put_model(m, impl="jax")
    dx = jax.tree.map(lambda x: jnp.stack([x] * batch), mjx.put_data(m, d))
    step = jax.jit(jax.vmap(lambda d: mjx.step(mx, d))).lower(dx).compile()
    print("compiled", flush=True)
    for _ in range(calls):
        dx = jax.block_until_ready(step(dx))
    print("ran", flush=True)


def probe(batch: int, fix: bool, timeout: float) -> dict:
    """One batch size in a fresh process: ``ran``, or ``hung`` (compiled, then no result
    within ``timeout`` seconds), with the wall time."""
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    if fix:
        env["XLA_FLAGS"] = f"{env.get('XLA_FLAGS', '')} {XLA_CPU_SCHEDULER_FIX}".strip()
    start = time.perf_counter()
    child = subprocess.Popen([sys.executable, __file__, "--child", str(batch)], env=env, stdout=subprocess.PIPE, text=True)
    try:
        out, _ = child.communicate(timeout=timeout)
        outcome = "ran" if "ran" in out else f"failed (exit {child.returncode})"
    except subprocess.TimeoutExpired:
        child.kill()
        out, _ = child.communicate()
        outcome = "hung" if "compiled" in out else "compile timed out"
    return {"batch": batch, "fix": fix, "outcome": outcome, "seconds": round(time.perf_counter() - start, 1)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", default="1,4,8,64", help="comma-separated batch sizes")
    parser.add_argument("--fix", action="store_true", help="XLA_CPU_SCHEDULER_FIX in the child's XLA_FLAGS")
    parser.add_argument("--timeout", type=float, default=120.0, help="seconds per batch size before it counts as hung")
    parser.add_argument("--json", action="store_true", help="one JSON line per batch size")
    parser.add_argument("--child", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        step_batch(args.child)
        return 0
    for batch in (int(b) for b in args.batch.split(",")):
        result = probe(batch, args.fix, args.timeout)
        print(json.dumps(result) if args.json else f"batch {batch}: {result['outcome']} ({result['seconds']} s)", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
