"""The BiRRT expert: planning, decimation, replay in the environment, storage, precompute."""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import random_joints
from hypothesis import given, settings
from hypothesis import strategies as st

from mjx_multiarm.env.reaching import EnvConfig, ReachingEnv, step_limits
from mjx_multiarm.env.wrappers import Outcomes, TaskBank, replay_actions
from mjx_multiarm.expert import __main__ as cli
from mjx_multiarm.expert import precompute as precompute_module
from mjx_multiarm.expert.decimate import corner_points, path_to_deltas
from mjx_multiarm.expert.planner import STATUSES, PlannerConfig
from mjx_multiarm.expert.precompute import precompute
from mjx_multiarm.expert.replan import replan_episode
from mjx_multiarm.expert.solve import solve_task
from mjx_multiarm.expert.store import (
    ExpertStore,
    ExpertTable,
    merge_experts,
    save_experts,
)
from mjx_multiarm.geometry.evaluate import evaluate_arms
from mjx_multiarm.geometry.robot import load_arm
from mjx_multiarm.planner.handover import birrt_handover
from mjx_multiarm.tasks.dataset import save_tasks
from mjx_multiarm.tasks.types import take, with_slots

MAX_STEP, SUBSTEPS = step_limits(load_arm())


@pytest.fixture(scope="module")
def small_tasks(generated):
    """Three 1-arm and three 2-arm tasks in 2 slots."""
    rows = np.concatenate([np.flatnonzero(generated.num_arms == k)[:3] for k in (1, 2)])
    return with_slots(take(generated, rows), 2)


@pytest.fixture(scope="module")
def solved(small_tasks):
    return [solve_task(small_tasks, i, PlannerConfig(time_limit=20)) for i in range(small_tasks.num_tasks)]


def test_expert_steps_replay_in_the_environment(small_tasks, solved):
    assert all(r.status == 0 for r in solved), [STATUSES[r.status] for r in solved]
    env = ReachingEnv(2, EnvConfig(max_steps=500))
    length = max(len(r.deltas) for r in solved)
    actions = np.zeros((len(solved), length, 2, 6), np.float32)
    for i, r in enumerate(solved):
        actions[i, : len(r.deltas), : r.deltas.shape[1]] = r.deltas
        assert np.all(np.abs(r.deltas) <= MAX_STEP + 1e-6)  # one environment step each
        arms = int(small_tasks.num_arms[i])
        end = small_tasks.start_joints[i, :arms] + r.deltas.astype(np.float64).sum(0)
        np.testing.assert_allclose(end, small_tasks.goal_joints[i, :arms], atol=1e-4)
    bank = TaskBank.from_tasks(small_tasks, 2)
    start = jax.jit(jax.vmap(lambda task: env.reset(None, task)))(bank.tasks)
    replay = jax.jit(jax.vmap(lambda s, a, n: replay_actions(env, s, a, n)))
    states, _ = replay(start, jnp.asarray(env.joint_deltas_to_actions(actions)), jnp.asarray([len(r.deltas) for r in solved]))
    assert np.asarray(states.success.any(axis=1)).all()
    assert not np.asarray(states.collided.any(axis=(1, 2))).any()


def test_planning_is_deterministic(small_tasks, solved):
    again = solve_task(small_tasks, 4, PlannerConfig(time_limit=20))
    np.testing.assert_array_equal(again.deltas, solved[4].deltas)
    assert again.iterations == solved[4].iterations


def test_failures_are_reported_with_their_reason(small_tasks, solved):
    pair = take(small_tasks, np.array([3]))
    crashed = pair.replace(base_pos=np.zeros_like(pair.base_pos))  # both bases at the same spot
    result = solve_task(crashed, 0, PlannerConfig(time_limit=20))
    assert STATUSES[result.status] == "start_in_collision" and result.iterations == 0 and len(result.deltas) == 0
    rng = np.random.default_rng(0)
    candidates = random_joints(rng, (64, 1), spread=2.0)
    hits = evaluate_arms(np.zeros((64, 1, 3)), candidates).collided[:, 0]
    goal = pair.goal_joints.copy()
    goal[0, 0] = candidates[np.argmax(hits), 0]  # arm 0's goal folds it into itself or the ground
    result = solve_task(pair.replace(goal_joints=goal), 0, PlannerConfig(time_limit=20))
    assert STATUSES[result.status] == "goal_in_collision" and result.iterations == 0
    hardest = int(np.argmax([r.iterations for r in solved]))
    cap = solved[hardest].iterations - 1  # this task needs a search: cap it below what it needs
    assert cap >= 1
    capped = solve_task(small_tasks, hardest, PlannerConfig(iterations=cap, time_limit=20))
    assert STATUSES[capped.status] == "iteration_limit" and capped.iterations == cap and len(capped.deltas) == 0


def test_handover_plans_the_timed_out_tasks_from_where_they_ended(small_tasks, solved):
    n, team = small_tasks.num_tasks, small_tasks.num_arms
    timeout = np.array([False, False, True, True, True, True])
    won = np.arange(n) == 0
    ended = Outcomes(team, won, np.arange(n) == 1, timeout, np.full(n, 10), np.where(won, team, 0))
    final = small_tasks.start_joints.copy()  # tasks 3-5 stuck at their start: the plan is the expert's
    candidates = random_joints(np.random.default_rng(0), (64, 1), spread=2.0)
    final[2, 0] = candidates[np.argmax(evaluate_arms(np.zeros((64, 1, 3)), candidates).collided[:, 0])]  # task 2: in collision
    handed, plan_s = birrt_handover(small_tasks, ended, final, PlannerConfig(time_limit=20))
    assert np.isnan(plan_s[:2]).all() and (plan_s[2:] > 0).all()  # only the timeouts are planned
    np.testing.assert_array_equal(handed.success, [True, False, False, True, True, True])
    np.testing.assert_array_equal(handed.timeout, [False, False, True, False, False, False])
    np.testing.assert_array_equal(handed.collision, ended.collision)
    assert [int(handed.steps[i]) for i in range(3, 6)] == [10 + len(solved[i].deltas) for i in range(3, 6)]
    np.testing.assert_array_equal(handed.reached, np.where(handed.success, team, 0))
    # The episode's limit holds for the policy's steps plus the plan's: a plan that would end past it fails.
    shortest = min(len(solved[i].deltas) for i in range(3, 6))
    for limit, solved_ones in ((10 + shortest - 1, 0), (10 + shortest, 1)):
        capped, _ = birrt_handover(small_tasks, ended, final, PlannerConfig(time_limit=20), max_steps=limit)
        assert capped.success[3:].sum() >= solved_ones and (capped.steps[3:][capped.success[3:]] <= limit).all()
        assert capped.success[3:].sum() == 0 or solved_ones
    with pytest.raises(ValueError, match="must match"):
        birrt_handover(small_tasks, ended, final[:2])


@settings(max_examples=40)
@given(st.integers(2, 8), st.integers(0, 2**31 - 1), st.booleans())
def test_decimation_follows_the_polyline(num_points, seed, collinear):
    rng = np.random.default_rng(seed)
    if collinear:  # waypoints along one straight line: only the end points remain corners
        t = np.sort(rng.uniform(0, 1, num_points))
        t[0], t[-1] = 0.0, 1.0
        a, b = rng.uniform(-3, 3, (2, 12))
        path = a + t[:, None] * (b - a)
    else:
        path = rng.uniform(-3, 3, (num_points, 12))
    corners = corner_points(path)
    np.testing.assert_array_equal(corners[[0, -1]], path[[0, -1]])
    if collinear:
        assert len(corners) == 2
    else:  # generic random waypoints are all corners
        assert len(corners) == num_points
    deltas = path_to_deltas(path.reshape(num_points, 2, 6), MAX_STEP)
    assert np.all(np.abs(deltas) <= MAX_STEP + 1e-6)
    np.testing.assert_allclose(deltas.astype(np.float64).sum(0).ravel(), path[-1] - path[0], atol=1e-4)
    visited = path[0] + np.cumsum(deltas.reshape(len(deltas), -1).astype(np.float64), axis=0)
    for corner in corners[1:]:  # the motion passes through every corner
        assert np.min(np.abs(visited - corner).max(axis=1)) < 1e-4


def test_expert_file_round_trip_and_corruption(tmp_path, solved):
    path = tmp_path / "e.experts"
    save_experts(path, ExpertTable.from_results(solved), {"note": "test"})
    store = ExpertStore(path)
    assert len(store) == len(solved) and store.metadata == {"note": "test"}
    for r in solved:
        np.testing.assert_array_equal(store.deltas(r.task_id), r.deltas)
    padded, lengths = store.padded(store.task_ids[::-1], 40, 3)
    assert padded.shape == (len(solved), 40, 3, 6)
    np.testing.assert_array_equal(lengths, [min(40, len(r.deltas)) for r in solved[::-1]])
    packed, offsets, packed_lengths = store.packed(store.task_ids[::-1], 40, 3)
    np.testing.assert_array_equal(packed_lengths, lengths)
    for b in range(len(solved)):  # the same steps, back to back
        np.testing.assert_array_equal(packed[offsets[b] : offsets[b] + lengths[b]], padded[b, : lengths[b]])
    assert store.summary()["solved"] == len(solved)
    with pytest.raises(KeyError, match="no expert for task"):
        store.deltas(-5)

    data = bytearray(path.read_bytes())
    flipped = tmp_path / "flipped.experts"
    data[-5] ^= 0xFF  # inside the last task's steps
    flipped.write_bytes(bytes(data))
    damaged = ExpertStore(flipped)
    with pytest.raises(ValueError, match="corrupt expert data for task"):
        damaged.verify()
    (tmp_path / "short.experts").write_bytes(path.read_bytes()[:-100])
    with pytest.raises(ValueError, match="truncated expert file"):
        ExpertStore(tmp_path / "short.experts")
    (tmp_path / "junk.experts").write_bytes(b"not an expert file at all")
    with pytest.raises(ValueError, match="not an expert file"):
        ExpertStore(tmp_path / "junk.experts")
    with pytest.raises(FileNotFoundError):
        ExpertStore(tmp_path / "missing.experts")


def test_merging_thousands_of_parts_keeps_few_files_open(tmp_path, solved):
    """A 100,000-task precompute leaves 6,250 chunk files: merging opens one at a time."""
    resource = pytest.importorskip("resource")
    parts = []
    for k in range(120):
        result = dataclasses.replace(solved[k % len(solved)], task_id=k)
        parts.append(tmp_path / f"part_{k}.experts")
        save_experts(parts[-1], ExpertTable.from_results([result]))
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    resource.setrlimit(resource.RLIMIT_NOFILE, (min(64, hard), hard))
    try:
        merge_experts(tmp_path / "all.experts", parts)
    finally:
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))
    merged = ExpertStore(tmp_path / "all.experts")
    merged.verify()
    assert merged.task_ids.tolist() == list(range(120))
    np.testing.assert_array_equal(merged.deltas(119), solved[119 % len(solved)].deltas)


def _same_experts(a: ExpertStore, b: ExpertStore) -> None:
    for name in ("task_id", "status", "steps", "iterations", "attempts", "crc"):
        np.testing.assert_array_equal(a.index[name], b.index[name], err_msg=name)
    for task_id in a.task_ids:
        np.testing.assert_array_equal(a.deltas(task_id), b.deltas(task_id))


def test_precompute_resumes_after_a_kill_with_identical_output(tmp_path, small_tasks, monkeypatch):
    tasks_file = tmp_path / "tasks.npz"
    save_tasks(tasks_file, take(small_tasks, np.arange(4)))
    config = PlannerConfig(time_limit=20)
    calls = {"n": 0}
    real = precompute_module.plan_chunk

    def killed(tasks, config, seed):
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt  # the run dies while planning its second chunk
        return real(tasks, config, seed)

    monkeypatch.setattr(precompute_module, "plan_chunk", killed)
    with pytest.raises(KeyboardInterrupt):
        precompute(tasks_file, tmp_path / "resumed.experts", config, seed=3, chunk_size=2)
    assert len(list((tmp_path / "resumed.experts.partial").glob("chunk_*.experts"))) == 1
    monkeypatch.setattr(precompute_module, "plan_chunk", real)
    progress = []
    resumed = precompute(tasks_file, tmp_path / "resumed.experts", config, seed=3, chunk_size=2,
                         on_progress=lambda *a: progress.append(a))
    assert progress == [(4, 2, 4)]  # only the missing chunk was planned
    assert not (tmp_path / "resumed.experts.partial").exists()
    cli.main(["--tasks", str(tasks_file), "--out", str(tmp_path / "whole.experts"), "--workers", "1",
              "--seed", "3", "--chunk-size", "2", "--time-limit", "20", "--quiet", "--json"])
    _same_experts(resumed, ExpertStore(tmp_path / "whole.experts"))
    with pytest.raises(ValueError, match="other tasks or settings"):
        (tmp_path / "again.experts.partial").mkdir()
        (tmp_path / "again.experts.partial" / "spec.json").write_text(json.dumps({"seed": 99}))
        precompute(tasks_file, tmp_path / "again.experts", config, seed=3, chunk_size=2)


def test_cli_json_summary(tmp_path, small_tasks, capsys):
    tasks_file = tmp_path / "tasks.npz"
    save_tasks(tasks_file, take(small_tasks, np.arange(2)))
    out = tmp_path / "e.experts"
    cli.main(["--tasks", str(tasks_file), "--out", str(out), "--workers", "1", "--time-limit", "20", "--quiet", "--json"])
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["tasks"] == 2 and summary["solved"] == 2
    assert summary["median_plan_s"] > 0 and summary["p95_plan_s"] >= summary["median_plan_s"]
    cli.main(["info", str(out), "--verify", "--json"])
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["solved"] == 2
    with pytest.raises(SystemExit, match="not an expert file"):
        (tmp_path / "bad.experts").write_bytes(b"garbage")
        cli.main(["info", str(tmp_path / "bad.experts")])


@pytest.mark.filterwarnings("ignore:os.fork:RuntimeWarning")  # Ray starts its processes by fork + exec
@pytest.mark.slow
def test_ray_backend_matches_local(tmp_path, small_tasks):
    ray = pytest.importorskip("ray")
    tasks_file = tmp_path / "tasks.npz"
    save_tasks(tasks_file, take(small_tasks, np.array([0, 3])))
    config = PlannerConfig(time_limit=20)
    local = precompute(tasks_file, tmp_path / "local.experts", config, seed=1, chunk_size=1)
    try:
        ray.init(num_cpus=1, include_dashboard=False, log_to_driver=False,
                 runtime_env={"env_vars": {"XLA_FLAGS": precompute_module.SINGLE_THREAD_XLA}})
        distributed = precompute(tasks_file, tmp_path / "ray.experts", config, seed=1, chunk_size=1, backend="ray")
    finally:
        ray.shutdown()
    _same_experts(local, distributed)


@pytest.mark.slow
def test_replanning_baseline_follows_moving_targets(small_tasks):
    env = ReachingEnv(2, EnvConfig(dynamic_targets=True, max_steps=300))
    results = [replan_episode(env, small_tasks, i, PlannerConfig(time_limit=20)) for i in (0, 3)]
    assert all(r.success and not r.collided for r in results), results
    assert all(r.plans >= 1 and r.plan_s > 0 and 0 < r.steps < 300 for r in results)
    with pytest.raises(ValueError, match="dynamic_targets"):
        replan_episode(ReachingEnv(2), small_tasks, 0)
