"""Cost of learning: SAC and behaviour-cloning updates, and whole training iterations.

Updates: ``--updates`` jitted SAC (or behaviour-cloning) updates in one ``lax.scan`` on a
fixed random batch of ``--batch`` observation sequences of 1, 2, 4, 10 elements (every
element observed), compile excluded; prints ms per update and the losses of the first
update on that batch (the same numbers before and after a change that keeps the math), for
actors of each ``--components`` entry (mixture components; 1: the original's Gaussian).

Iterations: :class:`train.trainer.Trainer` iterations of a preset's environment and
training settings (``--preset``, default ``cpu``: 64 environments x 16 steps, 16 updates of
batch 256, one hindsight copy) without experts (so no planning, no expert share of the
batches and no behaviour cloning of them) on generated tasks of each ``--teams`` entry
(``2``: two-arm tasks in two slots; ``1-4``: 1-4-arm tasks in four slots), past the
warm-up; prints env steps/s and updates/s.

    python benchmarks/update_cost.py                      # both parts
    python benchmarks/update_cost.py --elements 4 --teams 1-4 --json
    python benchmarks/update_cost.py --elements '' --teams 1-4 --preset team
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import time

import jax
import jax.numpy as jnp
import numpy as np
from common import cpu_name

from mjx_multiarm.cli import parse_arms
from mjx_multiarm.env.observation import ELEMENT_SIZE
from mjx_multiarm.env.reaching import ReachingEnv
from mjx_multiarm.env.wrappers import TaskBank
from mjx_multiarm.tasks.generate import GenerationSpec, generate_chunk
from train.agent import SACConfig, bc_update, create_agent, sac_update
from train.config import PRESETS
from train.replay import Transitions
from train.trainer import Trainer


def fixed_batch(size: int, elements: int, seed: int = 0) -> Transitions:
    """A reproducible batch of transitions with ``elements`` observed arms each."""
    keys = jax.random.split(jax.random.key(seed), 4)
    mask = jnp.ones((size, elements), bool)
    return Transitions(jax.random.normal(keys[0], (size, elements, ELEMENT_SIZE)), mask,
                       jax.random.uniform(keys[1], (size, 6), minval=-1, maxval=1), jax.random.normal(keys[2], (size,)),
                       jax.random.normal(keys[3], (size, elements, ELEMENT_SIZE)), mask, jnp.arange(size) % 7 == 0,
                       jnp.arange(size) % 3 == 0)


def time_updates(kind: str, batch: Transitions, updates: int, repeats: int = 3, components: int = 1) -> tuple[float, dict]:
    """(median ms per update, metrics of the first update) of ``updates`` scanned updates."""
    config = SACConfig(expert_bc=1.0, policy_average=5e-4, components=components)
    agent = create_agent(jax.random.key(1), config)

    def one(agent, key):
        return sac_update(agent, batch, key, config) if kind == "sac" else bc_update(agent, batch, config)

    run = jax.jit(lambda agent, key: jax.lax.scan(one, agent, jax.random.split(key, updates)))
    _, first = jax.block_until_ready(run(agent, jax.random.key(2)))  # compiles
    times = []
    for r in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(run(agent, jax.random.key(3 + r)))
        times.append(time.perf_counter() - start)
    return 1e3 * float(np.median(times)) / updates, {k: float(v[0]) for k, v in first.items()}


def time_iterations(teams: tuple[int, ...], iterations: int, preset: str = "cpu") -> dict:
    """Env steps/s and updates/s of training iterations (``preset``'s settings, no experts)
    on ``teams`` tasks."""
    slots = max(teams)
    spec = GenerationSpec(count=256, arm_counts=teams, mode="static", seed=0, max_arms=slots, chunk_size=256)
    run = PRESETS[preset]
    env = ReachingEnv(slots, run.env)
    config = dataclasses.replace(run.train, expert=False, expert_share=0.0, sac=dataclasses.replace(run.train.sac, expert_bc=0.0))
    trainer = Trainer(env, TaskBank.from_tasks(generate_chunk(spec, 0), slots), None, config)
    state = trainer.init(jax.random.key(0))
    while int(state.buffer.size) < config.warmup:  # compile, fill past the warm-up
        state, _ = jax.block_until_ready(trainer.iteration(state))
    steps, updates, start = int(state.env_steps), int(state.agent.updates), time.perf_counter()
    for _ in range(iterations):
        state, _ = jax.block_until_ready(trainer.iteration(state))
    seconds = time.perf_counter() - start
    return {"env_steps_per_s": (int(state.env_steps) - steps) / seconds, "updates_per_s": (int(state.agent.updates) - updates) / seconds}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--elements", default="1,2,4,10", help="observed arms per sequence, e.g. 1,2,4,10 ('' to skip)")
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--updates", type=int, default=20, help="updates per timed call")
    parser.add_argument("--components", default="1", help="comma-separated mixture components of the actor, e.g. 1,2,3")
    parser.add_argument("--teams", default="1,2,4,1-4", help="comma-separated team-size entries of iteration benchmarks, e.g. 1,2,4,1-4 ('' to skip)")
    parser.add_argument("--iterations", type=int, default=10, help="timed training iterations per entry")
    parser.add_argument("--preset", choices=sorted(PRESETS), default="cpu", help="settings of the iteration benchmarks")
    parser.add_argument("--json", action="store_true", help="one JSON line per measurement")
    args = parser.parse_args()
    print(f"device: {jax.devices()[0].device_kind} ({cpu_name()})")
    for elements in [int(e) for e in args.elements.split(",") if e]:
        batch = fixed_batch(args.batch, elements)
        for components, kind in itertools.product((int(k) for k in args.components.split(",")), ("sac", "bc")):
            ms, losses = time_updates(kind, batch, args.updates, components=components)
            shown = ", ".join(f"{k} {v:.6g}" for k, v in losses.items() if k in ("critic_loss", "actor_loss", "bc_loss"))
            print(f"{kind:>3} update, {components} component(s), {elements:>2} elements, batch {args.batch}: {ms:7.2f} ms "
                  f"({1e3 / ms:6.1f} updates/s); first: {shown}")
            if args.json:
                print(json.dumps({"kind": kind, "components": components, "elements": elements, "batch": args.batch,
                                  "ms_per_update": ms, "first_update": losses}))
    for entry in [t for t in args.teams.split(",") if t]:
        rates = time_iterations(parse_arms(entry), args.iterations, args.preset)
        print(f"training iterations ({args.preset}), {entry} arm tasks: {rates['env_steps_per_s']:,.0f} env steps/s, "
              f"{rates['updates_per_s']:.1f} updates/s")
        if args.json:
            print(json.dumps({"teams": entry, "preset": args.preset, **rates}))


if __name__ == "__main__":
    main()
