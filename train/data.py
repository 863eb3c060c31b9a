"""A run's data: training and evaluation tasks (generated or from files), their experts,
the environments and the device task banks."""

from __future__ import annotations

import dataclasses
import pathlib

import numpy as np

from mjx_multiarm.env.reaching import EVAL_TOLERANCE, ReachingEnv
from mjx_multiarm.env.wrappers import TaskBank
from mjx_multiarm.expert.planner import PlannerConfig
from mjx_multiarm.expert.precompute import file_digest, precompute
from mjx_multiarm.expert.store import ExpertStore
from mjx_multiarm.tasks.dataset import load_tasks, save_tasks
from mjx_multiarm.tasks.generate import GenerationSpec, generate_dataset
from mjx_multiarm.tasks.types import Tasks, take
from train.config import RunConfig
from train.trainer import Demonstrations

#: Generated evaluation tasks use the run's seed plus this (never a training seed).
EVAL_SEED_OFFSET = 10_000


@dataclasses.dataclass
class RunData:
    """What a run trains and evaluates on."""

    env: ReachingEnv  # training environment (the curriculum's tolerances)
    eval_env: ReachingEnv  # evaluation: 2 cm / 0.1 rad, every collision ends the episode
    bank: TaskBank
    eval_bank: TaskBank
    heldout_bank: TaskBank  # the evaluation tasks of evaluations during training (budget.eval_limit)
    demos: Demonstrations | None


def _generated_tasks(path: pathlib.Path, arms, count: int, seed: int, workers: int, layout: str = "stratified"):
    """The run's generated tasks at ``path`` (made resumably in ``workers`` processes if absent)."""
    if not path.exists():
        spec = GenerationSpec(count=count, arm_counts=tuple(arms), mode="static", seed=seed, max_arms=max(arms), chunk_size=256,
                              layout=layout)
        generate_dataset(spec, path, workers=min(workers, spec.num_chunks))
    return load_tasks(path)[0]


def heldout_subset(tasks: Tasks, limit: int) -> Tasks:
    """Up to ``limit`` of ``tasks``, the same number of each team size (the first ones)."""
    sizes = np.unique(tasks.num_arms)
    per_team = max(1, limit // len(sizes))
    rows = np.concatenate([np.flatnonzero(tasks.num_arms == k)[:per_team] for k in sizes])
    return take(tasks, np.sort(rows))


def _check_experts_fit(store: ExpertStore, tasks_path: pathlib.Path, log) -> None:
    """Raise ValueError if the expert file records that it was planned for another task file
    than ``tasks_path`` (task ids repeat across files made with the same seed)."""
    planned_for = store.metadata.get("precompute", {}).get("tasks")
    if planned_for is None:
        log(f"warning: {store.path} records no task file checksum; its experts are trusted to be those of {tasks_path}")
    elif planned_for != file_digest(tasks_path):
        raise ValueError(f"{store.path} was planned for another task file ({store.metadata.get('tasks_file', 'unrecorded')}), "
                         f"not {tasks_path}: plan its experts with python -m mjx_multiarm.expert --tasks {tasks_path} --out FILE")


def prepare(config: RunConfig, run_dir: pathlib.Path, workers: int, log=print) -> RunData:
    """Tasks, experts (planned into ``run_dir`` where the configuration names no file),
    environments and task banks of a run; files already in ``run_dir`` are reused, so an
    interrupted preparation resumes."""
    data = config.data
    if data.tasks:
        tasks = load_tasks(data.tasks)[0]
        tasks_path = pathlib.Path(data.tasks)
        if data.task_limit:
            tasks = take(tasks, slice(0, data.task_limit))
            if config.train.expert and not data.experts:  # experts to plan: those of the subset only
                tasks_path = run_dir / "tasks.npz"
                if not tasks_path.exists():
                    save_tasks(tasks_path, tasks, {"subset_of": data.tasks, "first": data.task_limit})
    else:
        tasks_path = run_dir / "tasks.npz"
        log(f"generating {data.train_tasks} training tasks ({','.join(map(str, data.arms))} arms)...")
        tasks = _generated_tasks(tasks_path, data.arms, data.train_tasks, config.seed, workers, data.layout)
    if data.eval_tasks:
        eval_tasks = load_tasks(data.eval_tasks)[0]
    else:
        eval_tasks = _generated_tasks(run_dir / "eval_tasks.npz", sorted(set(tasks.num_arms.tolist())), data.eval_count,
                                      config.seed + EVAL_SEED_OFFSET, workers)
    max_arms = max(int(tasks.num_arms.max()), int(eval_tasks.num_arms.max()))
    env = ReachingEnv(max_arms, config.env)
    eval_env = ReachingEnv(max_arms, dataclasses.replace(config.env, tolerance=EVAL_TOLERANCE, end_on_collision=True,
                                                              collisions_end_at=0.0))
    bank = TaskBank.from_tasks(tasks, max_arms)
    demos = None
    if config.train.expert:
        experts = pathlib.Path(data.experts) if data.experts else run_dir / "tasks.experts"
        if not experts.exists():
            log(f"planning experts for {tasks.num_tasks} tasks ({workers} processes)...")
            precompute(tasks_path, experts, PlannerConfig(time_limit=30.0), seed=config.seed, workers=workers)
        store = ExpertStore(experts)
        _check_experts_fit(store, tasks_path, log)
        demos = Demonstrations.from_store(store, bank, env, config.train.expert_steps)
    heldout = heldout_subset(eval_tasks, config.budget.eval_limit)
    return RunData(env, eval_env, bank, TaskBank.from_tasks(eval_tasks, max_arms), TaskBank.from_tasks(heldout, max_arms), demos)
