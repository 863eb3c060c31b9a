"""The training chain of issue 50: fine-tunes in parts, each judged on the validation sets.

    python benchmarks/chain.py record runs/part1 --data DATA --note "..."   # evaluate a part, keep it if better
    python benchmarks/chain.py plot                                            # the curve across the parts
    python benchmarks/chain.py table                                           # the parts as a markdown table
    python benchmarks/chain.py evaluate runs/lever/policy.npz --data DATA        # a lever's policy, not recorded

``record`` evaluates the part's ``policy.npz`` (plain policy, mean actions, 500 steps,
2 cm / 0.1 rad) on the validation sets ``DATA/val2048.npz`` (the paper's bins) and
``DATA/crowdval2048.npz`` (crowded), appends a row to ``benchmarks/chain.json`` (the part's
parent, its own and the chain's env steps and training hours, success / collision /
timeout rates per team size on each set) and, when the part's success over both sets
(4,096 tasks, pooled) beats the best part so far (or the chain's root, evaluated the first
time), copies its policy to ``benchmarks/chain/best.npz``. Every part is also copied to
``benchmarks/chain/head.npz``, the policy the next part starts from (``python -m train.sac
--init benchmarks/chain/head.npz``): it carries its trained critics, so a part that is not
better than the best is continued rather than thrown away with the training it holds. Test
sets are never used here. The chain's root, the policy shipped before the chain ended (its
best part is shipped now, ``mjx_multiarm/assets/policy.npz``), is kept as
``benchmarks/chain/root.npz``: the figures measured with it name it.
``plot`` draws validation success per team size after each part against the env steps and
hours the chain has spent (``benchmarks/chain_curve.png``).
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import shutil
import subprocess
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]
TABLE = ROOT / "benchmarks" / "chain.json"
BEST = ROOT / "benchmarks" / "chain" / "best.npz"
HEAD = ROOT / "benchmarks" / "chain" / "head.npz"
VALIDATION = ("val2048", "crowdval2048")


def evaluate(policy: pathlib.Path, data: pathlib.Path) -> dict:
    """Per-set, per-team-size rates of ``policy`` on the validation sets in ``data`` (the
    ``eval.benchmark --json`` lines are kept in ``DATA/eval_cache/``, named by the policy's
    checksum, so a policy is evaluated once)."""
    sha, _ = _provenance(policy)
    result = {}
    for name in VALIDATION:
        cache = data / "eval_cache" / f"{sha[:16]}_{name}.json"
        if not cache.exists():
            command = [sys.executable, "-m", "eval.benchmark", "--checkpoint", str(policy), "--tasks", str(data / f"{name}.npz"),
                       "--mode", "static", "--json"]
            print("$ " + " ".join(command[1:]), file=sys.stderr, flush=True)
            out = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, check=True).stdout
            cache.parent.mkdir(exist_ok=True)
            cache.write_text(out.strip().splitlines()[-1])
        rows = json.loads(cache.read_text())["by_team_size"]
        result[name] = {arms: {k: row[k] for k in ("tasks", "success_rate", "collision_rate", "timeout_rate")} for arms, row in rows.items()}
    return result


def pooled(validation: dict) -> float:
    """Success over every task of every validation set."""
    rows = [row for per_set in validation.values() for row in per_set.values()]
    return sum(r["success_rate"] * r["tasks"] for r in rows) / sum(r["tasks"] for r in rows)


def _provenance(policy: pathlib.Path) -> tuple[str, dict]:
    from mjx_multiarm.planner.policy_file import load_policy

    loaded = load_policy(policy)
    return loaded.meta["sha256"], loaded.provenance


def _atomic_json(path: pathlib.Path, value) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(value, indent=1))
    os.replace(tmp, path)


def record(run_dir: pathlib.Path, data: pathlib.Path, note: str) -> None:
    table = json.loads(TABLE.read_text()) if TABLE.exists() else []
    policy = run_dir / "policy.npz"
    sha, provenance = _provenance(policy)
    parent = provenance.get("parent")
    if parent is None:
        sys.exit(f"{policy}: not a fine-tune (no parent recorded); the chain's parts start with --init")
    if not table:  # the chain's root: its validation figures are the first bar to beat
        root = pathlib.Path(parent["path"])
        table.append({"part": 0, "sha256": parent["sha256"], "policy": str(root), "env_steps": parent["env_steps"],
                      "chain_env_steps": parent["total_env_steps"], "train_hours": parent["train_seconds"] / 3600,
                      "chain_train_hours": parent["total_train_seconds"] / 3600, "note": "the chain's root",
                      "validation": evaluate(root, data)})
        table[0]["pooled_success"] = pooled(table[0]["validation"])
        table[0]["kept"] = True
    validation = evaluate(policy, data)
    best = max((row for row in table if row["kept"]), key=lambda row: row["pooled_success"])
    row = {"part": table[-1]["part"] + 1, "sha256": sha, "parent_sha256": parent["sha256"], "run_dir": str(run_dir),
           "env_steps": provenance["env_steps"], "chain_env_steps": parent["total_env_steps"] + provenance["env_steps"],
           "train_hours": provenance["train_seconds"] / 3600,
           "chain_train_hours": (parent["total_train_seconds"] + provenance["train_seconds"]) / 3600,
           "note": note, "validation": validation, "pooled_success": pooled(validation)}
    row["kept"] = row["pooled_success"] > best["pooled_success"]
    for target in (HEAD, BEST) if row["kept"] else (HEAD,):
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(policy, target.with_name(f".{target.name}.tmp"))
        os.replace(target.with_name(f".{target.name}.tmp"), target)
    table.append(row)
    _atomic_json(TABLE, table)
    verdict = f"kept: {BEST}" if row["kept"] else f"not kept (best: part {best['part']}, {best['pooled_success']:.4f})"
    print(f"part {row['part']}: pooled validation success {row['pooled_success']:.4f}; {verdict}")
    for name, per_set in validation.items():
        cells = "  ".join(f"{arms}: {100 * r['success_rate']:.1f} ({100 * r['collision_rate']:.1f}/{100 * r['timeout_rate']:.1f})"
                          for arms, r in sorted(per_set.items(), key=lambda kv: int(kv[0])))
        print(f"  {name}: {cells}")


def table() -> str:
    """The chain's parts as a markdown table: each part's own and the chain's spent env steps
    and hours, its validation success per team size and pooled, and whether it was kept."""
    rows = json.loads(TABLE.read_text())
    header = ("| part | parent | env steps | spent: env steps / hours | "
              + " | ".join(f"`{name}`: 1 / 2 / 3 / 4 arms" for name in VALIDATION) + " | pooled | kept |")
    lines = [header, "|" + "---|" * (6 + len(VALIDATION))]
    parts = {row["sha256"]: row["part"] for row in rows}
    steps = hours = 0.0
    for row in rows:
        steps, hours = steps + row["env_steps"], hours + row["train_hours"]
        cells = [" / ".join(f"{100 * per_set[arms]['success_rate']:.1f}" for arms in sorted(per_set, key=int))
                 for per_set in (row["validation"][name] for name in VALIDATION)]
        parent = parts.get(row.get("parent_sha256"), "-")
        lines.append(f"| {row['part']} | {parent} | {row['env_steps'] / 1e6:.2f} M | {steps / 1e6:.2f} M / {hours:.2f} h | "
                     + " | ".join(cells) + f" | {100 * row['pooled_success']:.2f} | {'yes' if row['kept'] else 'no'} |")
    return "\n".join(lines)


#: The paper's static success at 1-4 arms (its policy, Table 1), drawn beside the paper's bins.
PAPER = {"1": 0.988, "2": 0.943, "3": 0.960, "4": 0.951}


def plot(out: pathlib.Path) -> None:
    """Validation success per team size after each part, against what the chain has spent
    (env steps and training hours of every part so far, in the order they ran: parts that
    restart from the best part count too); kept parts are filled, the paper's figures dotted."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    table = json.loads(TABLE.read_text())
    spent = {"env steps spent by the chain": np.cumsum([row["env_steps"] for row in table]),
             "training hours spent by the chain (2-core CPU)": np.cumsum([row["train_hours"] for row in table])}
    kept = np.array([row["kept"] for row in table])
    figure, axes = plt.subplots(len(VALIDATION), 2, figsize=(11, 4 * len(VALIDATION)), squeeze=False)
    for i, name in enumerate(VALIDATION):
        for j, (label, x) in enumerate(spent.items()):
            axis = axes[i, j]
            for arms in sorted(table[0]["validation"][name], key=int):
                y = np.array([row["validation"][name][arms]["success_rate"] for row in table])
                line, = axis.plot(x, y, "-", lw=0.8, alpha=0.6)
                axis.plot(x[kept], y[kept], "o", color=line.get_color(), label=f"{arms} arm{'s' if arms != '1' else ''}")
                axis.plot(x[~kept], y[~kept], "o", mfc="none", color=line.get_color())
                if name == "val2048" and arms in PAPER:
                    axis.axhline(PAPER[arms], ls=":", lw=1, color=line.get_color())
            axis.set(xlabel=label, ylabel="success (plain policy)", ylim=(0.4, 1.02),
                     title=f"{name} (validation; filled: kept parts" + ("; dotted: the paper)" if name == "val2048" else ")"))
            axis.grid(alpha=0.3)
            axis.legend(fontsize=8, loc="lower right")
    figure.tight_layout()
    figure.savefig(out, dpi=110)
    print(out)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True)
    rec = commands.add_parser("record", help="evaluate a part on the validation sets and keep it if better")
    rec.add_argument("run_dir", type=pathlib.Path)
    rec.add_argument("--data", type=pathlib.Path, required=True, help="folder holding val2048.npz and crowdval2048.npz")
    rec.add_argument("--note", default="", help="what this part changed")
    scored = commands.add_parser("evaluate", help="print a policy's validation rates (a lever's), without recording it")
    scored.add_argument("policy", type=pathlib.Path)
    scored.add_argument("--data", type=pathlib.Path, required=True, help="folder holding val2048.npz and crowdval2048.npz")
    commands.add_parser("table", help="the parts as a markdown table")
    drawn = commands.add_parser("plot", help="validation success across the parts")
    drawn.add_argument("--out", type=pathlib.Path, default=ROOT / "benchmarks" / "chain_curve.png")
    args = parser.parse_args(argv)
    if args.command == "record":
        record(args.run_dir.absolute(), args.data.absolute(), args.note)
    elif args.command == "evaluate":
        validation = evaluate(args.policy.absolute(), args.data.absolute())
        print(json.dumps({"policy": str(args.policy), "env_steps": _provenance(args.policy)[1].get("env_steps"),
                          "pooled_success": pooled(validation), "validation": validation}))
    elif args.command == "table":
        print(table())
    else:
        plot(args.out)


if __name__ == "__main__":
    main()
