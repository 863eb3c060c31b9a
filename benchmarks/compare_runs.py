"""Learning curves of several training runs side by side (e.g. two seeds of one recipe).

Reads each run's ``metrics.csv`` (written by ``python -m train.sac`` at every checkpoint)
and plots, against training minutes (or environment steps: ``--by-steps``), the curriculum
level and the training success of the latest episodes per team size: one colour per team
size, one line style per run. Prints, at each of ``--minutes``, every run's environment
steps, levels and training success per team size (success averaged over the iterations of
the preceding ``--window`` minutes, as the per-iteration window is noisy).

    python benchmarks/compare_runs.py runs/seed0 runs/seed1 --minutes 10,30,60,120 --out curves.png
"""

from __future__ import annotations

import argparse
import csv
import json
import pathlib

import numpy as np


def read_metrics(run_dir: pathlib.Path) -> dict[str, np.ndarray]:
    """The columns of ``run_dir/metrics.csv`` as float arrays."""
    path = run_dir / "metrics.csv"
    if not path.exists():
        raise FileNotFoundError(f"{path}: no metrics (is {run_dir} a train.sac run directory?)")
    with path.open() as f:
        rows = list(csv.DictReader(f))
    if not rows:
        raise ValueError(f"{path} has no rows")
    return {key: np.array([float(row[key]) for row in rows]) for key in rows[0]}


def team_sizes(metrics: dict[str, np.ndarray]) -> list[int]:
    """Team sizes with a per-team curriculum column (``level_N``); [] for a mixed curriculum."""
    return sorted(int(key[len("level_"):]) for key in metrics if key.startswith("level_"))


def at_minute(metrics: dict[str, np.ndarray], minute: float, window: float) -> dict | None:
    """Steps, levels (1-based) and mean training success per team size at ``minute``; None past the run's end."""
    minutes = metrics["seconds"] / 60.0
    if minute > minutes[-1] + 1e-9:
        return None
    last = int(np.searchsorted(minutes, minute, side="right")) - 1
    if last < 0:
        return None
    recent = (minutes > minute - window) & (minutes <= minute)
    teams = team_sizes(metrics)
    return {"minute": minute, "env_steps": int(metrics["env_steps"][last]),
            "level": {t: int(metrics[f"level_{t}"][last]) + 1 for t in teams} or {"all": int(metrics["level"][last]) + 1},
            "success": {t: float(metrics[f"window_success_{t}"][recent].mean()) for t in teams}
            or {"all": float(metrics["window_success"][recent].mean())}}


def trailing_mean(values: np.ndarray, count: int) -> np.ndarray:
    """Mean of each value and the ``count - 1`` before it (fewer at the start)."""
    total = np.concatenate([[0.0], np.cumsum(values)])
    index = np.arange(1, len(values) + 1)
    first = np.maximum(index - count, 0)
    return (total[index] - total[first]) / (index - first)


def plot(runs: dict[str, dict[str, np.ndarray]], path: pathlib.Path, by_steps: bool = False) -> None:
    """Levels and training success per team size against training minutes (or env steps), one line style per run."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    styles = ["-", "--", ":", "-."]
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(8, 7), sharex=True)
    for index, (name, metrics) in enumerate(runs.items()):
        x, style = metrics["env_steps"] / 1e6 if by_steps else metrics["seconds"] / 60.0, styles[index % len(styles)]
        for colour, team in enumerate(team_sizes(metrics) or [None]):
            suffix = "" if team is None else f"_{team}"
            label = f"{name}" + ("" if team is None else f", {team} arm{'s' if team > 1 else ''}")
            top.plot(x, trailing_mean(metrics[f"window_success{suffix}"], 25), style, color=f"C{colour}", label=label)
            bottom.plot(x, metrics[f"level{suffix}"] + 1, style, color=f"C{colour}")
    top.set_ylabel("training success (latest episodes,\ncurrent level; smoothed)")
    top.set_ylim(-0.02, 1.02)
    top.legend(loc="lower right", fontsize=7, ncol=2)
    bottom.set_ylabel("curriculum level")
    bottom.set_xlabel("million environment steps" if by_steps else "training minutes")
    fig.suptitle("train.sac: " + " vs ".join(runs))
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", type=pathlib.Path, help="train.sac run directories")
    parser.add_argument("--minutes", default="10,20,30,60,120", help="comma-separated training minutes to tabulate")
    parser.add_argument("--window", type=float, default=5.0, help="minutes of iterations averaged for training success")
    parser.add_argument("--out", type=pathlib.Path, help="PNG of the curves")
    parser.add_argument("--by-steps", action="store_true", help="plot against environment steps, not minutes")
    parser.add_argument("--json", action="store_true", help="end with one JSON line")
    args = parser.parse_args()
    names = [run.name for run in args.runs]
    names = names if len(set(names)) == len(names) else [str(run) for run in args.runs]
    runs = {name: read_metrics(run) for name, run in zip(names, args.runs)}
    table = {name: [point for m in args.minutes.split(",") if (point := at_minute(metrics, float(m), args.window))]
             for name, metrics in runs.items()}
    for name, points in table.items():
        print(f"{name} (ends at {runs[name]['seconds'][-1] / 60:.1f} min)")
        for p in points:
            levels = " ".join(f"{t}:{v}" for t, v in p["level"].items())
            success = " ".join(f"{t}:{v:.2f}" for t, v in p["success"].items())
            print(f"  {p['minute']:6.1f} min {p['env_steps']:>11,} steps | levels {levels} | training success {success}")
    if args.out:
        plot(runs, args.out, args.by_steps)
        print(f"wrote {args.out}")
    if args.json:
        print(json.dumps(table))


if __name__ == "__main__":
    main()
