"""Shared fixtures and helpers: random multi-arm scenes, hand-made tasks, jitted rollouts, the
optional reference data."""

from __future__ import annotations

import os
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import settings

from mjx_multiarm.env.reaching import ReachingEnv
from mjx_multiarm.env.scripted import ik_actions
from mjx_multiarm.env.wrappers import batched_step
from mjx_multiarm.geometry.evaluate import base_pose_arrays
from mjx_multiarm.geometry.ik import solve_positions
from mjx_multiarm.geometry.kinematics import forward_kinematics
from mjx_multiarm.geometry.robot import load_arm
from mjx_multiarm.tasks.dataset import load_tasks, save_tasks
from mjx_multiarm.tasks.generate import GenerationSpec, generate_chunk
from mjx_multiarm.tasks.types import Tasks

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


def pytest_configure(config):
    """The fast tier (``-m 'not slow'``, the default) is mostly XLA compilation of small
    programs: it compiles them with unoptimized code generation, faster to compile and slower
    to run, which its tiny batches do not notice (benchmarks/RESULTS.md, issue 51). The slow
    tier's training runs keep XLA's default. Set before JAX starts its backend (no test module
    starts it at import); an ``XLA_FLAGS`` that sets the level already wins."""
    flags = os.environ.get("XLA_FLAGS", "")
    if config.getoption("markexpr") == "not slow" and "xla_backend_optimization_level" not in flags:
        os.environ["XLA_FLAGS"] = f"{flags} --xla_backend_optimization_level=0".strip()


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
def generated(tmp_path_factory, worker_id):
    """256 dynamic-capable tasks of 1-10 arms in 10 slots (one chunk, seed 7), generated once
    per test run: the first xdist worker to claim them writes them to the run's temporary
    root (atomically), and the others read that file instead of generating them again."""
    spec = GenerationSpec(count=256, arm_counts=tuple(range(1, 11)), mode="dynamic", seed=7)
    if worker_id == "master":  # no xdist workers
        return generate_chunk(spec, 0)
    shared = tmp_path_factory.getbasetemp().parent / "generated.npz"
    try:
        os.close(os.open(shared.with_suffix(".claimed"), os.O_CREAT | os.O_EXCL))
    except FileExistsError:  # another worker generates them
        for _ in range(3000):
            if shared.exists():
                return load_tasks(shared)[0]
            time.sleep(0.2)
        raise TimeoutError(f"{shared}: the worker that claimed the generated tasks wrote none in 10 minutes")
    tasks = generate_chunk(spec, 0)
    save_tasks(shared, tasks)
    return tasks


def make_tasks(bases, start, goal) -> Tasks:
    """Numpy tasks from planar bases [N, A, 3] and joints [N, A, 6] (all slots active)."""
    arm = load_arm()
    pos, quat = base_pose_arrays(bases)
    frames = forward_kinematics(arm, pos, quat, jnp.asarray(goal, jnp.float32))
    n, a = bases.shape[:2]
    return Tasks(
        task_id=np.arange(n, dtype=np.int64), active=np.ones((n, a), bool), base_pos=pos, base_quat=quat,
        start_joints=start, goal_joints=goal, dynamic_start_joints=goal,
        target_pos=np.asarray(frames.ee_pos, np.float64), target_quat=np.asarray(frames.ee_quat, np.float64),
        difficulty=np.zeros(n), speed=np.zeros(n),
    )


def rollout(env: ReachingEnv, steps: int, policy=None):
    """jit(vmap) rollout from reset: (final states, stacked stepped states, actions)."""
    policy = policy or (lambda state: ik_actions(env, state))

    @jax.jit
    def run(tasks, tolerance):
        start = jax.vmap(lambda task: env.reset(None, task, tolerance))(tasks)

        def body(state, _):
            actions = jax.vmap(policy)(state)
            state = batched_step(env)(state, actions)
            return state, (state, actions)

        final, (states, actions) = jax.lax.scan(body, start, None, steps)
        return final, states, actions

    return run


def facing_pair():
    """Two arms 0.8 m apart facing each other, each driven to a point past the other's target."""
    arm = load_arm()
    bases = np.array([[[0.0, 0.0, 0.0], [0.8, 0.0, np.pi]]])
    goal, error = solve_positions(arm, jnp.array([[0.55, 0.0, 0.35]]), jnp.asarray(arm.home[None], jnp.float32), iterations=80)
    assert float(error[0]) < 1e-3
    goal = np.repeat(np.asarray(goal, np.float64)[None], 2, axis=1)
    start = np.repeat(arm.home[None, None], 2, axis=1)
    return make_tasks(bases, start, goal)
