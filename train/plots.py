"""The learning curve of a run: held-out success, training success and curriculum level."""

from __future__ import annotations

import math
import pathlib

from mjx_multiarm.files import atomic_write


def _teams(rows: list[dict], prefix: str) -> list[int]:
    """Team sizes with a ``{prefix}{k}`` column."""
    keys = {k for row in rows for k in row}
    return sorted(int(k[len(prefix):]) for k in keys if k.startswith(prefix) and k[len(prefix):].isdigit())


def _label(team: int) -> str:
    return f"{team} arm{'s' if team > 1 else ''}"


def plot_learning_curve(rows: list[dict], path: pathlib.Path) -> None:
    """Three panels against environment steps: the deployed policy's held-out success per
    team size (mean actions, 2 cm / 0.1 rad; the evaluations during training and the final
    one), training success over the latest 100 episodes at the current curriculum level,
    and the curriculum level (per team size where the run has one per team size)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (heldout, training, level) = plt.subplots(3, 1, figsize=(7, 8.5), sharex=True)
    colours = plt.get_cmap("tab10")
    evaluated = [r for r in rows if not math.isnan(r.get("heldout_success", math.nan))]
    for team in _teams(evaluated, "heldout_success_"):
        heldout.plot([r["env_steps"] for r in evaluated], [r[f"heldout_success_{team}"] for r in evaluated], "o-",
                     color=colours(team - 1), label=_label(team))
    heldout.set_ylabel("held-out success\n(2 cm / 0.1 rad)")
    heldout.set_ylim(-0.02, 1.02)
    steps = [r["env_steps"] for r in rows]
    by_team = _teams(rows, "window_success_")
    for team in by_team:
        training.plot(steps, [r[f"window_success_{team}"] for r in rows], color=colours(team - 1), label=_label(team))
        level.plot(steps, [r[f"level_{team}"] + 1 for r in rows], color=colours(team - 1), label=_label(team))
    if not by_team:
        training.plot(steps, [r["window_success"] for r in rows], color="tab:blue")
        level.plot(steps, [r["level"] + 1 for r in rows], color="tab:orange")
    training.set_ylabel("training success\n(latest 100, current level)")
    training.set_ylim(-0.02, 1.02)
    level.set_ylabel("curriculum level")
    level.set_xlabel("environment steps")
    for axis in (heldout, training, level):
        if axis.get_legend_handles_labels()[0]:
            axis.legend(loc="lower right" if axis is not level else "upper left", fontsize="small")
    fig.suptitle("train.sac learning curve")
    fig.tight_layout()
    atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=100))
    plt.close(fig)
