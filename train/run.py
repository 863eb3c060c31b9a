"""The training API: :func:`train` runs (or resumes) a whole training run in a directory.

    from train.config import PRESETS
    from train.run import train

    result = train(PRESETS["tiny"], "runs/tiny")
    result.summary["success_rate"], result.policy       # held-out success, the deployed actor

A run directory receives ``config.json`` (the :class:`~train.config.RunConfig`),
``tasks.npz`` / ``eval_tasks.npz`` and the expert file where it generates them,
``metrics.csv`` (one row per iteration; held-out success per team size where the deployed
policy was evaluated), ``learning_curve.png``, ``checkpoints/`` (Orbax, the latest 3),
``policy.npz`` (the deployed actor and the twin critics, rewritten at every checkpoint),
``summary.json`` and, for a fine-tune (``config.init``, :mod:`train.finetune`),
``parent.json`` (the record of the policy it started from). SIGINT / SIGTERM stop the run
at the end of an iteration with a checkpoint (:class:`TrainingStopped`); a run directory
without a checkpoint yet (a failed or stopped start) is started again by the next call. A
run stops after ``budget.steps`` environment steps or ``budget.minutes`` of training,
whichever comes first; every ``budget.eval_minutes`` of training the deployed policy's
mean actions are evaluated on (up to ``budget.eval_limit`` of) the evaluation tasks at
2 cm / 0.1 rad, outside the training clock and without touching the training state, so
these evaluations change no training figure. At the end the deployed policy (mean actions,
as the paper's benchmark) and the training policy (sampled actions) are evaluated on every
evaluation task.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import os
import pathlib
import shutil
import signal
import sys
import threading
import time
from collections.abc import Callable

import jax
from flax import nnx

from mjx_multiarm.files import atomic_write
from mjx_multiarm.options import from_dict, leaves, to_dict, value_at
from mjx_multiarm.planner.policy import policy_env_settings
from mjx_multiarm.planner.policy_file import LoadedPolicy, load_policy, save_policy
from models.networks import widened
from train.agent import agent_from_parameters
from train.checkpoint import Checkpoints
from train.config import RunConfig
from train.data import prepare
from train.evaluation import evaluate_policy, policy_evaluator
from train.finetune import check_architecture, load_parent, parent_record, widens
from train.plots import plot_learning_curve
from train.relabel import CollisionRelabeller
from train.trainer import Trainer

CONFIG_FILE = "config.json"
PARENT_FILE = "parent.json"


@dataclasses.dataclass
class TrainResult:
    """What :func:`train` returns."""

    run_dir: pathlib.Path
    config: RunConfig
    policy: LoadedPolicy  # the deployed actor (``run_dir/policy.npz``)
    summary: dict  # as ``summary.json``
    metrics: list[dict]  # the rows of ``metrics.csv``


def load_config(path: str | os.PathLike) -> RunConfig:
    """The configuration of a run: ``path`` is its run directory (its ``config.json``) or a
    policy file it wrote (which records the configuration it was trained with).

    Raises FileNotFoundError if ``path`` is neither, ValueError if it holds no configuration
    this version reads."""
    path = pathlib.Path(path)
    if path.is_file():
        provenance = load_policy(path).meta["provenance"]
        if "config" not in provenance:
            raise ValueError(f"{path}: the policy file records no run configuration (written before train.config)")
        return from_dict(RunConfig, provenance["config"], f"{path} config")
    config_file = path / CONFIG_FILE
    if not config_file.is_file():
        raise FileNotFoundError(f"{path}: not a run directory (no {CONFIG_FILE})")
    try:
        return from_dict(RunConfig, json.loads(config_file.read_text()), str(config_file))
    except json.JSONDecodeError as error:
        raise ValueError(f"{config_file}: not JSON ({error})") from error


def _stderr(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def _megabytes(tree) -> str:
    """Size of a pytree's arrays, e.g. '52.3 MB' (0 for None)."""
    return f"{sum(x.nbytes for x in jax.tree.leaves(tree)) / 1e6:.1f} MB"


def _json_safe(value):
    """NaN (e.g. steps to success without a success) as null: strict JSON."""
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, float) and value != value:
        return None
    return value


def _write_metrics(path: pathlib.Path, rows: list[dict]) -> None:
    """``rows`` as CSV: columns in order of first appearance, missing values as nan."""
    header = list(dict.fromkeys(k for row in rows for k in row))
    lines = [",".join(header)] + [",".join(str(row.get(k, math.nan)) for k in header) for row in rows]
    atomic_write(path, lambda f: f.write(("\n".join(lines) + "\n").encode()))


def _read_metrics(path: pathlib.Path, last_iteration: int) -> list[dict]:
    """The rows of ``path`` up to ``last_iteration`` (a resumed run continues from there)."""
    if not path.exists():
        return []
    with path.open() as f:
        rows = [{k: float(v) for k, v in row.items()} for row in csv.DictReader(f)]
    return [row for row in rows if row["iteration"] <= last_iteration]


def _iteration_columns(metrics: dict) -> dict:
    """Metrics columns of a training iteration: curriculum, episodes, losses."""
    return {"level": int(metrics["level"]), "window_success": float(metrics["window_success"]),
            "episodes": int(metrics["ended"]), "successes": int(metrics["successes"]),
            **({"shielded_arm_steps": int(metrics["shielded_arm_steps"])} if "shielded_arm_steps" in metrics else {}),
            **{k: float(metrics[k]) for k in ("critic_loss", "actor_loss", "q", "entropy", "alpha", "bc_loss", "expert_bc_loss",
                                              "expert_bc_share") if k in metrics},
            **{k: float(v) for k, v in metrics.items() if k.startswith(("level_", "window_success_"))}}


def _heldout_columns(evaluation: dict) -> dict:
    """Metrics columns of a held-out evaluation: overall and per team size."""
    columns = {"heldout_success": evaluation["all"]["success_rate"], "heldout_collision": evaluation["all"]["collision_rate"]}
    for team, row in sorted(evaluation["by_team_size"].items()):
        columns[f"heldout_success_{team}"] = row["success_rate"]
    return columns


class TrainingStopped(Exception):
    """A run stopped by SIGINT / SIGTERM after saving a checkpoint (``--resume`` continues it)."""


class StopRequest:
    """SIGINT and SIGTERM ask the training loop to stop at the end of the iteration (which
    then saves a checkpoint) instead of killing it mid-step; a second signal stops at once."""

    def __init__(self):
        self.requested: str | None = None
        self.previous = {}
        if threading.current_thread() is threading.main_thread():  # handlers can only be set there
            for number in (signal.SIGINT, signal.SIGTERM):
                self.previous[number] = signal.signal(number, self._handle)

    def _handle(self, number, frame):
        if self.requested:
            raise KeyboardInterrupt
        self.requested = signal.Signals(number).name
        print(f"\n{self.requested}: stopping after this iteration and saving a checkpoint (again to stop at once)...",
              file=sys.stderr, flush=True)

    def release(self) -> None:
        """Restore the handlers the run found."""
        for number, handler in self.previous.items():
            signal.signal(number, handler)
        self.previous = {}


def _discard_stale_data(run_dir: pathlib.Path, saved: RunConfig, config: RunConfig, log) -> None:
    """Remove what a run stopped before its first checkpoint generated, where ``config``
    would generate it differently (other seed or data settings); the rest is reused."""
    if (saved.seed, saved.data) == (config.seed, config.data):
        return
    for name in ("tasks.npz", "eval_tasks.npz", "tasks.experts", PARENT_FILE):
        for path in (run_dir / name, run_dir / f"{name}.partial"):
            if path.is_dir():
                shutil.rmtree(path)
            elif path.exists():
                path.unlink()
            else:
                continue
            log(f"removed {path}: made for another configuration")


def _parent(config: RunConfig, run_dir: pathlib.Path, resume: bool) -> dict | None:
    """The record of the policy a fine-tune starts from (``PARENT_FILE`` in the run
    directory, written at the start, so that a resumed run records the same parent)."""
    if not config.init:
        return None
    path = run_dir / PARENT_FILE
    if resume and path.exists():
        return json.loads(path.read_text())
    parent = parent_record(*load_parent(config.init))
    atomic_write(path, lambda f: f.write(json.dumps(parent, indent=2).encode()))
    return parent


def train(config: RunConfig, run_dir: str | os.PathLike, *, resume: bool = False, workers: int | None = None,
          devices: int | None = None, progress: Callable[[dict], None] | None = None,
          log: Callable[[str], None] = _stderr) -> TrainResult:
    """Run (or with ``resume``, continue) a training run in ``run_dir``.

    ``config``: the run's configuration; on ``resume`` only its budget may differ from the
    run's ``config.json`` (the rest must match). ``workers``: processes generating tasks and
    planning experts (default: all cores). ``devices``: train data-parallel over this many
    local devices (default: all). ``progress(row)`` is called after every iteration with
    the iteration's metrics row plus ``env_steps_per_s`` and ``eta_minutes``; ``log``
    receives one-line messages.

    Raises ValueError for an inconsistent configuration or a run directory that does not
    fit (an existing run without ``resume``, a different configuration with it), and
    FileNotFoundError for missing task, expert or checkpoint files.
    """
    run_dir = pathlib.Path(run_dir)
    if workers is not None and workers < 1:
        raise ValueError(f"workers must be >= 1 (processes generating tasks and planning experts), got {workers}")
    workers = workers or os.cpu_count() or 1
    started = Checkpoints.exist(run_dir / "checkpoints")
    if resume and started:
        saved = load_config(run_dir)
        if dataclasses.replace(saved, budget=config.budget) != config:
            changed = [leaf.path for leaf in leaves(RunConfig) if value_at(config, leaf.path) != value_at(saved, leaf.path)]
            raise ValueError(f"{run_dir}: resuming changes {changed}; only the budget may change on resume")
    elif started:
        raise ValueError(f"{run_dir} already holds a run; resume it or use another run directory")
    elif (run_dir / CONFIG_FILE).exists():  # stopped before its first checkpoint: start again, keeping what still fits
        if resume:
            config = dataclasses.replace(load_config(run_dir), budget=config.budget)
        _discard_stale_data(run_dir, load_config(run_dir), config, log)
        log(f"{run_dir} was stopped before its first checkpoint: starting it again")
        resume = False
    elif resume:
        raise FileNotFoundError(f"{run_dir}: not a run directory (no {CONFIG_FILE})")
    run_dir.mkdir(parents=True, exist_ok=True)
    atomic_write(run_dir / CONFIG_FILE, lambda f: f.write(json.dumps(to_dict(config), indent=2, sort_keys=True).encode()))
    parent = _parent(config, run_dir, resume)

    data = prepare(config, run_dir, workers, log)
    chosen = jax.local_devices()[:devices] if devices else jax.local_devices()
    trainer = Trainer(data.env, data.bank, data.demos, config.train, chosen)
    budget = config.budget
    checkpoints = Checkpoints(run_dir / "checkpoints", keep=3, with_buffer=budget.buffer_checkpoint)
    state = trainer.init(jax.random.key(config.seed))
    if config.init and not resume:
        _, policy = load_parent(config.init)
        check_architecture(config, policy, config.init)
        if policy.env != policy_env_settings(data.env):
            raise ValueError(f"--init {config.init}: the policy was trained for environment settings {policy.env}, this run's "
                             f"are {policy_env_settings(data.env)}")
        actor = (widened(policy.actor, config.train.sac.components, config.train.sac.widen_weight or None) if widens(config, policy)
                 else policy.actor)
        agent = agent_from_parameters(jax.random.key(config.seed), config.train.sac, nnx.state(actor), policy.critic)
        state = trainer.place(state.replace(agent=agent))
        log(f"fine-tuning {parent['path']} ({parent['total_env_steps']:,} env steps in its chain; "
            f"{'actor and critics' if policy.critic is not None else 'actor only, fresh critics'}, "
            f"{f'widened into {actor.components} mixture components, ' if widens(config, policy) else ''}curriculum level "
            f"{config.train.start_level + 1}, actor frozen for {config.train.sac.actor_freeze} updates)")
    log(f"device memory: task bank {_megabytes(data.bank)} ({data.bank.size} tasks), demonstrations {_megabytes(data.demos)}, "
        f"replay buffer {_megabytes(state.buffer)}, expert buffer {_megabytes(state.expert_buffer)}, "
        f"evaluation tasks {_megabytes(data.eval_bank)}")
    elapsed, iteration = 0.0, 0
    if config.train.expert_prefill and not resume:
        log(f"replaying {config.train.expert_prefill} expert demonstrations into the buffer...")
        state = trainer.prefill(state, config.train.expert_prefill, config.seed)
    if resume:
        state, meta = checkpoints.restore(state, warn=log)
        state = trainer.place(state)
        elapsed, iteration = meta["train_seconds"], meta["iteration"]
        log(f"resumed {run_dir} at iteration {iteration}, {int(state.env_steps):,} environment steps")

    metrics_file = run_dir / "metrics.csv"
    rows = _read_metrics(metrics_file, iteration) if resume else []
    log(f"run directory {run_dir}; compiling the training step...")
    budget_s = budget.minutes * 60.0
    last_checkpoint = time.perf_counter()
    next_eval = (math.floor(elapsed / (60 * budget.eval_minutes)) + 1) * 60 * budget.eval_minutes if budget.eval_minutes else math.inf
    heldout = policy_evaluator(state.agent.actor_def, data.eval_env, data.heldout_bank)  # compiled once, at the first use
    start_steps, start_elapsed, start_clock = int(state.env_steps), elapsed, time.perf_counter() - elapsed

    saved_at = iteration if resume else None

    def save():
        nonlocal saved_at
        if saved_at == iteration:  # a checkpoint of this iteration is on disk already
            return
        saved_at = iteration
        meta = {"iteration": iteration, "train_seconds": elapsed, "env_steps": int(state.env_steps),
                "updates": int(state.agent.updates), "curriculum_level": int(trainer.level(state.curriculum)),
                "with_buffer": budget.buffer_checkpoint}
        checkpoints.save(iteration, state, meta)
        save_policy(run_dir / "policy.npz", state.agent.average_actor, config.train.sac.squash, policy_env_settings(data.env),
                    {"run_dir": str(run_dir), "config": to_dict(config), **meta, "parent": parent},
                    inputs=config.train.sac.inputs, critic=state.agent.critic, components=config.train.sac.components)
        _write_metrics(metrics_file, rows)

    relabeller = CollisionRelabeller(trainer, config.seed) if config.train.relabel else None
    first = True
    stop = StopRequest()
    try:
        while int(state.env_steps) < budget.steps and elapsed < budget_s and not stop.requested:
            clock = time.perf_counter()
            relabelled, relabel_stats = None, {}
            if relabeller is not None:
                state, relabelled, relabel_stats = relabeller(state, iteration)
            state, metrics = trainer.iteration(state, relabelled)
            metrics = jax.device_get(metrics)
            iteration += 1
            if first:  # the first call compiles: keep it out of the training clock
                start_clock, first = start_clock + (time.perf_counter() - clock), False
                start_steps = int(state.env_steps)
            elapsed = time.perf_counter() - start_clock
            steps = int(state.env_steps)
            row = {"iteration": iteration, "env_steps": steps, "updates": int(state.agent.updates), "seconds": round(elapsed, 3),
                   **_iteration_columns(metrics), **relabel_stats}
            if elapsed >= next_eval:
                clock = time.perf_counter()
                row.update(_heldout_columns(heldout(state.agent.average_actor)))
                start_clock += time.perf_counter() - clock  # evaluations stay out of the training clock
                next_eval += 60 * budget.eval_minutes
            rows.append(row)
            if progress is not None:
                rate = (steps - start_steps) / max(elapsed - start_elapsed, 1e-9)
                remaining = min((budget.steps - steps) / max(rate, 1e-9), budget_s - elapsed)
                progress({**row, "env_steps_per_s": rate, "eta_minutes": remaining / 60})
            if time.perf_counter() - last_checkpoint > budget.checkpoint_minutes * 60:
                save()
                last_checkpoint = time.perf_counter()
        save()
        checkpoints.close()
    finally:
        stop.release()
    if stop.requested:
        raise TrainingStopped(f"stopped by {stop.requested} at iteration {iteration} ({int(state.env_steps):,} env steps): "
                              f"checkpoint saved; continue with python -m train.sac --resume {run_dir}")
    log("evaluating the policy at 2 cm / 0.1 rad (mean actions, then sampled actions)...")
    evaluation = evaluate_policy(state.agent, data.eval_env, data.eval_bank)
    sampled = evaluate_policy(state.agent, data.eval_env, data.eval_bank, jax.random.key(config.seed + 1),
                              float(trainer.std_scale(state)))
    if rows:
        rows[-1].update(_heldout_columns(evaluation))
        _write_metrics(metrics_file, rows)
        plot_learning_curve(rows, run_dir / "learning_curve.png")
    env_rate = (int(state.env_steps) - start_steps) / max(elapsed - start_elapsed, 1e-9)
    summary = _json_safe({
        "env_steps": int(state.env_steps), "updates": int(state.agent.updates), "expert_steps": int(state.expert_steps),
        "train_seconds": elapsed, "env_steps_per_s": env_rate, "updates_per_s": int(state.agent.updates) / max(elapsed, 1e-9),
        "success_rate": evaluation["all"]["success_rate"], "evaluation": evaluation,
        "sampled_success_rate": sampled["all"]["success_rate"],
        "curriculum_level": int(trainer.level(state.curriculum)) + 1,
        "curriculum_levels_by_team": {int(t): int(state.curriculum.level[trainer.team_group[t - 1]]) + 1 for t in trainer.teams},
        "checkpoint": str(checkpoints.directory / str(iteration)),
        "run_dir": str(run_dir),
    })
    atomic_write(run_dir / "summary.json", lambda f: f.write(json.dumps(summary, indent=2).encode()))
    return TrainResult(run_dir, config, load_policy(run_dir / "policy.npz"), summary, rows)
