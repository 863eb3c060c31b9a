"""Training learns: a short fixed-seed run of the ``cpu`` recipe lifts held-out success on
single-arm reaching far above what the same run reaches with its updates broken (issue 51:
a test that fails when learning breaks; the margin is measured in benchmarks/RESULTS.md,
"A test that fails when learning breaks")."""

from __future__ import annotations

import numpy as np
import pytest

from mjx_multiarm.env.wrappers import Outcomes, TaskBank, final_states, make_episodes
from mjx_multiarm.options import apply
from mjx_multiarm.planner.policy import Planner
from mjx_multiarm.tasks.generate import GenerationSpec, generate_chunk
from train.config import PRESETS
from train.curriculum import LEVELS
from train.run import train

#: Environment steps of the run (about 2 minutes of training on a 2-core CPU).
STEPS = 300_000
#: Held-out success (128 single-arm tasks, the curriculum's first tolerance, mean actions)
#: the run must exceed: measured 0.44 (seed 0; seed 1: 0.27) against 0.008 with the learning
#: rates at 1e-12 (the actor stays at its initialization).
THRESHOLD = 0.1


def heldout_success_after_training(run_dir, **overrides) -> float:
    """Train the ``cpu`` preset (seed 0) for :data:`STEPS` with ``overrides``, then run its
    policy on 128 held-out single-arm tasks and return the share within the curriculum's first
    tolerance (10 cm, 0.2 rad) within 200 steps."""
    config = apply(PRESETS["cpu"], {"budget.steps": STEPS, "budget.minutes": 1e3, "budget.eval_minutes": 0.0,
                                    "budget.checkpoint_minutes": 1e3, "data.train_tasks": 256, "data.eval_count": 16,
                                    **overrides})
    planner = Planner(train(config, run_dir, workers=1, log=lambda message: None).policy)
    held_out = generate_chunk(GenerationSpec(count=128, arm_counts=(1,), mode="static", seed=99, max_arms=1), 0)
    env = planner.environment(1, max_steps=200, tolerance=tuple(map(float, LEVELS[0])))
    final = final_states(make_episodes(env, planner.policy_fn(), 200), planner.params, TaskBank.from_tasks(held_out, 1), 128)
    return float(np.mean(Outcomes.of(final).success))


@pytest.mark.slow
@pytest.mark.parametrize("updates", ["working", "broken"])
def test_training_lifts_heldout_success_above_a_broken_update(tmp_path, updates):
    broken = {"train.sac.actor_lr": 1e-12, "train.sac.critic_lr": 1e-12} if updates == "broken" else {}
    success = heldout_success_after_training(tmp_path / "run", **broken)
    assert (success > THRESHOLD) == (updates == "working"), f"{updates} updates: held-out success {success:.3f}"
