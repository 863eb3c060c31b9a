"""Command-line tools for task datasets.

    python -m mjx_multiarm.tasks generate --arms 1-4 --count 1000 --mode static --seed 0 --out tasks.npz
    python -m mjx_multiarm.tasks generate --preset test --out test.npz
    python -m mjx_multiarm.tasks generate --cell cell.json --count 20000 --out mine.npz   # a work cell of one's own
    python -m mjx_multiarm.tasks info tasks.npz [--json]
    python -m mjx_multiarm.tasks merge a.npz b.npz --out mix.npz      # e.g. stratified + crowded training tasks
    python -m mjx_multiarm.tasks select mix.npz --per-team 11250 --detour-share 0.5 --out detour.npz
    python -m mjx_multiarm.tasks import-json DIR --out tasks.npz [--json]
    python -m mjx_multiarm.tasks export-json tasks.npz --out DIR

``--cell FILE`` fixes the bases of every task: FILE is JSON, a list of ``[x, y, yaw]`` per
arm (metres, radians), so the tasks are those of one's own work cell (team size: its arms).
``generate`` is resumable: finished chunks are kept in ``OUT.partial/``; re-running the
same command after an interruption continues where it stopped and writes the same file.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import pathlib
import sys

import numpy as np

from mjx_multiarm.cli import Progress, parse_arms
from mjx_multiarm.tasks.dataset import load_tasks, save_tasks
from mjx_multiarm.tasks.generate import (
    DATASETS,
    LAYOUTS,
    MODES,
    GenerationSpec,
    check_cell,
    generate_dataset,
)
from mjx_multiarm.tasks.original_json import export_tasks, import_tasks
from mjx_multiarm.tasks.select import detour_rows, straight_motion_free
from mjx_multiarm.tasks.types import (
    DIFFICULTY_BINS,
    SPEED_BINS,
    Tasks,
    bin_index,
    concatenate,
    take,
    with_slots,
)


def _counts(values, bins) -> dict[str, int]:
    index = bin_index(values, bins)
    return {name: int((index == i).sum()) for i, name in enumerate(bins)}


def summarize(tasks: Tasks) -> dict:
    """Counts per team size, per difficulty bin (all tasks) and speed bin (dynamic-capable tasks)."""
    arms = tasks.num_arms
    summary = {"count": int(tasks.num_tasks), "max_arms": int(tasks.max_arms), "by_team_size": {}}
    for team in sorted(set(arms.tolist())):
        rows = arms == team
        difficulty = tasks.difficulty[rows]
        summary["by_team_size"][str(team)] = {
            "count": int(rows.sum()),
            "difficulty": _counts(difficulty, DIFFICULTY_BINS) | {"outside": int((bin_index(difficulty, DIFFICULTY_BINS) < 0).sum())},
            "speed": _counts(tasks.speed[rows & tasks.has_dynamic_mode], SPEED_BINS),
        }
    return summary


def _print_summary(summary: dict) -> None:
    d_names, s_names = list(DIFFICULTY_BINS) + ["outside"], list(SPEED_BINS)
    print(f"{summary['count']} tasks, {summary['max_arms']} slots")
    print(f"{'arms':>4} {'count':>7} " + " ".join(f"{n:>7}" for n in d_names) + " | " + " ".join(f"{n:>7}" for n in s_names))
    for team, row in summary["by_team_size"].items():
        cells = " ".join(f"{row['difficulty'][n]:>7}" for n in d_names)
        speeds = " ".join(f"{row['speed'][n]:>7}" for n in s_names)
        print(f"{team:>4} {row['count']:>7} {cells} | {speeds}")


def merge_datasets(paths: list[pathlib.Path]) -> tuple[Tasks, dict]:
    """The tasks of several dataset files, in order, padded to the most slots, and the
    metadata recording each source (its path, task count and own metadata). Task ids must
    stay unique (generated sets of different seeds have distinct ids)."""
    loaded = [(path, *load_tasks(path)) for path in paths]
    slots = max(tasks.max_arms for _, tasks, _ in loaded)
    merged = concatenate([with_slots(tasks, slots, str(path)) for path, tasks, _ in loaded])
    sources = [{"path": str(path), "count": int(tasks.num_tasks), "metadata": meta} for path, tasks, meta in loaded]
    return merged, {"merged_from": sources}


def read_cell(path: pathlib.Path) -> tuple[tuple[float, float, float], ...]:
    """The bases of a cell file (JSON: a list of ``[x, y, yaw]`` per arm), checked."""
    try:
        bases = json.loads(pathlib.Path(path).read_text())
    except json.JSONDecodeError as error:
        raise ValueError(f"--cell {path}: not JSON ({error})") from None
    if not isinstance(bases, list) or not all(isinstance(b, list) and len(b) == 3 and all(isinstance(v, (int, float)) for v in b) for b in bases):
        raise ValueError(f"--cell {path}: expected a list of [x, y, yaw] per arm (m, m, rad), got {bases!r}")
    cell = tuple(tuple(float(v) for v in base) for base in bases)
    check_cell(cell)
    return cell


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog="python -m mjx_multiarm.tasks", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True)
    gen = commands.add_parser("generate", help="generate a task dataset (resumable)")
    gen.add_argument("--preset", choices=sorted(DATASETS), help="named dataset; other flags override its fields")
    gen.add_argument("--arms", type=parse_arms, help="team sizes, e.g. 1-4 or 2,5")
    gen.add_argument("--count", type=int, help="number of tasks")
    gen.add_argument("--mode", choices=MODES, help="static, or dynamic (tasks usable in both modes)")
    gen.add_argument("--seed", type=int)
    gen.add_argument("--max-arms", type=int, help="arm slots (default: the largest team)")
    gen.add_argument("--layout", choices=LAYOUTS, help="base placement: stratified over difficulty bins (default) or "
                     "original (the original code's random walk, difficulty up to ~0.99)")
    gen.add_argument("--cell", type=pathlib.Path, help="JSON file: the fixed bases of every task, a list of [x, y, yaw] "
                     "(m, m, rad) per arm (one's own work cell)")
    gen.add_argument("--out", type=pathlib.Path, required=True)
    gen.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="processes (default: all cores)")
    gen.add_argument("--quiet", action="store_true", help="no progress bar")
    info = commands.add_parser("info", help="counts per team size and difficulty/speed bin")
    info.add_argument("path", type=pathlib.Path)
    info.add_argument("--json", action="store_true", help="end with one JSON line")
    merge = commands.add_parser("merge", help="join task datasets into one file (padded to the most slots)")
    merge.add_argument("paths", type=pathlib.Path, nargs="+")
    merge.add_argument("--out", type=pathlib.Path, required=True)
    sel = commands.add_parser("select", help="a subset with PER_TEAM tasks of each team size, a share of them detour tasks "
                              "(whose straight start-goal motion collides)")
    sel.add_argument("path", type=pathlib.Path)
    sel.add_argument("--per-team", type=int, required=True, help="tasks of each team size")
    sel.add_argument("--detour-share", type=float, required=True, help="share of detour tasks per team size, where there are enough")
    sel.add_argument("--seed", type=int, default=0)
    sel.add_argument("--out", type=pathlib.Path, required=True)
    imp = commands.add_parser("import-json", help="convert a folder of original per-task JSON files")
    imp.add_argument("source", type=pathlib.Path)
    imp.add_argument("--out", type=pathlib.Path, required=True)
    imp.add_argument("--max-arms", type=int)
    imp.add_argument("--json", action="store_true", help="end with one JSON line (the import report)")
    exp = commands.add_parser("export-json", help="write a dataset as original per-task JSON files")
    exp.add_argument("path", type=pathlib.Path)
    exp.add_argument("--out", type=pathlib.Path, required=True)
    args = parser.parse_args(argv)

    try:
        out = getattr(args, "out", None)
        if args.command == "export-json" and out is not None and out.exists() and not out.is_dir():
            raise ValueError(f"--out {out} is a file; export-json writes a folder of JSON files")
        if args.command != "export-json" and out is not None and out.is_dir():
            raise ValueError(f"--out {out} is a directory; give the .npz file to write")
        if args.command == "generate":
            base = DATASETS[args.preset] if args.preset else None
            cell = read_cell(args.cell) if args.cell else None
            arms = args.arms if args.arms is not None or cell is None else (len(cell),)
            if base is None and (arms is None or args.count is None):
                parser.error("generate: give --preset, or --arms (or --cell) and --count")
            fields = {"arm_counts": arms, "count": args.count, "mode": args.mode, "seed": args.seed, "max_arms": args.max_arms,
                      "layout": args.layout, "cell": cell}
            overrides = {k: v for k, v in fields.items() if v is not None}
            spec = dataclasses.replace(base, **overrides) if base else GenerationSpec(**overrides)
            progress = None if args.quiet else Progress(spec.count, "tasks")
            tasks = generate_dataset(spec, args.out, args.workers, progress.update if progress else None)
            if progress:
                progress.close()
            print(f"wrote {tasks.num_tasks} tasks to {args.out}")
        elif args.command == "info":
            summary = summarize(load_tasks(args.path)[0])
            _print_summary(summary)
            if args.json:
                print(json.dumps(summary))
        elif args.command == "merge":
            tasks, metadata = merge_datasets(args.paths)
            save_tasks(args.out, tasks, metadata)
            print(f"wrote {tasks.num_tasks} tasks from {len(args.paths)} files to {args.out}")
        elif args.command == "select":
            tasks, metadata = load_tasks(args.path)
            free = straight_motion_free(tasks)
            rows = detour_rows(tasks.num_arms, free, args.per_team, args.detour_share, args.seed)
            subset = take(tasks, rows)
            detours = {int(k): int((~free[rows] & (subset.num_arms == k)).sum()) for k in np.unique(subset.num_arms)}
            save_tasks(args.out, subset, {"selected_from": str(args.path), "source_metadata": metadata, "per_team": args.per_team,
                                          "detour_share": args.detour_share, "seed": args.seed, "detours_by_team": detours})
            print(f"wrote {subset.num_tasks} tasks to {args.out}; detour tasks by team size: {detours} "
                  f"(in {args.path}: {int((~free).sum())} of {tasks.num_tasks})")
        elif args.command == "import-json":
            tasks, report = import_tasks(args.source, args.max_arms)
            save_tasks(args.out, tasks, {"imported_from": str(args.source)})
            print(f"imported {report.count} tasks ({report.arms_total} arms) to {args.out}")
            print(f"FK of goal_config vs target_eff_poses: {report.max_fk_position_error_m:.2e} m, "
                  f"{report.max_fk_rotation_error_rad:.2e} rad; difficulty recomputed: max difference {report.max_difficulty_error:.4f}")
            if args.json:
                fields = ("count", "arms_total", "max_fk_position_error_m", "max_fk_rotation_error_rad", "max_difficulty_error")
                print(json.dumps({name: float(getattr(report, name)) if "max" in name else int(getattr(report, name)) for name in fields}))
        else:
            paths = export_tasks(load_tasks(args.path)[0], args.out)
            print(f"wrote {len(paths)} JSON files to {args.out}")
    except (ValueError, FileNotFoundError) as error:
        sys.exit(f"error: {error}")


if __name__ == "__main__":
    main()
