"""Train the decentralized multi-arm planner with SAC, expert demonstrations and a curriculum.

    python -m train.sac                                   # default CPU preset, embedded defaults
    python -m train.sac --preset paper --run-dir runs/paper
    python -m train.sac --arms 1-4 --minutes 60 --run-dir runs/four
    python -m train.sac --resume runs/four --minutes 120  # continue a killed or finished run exactly
    python -m train.sac --preset team --init runs/four --tasks mine.npz --run-dir runs/mine   # fine-tune a trained policy
    python -m train.sac --tasks train.npz --experts train.experts --run-dir runs/big
    python -m train.sac --tasks train.npz --experts train.experts --task-limit 10000   # its first 10,000
    python -m train.sac --train.sac.gamma 0.98            # any field of the run configuration

Without ``--tasks`` the run generates its training and evaluation tasks and plans their
experts itself (a small set; seconds to a minute), so it needs no precompute step. The run
directory and what it holds: :mod:`train.run`. The run ends with the deployed policy's mean
actions (``success_rate``, as the paper's benchmark) and the training policy's sampled
actions (``sampled_success_rate``) evaluated on the evaluation tasks at 2 cm / 0.1 rad.

Every field of the run configuration (:class:`train.config.RunConfig`: environment, trainer
with SAC, data, budget) is a flag, ``--section.field`` or just ``--field``; the help shows
the ``cpu`` preset's values, and ``--preset`` picks another base (``paper``: the original's
hyperparameters; ``team``: the 1-4-arm recipe of benchmarks/RESULTS.md "Teams"; ``tiny``:
seconds, for tests). On ``--resume`` only the budget flags apply.

The ``cpu`` preset adds three things to the original's SAC: every policy transition is
stored a second time relabelled with a hindsight goal (``--hindsight 1``), the actor
imitates the expert where the critic prefers it (``--expert-bc 1``), and the deployed
policy (evaluation, ``policy.npz``) is a Polyak average of the actor's parameters
(``--policy-average 5e-4``). ``--hindsight 0 --expert-bc 0 --policy-average 0`` gives the
original on any preset. Ablations (paper section 5): ``--no-expert``, ``--bc``,
``--reward selfish``, ``--observe self``.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

from mjx_multiarm.cli import Progress
from mjx_multiarm.options import add_flags, apply, overrides
from train.config import PRESETS, RunConfig, behaviour_cloning, without_expert
from train.curriculum import LEVELS
from train.finetune import fine_tune_config, load_parent
from train.run import TrainingStopped, load_config, train

#: Shortcut flags: value -> the settings it stands for.
SHORTCUTS = {
    "sac": {"original": {"train.sac.squash": False, "train.sac.learn_alpha": False},
            "standard": {"train.sac.squash": True, "train.sac.learn_alpha": True}},
    "observe": {"neighbours": {}, "self": {"env.neighbour_radius": 0.0}},
    "collisions": {"end": {"env.end_on_collision": True}, "restore": {"env.end_on_collision": False}},
}


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m train.sac", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    run = parser.add_argument_group("run")
    run.add_argument("--preset", choices=sorted(PRESETS), default="cpu", help="named configuration (default cpu)")
    run.add_argument("--run-dir", type=pathlib.Path, default=None, help="output directory (default runs/<preset>-<time>)")
    run.add_argument("--resume", type=pathlib.Path, default=None, help="continue the run in this directory from its latest checkpoint")
    run.add_argument("--workers", type=int, default=None, help="processes generating tasks and planning experts (default: all cores)")
    run.add_argument("--devices", type=int, default=None, help="data-parallel over this many local devices (default: all)")
    run.add_argument("--json", action="store_true", help="end with one JSON line")
    shortcuts = parser.add_argument_group("ablations and shortcuts")
    shortcuts.add_argument("--no-expert", action="store_true", help="ablation: no expert demonstrations (drops the preset's expert terms)")
    shortcuts.add_argument("--bc", action="store_true", help="ablation: behaviour cloning on the expert data only")
    shortcuts.add_argument("--sac", choices=list(SHORTCUTS["sac"]), help="original: the bounded-variance Gaussian with a fixed "
                           "temperature; standard: tanh-squashed samples and a learned temperature")
    shortcuts.add_argument("--observe", choices=list(SHORTCUTS["observe"]), help="self: the individualistic ablation "
                           "(neighbour radius 0)")
    shortcuts.add_argument("--collisions", choices=list(SHORTCUTS["collisions"]), help="during training a collision ends the "
                           "episode (end, the original) or puts the colliding arms back, penalized (restore)")
    add_flags(parser, PRESETS["cpu"], default_label="cpu preset:")
    return parser


def config_from_args(args: argparse.Namespace) -> RunConfig:
    """The run configuration the parsed command line asks for (raises ValueError)."""
    changes = overrides(args, RunConfig)
    shortcut_changes = {k: v for name in SHORTCUTS if getattr(args, name) for k, v in SHORTCUTS[name][getattr(args, name)].items()}
    if args.resume:
        fixed = sorted(k for k in changes if not k.startswith("budget.")) + [f"--{k}" for k in ("no_expert", "bc") if getattr(args, k)]
        if fixed or shortcut_changes:
            raise ValueError(f"--resume continues a run as configured; only budget settings may change, not {fixed or sorted(shortcut_changes)}")
        return apply(load_config(args.resume), changes)
    if "data.train_tasks" in changes and "data.tasks" in changes:
        raise ValueError("--train-tasks counts generated tasks; --task-limit N takes the first N of a --tasks file")
    config = PRESETS[args.preset]
    if args.no_expert:
        config = without_expert(config)
    if args.bc:
        config = behaviour_cloning(config)
    config = apply(config, {**shortcut_changes, **changes})
    if config.init:
        config = fine_tune_config(config, load_parent(config.init)[1], set(changes) | set(shortcut_changes))
    return config


class TrainingProgress(Progress):
    """Training's rows on the progress line (rewritten every 2 s at most)."""

    def __init__(self):
        super().__init__(interval=2.0)
        self.heldout = None

    def row(self, row: dict) -> None:
        if "heldout_success" in row:
            self.heldout = row["heldout_success"]
        level = int(row["level"])
        eps_p, eps_r = LEVELS[level]
        heldout = f" held-out {self.heldout:5.1%} |" if self.heldout is not None else ""
        self.show(f"{row['env_steps']:>11,} env steps {row['env_steps_per_s']:8,.0f}/s | {row['updates']:>8,} updates | "
                  f"level {level + 1}/{len(LEVELS)} ({100 * eps_p:.1f} cm, {eps_r:.2f} rad) success "
                  f"{row['window_success']:5.1%} |{heldout} ETA {row['eta_minutes']:5.1f} min")


def main(argv=None) -> None:
    args = _parser().parse_args(argv)
    try:
        config = config_from_args(args)
    except (ValueError, FileNotFoundError) as error:
        sys.exit(f"error: {error}")
    run_dir = args.resume or args.run_dir or pathlib.Path("runs") / f"{args.preset}-{time.strftime('%Y%m%d-%H%M%S')}"
    line = TrainingProgress()
    try:
        result = train(config, run_dir, resume=bool(args.resume), workers=args.workers, devices=args.devices,
                       progress=line.row, log=line.log)
    except (ValueError, FileNotFoundError) as error:
        sys.exit(f"error: {error}")
    except TrainingStopped as stopped:
        line.log(str(stopped))
        return
    except KeyboardInterrupt:
        sys.exit(f"\ninterrupted: {run_dir} keeps what it had saved; --resume {run_dir} continues it (from the start, "
                 "with the prepared tasks and experts, if it had no checkpoint yet)")
    line.close()
    summary = result.summary
    for team, row in sorted(summary["evaluation"]["by_team_size"].items()):
        print(f"{team} arm(s): success {row['success_rate']:.1%}  collision {row['collision_rate']:.1%}  timeout {row['timeout_rate']:.1%} "
              f"arms reached {row['arm_reach_rate']:.1%} ({row['episodes']} tasks)")
    print(f"sampled actions (the training policy): success {summary['sampled_success_rate']:.1%}")
    print(f"{summary['env_steps']:,} env steps, {summary['updates']:,} updates in {summary['train_seconds'] / 60:.1f} min; "
          f"curriculum level {summary['curriculum_level']}; results in {run_dir}")
    if args.json:
        print(json.dumps(summary))


if __name__ == "__main__":
    main()
