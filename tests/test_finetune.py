"""Fine-tuning from a policy file (``--init``), its lineage, and training that survives faults
(signals, damaged checkpoints, runs stopped before their first checkpoint, mismatched files)."""

from __future__ import annotations

import json
import os
import pathlib
import signal
import subprocess
import sys

import jax
import numpy as np
import pytest
from flax import nnx

from mjx_multiarm.expert.planner import PlannerConfig
from mjx_multiarm.expert.precompute import precompute
from mjx_multiarm.options import apply
from mjx_multiarm.env.observation import InputFeatures
from mjx_multiarm.geometry.robot import NUM_JOINTS
from mjx_multiarm.planner.policy_file import load_policy, save_policy
from mjx_multiarm.tasks.generate import GenerationSpec, generate_dataset
from models.networks import Actor
from train import sac
from train.config import PRESETS
from train.finetune import DEFAULT_ACTOR_FREEZE, lineage
from train.run import TrainingStopped, train

SHIPPED = pathlib.Path(__file__).resolve().parents[1] / "mjx_multiarm" / "assets" / "policy.npz"
ROOT = pathlib.Path(__file__).resolve().parents[1] / "benchmarks" / "chain" / "root.npz"  # the chain's root: version 1, actor only
QUIET = dict(workers=1, log=lambda message: None)


def _config(flags):
    return sac.config_from_args(sac._parser().parse_args(flags))


def _params(state):
    return [np.asarray(x) for x in jax.tree.leaves(state)]


def test_init_takes_the_networks_and_curriculum_level_from_the_policy_file():
    """The chain's root (a version 1, actor-only file): its input features, the level it
    reached, and a critic warm-up, unless the command line says otherwise; a conflicting
    architecture or a missing file fails before the run starts."""
    config = _config(["--init", str(ROOT)])  # the cpu preset has no goal features: the file's win
    recorded = load_policy(ROOT).provenance["curriculum_level"]
    assert config.train.sac.inputs.goal and config.train.start_level == recorded == 21
    assert config.train.sac.actor_freeze == DEFAULT_ACTOR_FREEZE
    config = _config(["--preset", "team", "--init", str(ROOT), "--start-level", "3", "--actor-freeze", "0"])
    assert (config.train.start_level, config.train.sac.actor_freeze) == (3, 0)
    with pytest.raises(ValueError, match=r"networks differ .*--goal-features 1"):
        _config(["--init", str(ROOT), "--goal-features", "0"])
    with pytest.raises(FileNotFoundError, match="no such policy file or run directory"):
        _config(["--init", "nowhere.npz"])


def test_the_shipped_policy_carries_its_critics_and_its_chain_of_parents():
    """The shipped policy is a part of the training chain: a small version 2 file with its
    twin critics (what fine-tuning needs), whose lineage of parents ends at the chain's root
    (a first training run, without a parent) with the chain's totals."""
    shipped, root = load_policy(SHIPPED), load_policy(ROOT)
    assert SHIPPED.stat().st_size <= 8 * 2**20 and shipped.meta["version"] == 2 and shipped.critic is not None
    assert (root.meta["version"], root.critic, lineage(root.provenance)) == (1, None, [])
    chain = lineage(shipped.provenance)
    assert len(chain) >= 2 and chain[-1]["sha256"] == root.meta["sha256"]
    assert chain[-1]["total_env_steps"] == chain[-1]["env_steps"] == root.provenance["env_steps"]
    for child, parent in zip(chain, chain[1:]):
        assert child["total_env_steps"] == child["env_steps"] + parent["total_env_steps"]


def test_a_one_component_policy_fine_tunes_as_a_mixture_and_a_mixture_keeps_its_size(tmp_path):
    """--components K widens a one-component parent; a mixture parent fixes K."""
    assert _config(["--init", str(SHIPPED), "--components", "3"]).train.sac.components == 3
    assert _config(["--init", str(SHIPPED)]).train.sac.components == 1
    assert _config(["--init", str(ROOT), "--components", "2"]).train.sac.components == 2
    mixture = tmp_path / "mixture.npz"
    save_policy(mixture, nnx.state(Actor(nnx.Rngs(0), InputFeatures(goal=True), NUM_JOINTS, components=2)), False, {},
                inputs=InputFeatures(goal=True), components=2)
    assert _config(["--init", str(mixture)]).train.sac.components == 2
    with pytest.raises(ValueError, match=r"networks differ .*--components 2"):
        _config(["--init", str(mixture), "--components", "3"])


def _read_back(path):
    policy = load_policy(path)
    return policy, _params(nnx.state(policy.actor))


@pytest.mark.slow
def test_fine_tunes_start_from_their_parent_and_record_the_chain(tmp_path):
    """A frozen actor comes out as the parent's exactly; the critics travel in the file; each
    policy file records its parent's checksum and the chain's totals."""
    base = apply(PRESETS["tiny"], {"budget.steps": 160})
    train(base, tmp_path / "a", **QUIET)
    parent, parent_actor = _read_back(tmp_path / "a" / "policy.npz")
    assert parent.critic is not None and parent.meta["version"] == 2
    child_config = apply(base, {"init": str(tmp_path / "a"), "train.sac.actor_freeze": 10**6})
    train(child_config, tmp_path / "b", **QUIET)
    child, child_actor = _read_back(tmp_path / "b" / "policy.npz")
    for a, b in zip(parent_actor, child_actor):
        np.testing.assert_allclose(a, b, atol=1e-6)
    assert any(not np.allclose(a, b) for a, b in zip(_params(parent.critic), _params(child.critic)))  # the critics learnt
    (record,) = lineage(child.provenance)
    assert record["sha256"] == parent.meta["sha256"] and record["env_steps"] == 160 and record["total_env_steps"] == 160

    train(apply(base, {"init": str(tmp_path / "b" / "policy.npz")}), tmp_path / "c", **QUIET)
    grandchild, grandchild_actor = _read_back(tmp_path / "c" / "policy.npz")
    assert [r["sha256"] for r in lineage(grandchild.provenance)] == [child.meta["sha256"], parent.meta["sha256"]]
    assert lineage(grandchild.provenance)[0]["total_env_steps"] == 320
    with pytest.raises(ValueError, match="networks differ"):
        train(apply(base, {"init": str(tmp_path / "a"), "train.sac.inputs.goal": True}), tmp_path / "d", **QUIET)

    # a mixture fine-tune of a one-component parent starts as the parent's policy
    train(apply(child_config, {"train.sac.components": 3}), tmp_path / "m", **QUIET)
    wide = load_policy(tmp_path / "m" / "policy.npz")
    assert wide.components == 3 and lineage(wide.provenance)[0]["sha256"] == parent.meta["sha256"]
    obs = np.random.default_rng(0).normal(size=(5, 2, 107)).astype(np.float32)
    mask = np.ones((5, 2), bool)
    np.testing.assert_allclose(wide.actor(obs, mask)[0], parent.actor(obs, mask)[0], atol=1e-6)


@pytest.mark.slow
def test_a_signal_saves_a_checkpoint_and_a_damaged_checkpoint_falls_back(tmp_path):
    """SIGTERM mid-run stops at the end of the iteration with a checkpoint; a truncated latest
    checkpoint is set aside with a warning and the run resumes from the newest intact one."""
    config = apply(PRESETS["tiny"], {"budget.steps": 160, "budget.checkpoint_minutes": 0.0})
    run = tmp_path / "run"

    def stop_at_third(row):
        if row["iteration"] == 3:
            os.kill(os.getpid(), signal.SIGTERM)

    handler_before = signal.getsignal(signal.SIGTERM)  # not always SIG_DFL: a library may have set one
    with pytest.raises(TrainingStopped, match="stopped by SIGTERM at iteration 3 .*--resume"):
        train(config, run, progress=stop_at_third, **QUIET)
    assert signal.getsignal(signal.SIGTERM) is handler_before  # the run's handler is gone
    steps = sorted(int(p.name) for p in (run / "checkpoints").iterdir() if p.name.isdigit())
    assert steps[-1] == 3
    latest = max((p for p in (run / "checkpoints" / "3").rglob("*") if p.is_file()), key=lambda p: p.stat().st_size)
    latest.write_bytes(latest.read_bytes()[: latest.stat().st_size // 2])
    messages = []
    result = train(config, run, resume=True, workers=1, log=messages.append)
    assert result.summary["env_steps"] == 160
    assert any("checkpoint 3" in m and "does not read back" in m for m in messages), messages
    assert any("resumed" in m and "iteration 2" in m for m in messages), messages
    assert (run / "checkpoints" / "3.corrupt").is_dir()


def _task_file(path, seed):
    spec = GenerationSpec(count=8, arm_counts=(1,), mode="static", seed=seed, max_arms=1, chunk_size=8)
    generate_dataset(spec, path, workers=1)
    return path


@pytest.mark.slow
def test_a_run_stopped_before_its_first_checkpoint_starts_again_and_experts_must_match(tmp_path):
    """A failed start (corrupt task file) leaves a directory the corrected command reuses;
    experts planned for another task file are refused."""
    good, other = _task_file(tmp_path / "good.npz", 1), _task_file(tmp_path / "other.npz", 2)
    precompute(good, tmp_path / "good.experts", PlannerConfig(time_limit=5.0))
    (tmp_path / "corrupt.npz").write_bytes(good.read_bytes()[:100])
    run, base = tmp_path / "run", apply(PRESETS["tiny"], {"budget.steps": 64})
    with pytest.raises(ValueError):
        train(apply(base, {"data.tasks": str(tmp_path / "corrupt.npz")}), run, **QUIET)
    with pytest.raises(ValueError, match="planned for another task file"):
        train(apply(base, {"data.tasks": str(other), "data.experts": str(tmp_path / "good.experts")}), run, **QUIET)
    result = train(apply(base, {"data.tasks": str(good), "data.experts": str(tmp_path / "good.experts")}), run, **QUIET)
    assert result.summary["env_steps"] == 64


@pytest.mark.slow
def test_the_gpu_recipe_runs_end_to_end_at_a_tiny_size(tmp_path):
    """benchmarks/gpu_finetune.py: tasks, experts, a fine-tune of the shipped policy and the
    evaluations on every validation and test set, at the tiny size on the CPU."""
    script = pathlib.Path(__file__).resolve().parents[1] / "benchmarks" / "gpu_finetune.py"
    subprocess.run([sys.executable, str(script), "--size", "tiny", "--out", str(tmp_path)], check=True, capture_output=True)
    figures = json.loads((tmp_path / "figures.json").read_text())
    assert {name: entry["role"] for name, entry in figures["sets"].items()} == {
        "held512": "validation", "crowdval2048": "validation", "test1to10": "test", "crowd1to10": "test"}
    assert sorted(figures["sets"]["test1to10"]["fine_tuned"], key=int) == [str(k) for k in range(1, 11)]
    assert figures["env_steps"] >= 64
    assert lineage(load_policy(tmp_path / "run" / "policy.npz").provenance)[0]["sha256"] == load_policy(SHIPPED).meta["sha256"]
