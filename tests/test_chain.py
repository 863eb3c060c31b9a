"""benchmarks/chain.py: recording the training chain's parts, keeping the best, the table
and the curve (the evaluations themselves are replaced by fixed rates)."""

import importlib.util
import json
import pathlib

import pytest
from flax import nnx

from mjx_multiarm.env.observation import InputFeatures
from mjx_multiarm.geometry.robot import NUM_JOINTS
from mjx_multiarm.planner.policy_file import load_policy, save_policy
from models.networks import Actor

_spec = importlib.util.spec_from_file_location("chain", pathlib.Path(__file__).parents[1] / "benchmarks" / "chain.py")
chain = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(chain)

HOUR = 3600.0


def _rates(success: float) -> dict:
    """Validation rates with one success rate for every set and team size (128 tasks each)."""
    row = {"tasks": 128, "success_rate": success, "collision_rate": 1 - success, "timeout_rate": 0.0}
    return {name: {str(arms): dict(row) for arms in range(1, 5)} for name in chain.VALIDATION}


def _policy(path: pathlib.Path, seed: int, provenance: dict) -> str:
    save_policy(path, nnx.state(Actor(nnx.Rngs(seed), InputFeatures(goal=True), NUM_JOINTS)), False, {},
                provenance=provenance, inputs=InputFeatures(goal=True))
    return load_policy(path).meta["sha256"]


@pytest.fixture
def chain_dir(tmp_path, monkeypatch):
    """A chain whose table and policies live in ``tmp_path``, and whose evaluation returns
    the rate each policy file names in its provenance (``rate``)."""
    for name, file in (("TABLE", "chain.json"), ("BEST", "best.npz"), ("HEAD", "head.npz")):
        monkeypatch.setattr(chain, name, tmp_path / file)
    monkeypatch.setattr(chain, "evaluate", lambda policy, data: _rates(load_policy(policy).provenance["rate"]))
    return tmp_path


def _part(tmp_path, name, seed, rate, parent_path, steps, hours):
    """A run directory whose policy fine-tuned ``parent_path``."""
    parent = load_policy(parent_path)
    own = parent.provenance
    record = {"path": str(parent_path), "sha256": parent.meta["sha256"], "env_steps": own["env_steps"],
              "train_seconds": own["train_seconds"], "total_env_steps": own.get("total_env_steps", own["env_steps"]),
              "total_train_seconds": own.get("total_train_seconds", own["train_seconds"]), "parent": own.get("parent")}
    run = tmp_path / name
    _policy(run / "policy.npz", seed, {"rate": rate, "env_steps": steps, "train_seconds": hours * HOUR, "parent": record,
                                       "total_env_steps": record["total_env_steps"] + steps,
                                       "total_train_seconds": record["total_train_seconds"] + hours * HOUR})
    return run


def test_record_keeps_only_a_better_part_and_tabulates_what_the_chain_spent(chain_dir, capsys):
    root = chain_dir / "root.npz"
    root_sha = _policy(root, 0, {"rate": 0.80, "env_steps": 4_000_000, "train_seconds": 1.0 * HOUR})
    worse = _part(chain_dir, "part1", 1, 0.78, root, 2_000_000, 2.0)
    chain.record(worse, chain_dir, "worse")
    table = json.loads(chain.TABLE.read_text())
    assert [(row["part"], row["kept"]) for row in table] == [(0, True), (1, False)]
    assert table[0]["sha256"] == root_sha and table[1]["parent_sha256"] == root_sha
    assert table[1]["chain_env_steps"] == 6_000_000 and table[1]["pooled_success"] == pytest.approx(0.78)
    assert chain.HEAD.exists() and not chain.BEST.exists()  # the head continues a part that is not better
    better = _part(chain_dir, "part2", 2, 0.85, root, 1_000_000, 2.0)  # from the root again: the best part so far
    chain.record(better, chain_dir, "better")
    assert load_policy(chain.BEST).meta["sha256"] == load_policy(better / "policy.npz").meta["sha256"]
    assert "kept" in capsys.readouterr().out
    rows = chain.table().splitlines()
    assert len(rows) == 2 + 3
    # spent: every part in the order it ran, the worse one included; the lineage total is 5 M
    assert "| 2 | 0 | 1.00 M | 7.00 M / 5.00 h | 85.0 / 85.0 / 85.0 / 85.0 |" in rows[-1] and rows[-1].endswith("| 85.00 | yes |")
    assert json.loads(chain.TABLE.read_text())[2]["chain_env_steps"] == 5_000_000
    out = chain_dir / "curve.png"
    chain.plot(out)
    assert out.stat().st_size > 0


def test_record_refuses_a_policy_without_a_parent(chain_dir):
    run = chain_dir / "scratch"
    _policy(run / "policy.npz", 0, {"rate": 0.5, "env_steps": 1, "train_seconds": 1.0})
    with pytest.raises(SystemExit, match="not a fine-tune"):
        chain.record(run, chain_dir, "")
