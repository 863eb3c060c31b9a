"""The run configuration of ``python -m train.sac`` / :func:`train.run.train`, and its presets.

One nested frozen dataclass, :class:`RunConfig`: the environment (:class:`EnvConfig`), the
trainer (:class:`TrainConfig`, with SAC's :class:`SACConfig` and the networks' input
features inside), the data (:class:`DataConfig`) and the budget (:class:`BudgetConfig`).
A preset is an instance; the command line derives one flag per field
(:mod:`mjx_multiarm.options`); ``config.json`` in a run directory is the instance
serialized, read back by ``--resume``. Adding a training option is adding one field, with
its default, help and check, to the class that owns it.
"""

from __future__ import annotations

import dataclasses

from mjx_multiarm.cli import parse_arms
from mjx_multiarm.env.observation import InputFeatures
from mjx_multiarm.env.reaching import EnvConfig
from mjx_multiarm.options import apply, option
from mjx_multiarm.tasks.generate import LAYOUTS
from train.agent import SACConfig
from train.trainer import TrainConfig


@dataclasses.dataclass(frozen=True)
class DataConfig:
    """Where the training and evaluation tasks and their experts come from."""

    arms: tuple[int, ...] = option((1,), "team sizes of generated tasks, e.g. 1 or 1-4", parse=parse_arms)
    layout: str = option("stratified", "base placement of generated training tasks: stratified over the paper's difficulty "
                                       "bins, or as the original code's training tasks (difficulty up to ~0.99); "
                                       "evaluation tasks stay stratified", choices=LAYOUTS)
    train_tasks: int = option(512, "generated training tasks")
    eval_count: int = option(128, "generated evaluation tasks")
    tasks: str | None = option(None, "training task dataset (.npz) instead of generated tasks")
    task_limit: int | None = option(None, "use only the first N tasks of --tasks (none: all)")
    experts: str | None = option(None, "expert file of --tasks (planned into the run directory if absent)")
    eval_tasks: str | None = option(None, "evaluation task dataset (.npz; default: generated)")

    def __post_init__(self):
        if not self.arms or min(self.arms) < 1:
            raise ValueError(f"DataConfig.arms must be team sizes >= 1, got {self.arms}")
        if self.layout not in LAYOUTS:
            raise ValueError(f"DataConfig.layout must be one of {LAYOUTS}, got {self.layout!r}")
        if self.tasks and self.layout != "stratified":
            raise ValueError("--layout places generated tasks; --tasks gives a file (generate it with "
                             "python -m mjx_multiarm.tasks generate --layout ...)")
        for name in ("train_tasks", "eval_count"):
            if getattr(self, name) < 1:
                raise ValueError(f"DataConfig.{name} must be >= 1, got {getattr(self, name)}")
        if self.task_limit is not None and (self.task_limit < 1 or not self.tasks):
            raise ValueError(f"DataConfig.task_limit={self.task_limit} takes the first N >= 1 tasks of a --tasks file")
        if self.experts and not self.tasks:
            raise ValueError("DataConfig.experts is the expert file of --tasks; generated tasks plan their own")


@dataclasses.dataclass(frozen=True)
class BudgetConfig:
    """When a run stops, how it saves, and how often it measures the deployed policy."""

    minutes: float = option(10.0, "stop after this much training time (evaluations and checkpoints not counted)")
    steps: int = option(10**9, "stop after this many environment steps")
    checkpoint_minutes: float = option(5.0, "minutes between checkpoints")
    buffer_checkpoint: bool = option(True, "checkpoints hold the replay buffer (--no-buffer-checkpoint: leave it out)")
    eval_minutes: float = option(1.0, "minutes of training between held-out evaluations of the deployed policy "
                                      "(mean actions, 2 cm / 0.1 rad; 0: only at the end)")
    eval_limit: int = option(128, "evaluation tasks of each held-out evaluation during training (the final one uses all)")

    def __post_init__(self):
        for name in ("minutes", "checkpoint_minutes", "eval_minutes"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"BudgetConfig.{name} must be >= 0, got {getattr(self, name)}")
        for name in ("steps", "eval_limit"):
            if getattr(self, name) < 1:
                raise ValueError(f"BudgetConfig.{name} must be >= 1, got {getattr(self, name)}")


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """Everything that defines a training run (defaults: the ``cpu`` preset)."""

    seed: int = option(0, "seed of the networks, environments and generated tasks")
    init: str | None = option(None, "fine-tune: start from this policy file or run directory (the actor, and the critics if "
                                    "the file carries them), curriculum at the parent's level; see train.finetune")
    env: EnvConfig = EnvConfig(max_steps=200)
    train: TrainConfig = TrainConfig(hindsight=1, sac=SACConfig(expert_bc=1.0, policy_average=5e-4))
    data: DataConfig = DataConfig()
    budget: BudgetConfig = BudgetConfig()

    def __post_init__(self):
        if self.train.hindsight and self.env.dynamic_targets:
            raise ValueError("hindsight relabelling needs static targets: --hindsight 0 with --dynamic-targets")


def without_expert(config: RunConfig) -> RunConfig:
    """The paper's no-expert ablation: no demonstrations, and the preset's expert terms
    (expert behaviour cloning, expert share, cloned start, prefill) go with them."""
    return apply(config, {"train.expert": False, "train.sac.expert_bc": 0.0, "train.expert_share": 0.0,
                          "train.sac.bc_start": 0, "train.expert_prefill": 0})


def behaviour_cloning(config: RunConfig) -> RunConfig:
    """The paper's behaviour-cloning ablation: the actor learns from the expert data only
    (no policy transitions stored, so nothing to relabel or to sample beside them)."""
    return apply(config, {"train.bc": True, "train.sac.expert_bc": 0.0, "train.hindsight": 0, "train.expert_share": 0.0,
                          "train.sac.bc_start": 0, "train.expert_prefill": 0})


#: Named configurations (``--preset``); every field can be overridden on the command line.
PRESETS = {
    # About 10-15 minutes on a 2-core CPU, single-arm tasks; hindsight goals, expert
    # behaviour cloning and an averaged deployed actor added to the original's SAC
    # (benchmarks/RESULTS.md).
    "cpu": RunConfig(),
    # The paper's hyperparameters (appendix): batch 4096, warm-up 20,000, replay 50,000, 1-4 arms.
    "paper": RunConfig(
        env=EnvConfig(max_steps=500),
        train=TrainConfig(num_envs=1024, updates_per_iteration=10, batch_size=4096, warmup=20_000, expert_replays=64,
                          expert_steps=128),
        data=DataConfig(arms=(1, 2, 3, 4), train_tasks=20_000, eval_count=1_000),
        budget=BudgetConfig(minutes=10**9, steps=700_000_000, eval_minutes=10.0, eval_limit=256)),
    # 1-4-arm teams on a 2-core CPU (issue 19: the best rung of the ablation ladder in
    # benchmarks/RESULTS.md "Teams"): the cpu recipe on 100,000 generated tasks with experts
    # (~5 minutes of precompute), a curriculum per team size, colliding arms restored during
    # training, a quarter of every batch from a separate expert buffer, the end effectors'
    # errors to their targets as network inputs; 4 hours, resumable.
    "team": RunConfig(
        env=EnvConfig(max_steps=200, end_on_collision=False),
        train=TrainConfig(hindsight=1, curriculum_by_team=True, expert_share=0.25,
                          sac=SACConfig(expert_bc=1.0, policy_average=5e-4, inputs=InputFeatures(goal=True))),
        data=DataConfig(arms=(1, 2, 3, 4), train_tasks=100_000, eval_count=512),
        budget=BudgetConfig(minutes=240.0, steps=10**10, eval_minutes=5.0)),
    # For tests and smoke checks: seconds.
    "tiny": RunConfig(
        env=EnvConfig(max_steps=20),
        train=TrainConfig(num_envs=4, rollout_steps=4, updates_per_iteration=2, batch_size=16, buffer_size=2048, warmup=8,
                          expert_replays=2, expert_steps=48, hindsight=1, sac=SACConfig(expert_bc=1.0, policy_average=0.1)),
        data=DataConfig(train_tasks=8, eval_count=4),
        budget=BudgetConfig(minutes=1.0, steps=400, eval_minutes=0.0)),
}
