"""Command-line helpers shared by every entry point: team-size ranges and the one progress line."""

from __future__ import annotations

import argparse
import sys
import time


class Progress:
    """The one progress line on stderr, rewritten in place (at most every ``interval`` s), with
    log messages printed on lines of their own: :meth:`update` draws a bar of ``done`` of
    ``total`` with its rate and ETA, :meth:`show` any text (training's rows)."""

    def __init__(self, total: int = 0, unit: str = "", interval: float = 0.0):
        self.total, self.unit, self.interval = total, unit, interval
        self.start, self.last, self.open = time.perf_counter(), -float("inf"), False

    def update(self, done: int, new: int, note: str = "") -> None:
        """``done`` of ``total`` finished, ``new`` of them by this run (the rate counts those)."""
        elapsed = time.perf_counter() - self.start
        rate = new / elapsed if elapsed > 0 and new else 0.0
        eta = (self.total - done) / rate if rate else float("nan")
        bar = "#" * int(30 * done / max(self.total, 1))
        self.show(f"[{bar:<30}] {done}/{self.total} {self.unit} {rate:,.1f}/s ETA {eta:,.0f}s {note}")

    def show(self, text: str) -> None:
        """Rewrite the line with ``text`` (skipped within ``interval`` of the last time)."""
        now = time.perf_counter()
        if now - self.last < self.interval:
            return
        self.last, self.open = now, True
        print(f"\r{text} ", end="", file=sys.stderr, flush=True)

    def log(self, message: str) -> None:
        """A message on a line of its own, below the progress line."""
        self.close()
        print(message, file=sys.stderr, flush=True)

    def close(self) -> None:
        """End the progress line."""
        if self.open:
            print(file=sys.stderr)
            self.open = False


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
