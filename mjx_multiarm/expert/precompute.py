"""Batched, resumable expert precompute over a task dataset, in local processes or on Ray.

Tasks are planned in chunks; every finished chunk is written atomically to
``OUT.partial/`` beside the requested output, so a killed run, started again with the same
arguments, plans only the chunks it had not finished and writes the same file (each task's
plan depends only on the task, the planner settings and the seed: see
:mod:`mjx_multiarm.expert.planner`). When every chunk is done they are merged into ``OUT``.

Backends: ``local`` plans chunks in ``workers`` processes (one CPU thread each); ``ray``
submits them as Ray tasks (``pip install ".[ray]"``; a running cluster via ``ray_address``,
otherwise a local one), and this process writes the results.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import dataclasses
import hashlib
import json
import multiprocessing
import os
import pathlib
import shutil
from collections.abc import Callable, Iterator

from mjx_multiarm.expert.planner import SOLVED, PlannerConfig
from mjx_multiarm.expert.solve import solve_task
from mjx_multiarm.expert.store import (
    ExpertStore,
    ExpertTable,
    merge_experts,
    save_experts,
)
from mjx_multiarm.tasks.dataset import load_tasks
from mjx_multiarm.tasks.types import Tasks, take

BACKENDS = ("local", "ray")
#: Tasks per chunk (the unit of resumption and of work handed to a worker).
CHUNK_SIZE = 16
#: XLA flags of worker processes: one CPU thread each, so N workers use N cores.
SINGLE_THREAD_XLA = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"


def plan_chunk(tasks: Tasks, config: PlannerConfig, seed: int) -> ExpertTable:
    """The experts of every task in ``tasks`` (the unit of work of a worker)."""
    return ExpertTable.from_results([solve_task(tasks, i, config, seed) for i in range(tasks.num_tasks)])


@contextlib.contextmanager
def _single_thread_children():
    """Processes started inside inherit single-threaded XLA flags."""
    previous = os.environ.get("XLA_FLAGS")
    os.environ["XLA_FLAGS"] = f"{previous or ''} {SINGLE_THREAD_XLA}".strip()
    try:
        yield
    finally:
        if previous is None:
            os.environ.pop("XLA_FLAGS")
        else:
            os.environ["XLA_FLAGS"] = previous


def _run_local(jobs, config, seed, workers) -> Iterator[tuple[int, ExpertTable]]:
    if workers <= 1 or len(jobs) <= 1:
        for chunk, tasks in jobs:
            yield chunk, plan_chunk(tasks, config, seed)
        return
    context = multiprocessing.get_context("spawn")  # JAX is not fork-safe
    with _single_thread_children(), concurrent.futures.ProcessPoolExecutor(min(workers, len(jobs)), mp_context=context) as pool:
        futures = {pool.submit(plan_chunk, tasks, config, seed): chunk for chunk, tasks in jobs}
        for future in concurrent.futures.as_completed(futures):
            yield futures[future], future.result()


def _run_ray(jobs, config, seed, address) -> Iterator[tuple[int, ExpertTable]]:
    try:
        import ray
    except ImportError as error:
        raise RuntimeError("the ray backend needs Ray: pip install '.[ray]'") from error
    if not ray.is_initialized():
        ray.init(address=address, runtime_env={"env_vars": {"XLA_FLAGS": SINGLE_THREAD_XLA}}, log_to_driver=False)
    remote = ray.remote(num_cpus=1)(plan_chunk)
    pending = {remote.remote(tasks, config, seed): chunk for chunk, tasks in jobs}
    while pending:
        ready, _ = ray.wait(list(pending), num_returns=1)
        yield pending.pop(ready[0]), ray.get(ready[0])


def file_digest(path: str | os.PathLike) -> str:
    """SHA-256 of a file's bytes (what an expert file records of its task file)."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def precompute(
    tasks_path: str | os.PathLike,
    out: str | os.PathLike,
    config: PlannerConfig = PlannerConfig(),
    seed: int = 0,
    workers: int = 1,
    backend: str = "local",
    chunk_size: int = CHUNK_SIZE,
    ray_address: str | None = None,
    on_progress: Callable[[int, int, int], None] | None = None,
) -> ExpertStore:
    """Plan every task of the dataset ``tasks_path`` into the expert file ``out``, resumably.

    ``on_progress(done, planned_now, solved)`` is called after each chunk.
    Raises ValueError when ``OUT.partial/`` holds a run with other arguments.
    """
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if chunk_size < 1:
        raise ValueError(f"chunk_size must be >= 1, got {chunk_size}")
    tasks_path, out = pathlib.Path(tasks_path), pathlib.Path(out)
    tasks, _ = load_tasks(tasks_path)
    record = {"tasks": file_digest(tasks_path), "planner": dataclasses.asdict(config), "seed": seed, "chunk_size": chunk_size}
    partial = out.with_name(out.name + ".partial")
    partial.mkdir(parents=True, exist_ok=True)
    spec_file = partial / "spec.json"
    if spec_file.exists() and json.loads(spec_file.read_text()) != record:
        raise ValueError(f"{partial}: holds a precompute with other tasks or settings; delete it or use another --out")
    spec_file.write_text(json.dumps(record, sort_keys=True))

    bounds = [(start, min(start + chunk_size, tasks.num_tasks)) for start in range(0, tasks.num_tasks, chunk_size)]
    chunk_path = [partial / f"chunk_{c:06d}.experts" for c in range(len(bounds))]
    todo = [c for c, path in enumerate(chunk_path) if not path.exists()]
    done_chunks = [c for c in range(len(bounds)) if c not in set(todo)]
    done = sum(bounds[c][1] - bounds[c][0] for c in done_chunks)
    solved = sum(int(ExpertStore(chunk_path[c]).solved.sum()) for c in done_chunks)
    resumed = done
    jobs = [(c, take(tasks, slice(*bounds[c]))) for c in todo]
    results = _run_ray(jobs, config, seed, ray_address) if backend == "ray" else _run_local(jobs, config, seed, workers)
    for chunk, table in results:
        save_experts(chunk_path[chunk], table)
        done += len(table.blocks)
        solved += int((table.index["status"] == SOLVED).sum())
        if on_progress:
            on_progress(done, done - resumed, solved)
    merge_experts(out, chunk_path, {"precompute": record, "tasks_file": str(tasks_path)})
    shutil.rmtree(partial)
    return ExpertStore(out)
