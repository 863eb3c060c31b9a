"""Helpers shared by the benchmark scripts: the machine's name and the timing options."""

from __future__ import annotations

import argparse
import platform

import jax


def cpu_name() -> str:
    """The CPU model (Linux), else the machine type."""
    try:
        with open("/proc/cpuinfo") as f:
            return next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        return platform.machine()


def add_timing_arguments(parser: argparse.ArgumentParser, steps: int, steps_help: str) -> None:
    """The options every throughput benchmark shares: device, steps per rollout, timing, JSON."""
    parser.add_argument("--device", choices=["cpu", "gpu"], default=None, help="default: JAX's default device")
    parser.add_argument("--steps", type=int, default=steps, help=steps_help)
    parser.add_argument("--seconds", type=float, default=2.0, help="minimum timing per measurement")
    parser.add_argument("--json", action="store_true", help="print one JSON line per measurement")


def selected_device(args) -> jax.Device:
    """The device named by ``--device`` (default: JAX's default device)."""
    return jax.devices(args.device)[0] if args.device else jax.devices()[0]
