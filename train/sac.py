"""Train the decentralized multi-arm planner with SAC, expert demonstrations and a curriculum.

    python -m train.sac                                   # default CPU preset, embedded defaults
    python -m train.sac --preset paper --run-dir runs/paper
    python -m train.sac --arms 1-4 --minutes 60 --run-dir runs/four
    python -m train.sac --resume runs/four                # continue a killed run exactly
    python -m train.sac --tasks train.npz --experts train.experts --run-dir runs/big
    python -m train.sac --tasks train.npz --experts train.experts --train-tasks 10000   # its first 10,000

Without ``--tasks`` the run generates its training and evaluation tasks and plans their
experts itself (a small set; seconds to a minute), so it needs no precompute step. The
run directory receives ``config.json``, ``tasks.npz`` / ``eval_tasks.npz``, the expert
file, ``metrics.csv``, ``learning_curve.png``, ``checkpoints/`` (Orbax, the latest 3) and
``summary.json``, and ``policy.npz`` (the actor alone, for :class:`mjx_multiarm.Planner`
and ``eval.benchmark``; rewritten at every checkpoint). A run stops after ``--steps``
environment steps or ``--minutes`` of training, whichever comes first, then evaluates the
policy's mean actions (``success_rate``, as the paper's benchmark) and its sampled actions
(``sampled_success_rate``, the training policy) on the evaluation tasks at 2 cm / 0.1 rad.

The ``cpu`` (and ``tiny``) preset adds three things to the original's SAC: every policy
transition is stored a second time relabelled with a hindsight goal (``--hindsight 1``),
the actor imitates the expert where the critic prefers it (``--expert-bc 1``), and the
deployed policy (evaluation, ``policy.npz``) is a Polyak average of the actor's parameters
(``--policy-average 5e-4``); ``paper`` is the original's algorithm. ``--hindsight 0
--expert-bc 0 --policy-average 0`` gives the original on any preset.

Ablations (paper section 5): ``--no-expert``, ``--bc`` (behaviour cloning on the expert
data only; both drop the preset's expert term), ``--reward selfish``, ``--observe self``
(individualistic observations).
``--sac standard`` uses tanh-squashed samples and a learned temperature instead of the
original's bounded-variance Gaussian with fixed temperature 0.001.

Options for teams (each off in ``paper`` and ``cpu``; measured in benchmarks/RESULTS.md,
"Teams: ablation ladder"): ``--curriculum-by-team 1`` (a curriculum level per team size),
``--collisions restore`` (a training collision puts the colliding arms back, penalized, and
the episode goes on; evaluation always ends it), ``--expert-share F`` (a fraction F of
every batch from a separate buffer of expert transitions), ``--rotations 1`` (orientations
enter the networks as rotation-matrix columns), ``--goal-features 1`` (the networks see each
end effector's error to its target besides the two poses), ``--bc-start N`` (the first N updates clone
the expert transitions of each batch, then SAC), ``--expert-prefill M`` (the experts of M
training tasks replayed into the buffer before the first iteration).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import os
import pathlib
import sys
import time

import jax

from mjx_multiarm.cli import parse_arms
from mjx_multiarm.env.observation import InputFeatures
from mjx_multiarm.env.reaching import EVAL_TOLERANCE, EnvConfig, ReachingEnv
from mjx_multiarm.env.wrappers import TaskBank
from mjx_multiarm.expert.planner import PlannerConfig
from mjx_multiarm.expert.precompute import precompute
from mjx_multiarm.expert.store import ExpertStore
from mjx_multiarm.files import atomic_write
from mjx_multiarm.planner.policy import policy_env_settings
from mjx_multiarm.planner.policy_file import save_policy
from mjx_multiarm.tasks.dataset import load_tasks, save_tasks
from mjx_multiarm.tasks.generate import LAYOUTS, GenerationSpec, generate_dataset
from mjx_multiarm.tasks.types import take
from train.agent import SACConfig
from train.checkpoint import Checkpoints
from train.curriculum import LEVELS
from train.evaluation import evaluate_policy
from train.trainer import Demonstrations, TrainConfig, Trainer


@dataclasses.dataclass(frozen=True)
class Preset:
    """A named run configuration (every field can be overridden on the command line)."""

    arms: tuple[int, ...]
    train_tasks: int
    eval_tasks: int
    episode_steps: int
    expert_steps: int  # longest expert sequence kept (longer ones are cut)
    num_envs: int
    rollout_steps: int
    updates_per_iteration: int
    batch_size: int
    buffer_size: int
    warmup: int
    expert_replays: int
    minutes: float
    steps: int
    alpha: float | str | None = None  # entropy temperature, "auto" (learned) or None: the SAC variant's default
    target_entropy: float = SACConfig.target_entropy
    gamma: float = SACConfig.gamma
    noise_decay: float = 0.0  # curriculum noise schedule (TrainConfig.noise_decay)
    expert_bc: float = 0.0  # Q-filtered expert behaviour cloning in the actor loss (SACConfig.expert_bc)
    hindsight: int = 0  # hindsight-relabelled copies of each policy transition (TrainConfig.hindsight)
    shaping: float = 0.0  # potential-based reward shaping (EnvConfig.shaping)
    policy_average: float = 0.0  # Polyak rate of the deployed average actor (SACConfig.policy_average)
    curriculum_by_team: bool = False  # one curriculum level per team size (TrainConfig.curriculum_by_team)
    collisions: str = "end"  # training collisions: "end" the episode (the paper) or "restore" the arm (EnvConfig.end_on_collision)
    expert_share: float = 0.0  # fraction of each batch from a separate expert buffer (TrainConfig.expert_share)
    rotations: bool = False  # orientations enter the networks as rotation-matrix columns (InputFeatures.rotations)
    goal_features: bool = False  # the networks see each end effector's error to its target (InputFeatures.goal)
    bc_start: int = 0  # updates of behaviour-cloned start before SAC's actor step (SACConfig.bc_start)
    expert_prefill: int = 0  # expert demonstrations replayed into the buffer before training (Trainer.prefill)
    expert_buffer: int = 50_000  # rows of the separate expert buffer (TrainConfig.expert_buffer)


PRESETS = {
    # About 10-15 minutes on a 2-core CPU, single-arm tasks; hindsight goals, expert
    # behaviour cloning and an averaged deployed actor added to the original's SAC
    # (benchmarks/RESULTS.md).
    "cpu": Preset(arms=(1,), train_tasks=512, eval_tasks=128, episode_steps=200, expert_steps=64, num_envs=64,
                  rollout_steps=16, updates_per_iteration=16, batch_size=256, buffer_size=50_000, warmup=2_000,
                  expert_replays=8, minutes=10.0, steps=10**9, expert_bc=1.0, hindsight=1, policy_average=5e-4),
    # The paper's hyperparameters (appendix): batch 4096, warm-up 20,000, replay 50,000, 1-4 arms.
    "paper": Preset(arms=(1, 2, 3, 4), train_tasks=20_000, eval_tasks=1_000, episode_steps=500, expert_steps=128,
                    num_envs=1024, rollout_steps=16, updates_per_iteration=10, batch_size=4096, buffer_size=50_000,
                    warmup=20_000, expert_replays=64, minutes=10**9, steps=700_000_000),
    # 1-4-arm teams on a 2-core CPU (issue 19: the best rung of the ablation ladder in
    # benchmarks/RESULTS.md "Teams"): the cpu recipe on 100,000 generated tasks with experts
    # (~5 minutes of precompute), a curriculum per team size, colliding arms restored during
    # training, a quarter of every batch from a separate expert buffer, the end effectors'
    # errors to their targets as network inputs; 4 hours, resumable.
    "team": Preset(arms=(1, 2, 3, 4), train_tasks=100_000, eval_tasks=512, episode_steps=200, expert_steps=64, num_envs=64,
                   rollout_steps=16, updates_per_iteration=16, batch_size=256, buffer_size=50_000, warmup=2_000, expert_replays=8,
                   minutes=240.0, steps=10**10, expert_bc=1.0, hindsight=1, policy_average=5e-4, curriculum_by_team=True,
                   collisions="restore", expert_share=0.25, goal_features=True),
    # For tests and smoke checks: seconds.
    "tiny": Preset(arms=(1,), train_tasks=8, eval_tasks=4, episode_steps=20, expert_steps=48, num_envs=4, rollout_steps=4,
                   updates_per_iteration=2, batch_size=16, buffer_size=2048, warmup=8, expert_replays=2, minutes=1.0, steps=400,
                   expert_bc=1.0, hindsight=1, policy_average=0.1),
}


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m train.sac", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", choices=sorted(PRESETS), default="cpu", help="named configuration (default cpu)")
    parser.add_argument("--run-dir", type=pathlib.Path, default=None, help="output directory (default runs/<preset>-<time>)")
    parser.add_argument("--resume", type=pathlib.Path, default=None, help="continue the run in this directory from its latest checkpoint")
    parser.add_argument("--steps", type=int, help="stop after this many environment steps")
    parser.add_argument("--minutes", type=float, help="stop after this much training time")
    parser.add_argument("--arms", type=parse_arms, help="team sizes of generated tasks, e.g. 1 or 1-4")
    parser.add_argument("--layout", choices=LAYOUTS, default="stratified", help="base placement of generated training tasks: "
                        "stratified over the paper's difficulty bins (default) or as the original code's training tasks "
                        "(difficulty up to ~0.99); evaluation tasks stay stratified")
    parser.add_argument("--tasks", type=pathlib.Path, help="training task dataset (.npz) instead of generated tasks")
    parser.add_argument("--experts", type=pathlib.Path, help="expert file of --tasks (planned into the run dir if absent)")
    parser.add_argument("--eval-tasks", type=pathlib.Path, help="evaluation task dataset (default: generated)")
    for name in ("train_tasks", "eval_count", "num_envs", "rollout_steps", "updates_per_iteration", "batch_size", "buffer_size", "warmup",
                 "expert_replays", "episode_steps"):
        parser.add_argument("--" + name.replace("_", "-"), dest=name, type=int, help=f"override the preset's {name.replace('_', ' ')}")
    parser.add_argument("--no-expert", action="store_true", help="ablation: no expert demonstrations")
    parser.add_argument("--bc", action="store_true", help="ablation: behaviour cloning on the expert data only")
    parser.add_argument("--reward", choices=["team", "selfish"], default="team", help="reward (selfish: ablation)")
    parser.add_argument("--observe", choices=["neighbours", "self"], default="neighbours", help="self: individualistic ablation")
    parser.add_argument("--sac", choices=["original", "standard"], default="original", help="policy parametrization and temperature")
    parser.add_argument("--alpha", type=_alpha, help="entropy temperature: a number (fixed) or 'auto' (learned; default: the preset's)")
    parser.add_argument("--target-entropy", type=float, help="target policy entropy of a learned temperature (default -6)")
    parser.add_argument("--gamma", type=float, help="discount factor (default: the preset's)")
    parser.add_argument("--noise-decay", type=float, help="shrink the policy's standard-deviation bound with the curriculum: "
                        "x (eps_p / 10 cm) ** P (default: the preset's; 0 = the original's fixed bound)")
    parser.add_argument("--expert-bc", type=float, help="weight of a behaviour-cloning term on the expert transitions in the actor "
                        "loss, applied where the critic rates the expert's action above the policy's (Nair et al. 2018; "
                        "default: the preset's; 0 = the original's pure SAC)")
    parser.add_argument("--hindsight", type=int, help="add this many copies of every policy transition relabelled with a "
                        "hindsight goal (the pose an arm reached later in the episode; Andrychowicz et al. 2017; default: "
                        "the preset's; 0 = the original's replay)")
    parser.add_argument("--shaping", type=float, help="add potential-based reward shaping: every step pays K x the "
                        "decrease of (position error in m + 0.2 x orientation error in rad) (Ng et al. 1999; default: the "
                        "preset's; 0 = the paper's reward)")
    parser.add_argument("--policy-average", type=float, help="deploy (evaluate and export) a Polyak average of the "
                        "actor's parameters, updated at this rate per gradient update (default: the preset's; 0 = the "
                        "latest actor, as the original)")
    parser.add_argument("--no-curriculum", action="store_true", help="train at 2 cm / 0.1 rad from the start")
    parser.add_argument("--curriculum-by-team", type=_flag, help="1: every team size has its own curriculum level, "
                        "graduating on its own episodes; 0: one level for all (the original; default: the preset's)")
    parser.add_argument("--collisions", choices=["end", "restore"], help="during training, a collision ends the episode "
                        "(the original) or puts the colliding arms back with the collision penalty and goes on "
                        "(default: the preset's; evaluation always ends it)")
    parser.add_argument("--rotations", type=_flag, help="1: the networks see every orientation as two rotation-matrix "
                        "columns (continuous) instead of a sign-canonical quaternion (0, the original; default: the preset's)")
    parser.add_argument("--goal-features", type=_flag, help="1: the networks see each end effector's position and "
                        "rotation error to its target besides the two poses (0, the original; default: the preset's)")
    parser.add_argument("--bc-start", type=int, help="the first N updates train the actor by cloning the batch's expert "
                        "transitions (the critics learn meanwhile), then SAC takes over (default: the preset's; 0 = none)")
    parser.add_argument("--expert-prefill", type=int, help="replay the experts of this many random training tasks into "
                        "the buffer before the first iteration (default: the preset's; 0 = none, as the original)")
    parser.add_argument("--expert-buffer-size", dest="expert_buffer", type=int, help="rows of the expert buffer of "
                        "--expert-share (default: the preset's)")
    parser.add_argument("--expert-share", type=float, help="draw this fraction of every batch from a separate buffer of "
                        "expert transitions (default: the preset's; 0 = one buffer for all, the original)")
    parser.add_argument("--checkpoint-minutes", type=float, default=5.0, help="minutes between checkpoints (default 5)")
    parser.add_argument("--no-buffer-checkpoint", action="store_true", help="leave the replay buffer out of checkpoints")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="processes planning experts (default: all cores)")
    parser.add_argument("--devices", type=int, default=None, help="data-parallel over this many local devices (default: all)")
    parser.add_argument("--json", action="store_true", help="end with one JSON line")
    return parser


def _flag(text: str) -> bool:
    if text not in ("0", "1"):
        raise argparse.ArgumentTypeError(f"expected 0 or 1, got {text!r}")
    return text == "1"


def _alpha(text: str) -> float | str:
    if text == "auto":
        return text
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive number or 'auto', got {text!r}") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"the temperature must be positive, got {text}")
    return value


def _settings(args) -> dict:
    """The run's configuration as JSON data (stored in config.json, reused by --resume)."""
    preset = dataclasses.asdict(PRESETS[args.preset])
    if args.no_expert or args.bc:  # ablations of the expert data: the preset's expert term goes with it
        preset["expert_bc"] = 0.0
    if args.bc:  # behaviour cloning stores no policy transitions to relabel
        preset["hindsight"] = 0
    if args.no_expert or args.bc:  # no policy transitions to sample beside (bc) / no experts (no-expert)
        preset["expert_share"], preset["bc_start"], preset["expert_prefill"] = 0.0, 0, 0
    overrides = {"train_tasks": args.train_tasks, "eval_tasks": args.eval_count, "num_envs": args.num_envs,
                 "rollout_steps": args.rollout_steps, "updates_per_iteration": args.updates_per_iteration,
                 "batch_size": args.batch_size, "buffer_size": args.buffer_size, "warmup": args.warmup, "expert_replays": args.expert_replays,
                 "episode_steps": args.episode_steps, "steps": args.steps, "minutes": args.minutes,
                 "arms": list(args.arms) if args.arms else None, "alpha": args.alpha, "target_entropy": args.target_entropy,
                 "gamma": args.gamma, "noise_decay": args.noise_decay, "expert_bc": args.expert_bc,
                 "hindsight": args.hindsight, "shaping": args.shaping,
                 "policy_average": args.policy_average, "curriculum_by_team": args.curriculum_by_team,
                 "collisions": args.collisions, "expert_share": args.expert_share, "rotations": args.rotations,
                 "goal_features": args.goal_features,
                 "bc_start": args.bc_start, "expert_prefill": args.expert_prefill, "expert_buffer": args.expert_buffer}
    preset.update({k: v for k, v in overrides.items() if v is not None})
    preset["arms"] = list(preset["arms"])
    return {
        "preset": args.preset, **preset, "seed": args.seed, "expert": not args.no_expert, "bc": args.bc, "reward": args.reward,
        "observe": args.observe, "sac": args.sac, "curriculum": not args.no_curriculum, "tasks": str(args.tasks) if args.tasks else None,
        "task_limit": args.train_tasks if args.tasks else None, "layout": args.layout,
        "experts": str(args.experts) if args.experts else None, "eval_tasks_file": str(args.eval_tasks) if args.eval_tasks else None,
        "with_buffer": not args.no_buffer_checkpoint, "checkpoint_minutes": args.checkpoint_minutes,
    }


def _megabytes(tree) -> str:
    """Size of a pytree's arrays, e.g. '52.3 MB' (0 for None)."""
    return f"{sum(x.nbytes for x in jax.tree.leaves(tree)) / 1e6:.1f} MB"


def _generated_tasks(path: pathlib.Path, arms, count: int, seed: int, workers: int, layout: str = "stratified"):
    """The run's generated tasks at ``path`` (made resumably in ``workers`` processes if absent)."""
    if not path.exists():
        spec = GenerationSpec(count=count, arm_counts=tuple(arms), mode="static", seed=seed, max_arms=max(arms), chunk_size=256,
                              layout=layout)
        generate_dataset(spec, path, workers=min(workers, spec.num_chunks))
    return load_tasks(path)[0]


def _prepare(run_dir: pathlib.Path, settings: dict, env_config: EnvConfig, workers: int, log):
    """Training and evaluation tasks, the expert file, environments."""
    arms = settings["arms"]
    if settings["tasks"]:
        tasks = load_tasks(settings["tasks"])[0]
        tasks_path = pathlib.Path(settings["tasks"])
        if settings.get("task_limit"):  # --train-tasks N with --tasks: the file's first N tasks
            tasks = take(tasks, slice(0, settings["task_limit"]))
            if settings["expert"] and not settings["experts"]:  # experts to plan: those of the subset only
                tasks_path = run_dir / "tasks.npz"
                if not tasks_path.exists():
                    save_tasks(tasks_path, tasks, {"subset_of": settings["tasks"], "first": settings["task_limit"]})
    else:
        tasks_path = run_dir / "tasks.npz"
        log(f"generating {settings['train_tasks']} training tasks ({','.join(map(str, arms))} arms)...")
        tasks = _generated_tasks(tasks_path, arms, settings["train_tasks"], settings["seed"], workers, settings.get("layout", "stratified"))
    if settings["eval_tasks_file"]:
        eval_tasks = load_tasks(settings["eval_tasks_file"])[0]
    else:
        eval_tasks = _generated_tasks(run_dir / "eval_tasks.npz", sorted(set(tasks.num_arms.tolist())), settings["eval_tasks"],
                                      settings["seed"] + 10_000, workers)
    max_arms = max(int(tasks.num_arms.max()), int(eval_tasks.num_arms.max()))
    store = None
    if settings["expert"]:
        experts = pathlib.Path(settings["experts"]) if settings["experts"] else run_dir / "tasks.experts"
        if not experts.exists():
            log(f"planning experts for {tasks.num_tasks} tasks ({workers} processes)...")
            precompute(tasks_path, experts, PlannerConfig(time_limit=30.0), seed=settings["seed"], workers=workers)
        store = ExpertStore(experts)
    env = ReachingEnv(max_arms, env_config)
    eval_env = ReachingEnv(max_arms, dataclasses.replace(env_config, tolerance=EVAL_TOLERANCE, end_on_collision=True))
    bank = TaskBank.from_tasks(tasks, max_arms)
    demos = Demonstrations.from_store(store, bank, env, settings["expert_steps"]) if store else None
    return env, eval_env, bank, TaskBank.from_tasks(eval_tasks, max_arms), demos


def _env_config(settings: dict) -> EnvConfig:
    """The training environment's configuration (evaluation differs in tolerance and ends every
    episode on a collision)."""
    return EnvConfig(max_steps=settings["episode_steps"], reward=settings["reward"], shaping=settings.get("shaping", 0.0),
                     neighbour_radius=0.0 if settings["observe"] == "self" else EnvConfig().neighbour_radius,
                     end_on_collision=settings.get("collisions", "end") == "end")


def _train_config(settings: dict) -> TrainConfig:
    standard = settings["sac"] == "standard"
    alpha = settings.get("alpha") if settings.get("alpha") is not None else ("auto" if standard else SACConfig.alpha)
    learned = alpha == "auto"
    return TrainConfig(
        num_envs=settings["num_envs"], rollout_steps=settings["rollout_steps"], updates_per_iteration=settings["updates_per_iteration"],
        batch_size=settings["batch_size"], buffer_size=settings["buffer_size"], warmup=settings["warmup"], expert=settings["expert"],
        expert_replays=settings["expert_replays"], bc=settings["bc"], curriculum=settings["curriculum"],
        noise_decay=settings.get("noise_decay", 0.0), hindsight=settings.get("hindsight", 0),
        curriculum_by_team=settings.get("curriculum_by_team", False), expert_share=settings.get("expert_share", 0.0),
        expert_buffer=settings.get("expert_buffer", TrainConfig.expert_buffer),
        sac=SACConfig(squash=standard, learn_alpha=learned, alpha=SACConfig.alpha if learned else alpha,
                      target_entropy=settings.get("target_entropy", SACConfig.target_entropy), gamma=settings.get("gamma", SACConfig.gamma),
                      expert_bc=settings.get("expert_bc", 0.0), policy_average=settings.get("policy_average", 0.0),
                      inputs=InputFeatures(rotations=settings.get("rotations", False), goal=settings.get("goal_features", False)),
                      bc_start=settings.get("bc_start", 0)),
    )


def _plot(rows: list[dict], path: pathlib.Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = [r["env_steps"] for r in rows]
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(7, 6), sharex=True)
    top.plot(steps, [r["window_success"] for r in rows], label="success, latest 100 episodes (current level)")
    top.set_ylabel("success rate")
    top.set_ylim(-0.02, 1.02)
    top.legend(loc="lower right")
    teams = sorted(int(k[len("level_"):]) for k in rows[0] if k.startswith("level_"))
    if teams:
        for team in teams:
            bottom.plot(steps, [r[f"level_{team}"] + 1 for r in rows], label=f"{team} arm{'s' if team > 1 else ''}")
        bottom.legend(loc="upper left")
    else:
        bottom.plot(steps, [r["level"] + 1 for r in rows], color="tab:orange")
    bottom.set_ylabel("curriculum level")
    bottom.set_xlabel("environment steps")
    fig.suptitle("train.sac learning curve")
    fig.tight_layout()
    atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=100))
    plt.close(fig)


def _json_safe(value):
    """NaN (e.g. steps to success without a success) as null: strict JSON."""
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, float) and value != value:
        return None
    return value


def _log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def _progress(line: str) -> None:
    """Rewrite the live progress line on stderr."""
    print(line, end="", file=sys.stderr, flush=True)


def main(argv=None) -> None:
    args = _parser().parse_args(argv)
    if args.resume:
        run_dir = args.resume
        config_file = run_dir / "config.json"
        if not config_file.is_file():
            sys.exit(f"error: {run_dir}: not a run directory (no config.json)")
        settings = json.loads(config_file.read_text())
        if args.steps is not None:
            settings["steps"] = args.steps
        if args.minutes is not None:
            settings["minutes"] = args.minutes
    else:
        if args.tasks and args.layout != "stratified":
            sys.exit("error: --layout places generated tasks; --tasks gives a file (generate it with "
                     "python -m mjx_multiarm.tasks generate --layout ...)")
        settings = _settings(args)
        run_dir = args.run_dir or pathlib.Path("runs") / f"{args.preset}-{time.strftime('%Y%m%d-%H%M%S')}"
    try:
        # inconsistent flags fail here, before a run directory or experts exist
        env_config, config = _env_config(settings), _train_config(settings)
    except ValueError as error:
        sys.exit(f"error: {error}")
    if not args.resume:
        if (run_dir / "config.json").exists():
            sys.exit(f"error: {run_dir} already holds a run; use --resume {run_dir} or another --run-dir")
        run_dir.mkdir(parents=True, exist_ok=True)
        atomic_write(run_dir / "config.json", lambda f: f.write(json.dumps(settings, indent=2, sort_keys=True).encode()))

    try:
        env, eval_env, bank, eval_bank, demos = _prepare(run_dir, settings, env_config, args.workers, _log)
    except (ValueError, FileNotFoundError) as error:
        sys.exit(f"error: {error}")
    devices = jax.local_devices()[: args.devices] if args.devices else jax.local_devices()
    try:
        trainer = Trainer(env, bank, demos, config, devices)
    except ValueError as error:
        sys.exit(f"error: {error}")
    checkpoints = Checkpoints(run_dir / "checkpoints", keep=3, with_buffer=settings["with_buffer"])
    state = trainer.init(jax.random.key(settings["seed"]))
    _log(f"device memory: task bank {_megabytes(bank)} ({bank.size} tasks), demonstrations {_megabytes(demos)}, "
         f"replay buffer {_megabytes(state.buffer)}, expert buffer {_megabytes(state.expert_buffer)}, "
         f"evaluation tasks {_megabytes(eval_bank)}")
    elapsed, iteration = 0.0, 0
    if settings.get("expert_prefill") and not args.resume:
        _log(f"replaying {settings['expert_prefill']} expert demonstrations into the buffer...")
        try:
            state = trainer.prefill(state, settings["expert_prefill"], settings["seed"])
        except ValueError as error:
            sys.exit(f"error: {error}")
    if args.resume:
        try:
            state, meta = checkpoints.restore(state)
        except (ValueError, FileNotFoundError) as error:
            sys.exit(f"error: {error}")
        state = trainer.place(state)
        elapsed, iteration = meta["train_seconds"], meta["iteration"]
        _log(f"resumed {run_dir} at iteration {iteration}, {int(state.env_steps):,} environment steps")

    metrics_file = run_dir / "metrics.csv"
    rows = list(csv.DictReader(metrics_file.open())) if metrics_file.exists() and args.resume else []
    rows = [{k: float(v) for k, v in r.items()} for r in rows if float(r["iteration"]) <= iteration]
    _log(f"run directory {run_dir}; compiling the training step...")
    budget_s = settings["minutes"] * 60.0
    last_checkpoint = last_print = time.perf_counter()
    start_steps, start_elapsed, start_clock = int(state.env_steps), elapsed, time.perf_counter() - elapsed

    def save():
        meta = {"iteration": iteration, "train_seconds": elapsed, "env_steps": int(state.env_steps),
                "updates": int(state.agent.updates), "curriculum_level": int(trainer.level(state.curriculum)),
                "with_buffer": settings["with_buffer"]}
        checkpoints.save(iteration, state, meta)
        save_policy(run_dir / "policy.npz", state.agent.average_actor, trainer.config.sac.squash, policy_env_settings(env),
                    {"run_dir": str(run_dir), "settings": settings, **meta}, inputs=trainer.config.sac.inputs)
        header = list(rows[0]) if rows else []
        atomic_write(metrics_file, lambda f: f.write((",".join(header) + "\n" + "".join(",".join(str(r[k]) for k in header) + "\n" for r in rows)).encode()))

    first = True
    while int(state.env_steps) < settings["steps"] and elapsed < budget_s:
        clock = time.perf_counter()
        state, metrics = trainer.iteration(state)
        metrics = jax.device_get(metrics)
        iteration += 1
        if first:  # the first call compiles: keep it out of the training clock
            start_clock, first = start_clock + (time.perf_counter() - clock), False
            start_steps = int(state.env_steps)
        elapsed = time.perf_counter() - start_clock
        steps = int(state.env_steps)
        rows.append({"iteration": iteration, "env_steps": steps, "updates": int(state.agent.updates), "seconds": round(elapsed, 3),
                     "level": int(metrics["level"]), "window_success": float(metrics["window_success"]),
                     "episodes": int(metrics["ended"]), "successes": int(metrics["successes"]),
                     **{k: float(metrics[k]) for k in ("critic_loss", "actor_loss", "q", "entropy", "alpha", "bc_loss", "expert_bc_loss",
                                                       "expert_bc_share") if k in metrics},
                     **{k: float(v) for k, v in metrics.items() if k.startswith(("level_", "window_success_"))}})
        now = time.perf_counter()
        if now - last_print > 2.0:
            rate = (steps - start_steps) / max(elapsed - start_elapsed, 1e-9)
            remaining = min((settings["steps"] - steps) / max(rate, 1e-9), budget_s - elapsed)
            eps_p, eps_r = LEVELS[int(metrics["level"])]
            _progress(f"\r{steps:>11,} env steps {rate:8,.0f}/s | {int(state.agent.updates):>8,} updates | level {int(metrics['level']) + 1}/{len(LEVELS)} "
                 f"({100 * eps_p:.1f} cm, {eps_r:.2f} rad) success {float(metrics['window_success']):5.1%} | ETA {remaining / 60:5.1f} min")
            last_print = now
        if now - last_checkpoint > settings["checkpoint_minutes"] * 60:
            save()
            last_checkpoint = now
    _log("")
    save()
    checkpoints.close()
    if rows:
        _plot(rows, run_dir / "learning_curve.png")
    _log("evaluating the policy at 2 cm / 0.1 rad (mean actions, then sampled actions)...")
    evaluation = evaluate_policy(state.agent, eval_env, eval_bank)
    sampled = evaluate_policy(state.agent, eval_env, eval_bank, jax.random.key(settings["seed"] + 1), float(trainer.std_scale(state)))
    env_rate = (int(state.env_steps) - start_steps) / max(elapsed - start_elapsed, 1e-9)
    summary = {
        "env_steps": int(state.env_steps), "updates": int(state.agent.updates), "expert_steps": int(state.expert_steps),
        "train_seconds": elapsed, "env_steps_per_s": env_rate, "updates_per_s": int(state.agent.updates) / max(elapsed, 1e-9),
        "success_rate": evaluation["all"]["success_rate"], "evaluation": evaluation,
        "sampled_success_rate": sampled["all"]["success_rate"],
        "curriculum_level": int(trainer.level(state.curriculum)) + 1,
        "curriculum_levels_by_team": {int(t): int(state.curriculum.level[trainer.team_group[t - 1]]) + 1 for t in trainer.teams},
        "checkpoint": str(checkpoints.directory / str(iteration)),
        "run_dir": str(run_dir),
    }
    summary = _json_safe(summary)
    atomic_write(run_dir / "summary.json", lambda f: f.write(json.dumps(summary, indent=2).encode()))
    for team, row in sorted(evaluation["by_team_size"].items()):
        print(f"{team} arm(s): success {row['success_rate']:.1%}  collision {row['collision_rate']:.1%}  timeout {row['timeout_rate']:.1%} "
              f"arms reached {row['arm_reach_rate']:.1%} ({row['episodes']} tasks)")
    print(f"sampled actions (the training policy): success {summary['sampled_success_rate']:.1%}")
    print(f"{summary['env_steps']:,} env steps, {summary['updates']:,} updates in {elapsed / 60:.1f} min; "
          f"curriculum level {summary['curriculum_level']}; results in {run_dir}")
    if args.json:
        print(json.dumps(summary))


if __name__ == "__main__":
    main()
