"""Demo: random motions of multi-arm teams with swept collision checking, under one jit.

Until ``python -m train.sac`` exists this is the project's main job. It builds a padded
scene, places teams of arms on a grid, and moves every arm by random velocity-limited joint
steps for a number of control steps; each step is checked along the motion (swept, at most
0.05 rad of joint motion between checks), and an arm whose motion collides stays where it
was. Prints how often each kind of contact stopped an arm, and the throughput.

    python -m mjx_multiarm.demo --arms 4 --slots 10 --batch 256 --steps 100
"""

from __future__ import annotations

import argparse
import math
import time

import jax
import jax.numpy as jnp
import numpy as np

from mjx_multiarm.collision import SWEEP_RESOLUTION, swept_contacts
from mjx_multiarm.scene import build_scene
from mjx_multiarm.transforms import yaw_quat

CONTROL_PERIOD = 0.05  # s, one action per control step (as in the paper)


def grid_bases(rng: np.random.Generator, batch: int, num_arms: int, spacing: float):
    """Bases on a square grid ``spacing`` apart, jittered by 5 cm, random yaw."""
    side = math.ceil(math.sqrt(num_arms))
    cells = np.stack(np.meshgrid(np.arange(side), np.arange(side)), -1).reshape(-1, 2)[:num_arms]
    xy = spacing * cells + rng.normal(0.0, 0.05, (batch, num_arms, 2))
    pos = np.concatenate([xy, np.zeros((batch, num_arms, 1))], axis=-1)
    return pos.astype(np.float32), np.asarray(yaw_quat(rng.uniform(-np.pi, np.pi, (batch, num_arms))), np.float32)


def make_rollout(scene, steps: int):
    """A jitted rollout of ``steps`` random velocity-limited motions with swept checks."""
    arm = scene.arm
    max_step = jnp.asarray(arm.velocity_limit * CONTROL_PERIOD, jnp.float32)
    substeps = math.ceil(float(max_step.max()) / SWEEP_RESOLUTION)
    lower, upper = (jnp.asarray(arm.joint_range[:, i], jnp.float32) for i in (0, 1))

    @jax.jit
    def rollout(rng, base_pos, base_quat, active):
        joints = jnp.broadcast_to(jnp.asarray(arm.home, jnp.float32), (*active.shape, 6))

        def step(joints, key):
            target = jnp.clip(joints + jax.random.uniform(key, joints.shape, minval=-1, maxval=1) * max_step, lower, upper)
            contacts = swept_contacts(scene, base_pos, base_quat, joints, target, active, substeps)
            stopped = contacts.collided[..., None]
            kinds = jnp.stack([contacts.between_arms < 0, contacts.within_arm < 0, contacts.ground < 0])
            return jnp.where(stopped, joints, target), kinds.sum(axis=(1, 2))

        _, counts = jax.lax.scan(step, joints, jax.random.split(rng, steps))
        return counts.sum(axis=0)

    return rollout


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--arms", type=int, default=4, help="arms per team (default 4)")
    parser.add_argument("--slots", type=int, default=None, help="padded arm slots of the compiled scene (default: --arms)")
    parser.add_argument("--batch", type=int, default=256, help="teams simulated in parallel (default 256)")
    parser.add_argument("--steps", type=int, default=100, help="control steps per rollout (default 100)")
    parser.add_argument("--spacing", type=float, default=0.9, help="base grid spacing in m (default 0.9)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    args.slots = args.slots or args.arms
    if not 1 <= args.arms <= args.slots:
        parser.error(f"--arms must be in [1, --slots={args.slots}], got {args.arms}")

    scene = build_scene(args.slots)
    rng = np.random.default_rng(args.seed)
    base_pos, base_quat = grid_bases(rng, args.batch, args.slots, args.spacing)
    active = np.zeros((args.batch, args.slots), bool)
    active[:, : args.arms] = True
    rollout = make_rollout(scene, args.steps)
    print(f"{args.batch} teams of {args.arms} arms in a {args.slots}-slot scene, {args.steps} steps; compiling...")
    start = time.perf_counter()
    rollout(jax.random.key(args.seed), base_pos, base_quat, active).block_until_ready()
    compile_s = time.perf_counter() - start
    start = time.perf_counter()
    counts = np.asarray(rollout(jax.random.key(args.seed + 1), base_pos, base_quat, active))
    run_s = time.perf_counter() - start
    arm_steps = args.batch * args.arms * args.steps
    print(f"compile {compile_s:.1f} s, run {run_s:.2f} s on {jax.devices()[0].device_kind}")
    print(f"{arm_steps / run_s:,.0f} arm-steps/s ({args.batch * args.steps / run_s:,.0f} team-steps/s), swept checks included")
    for name, count in zip(("another arm", "itself", "the ground"), counts):
        print(f"motions stopped by contact with {name:<12} {count / arm_steps:7.2%}")


if __name__ == "__main__":
    main()
