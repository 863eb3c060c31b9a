"""Command-line helpers shared by every entry point: team-size ranges and a progress bar."""

from __future__ import annotations

import argparse
import sys
import time


class Progress:
    """A one-line progress bar on stderr: done/total, rate, ETA, and a note."""

    def __init__(self, total: int, unit: str):
        self.total, self.unit, self.start = total, unit, time.perf_counter()

    def update(self, done: int, new: int, note: str = "") -> None:
        """``done`` of ``total`` finished, ``new`` of them by this run (the rate counts those)."""
        elapsed = time.perf_counter() - self.start
        rate = new / elapsed if elapsed > 0 and new else 0.0
        eta = (self.total - done) / rate if rate else float("nan")
        bar = "#" * int(30 * done / max(self.total, 1))
        print(f"\r[{bar:<30}] {done}/{self.total} {self.unit} {rate:,.1f}/s ETA {eta:,.0f}s {note} ", end="", file=sys.stderr, flush=True)

    def close(self) -> None:
        print(file=sys.stderr)


def parse_arms(text: str) -> tuple[int, ...]:
    """'1-4' -> (1, 2, 3, 4); '2,5' -> (2, 5)."""
    counts: list[int] = []
    try:
        for part in text.split(","):
            low, _, high = part.partition("-")
            counts += range(int(low), int(high or low) + 1)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--arms: expected a range like 1-4 or a list like 2,5; got {text!r}") from None
    if not counts or min(counts) < 1:
        raise argparse.ArgumentTypeError(f"--arms: team sizes must be >= 1; got {text!r}")
    return tuple(counts)
