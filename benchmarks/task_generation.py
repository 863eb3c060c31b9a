"""Task generation throughput: tasks/s for a team size, compile excluded.

    python benchmarks/task_generation.py --arms 4 --count 512 --mode static
    python benchmarks/task_generation.py --arms 10 --count 512 --mode dynamic --json

Generates one warm-up chunk (compiles IK, collision and difficulty kernels), then times
``--count`` tasks made chunk by chunk exactly as ``python -m mjx_multiarm.tasks generate``
does. With ``--json`` the last line is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import time

import jax

from mjx_multiarm.tasks.generate import (
    CHUNK_SIZE,
    MODES,
    GenerationSpec,
    generate_chunk,
)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--arms", type=int, required=True, help="team size")
    parser.add_argument("--count", type=int, default=2 * CHUNK_SIZE, help="tasks to time")
    parser.add_argument("--mode", choices=MODES, default="static")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    spec = GenerationSpec(count=args.count + CHUNK_SIZE, arm_counts=(args.arms,), mode=args.mode, seed=args.seed)
    generate_chunk(spec, 0)  # warm-up: compiles
    start = time.perf_counter()
    done = sum(generate_chunk(spec, c).num_tasks for c in range(1, spec.num_chunks))
    seconds = time.perf_counter() - start
    result = {
        "arms": args.arms,
        "mode": args.mode,
        "tasks": done,
        "seconds": seconds,
        "tasks_per_s": done / seconds,
        "device": jax.devices()[0].device_kind,
    }
    print(f"{args.arms} arms, {args.mode}: {done} tasks in {seconds:.1f} s = {done / seconds:.1f} tasks/s")
    if args.json:
        print(json.dumps(result))


if __name__ == "__main__":
    main()
