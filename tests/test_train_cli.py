"""``python -m train.sac`` end to end at the tiny preset, and exact resumption."""

from __future__ import annotations

import json

import jax
import numpy as np
import orbax.checkpoint as ocp
import pytest
from flax import nnx

from models.policy_file import load_policy
from train import sac
from train.checkpoint import Checkpoints


def _final_actor(run_dir, field="actor"):
    """The actor (or ``field``) parameters of a run's latest checkpoint (raw arrays)."""
    checkpoints = Checkpoints(run_dir / "checkpoints")
    step = checkpoints.latest()
    restored = checkpoints.manager.restore(step, args=ocp.args.Composite(state=ocp.args.StandardRestore()))
    checkpoints.close()
    return jax.tree.leaves(restored["state"]["agent"][field])


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


@pytest.mark.parametrize("flags, expert_bc, hindsight", [
    ([], 1.0, 1),
    (["--no-expert"], 0.0, 1),
    (["--bc"], 0.0, 0),
    (["--hindsight", "0", "--expert-bc", "0"], 0.0, 0),
    (["--preset", "paper"], 0.0, 0),
])
def test_preset_additions_give_way_to_the_ablations(flags, expert_bc, hindsight):
    """The cpu preset's expert term and hindsight goals step aside for the ablations that
    remove what they need, so ``--bc`` and ``--no-expert`` run without further flags."""
    settings = sac._settings(sac._parser().parse_args(flags))
    assert (settings["expert_bc"], settings["hindsight"]) == (expert_bc, hindsight)
    sac._train_config(settings)  # consistent: raises otherwise


@pytest.mark.parametrize("flags, message", [
    (["--bc", "--no-expert"], "needs expert=True"),
    (["--expert-bc", "1", "--no-expert"], "expert_bc adds behaviour cloning"),
    (["--hindsight", "-1"], "hindsight must be >= 0"),
    (["--hindsight", "1", "--bc"], "behaviour cloning"),
    (["--policy-average", "2"], r"policy_average must be in \[0, 1\]"),
    (["--policy-average", "-0.5"], r"policy_average must be in \[0, 1\]"),
    (["--shaping", "-0.5"], "shaping must be >= 0"),
    (["--episode-steps", "0"], "max_steps must be >= 1"),
])
def test_inconsistent_flags_fail_before_the_run_starts(tmp_path, flags, message):
    """The training and environment configurations' checks run before the run directory, tasks or experts exist."""
    run_dir = tmp_path / "run"
    with pytest.raises(SystemExit, match=message):
        sac.main(["--preset", "tiny", "--run-dir", str(run_dir), *flags])
    assert not run_dir.exists()
