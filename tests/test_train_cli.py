"""``python -m train.sac`` and the ``train()`` API end to end at the tiny preset, and exact resumption."""

from __future__ import annotations

import json

import jax
import numpy as np
import orbax.checkpoint as ocp
import pytest
from flax import nnx

from mjx_multiarm.env.observation import InputFeatures
from mjx_multiarm.options import apply
from mjx_multiarm.planner.policy_file import LoadedPolicy, load_policy
from train import sac
from train.checkpoint import Checkpoints
from train.config import PRESETS
from train.run import load_config, train


def _final_actor(run_dir, field="actor"):
    """The actor (or ``field``) parameters of a run's latest checkpoint (raw arrays)."""
    checkpoints = Checkpoints(run_dir / "checkpoints")
    step = checkpoints.latest()
    restored = checkpoints.manager.restore(step, args=ocp.args.Composite(state=ocp.args.StandardRestore()))
    checkpoints.close()
    return jax.tree.leaves(restored["state"]["agent"][field])


@pytest.mark.slow
def test_cli_runs_end_to_end_and_resumes_exactly(tmp_path, capsys):
    whole = tmp_path / "whole"
    sac.main(["--preset", "tiny", "--run-dir", str(whole), "--workers", "1", "--steps", "400", "--json"])
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    for key in ("env_steps", "updates", "env_steps_per_s", "success_rate", "curriculum_level", "checkpoint"):
        assert key in summary
    assert summary["env_steps"] == 400 and summary["updates"] > 0
    for name in ("config.json", "metrics.csv", "learning_curve.png", "summary.json", "tasks.npz", "tasks.experts", "policy.npz"):
        assert (whole / name).is_file(), name
    # the exported policy file holds the final averaged actor, for the Planner and eval.benchmark
    exported = load_policy(whole / "policy.npz")
    assert exported.meta["provenance"]["env_steps"] == 400
    for a, b in zip(jax.tree.leaves(nnx.state(exported.actor)), _final_actor(whole, "average_actor")):
        np.testing.assert_array_equal(np.asarray(a), b)

    split = tmp_path / "split"
    sac.main(["--preset", "tiny", "--run-dir", str(split), "--workers", "1", "--steps", "200"])
    sac.main(["--resume", str(split), "--workers", "1", "--steps", "400"])
    for field in ("actor", "average_actor"):
        for a, b in zip(_final_actor(whole, field), _final_actor(split, field)):
            np.testing.assert_array_equal(a, b)

    with pytest.raises(SystemExit, match="already holds a run"):
        sac.main(["--preset", "tiny", "--run-dir", str(whole)])
    with pytest.raises(SystemExit, match="not a run directory"):
        sac.main(["--resume", str(tmp_path / "nowhere")])


@pytest.mark.slow
def test_team_options_and_a_task_file_subset(tmp_path, capsys):
    """The team options end to end: per-team curriculum levels in metrics and summary,
    rotation features in the exported policy; --task-limit N of a task file without an
    expert file plans the experts of those N tasks only."""
    from mjx_multiarm.expert.store import ExpertStore
    from mjx_multiarm.tasks.dataset import load_tasks, save_tasks
    from mjx_multiarm.tasks.generate import GenerationSpec, generate_chunk

    save_tasks(tmp_path / "many.npz", generate_chunk(GenerationSpec(count=12, arm_counts=(1, 2), mode="static", seed=4, max_arms=2), 0))
    run = tmp_path / "team"
    sac.main(["--preset", "tiny", "--run-dir", str(run), "--workers", "1", "--steps", "64", "--tasks", str(tmp_path / "many.npz"),
              "--task-limit", "6", "--curriculum-by-team", "1", "--collisions", "restore", "--expert-share", "0.25",
              "--rotations", "1", "--goal-features", "1", "--json"])
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert load_tasks(run / "tasks.npz")[0].num_tasks == 6 and len(ExpertStore(run / "tasks.experts").task_ids) == 6
    assert set(summary["curriculum_levels_by_team"]) == {"1", "2"}
    header = (run / "metrics.csv").read_text().splitlines()[0].split(",")
    assert {"level_1", "level_2", "window_success_1", "window_success_2"} <= set(header)
    assert load_policy(run / "policy.npz").actor.encoder.inputs == InputFeatures(rotations=True, goal=True)
    assert set(summary["evaluation"]["by_team_size"]["1"]) >= {"arm_reach_rate", "collision_rate", "timeout_rate"}


@pytest.mark.parametrize("flags, expert_bc, hindsight", [
    ([], 1.0, 1),
    (["--no-expert"], 0.0, 1),
    (["--bc"], 0.0, 0),
    (["--hindsight", "0", "--expert-bc", "0"], 0.0, 0),
    (["--preset", "paper"], 0.0, 0),
    (["--preset", "team"], 1.0, 1),
    (["--preset", "team", "--bc"], 0.0, 0),
    (["--preset", "team", "--no-expert"], 0.0, 1),
])
def test_preset_additions_give_way_to_the_ablations(flags, expert_bc, hindsight):
    """The cpu preset's expert term and hindsight goals step aside for the ablations that
    remove what they need, so ``--bc`` and ``--no-expert`` run without further flags."""
    config = sac.config_from_args(sac._parser().parse_args(flags))  # consistent: raises otherwise
    assert (config.train.sac.expert_bc, config.train.hindsight) == (expert_bc, hindsight)


@pytest.mark.parametrize("flags, message", [
    (["--bc", "--no-expert"], "needs expert=True"),
    (["--expert-bc", "1", "--no-expert"], "expert_bc adds behaviour cloning"),
    (["--hindsight", "-1"], "hindsight must be >= 0"),
    (["--hindsight", "1", "--bc"], "behaviour cloning"),
    (["--policy-average", "2"], r"policy_average must be in \[0, 1\]"),
    (["--policy-average", "-0.5"], r"policy_average must be in \[0, 1\]"),
    (["--shaping", "-0.5"], "shaping must be >= 0"),
    (["--episode-steps", "0"], "max_steps must be >= 1"),
    (["--expert-share", "1.5"], r"expert_share must be in \[0, 1\)"),
    (["--expert-share", "0.25", "--no-expert"], "expert_share samples expert transitions"),
    (["--bc-start", "100", "--no-expert"], "bc_start clones expert transitions"),
    (["--bc-start", "-1"], "bc_start must be >= 0"),
    (["--actor-freeze", "-1"], "actor_freeze must be >= 0"),
    (["--workers", "0"], "workers must be >= 1"),
    (["--workers", "-2"], "workers must be >= 1"),
])
def test_inconsistent_flags_fail_before_the_run_starts(tmp_path, flags, message):
    """The training and environment configurations' checks run before the run directory, tasks or experts exist."""
    run_dir = tmp_path / "run"
    with pytest.raises(SystemExit, match=message):
        sac.main(["--preset", "tiny", "--run-dir", str(run_dir), *flags])
    assert not run_dir.exists()


@pytest.mark.slow
def test_train_api_logs_heldout_success_during_training(tmp_path):
    """``train()`` in-process: the result's policy, summary and metrics; the deployed policy
    evaluated on held-out tasks during training (per team size, in metrics.csv and the
    plot); resuming with another configuration than the run's is refused."""
    config = apply(PRESETS["tiny"], {"budget.steps": 160, "budget.eval_minutes": 1e-4})
    run, seen = tmp_path / "api", []
    result = train(config, run, workers=1, progress=seen.append, log=lambda message: None)
    assert isinstance(result.policy, LoadedPolicy) and result.summary["env_steps"] == 160 and len(seen) == len(result.metrics)
    evaluated = [r for r in result.metrics if r.get("heldout_success", float("nan")) == r.get("heldout_success")]
    assert len(evaluated) >= 3 and all(0 <= r["heldout_success_1"] <= 1 for r in evaluated)
    assert evaluated[-1]["heldout_success"] == result.summary["success_rate"]  # the final evaluation, all tasks
    assert "heldout_success_1" in (run / "metrics.csv").read_text().splitlines()[0].split(",")
    assert (run / "learning_curve.png").stat().st_size > 0 and load_config(run) == config == load_config(run / "policy.npz")
    with pytest.raises(ValueError, match="only the budget may change"):
        train(apply(config, {"train.sac.gamma": 0.5}), run, resume=True, workers=1)
