"""Task generation (paper section 4.1): vectorized, seeded, deterministic.

For each task of k arms: sample k planar base poses (random yaw, no two bases closer than
``MIN_BASE_SPACING``). The default ``layout="stratified"`` populates every difficulty bin
evenly (layouts are drawn until the task's difficulty falls in its assigned bin; tasks
harder than 0.5, beyond the paper's last bin, are rejected); ``layout="original"`` places
bases as the original code's training tasks were (:func:`sample_bases_original`: a random
walk, difficulty whatever it comes out, up to ~0.99); ``cell`` fixes the bases, the same in
every task (a work cell of one's own: :func:`cell_bases`). Then three collision-free composite configurations,
each from batched damped-least-squares IK toward random end-effector positions inside each
arm's workspace hemisphere, pulled toward the home configuration. Arms whose IK fails,
leaves the joint limits, or collides are resampled; a task stuck for ``MAX_ROUNDS`` rounds
gets a new layout.

Tasks are made in chunks; chunk ``c`` depends only on (seed, c, arguments), so any chunk can
be regenerated identically: :func:`generate_dataset` keeps finished chunks on disk, resumes
after an interruption, and can spread chunks over processes, always writing the same file. Within a chunk, team sizes cycle
through ``arm_counts`` and difficulty (and speed) bins cycle evenly.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import functools
import json
import multiprocessing
import pathlib
import shutil
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from mjx_multiarm.geometry.collision import CONTACTS_ONLY, scene_contacts
from mjx_multiarm.geometry.ik import solve_positions
from mjx_multiarm.geometry.kinematics import forward_kinematics
from mjx_multiarm.geometry.robot import REACH
from mjx_multiarm.geometry.scene import Scene, build_scene
from mjx_multiarm.geometry.transforms import yaw_quat
from mjx_multiarm.tasks.dataset import load_tasks, save_tasks
from mjx_multiarm.tasks.difficulty import task_difficulty
from mjx_multiarm.tasks.types import (
    DIFFICULTY_BINS,
    SPEED_BINS,
    Tasks,
    bin_index,
    concatenate,
)

MIN_BASE_SPACING = 0.3  # m
#: Per difficulty bin, the spacing scales of candidate layouts (m): the ranges where 1-10
#: arm layouts of that bin were found (measured), to raise the acceptance rate.
LAYOUT_SPACING = {"easy": (0.75, 1.9), "medium": (0.55, 1.35), "hard": (0.5, 1.3)}
IK_TOLERANCE = 1e-3  # m
IK_ITERATIONS = 30
INITIAL_NOISE = 0.3  # rad, spread of IK starting points around home
MAX_ROUNDS = 30
CHUNK_SIZE = 256
LAYOUT_BATCH = 512  # candidate layouts per draw (a fixed shape: one compile)
PROPOSALS = 16  # placement attempts per arm in a candidate layout
MAX_LAYOUT_DRAWS = 200  # draws of LAYOUT_BATCH candidates before a (team, bin) is given up
MODES = ("static", "dynamic")
LAYOUTS = ("stratified", "original")
#: The original code's base placement (configs/default.json, "random" generation): each
#: base offset from the previous one by up to this much along x and y (m).
ORIGINAL_MAX_OFFSET = 1.0


@dataclasses.dataclass(frozen=True)
class GenerationSpec:
    """What to generate: ``count`` tasks with team sizes cycling through ``arm_counts``."""

    count: int
    arm_counts: tuple[int, ...]
    mode: str = "static"
    seed: int = 0
    max_arms: int | None = None
    chunk_size: int = CHUNK_SIZE
    layout: str = "stratified"  # base placement: difficulty bins ("stratified") or as the original code ("original")
    cell: tuple[tuple[float, float, float], ...] | None = None  # fixed bases (x m, y m, yaw rad), one per arm, in every task

    def __post_init__(self):
        if self.count < 1:
            raise ValueError(f"count must be >= 1, got {self.count}")
        if not self.arm_counts or min(self.arm_counts) < 1:
            raise ValueError(f"arm_counts must be positive team sizes, got {self.arm_counts}")
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {self.mode!r}")
        if self.layout not in LAYOUTS:
            raise ValueError(f"layout must be one of {LAYOUTS}, got {self.layout!r}")
        if self.cell is not None:
            check_cell(self.cell)
            if self.arm_counts != (len(self.cell),):
                raise ValueError(f"a cell of {len(self.cell)} arms makes {len(self.cell)}-arm tasks only, got team sizes {self.arm_counts}")
            if self.layout != "stratified":
                raise ValueError(f"a cell fixes the bases; it takes no layout (got {self.layout!r})")
        if self.max_arms is not None and self.max_arms < max(self.arm_counts):
            raise ValueError(f"max_arms={self.max_arms} is smaller than the largest team {max(self.arm_counts)}")

    @property
    def slots(self) -> int:
        return self.max_arms or max(self.arm_counts)

    @property
    def num_chunks(self) -> int:
        return -(-self.count // self.chunk_size)

    def chunk_bounds(self, chunk: int) -> tuple[int, int]:
        """Global task indices [start, stop) of ``chunk``."""
        return chunk * self.chunk_size, min((chunk + 1) * self.chunk_size, self.count)


def _assignments(spec: GenerationSpec, start: int, stop: int):
    """Team size, difficulty bin and speed bin of global task indices [start, stop)."""
    index = np.arange(start, stop)
    teams = np.asarray(spec.arm_counts)[index % len(spec.arm_counts)]
    cycle = index // len(spec.arm_counts)
    difficulty_bins = np.where(teams == 1, 0, cycle % len(DIFFICULTY_BINS))
    speed_bins = (cycle // len(DIFFICULTY_BINS)) % len(SPEED_BINS)
    return index, teams, difficulty_bins, speed_bins


def _sample_layouts(rng: np.random.Generator, num_arms: int, spacing: tuple[float, float], count: int):
    """[count, num_arms, 2] candidate base positions and their validity.

    Each layout has a spacing scale s; arm i is placed about s from a random earlier arm,
    trying ``PROPOSALS`` directions for one that keeps at least ``max(0.3, 0.75 s)`` from
    every earlier base (so s controls how tightly the workspaces overlap).
    """
    scale = rng.uniform(*spacing, count)
    keep_out = np.maximum(MIN_BASE_SPACING, 0.75 * scale)
    xy = np.zeros((count, num_arms, 2))
    valid = np.ones(count, bool)
    rows = np.arange(count)
    for i in range(1, num_arms):
        anchor = xy[rows[:, None], rng.integers(0, i, (count, PROPOSALS))]  # [count, T, 2]
        angle = rng.uniform(-np.pi, np.pi, (count, PROPOSALS))
        dist = scale[:, None] * rng.uniform(0.9, 1.2, (count, PROPOSALS))
        proposal = anchor + dist[..., None] * np.stack([np.cos(angle), np.sin(angle)], -1)
        gap = np.linalg.norm(proposal[:, :, None] - xy[:, None, :i], axis=-1).min(axis=-1)  # [count, T]
        fits = gap >= keep_out[:, None]
        first = np.argmax(fits, axis=1)
        xy[:, i] = proposal[rows, first]
        valid &= fits[rows, first]
    return xy - xy.mean(axis=1, keepdims=True), valid, scale


def sample_bases(rng: np.random.Generator, teams, bins, slots: int):
    """Planar base positions [n, slots, 3], yaws [n, slots] and difficulty [n] per task.

    Candidate layouts are drawn until each task's difficulty lies in its bin; after a draw
    the spacing range narrows to the scales that produced accepted layouts (plus a margin).
    """
    n = len(teams)
    base_pos = np.zeros((n, slots, 3))
    difficulty = np.zeros(n)
    bin_names = list(DIFFICULTY_BINS)
    for team, b in sorted(set(zip(teams.tolist(), bins.tolist()))):
        todo = np.flatnonzero((teams == team) & (bins == b))
        spacing = LAYOUT_SPACING[bin_names[b]]
        for _ in range(MAX_LAYOUT_DRAWS):
            if not len(todo):
                break
            xy, valid, scale = _sample_layouts(rng, team, spacing, LAYOUT_BATCH)
            found = task_difficulty(xy, np.ones(xy.shape[:2], bool)) if team > 1 else np.zeros(len(xy))
            ok = valid & (bin_index(found, DIFFICULTY_BINS) == b)
            if ok.sum() >= 5:
                spacing = (scale[ok].min() - 0.05, scale[ok].max() + 0.05)
            take = np.flatnonzero(ok)[: len(todo)]
            base_pos[todo[: len(take)], :team, :2] = xy[take]
            difficulty[todo[: len(take)]] = found[take]
            todo = todo[len(take) :]
        if len(todo):
            raise RuntimeError(f"no {team}-arm layout in the {bin_names[b]} bin after {MAX_LAYOUT_DRAWS} draws")
    yaw = rng.uniform(-np.pi, np.pi, (n, slots))
    return base_pos, yaw, difficulty


def sample_bases_original(rng: np.random.Generator, teams, slots: int):
    """Base positions [n, slots, 3], yaws [n, slots] and difficulty [n] placed as the
    original's training tasks: every base is the previous one plus a uniform offset in
    [-1, 1] m along x and y, layouts redrawn until no two bases are closer than
    ``MIN_BASE_SPACING``; the difficulty is measured, not chosen."""
    n = len(teams)
    base_pos = np.zeros((n, slots, 3))
    for team in np.unique(teams):
        todo = np.flatnonzero(teams == team)
        while len(todo):
            steps = rng.uniform(-ORIGINAL_MAX_OFFSET, ORIGINAL_MAX_OFFSET, (len(todo), team, 2))
            xy = np.cumsum(steps, axis=1)
            gap = np.linalg.norm(xy[:, :, None] - xy[:, None], axis=-1) + np.eye(team) * 1e9
            ok = gap.min(axis=(1, 2)) > MIN_BASE_SPACING
            base_pos[todo[ok], :team, :2] = xy[ok] - xy[ok].mean(axis=1, keepdims=True)
            todo = todo[~ok]
    active = np.arange(slots) < np.asarray(teams)[:, None]
    return base_pos, rng.uniform(-np.pi, np.pi, (n, slots)), task_difficulty(base_pos, active)


def check_cell(cell) -> None:
    """Raise ValueError unless ``cell`` is a list of (x, y, yaw) bases no two closer than
    ``MIN_BASE_SPACING``."""
    rows = np.asarray(cell, dtype=float) if len(cell) else np.zeros((0, 3))
    if rows.ndim != 2 or rows.shape[1] != 3 or not len(rows):
        raise ValueError(f"a cell is a list of bases [x, y, yaw] (m, m, rad), one per arm; got {cell!r}")
    if not np.isfinite(rows).all():
        raise ValueError(f"a cell's bases must be finite numbers; got {cell!r}")
    gap = np.linalg.norm(rows[:, None, :2] - rows[None, :, :2], axis=-1) + np.eye(len(rows)) * 1e9
    if gap.min() < MIN_BASE_SPACING:
        i, j = np.unravel_index(np.argmin(gap), gap.shape)
        raise ValueError(f"cell bases {i} and {j} are {gap[i, j]:.3f} m apart, closer than {MIN_BASE_SPACING} m")


def cell_bases(cell, count: int, slots: int):
    """Base positions [count, slots, 3], yaws [count, slots] and difficulty [count] of
    ``count`` tasks in the fixed ``cell`` (the paper's difficulty of its layout)."""
    rows = np.asarray(cell, dtype=float)
    base_pos, yaw = np.zeros((count, slots, 3)), np.zeros((count, slots))
    base_pos[:, : len(rows), :2], yaw[:, : len(rows)] = rows[:, :2], rows[:, 2]
    active = np.broadcast_to(np.arange(slots) < len(rows), (count, slots))
    return base_pos, yaw, task_difficulty(base_pos, active)


def _hemisphere_targets(rng: np.random.Generator, shape) -> np.ndarray:
    """Uniform random points [*shape, 3] in the workspace hemisphere (base frame)."""
    direction = rng.normal(size=(*shape, 3))
    direction[..., 2] = np.abs(direction[..., 2])
    direction /= np.linalg.norm(direction, axis=-1, keepdims=True)
    return direction * REACH * rng.uniform(size=(*shape, 1)) ** (1 / 3)


@functools.cache
def _kernels(scene: Scene):
    """Jitted IK and composite collision check for one scene."""
    arm = scene.arm

    @jax.jit
    def ik(targets, initial):
        joints, error = solve_positions(arm, targets, initial, iterations=IK_ITERATIONS)
        lower, upper = (jnp.asarray(arm.joint_range[:, i], joints.dtype) for i in (0, 1))
        within = jnp.all((joints >= lower) & (joints <= upper), axis=-1)
        return joints, (error < IK_TOLERANCE) & within

    @jax.jit
    def collided(base_pos, base_quat, joints, active):
        return scene_contacts(scene, base_pos, base_quat, joints, active, CONTACTS_ONLY).collided

    return ik, collided


def _padded(x, rows: int):
    """``x`` with zero rows appended up to ``rows`` (a fixed shape for the jitted kernels)."""
    x = np.asarray(x)
    return np.concatenate([x, np.zeros((rows - len(x), *x.shape[1:]), x.dtype)]) if rows > len(x) else x


def sample_configurations(rng: np.random.Generator, scene: Scene, base_pos, base_quat, active, pad_to: int = 0):
    """One collision-free composite configuration per task: (joints [n, A, 6], ok [n]).

    The kernels run on ``max(n, pad_to)`` rows (padding rows are inactive), so the retries
    of a chunk, whatever their count, reuse one compilation; the random draws are the same.
    """
    ik, collided = _kernels(scene)
    arm = scene.arm
    n, rows = len(active), max(len(active), pad_to)
    joints = np.broadcast_to(arm.home, (*active.shape, 6)).copy()
    accepted = ~active
    base_pos, base_quat = _padded(base_pos, rows), _padded(base_quat, rows)
    for _ in range(MAX_ROUNDS):
        pending = ~accepted
        if not pending.any():
            break
        targets = _hemisphere_targets(rng, active.shape)
        initial = arm.home + rng.normal(0.0, INITIAL_NOISE, (*active.shape, 6))
        solved, ok = ik(jnp.asarray(_padded(targets, rows), jnp.float32), jnp.asarray(_padded(initial, rows), jnp.float32))
        tentative = pending & np.asarray(ok)[:n]
        trial = np.where(tentative[..., None], np.asarray(solved, np.float64)[:n], joints)
        hit = np.asarray(collided(base_pos, base_quat, jnp.asarray(_padded(trial, rows), jnp.float32),
                                  _padded(active & (accepted | tentative), rows)))[:n]
        keep = tentative & ~hit
        joints[keep] = trial[keep]
        accepted |= keep
    return joints, accepted.all(axis=-1)


def generate_chunk(spec: GenerationSpec, chunk: int) -> Tasks:
    """The tasks of chunk number ``chunk`` of ``spec``, identical whenever regenerated."""
    start, stop = spec.chunk_bounds(chunk)
    rng = np.random.default_rng([spec.seed, chunk])
    index, teams, difficulty_bins, speed_bins = _assignments(spec, start, stop)
    scene = build_scene(spec.slots)
    n, slots = len(index), spec.slots
    active = np.arange(slots) < teams[:, None]
    base_pos, base_quat = np.zeros((n, slots, 3)), np.zeros((n, slots, 4))
    difficulty, configs = np.zeros(n), np.zeros((3, n, slots, 6))
    todo = np.ones(n, bool)
    while todo.any():  # tasks whose configurations got stuck start over with a new layout
        if spec.cell is not None:
            pos, yaw, diff = cell_bases(spec.cell, int(todo.sum()), slots)
        elif spec.layout == "original":
            pos, yaw, diff = sample_bases_original(rng, teams[todo], slots)
        else:
            pos, yaw, diff = sample_bases(rng, teams[todo], difficulty_bins[todo], slots)
        quat = np.asarray(yaw_quat(yaw), np.float64)
        ok = np.ones(todo.sum(), bool)
        found = []
        for _ in range(3 if spec.mode == "dynamic" else 2):
            joints, done = sample_configurations(rng, scene, pos, quat, active[todo], pad_to=n)
            found.append(joints)
            ok &= done
        rows = np.flatnonzero(todo)[ok]
        base_pos[rows], base_quat[rows], difficulty[rows] = pos[ok], quat[ok], diff[ok]
        for c, joints in enumerate(found):
            configs[c, rows] = joints[ok]
        todo[rows] = False
    if spec.mode == "static":
        configs[2] = configs[1]
    frames = forward_kinematics(scene.arm, base_pos, base_quat, jnp.asarray(configs[1]))
    speed = np.zeros(n)
    if spec.mode == "dynamic":
        bounds = np.array(list(SPEED_BINS.values()))[speed_bins]
        speed = rng.uniform(bounds[:, 0], bounds[:, 1])
    identity = np.array([1.0, 0.0, 0.0, 0.0])
    pad = ~active[..., None]
    return Tasks(
        task_id=(spec.seed % 2**31) * 2**32 + index,
        active=active,
        base_pos=np.where(pad, 0.0, base_pos),
        base_quat=np.where(pad, identity, base_quat),
        start_joints=np.where(pad, 0.0, configs[0]),
        goal_joints=np.where(pad, 0.0, configs[1]),
        dynamic_start_joints=np.where(pad, 0.0, configs[2]),
        target_pos=np.where(pad, 0.0, np.asarray(frames.ee_pos, np.float64)),
        target_quat=np.where(pad, identity, np.asarray(frames.ee_quat, np.float64)),
        difficulty=difficulty,
        speed=speed,
    )


def spec_record(spec: GenerationSpec) -> dict:
    """``spec`` as JSON-serialisable data (stored beside partial and finished datasets)."""
    cell = None if spec.cell is None else [list(base) for base in spec.cell]
    return {**dataclasses.asdict(spec), "arm_counts": list(spec.arm_counts), "cell": cell}


def _make_chunk(spec: GenerationSpec, chunk: int, path: pathlib.Path) -> int:
    """Generate one chunk and save it atomically; returns its task count."""
    tasks = generate_chunk(spec, chunk)
    save_tasks(path, tasks)
    return tasks.num_tasks


def generate_dataset(
    spec: GenerationSpec,
    out: pathlib.Path,
    workers: int = 1,
    on_progress: Callable[[int, int], None] | None = None,
) -> Tasks:
    """Generate ``spec`` into the dataset file ``out``, resumably; returns the tasks.

    Finished chunks live in ``out.partial/`` until the dataset is written, so a re-run after
    an interruption only makes the missing chunks. ``workers`` > 1 makes chunks in that many
    processes (same output). ``on_progress(done, made_now)`` is called after each chunk.
    """
    out = pathlib.Path(out)
    partial = out.with_name(out.name + ".partial")
    partial.mkdir(parents=True, exist_ok=True)
    record = spec_record(spec)
    spec_file = partial / "spec.json"
    if spec_file.exists() and json.loads(spec_file.read_text()) != record:
        raise ValueError(f"{partial}: holds a generation with other arguments; delete it or use another --out")
    spec_file.write_text(json.dumps(record, sort_keys=True))
    chunk_path = [partial / f"chunk_{c:06d}.npz" for c in range(spec.num_chunks)]
    todo = [c for c, path in enumerate(chunk_path) if not path.exists()]
    resumed = done = spec.count - sum(min(spec.chunk_size, spec.count - c * spec.chunk_size) for c in todo)

    def finished(count: int) -> None:
        nonlocal done
        done += count
        if on_progress:
            on_progress(done, done - resumed)

    if workers > 1 and len(todo) > 1:
        context = multiprocessing.get_context("spawn")  # JAX is not fork-safe
        with concurrent.futures.ProcessPoolExecutor(min(workers, len(todo)), mp_context=context) as pool:
            futures = [pool.submit(_make_chunk, spec, c, chunk_path[c]) for c in todo]
            for future in concurrent.futures.as_completed(futures):
                finished(future.result())
    else:
        for c in todo:
            finished(_make_chunk(spec, c, chunk_path[c]))
    tasks = concatenate([load_tasks(p)[0] for p in chunk_path])
    save_tasks(out, tasks, {"generator": record})
    shutil.rmtree(partial)
    return tasks


#: Named datasets (``python -m mjx_multiarm.tasks generate --preset NAME``): the paper's train
#: and test sets, and small ones for the default CPU run and the tests.
DATASETS = {
    "train": GenerationSpec(count=1_000_000, arm_counts=(1, 2, 3, 4), mode="static", seed=0),
    "test": GenerationSpec(count=30_000, arm_counts=tuple(range(1, 11)), mode="dynamic", seed=1),
    "small": GenerationSpec(count=1_000, arm_counts=(1, 2, 3, 4), mode="static", seed=2),
    "tiny": GenerationSpec(count=40, arm_counts=(1, 2, 3, 4), mode="static", seed=3),
}
