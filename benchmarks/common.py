"""Helpers shared by the benchmark scripts: the machine's name, the timing options, and the
random two-arm steps of the collision-check benchmarks."""

from __future__ import annotations

import argparse
import platform

import jax
import numpy as np

from mjx_multiarm.env.reaching import ReachingEnv
from mjx_multiarm.geometry.transforms import yaw_quat


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


def random_two_arm_steps(n: int, rng: np.random.Generator):
    """Two-arm scenes (bases 0.5-0.9 m apart, random yaws, joints home + N(0, 1 rad)) and a
    full-speed step of every joint of both arms: (env, base_pos, base_quat, q0, q1)."""
    env = ReachingEnv(2)
    arm = env.scene.arm
    angle, gap = rng.uniform(-np.pi, np.pi, n), rng.uniform(0.5, 0.9, n)
    pos = np.zeros((n, 2, 3), np.float32)
    pos[:, 1, :2] = gap[:, None] * np.stack([np.cos(angle), np.sin(angle)], -1)
    quat = np.asarray(yaw_quat(rng.uniform(-np.pi, np.pi, (n, 2))), np.float32)
    q0 = np.clip(arm.home + rng.normal(0.0, 1.0, (n, 2, 6)), *arm.joint_range.T).astype(np.float32)
    q1 = (q0 + rng.choice([-1.0, 1.0], (n, 2, 6)) * env.max_step).astype(np.float32)
    return env, pos, quat, q0, q1
