"""Throughput of the reaching environment: arm-steps per second, observations included.

One arm-step is one arm's control step: action clipping, the swept collision check of the
motion (4 substeps of kinematics + every collision pair the arm takes part in), the targets,
rewards, termination, and the arm's 107-D neighbour-sequence observation. Environments run
under :class:`mjx_multiarm.env.wrappers.AutoReset` (finished episodes restart with tasks drawn
from a device task bank), ``--steps`` steps per jitted ``lax.scan``; compile excluded.

    python benchmarks/env_throughput.py --arms 1,4,10 --batch 1,64,1024
    python benchmarks/env_throughput.py --arms 4 --batch 1024 --json
    python benchmarks/env_throughput.py --arms 4 --slots 10 --batch 1024 --policy scripted

With ``--json`` every measurement also prints one JSON line (arms, batch, device,
arm_steps_per_s, ...); a single measurement's JSON line is the last line of the output.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import jax
from common import add_timing_arguments, cpu_name, selected_device

from mjx_multiarm.env.reaching import EnvConfig, ReachingEnv
from mjx_multiarm.env.scripted import ik_actions
from mjx_multiarm.env.wrappers import AutoReset, TaskBank
from mjx_multiarm.tasks.generate import GenerationSpec, generate_chunk

#: Tasks in the benchmark's bank (sampled uniformly, with replacement).
BANK_TASKS = 64


def measure(num_arms, batch, device, slots=None, policy="random", steps=50, min_seconds=2.0, seed=0):
    """Median arm-steps/s over repeated jitted rollouts of ``steps`` environment steps."""
    slots = slots or num_arms
    spec = GenerationSpec(count=BANK_TASKS, arm_counts=(num_arms,), mode="static", seed=seed, max_arms=slots, chunk_size=BANK_TASKS)
    env = ReachingEnv(slots, EnvConfig())
    with jax.default_device(device):
        wrapper = AutoReset(env, TaskBank.from_tasks(generate_chunk(spec, 0), slots))

        def act(state, key):
            if policy == "scripted":
                return jax.vmap(lambda s: ik_actions(env, s))(state.env)
            return jax.random.uniform(key, (batch, *env.action_shape), minval=-1.0, maxval=1.0)

        @jax.jit
        def rollout(state):
            def step(state, key):
                state, stepped = wrapper.step(state, act(state, key))
                return state, stepped.done.sum()

            return jax.lax.scan(step, state, jax.random.split(state.rng, steps))

        state = jax.jit(wrapper.reset, static_argnums=1)(jax.random.key(seed), batch)
        state, _ = jax.block_until_ready(rollout(state))  # compile
        times, episodes, start = [], 0, time.perf_counter()
        while time.perf_counter() - start < min_seconds or len(times) < 3:
            t = time.perf_counter()
            state, done = jax.block_until_ready(rollout(state))
            times.append(time.perf_counter() - t)
            episodes += int(done.sum())
    per_call = statistics.median(times)
    return {
        "arms": num_arms,
        "slots": slots,
        "batch": batch,
        "device": device.platform,
        "device_kind": device.device_kind,
        "policy": policy,
        "arm_steps_per_s": num_arms * batch * steps / per_call,
        "env_steps_per_s": batch * steps / per_call,
        "episodes_per_step": episodes / (len(times) * steps * batch),
        "substeps": env.substeps,
        "repeats": len(times),
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--arms", default="1,4,10", help="comma-separated team sizes")
    parser.add_argument("--slots", type=int, default=None, help="arm slots of the compiled scene (default: the team size)")
    parser.add_argument("--batch", default="1,64,1024", help="comma-separated batch sizes (environments)")
    parser.add_argument("--policy", choices=["random", "scripted"], default="random", help="uniform random actions or the IK controller")
    add_timing_arguments(parser, 50, "environment steps per jitted rollout")
    args = parser.parse_args(argv)

    device = selected_device(args)
    print(f"# {cpu_name()}, {device.device_kind}, jax {jax.__version__}, policy {args.policy}")
    print(f"{'arms':>4} {'slots':>5} {'batch':>6} {'arm-steps/s':>13} {'env-steps/s':>12} {'episodes/step':>13}")
    for num_arms in (int(a) for a in args.arms.split(",")):
        if args.slots is not None and num_arms > args.slots:
            parser.error(f"--arms {num_arms} is larger than --slots {args.slots}")
        for batch in (int(b) for b in args.batch.split(",")):
            r = measure(num_arms, batch, device, args.slots, args.policy, args.steps, args.seconds)
            print(f"{num_arms:>4} {r['slots']:>5} {batch:>6} {r['arm_steps_per_s']:>13,.0f} {r['env_steps_per_s']:>12,.0f} {r['episodes_per_step']:>13.4f}")
            if args.json:
                print(json.dumps(r))


if __name__ == "__main__":
    main()
