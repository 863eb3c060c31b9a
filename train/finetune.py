"""Fine-tuning: a run that starts from a trained policy (``python -m train.sac --init PATH``),
and the lineage a policy file records of the runs it came from.

A fine-tune takes the actor (and the twin critics where the file carries them) from a
policy file, fills a fresh replay buffer with its own rollouts and expert replays while
the actor stays frozen for ``train.sac.actor_freeze`` updates (a critic warm-up), and
starts the curriculum at the level the parent had reached. Its policy files record the
parent in ``provenance["parent"]``: the file's checksum, its own env steps and training
time, and the totals over the whole chain, the parent's own parent nested inside, so a
policy's whole training history can be read from its file (:func:`lineage`).
"""

from __future__ import annotations

import dataclasses
import os
import pathlib

from mjx_multiarm.options import apply, leaves, value_at
from mjx_multiarm.planner.policy_file import LoadedPolicy, load_policy

#: Critic warm-up of a fine-tune unless ``--actor-freeze`` says otherwise (updates).
DEFAULT_ACTOR_FREEZE = 2000


def policy_file_of(path: str | os.PathLike) -> pathlib.Path:
    """The policy file ``path`` names: the file itself, or a run directory's ``policy.npz``.

    Raises FileNotFoundError if it is neither."""
    path = pathlib.Path(path)
    if path.is_dir():
        path = path / "policy.npz"
        if not path.is_file():
            raise FileNotFoundError(f"{path.parent}: a directory without policy.npz (not a run directory, or one stopped before "
                                    "its first checkpoint)")
    elif not path.is_file():
        raise FileNotFoundError(f"--init {path}: no such policy file or run directory")
    return path


def parent_record(path: str | os.PathLike, policy: LoadedPolicy) -> dict:
    """What a fine-tune's policy files record of the policy file ``path`` it started from."""
    provenance = policy.provenance
    grandparent = provenance.get("parent")
    env_steps, seconds = int(provenance.get("env_steps", 0)), float(provenance.get("train_seconds", 0.0))
    return {"path": str(path), "sha256": policy.meta["sha256"], "env_steps": env_steps, "train_seconds": seconds,
            "updates": int(provenance.get("updates", 0)), "curriculum_level": provenance.get("curriculum_level"),
            "total_env_steps": env_steps + (grandparent["total_env_steps"] if grandparent else 0),
            "total_train_seconds": seconds + (grandparent["total_train_seconds"] if grandparent else 0.0),
            "parent": grandparent}


def lineage(provenance: dict) -> list[dict]:
    """The chain of parents a policy file's provenance records, nearest first (each
    without its own nested parent)."""
    chain, parent = [], provenance.get("parent")
    while parent:
        chain.append({k: v for k, v in parent.items() if k != "parent"})
        parent = parent.get("parent")
    return chain


def _architecture(policy: LoadedPolicy) -> dict:
    """The configuration leaves the policy file fixes: the actor's squash, input features and
    mixture components."""
    return {"train.sac.squash": policy.squash, "train.sac.components": policy.components,
            **{f"train.sac.inputs.{k}": v for k, v in dataclasses.asdict(policy.inputs).items()}}


def widens(config, policy: LoadedPolicy) -> bool:
    """Whether ``config`` fine-tunes the one-component ``policy`` as a mixture
    (:func:`models.networks.widened`)."""
    return policy.components == 1 and config.train.sac.components > 1


def check_architecture(config, policy: LoadedPolicy, path) -> None:
    """Raise ValueError if ``config``'s networks are not those of the policy file ``path``
    (a mixture of a one-component policy's copies is allowed: :func:`widens`)."""
    fixed = _architecture(policy)
    if widens(config, policy):
        del fixed["train.sac.components"]
    wrong = {k: v for k, v in fixed.items() if value_at(config, k) != v}
    if wrong:
        names = {leaf.path: leaf.name for leaf in leaves(type(config))}
        flags = ", ".join(f"--{names[k].replace('_', '-')} {int(v) if isinstance(v, bool) else v}" for k, v in wrong.items())
        raise ValueError(f"--init {path}: the policy's networks differ from this configuration's ({flags} would match)")


def fine_tune_config(config, policy: LoadedPolicy, given: set[str]):
    """``config`` for a fine-tune of ``policy``: its network architecture taken from the file,
    the curriculum started at the level the parent reached, and a critic warm-up, except
    where the command line ``given`` those settings (an architecture that conflicts with the
    file raises ValueError)."""
    path = config.init
    changes = {k: v for k, v in _architecture(policy).items() if k not in given}
    check_architecture(apply(config, changes), policy, path)
    level = policy.provenance.get("curriculum_level")
    if "train.start_level" not in given and level is not None:
        changes["train.start_level"] = int(level)
    if "train.sac.actor_freeze" not in given:
        changes["train.sac.actor_freeze"] = DEFAULT_ACTOR_FREEZE
    return apply(config, changes)


def load_parent(path: str | os.PathLike) -> tuple[pathlib.Path, LoadedPolicy]:
    """The policy file ``--init PATH`` names and the policy in it."""
    path = policy_file_of(path)
    return path, load_policy(path)
