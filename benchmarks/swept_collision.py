"""How often a one-step motion slips through the environment's swept collision check.

Samples two-arm scenes (bases 0.5-0.9 m apart, random yaws, joints home + N(0, 1 rad)) and
a full-speed step for both arms (every joint at +-velocity limit x 0.05 s). Among the steps
whose start and end are both collision-free, a dense reference check (``--dense``
configurations along the motion) finds those that pass into the other arm or the ground;
the environment's check (``ReachingEnv.substeps`` evenly spaced configurations) must flag
them. Reports how many it misses and how deep the missed ones go, also for other substep
counts (``--substeps``) on the same samples.

    python benchmarks/swept_collision.py --samples 100000 --json
    python benchmarks/swept_collision.py --samples 100000 --substeps 4,5,6,8
"""

from __future__ import annotations

import argparse
import json

import jax
import jax.numpy as jnp
import numpy as np
from common import cpu_name, random_two_arm_steps

from mjx_multiarm.env.reaching import ReachingEnv
from mjx_multiarm.geometry.collision import scene_contacts


def measure(samples: int, dense: int, seed: int = 0, batch: int = 8192, substeps: tuple[int, ...] = ()) -> dict:
    """Pass-throughs among ``samples`` steps, and what checks of ``substeps`` (default: the
    environment's count) evenly spaced configurations miss of them."""
    env = ReachingEnv(2)
    substeps = tuple(substeps) or (env.substeps,)

    @jax.jit
    def depths(pos, quat, q0, q1):
        """Smallest distance [dense + 1, n] along q0 -> q1 at fractions k / dense."""
        fractions = jnp.linspace(0.0, 1.0, dense + 1)[:, None, None, None]
        path = q0 + fractions * (q1 - q0)
        return jax.vmap(lambda q: scene_contacts(env.scene, pos, quat, q, jnp.ones(q.shape[:-1], bool)).min_distance.min(-1))(path)

    rng = np.random.default_rng(seed)
    checked = {s: dense * np.arange(1, s + 1) // s for s in substeps}
    free, crossing, crossing_depth = 0, 0, []
    missed = {s: [] for s in substeps}
    for start in range(0, samples, batch):
        _, pos, quat, q0, q1 = random_two_arm_steps(min(batch, samples - start), rng)
        d = np.asarray(depths(pos, quat, q0, q1))
        ends_free = (d[0] >= 0) & (d[-1] >= 0)
        crosses = ends_free & (d.min(0) < 0)
        free += int(ends_free.sum())
        crossing += int(crosses.sum())
        crossing_depth += (-d.min(0)[crosses]).tolist()
        for s, rows in checked.items():
            missed[s] += (-d.min(0)[crosses & ~(d[rows] < 0).any(0)]).tolist()
    checks = [{
        "substeps": s,
        "missed": len(depths_missed),
        "miss_rate": len(depths_missed) / crossing if crossing else float("nan"),
        "max_missed_depth_m": max(depths_missed, default=0.0),
    } for s, depths_missed in missed.items()]
    return {"samples": samples, "ends_free": free, "crossing": crossing,
            "median_crossing_depth_m": float(np.median(crossing_depth)) if crossing_depth else float("nan"),
            "dense": dense, "env_substeps": env.substeps, **checks[0], "checks": checks}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--samples", type=int, default=100_000, help="sampled two-arm steps")
    parser.add_argument("--dense", type=int, default=256, help="configurations of the reference check")
    parser.add_argument("--substeps", default="", help="substep counts to compare, e.g. 4,5,6 (default: the env's)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", action="store_true", help="end with one JSON line")
    args = parser.parse_args(argv)
    print(f"# {cpu_name()}, jax {jax.__version__}")
    r = measure(args.samples, args.dense, args.seed, substeps=tuple(int(s) for s in filter(None, args.substeps.split(","))))
    print(f"{r['samples']} full-speed steps, {r['ends_free']} with both ends free, {r['crossing']} of those pass into "
          f"contact (dense check, {r['dense']} configurations; median depth {1000 * r['median_crossing_depth_m']:.1f} mm); "
          f"the environment uses {r['env_substeps']} substeps")
    for c in r["checks"]:
        print(f"  {c['substeps']}-substep check misses {c['missed']} ({c['miss_rate']:.1%}), "
              f"at most {1000 * c['max_missed_depth_m']:.1f} mm deep")
    if args.json:
        print(json.dumps(r))


if __name__ == "__main__":
    main()
