"""Faults a training run meets, tried as a user would on the command line: what each one
prints, whether a traceback shows, and whether anything saved is lost (issue 50).

    python benchmarks/fault_drill.py --json                        # this tree
    python benchmarks/fault_drill.py --repo /tmp/old --json        # another checkout (before / after)

Each scenario runs ``python -m train.sac --preset tiny`` (and friends) in a scratch folder:

- ``sigterm`` / ``sigint``: SIGTERM once training runs, SIGINT while the training step
  compiles; then ``--resume``.
- ``truncated_checkpoint``: the latest checkpoint's largest file cut in half, then ``--resume``.
- ``failed_start``: ``--tasks`` a corrupt file, then the corrected command in the same directory.
- ``experts_of_another_file``: ``--experts`` planned for another task file.
- ``workers_0`` / ``workers_negative``: ``--workers 0`` / ``--workers -1``.

A row per step: its exit code, the number of traceback lines it printed, its last line, and
the scenario's outcome (``clear error``, ``recovered``, ``saved`` ... or what went wrong).
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import signal
import subprocess
import sys
import tempfile
import time

TINY = ["-m", "train.sac", "--preset", "tiny", "--workers", "1"]


class Drill:
    """Runs project command lines against one checkout in a scratch folder."""

    def __init__(self, repo: pathlib.Path, scratch: pathlib.Path):
        self.repo, self.scratch = repo, scratch
        self.env = {**os.environ, "PYTHONPATH": str(repo), "JAX_PLATFORMS": "cpu"}

    def run(self, args, timeout=900) -> tuple[int, str]:
        done = subprocess.run([sys.executable, *args], cwd=self.scratch, env=self.env, capture_output=True, text=True, timeout=timeout)
        return done.returncode, done.stdout + done.stderr

    def signal_when(self, args, marker: str, number: int, timeout=900) -> tuple[int, str]:
        """Start ``args``, send signal ``number`` once ``marker`` appears in its stderr."""
        log = self.scratch / f"signal_{number}.log"
        with open(log, "w") as out:
            process = subprocess.Popen([sys.executable, *args], cwd=self.scratch, env=self.env, stdout=out, stderr=subprocess.STDOUT)
            deadline = time.time() + timeout
            while marker not in log.read_text() and process.poll() is None and time.time() < deadline:
                time.sleep(0.2)
            if process.poll() is None:
                process.send_signal(number)
            try:
                process.wait(timeout=300)
            except subprocess.TimeoutExpired:
                process.kill()
                return -9, log.read_text() + "\n[hung: killed after 300 s]"
        return process.returncode, log.read_text()


def _row(scenario: str, step: str, code: int, output: str, outcome: str) -> dict:
    lines = [line for line in output.replace("\r", "\n").splitlines() if line.strip()]
    traceback = sum(1 for line in lines if line.startswith(("Traceback", "  File ")))
    return {"scenario": scenario, "step": step, "exit": code, "traceback_lines": traceback,
            "last_line": lines[-1][:160] if lines else "", "outcome": outcome}


def _checkpoints(run: pathlib.Path) -> list[int]:
    folder = run / "checkpoints"
    return sorted(int(p.name) for p in folder.iterdir() if p.name.isdigit()) if folder.is_dir() else []


def signal_scenario(drill: Drill, name: str, number: int, marker: str) -> list[dict]:
    run = drill.scratch / name
    code, output = drill.signal_when([*TINY, "--steps", "100000", "--minutes", "30", "--checkpoint-minutes", "30",
                                      "--run-dir", str(run)], marker, number)
    saved = _checkpoints(run)
    rows = [_row(name, f"{signal.Signals(number).name} after '{marker}'", code, output,
                 f"checkpoint {saved[-1]} saved" if saved else "nothing saved")]
    code, output = drill.run([*TINY[:2], "--resume", str(run), "--steps", "64" if not saved else "100000", "--minutes", "0.05",
                              "--workers", "1"])
    rows.append(_row(name, "--resume", code, output, "resumed" if code == 0 else "cannot resume"))
    return rows


def truncated_checkpoint(drill: Drill) -> list[dict]:
    run = drill.scratch / "truncated"
    drill.run([*TINY, "--steps", "64", "--checkpoint-minutes", "0", "--run-dir", str(run)])
    latest = _checkpoints(run)[-1]
    victim = max((p for p in (run / "checkpoints" / str(latest)).rglob("*") if p.is_file()), key=lambda p: p.stat().st_size)
    victim.write_bytes(victim.read_bytes()[: victim.stat().st_size // 2])
    code, output = drill.run([*TINY[:2], "--resume", str(run), "--steps", "96", "--workers", "1"])
    return [_row("truncated_checkpoint", f"--resume with checkpoint {latest} truncated", code, output,
                 "recovered from an older checkpoint" if code == 0 else "cannot resume")]


def failed_start(drill: Drill) -> list[dict]:
    run = drill.scratch / "failed_start"
    (drill.scratch / "corrupt.npz").write_bytes(b"PK\x03\x04 not a task file")
    code, output = drill.run([*TINY, "--tasks", "corrupt.npz", "--run-dir", str(run)])
    rows = [_row("failed_start", "--tasks corrupt.npz", code, output, "clear error" if code and "Traceback" not in output else "unclear")]
    code, output = drill.run([*TINY, "--steps", "64", "--run-dir", str(run)])
    rows.append(_row("failed_start", "corrected command, same --run-dir", code, output, "started again" if code == 0 else "refused"))
    return rows


def experts_of_another_file(drill: Drill) -> list[dict]:
    for name, seed in (("a", 1), ("b", 2)):
        drill.run(["-m", "mjx_multiarm.tasks", "generate", "--arms", "1", "--count", "8", "--seed", str(seed), "--max-arms", "1",
                   "--workers", "1", "--out", f"{name}.npz"])
    drill.run(["-m", "mjx_multiarm.expert", "--tasks", "a.npz", "--out", "a.experts", "--workers", "1"])
    code, output = drill.run([*TINY, "--steps", "64", "--tasks", "b.npz", "--experts", "a.experts", "--run-dir",
                              str(drill.scratch / "mismatch")])
    outcome = "refused" if code else "trained with another file's experts"
    return [_row("experts_of_another_file", "--tasks b.npz --experts a.experts", code, output, outcome)]


def workers(drill: Drill, value: int) -> list[dict]:
    name = "workers_0" if value == 0 else "workers_negative"
    code, output = drill.run([*TINY, "--steps", "64", "--workers", str(value), "--run-dir", str(drill.scratch / name)])
    return [_row(name, f"--workers {value}", code, output, "refused" if code else "ran silently")]


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repo", type=pathlib.Path, default=pathlib.Path(__file__).resolve().parents[1], help="checkout to drill")
    parser.add_argument("--only", nargs="*", default=None, help="scenario names to run (default: all)")
    parser.add_argument("--json", action="store_true", help="end with one JSON line")
    args = parser.parse_args(argv)
    scenarios = {
        "sigterm": lambda d: signal_scenario(d, "sigterm", signal.SIGTERM, "env steps"),
        "sigint": lambda d: signal_scenario(d, "sigint", signal.SIGINT, "compiling the training step"),
        "truncated_checkpoint": truncated_checkpoint,
        "failed_start": failed_start,
        "experts_of_another_file": experts_of_another_file,
        "workers_0": lambda d: workers(d, 0),
        "workers_negative": lambda d: workers(d, -1),
    }
    rows = []
    with tempfile.TemporaryDirectory() as scratch:
        drill = Drill(args.repo.absolute(), pathlib.Path(scratch))
        for name, scenario in scenarios.items():
            if args.only is None or name in args.only:
                rows += scenario(drill)
                print(f"{rows[-1]['scenario']}: " + " -> ".join(f"{r['step']}: exit {r['exit']}, {r['traceback_lines']} traceback "
                      f"lines, {r['outcome']}" for r in rows if r["scenario"] == name), file=sys.stderr, flush=True)
    if args.json:
        print(json.dumps(rows))


if __name__ == "__main__":
    main()
