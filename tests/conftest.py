"""Shared fixtures: random multi-arm scenes and the optional reference data."""

from __future__ import annotations

import os
import pathlib

import jax
import numpy as np
import pytest
from hypothesis import settings

from mjx_multiarm.geometry.robot import load_arm
from mjx_multiarm.tasks.generate import GenerationSpec, generate_chunk

# No per-example deadline for property tests: eager JAX compiles on the first call of each
# shape, which takes seconds on a loaded 2-core machine; speed is measured by benchmarks.
settings.register_profile("untimed", deadline=None)
settings.load_profile("untimed")

REFERENCE = pathlib.Path(__file__).resolve().parents[2] / "shared" / "reference" / "ur5"

# Compiled programs persist between test runs (and are shared by the xdist workers of one),
# so a re-run between edits compiles only what changed. MJX_MULTIARM_TEST_CACHE="" turns it off.
_CACHE = os.environ.get("MJX_MULTIARM_TEST_CACHE", str(pathlib.Path(__file__).resolve().parent / ".jax_cache"))
if _CACHE:
    jax.config.update("jax_compilation_cache_dir", _CACHE)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)


@pytest.fixture
def reference_dir() -> pathlib.Path:
    """``../shared/reference/ur5`` beside the checkout; skips where it is absent."""
    if not REFERENCE.is_dir():
        pytest.skip(f"reference data not found at {REFERENCE}")
    return REFERENCE


def random_bases(rng: np.random.Generator, num_arms: int, min_gap=0.3, max_gap=1.5) -> np.ndarray:
    """Planar base poses [num_arms, 3] (x, y, yaw): each base 0.3-1.5 m from an earlier one."""
    bases = np.zeros((num_arms, 3))
    bases[:, 2] = rng.uniform(-np.pi, np.pi, num_arms)
    for i in range(1, num_arms):
        while True:
            anchor = bases[rng.integers(i), :2]
            angle, dist = rng.uniform(-np.pi, np.pi), rng.uniform(min_gap, max_gap)
            xy = anchor + dist * np.array([np.cos(angle), np.sin(angle)])
            if np.min(np.linalg.norm(bases[:i, :2] - xy, axis=1)) >= min_gap:
                bases[i, :2] = xy
                break
    return bases


def random_joints(rng: np.random.Generator, shape, spread=1.0) -> np.ndarray:
    """Joint configurations [*shape, 6]: home plus Gaussian noise, within the joint limits."""
    arm = load_arm()
    q = arm.home + rng.normal(0.0, spread, (*shape, 6))
    return np.clip(q, arm.joint_range[:, 0], arm.joint_range[:, 1])


def random_padded_scenes(rng: np.random.Generator, count: int, max_arms: int, spread=1.0):
    """``count`` padded scenes with 1..max_arms active arms: (bases, joints, active)."""
    bases = np.zeros((count, max_arms, 3))
    active = np.zeros((count, max_arms), bool)
    for k in range(count):
        n = 1 + k % max_arms
        bases[k, :n] = random_bases(rng, n)
        active[k, :n] = True
    return bases, random_joints(rng, (count, max_arms), spread), active


@pytest.fixture(scope="session")
def generated():
    """256 dynamic-capable tasks of 1-10 arms in 10 slots (one chunk, seed 7)."""
    return generate_chunk(GenerationSpec(count=256, arm_counts=tuple(range(1, 11)), mode="dynamic", seed=7), 0)
