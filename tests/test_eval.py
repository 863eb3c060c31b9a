"""The evaluation suite: benchmark tables (policy and BiRRT), latency, renders, bad input."""

from __future__ import annotations

import json
import subprocess
import sys

import jax
import numpy as np
import pytest
from flax import nnx

from eval import benchmark
from mjx_multiarm import Planner
from mjx_multiarm.env.observation import InputFeatures
from mjx_multiarm.env.reaching import ReachingEnv
from mjx_multiarm.env.wrappers import TaskBank
from mjx_multiarm.geometry.robot import NUM_JOINTS
from mjx_multiarm.planner.policy import policy_env_settings
from mjx_multiarm.planner.policy_file import save_policy
from mjx_multiarm.render import RenderingUnavailable, record_episode, render_episode
from mjx_multiarm.tasks.dataset import save_tasks
from mjx_multiarm.tasks.generate import GenerationSpec, generate_chunk
from models.networks import Actor


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    root = tmp_path_factory.mktemp("eval")
    save_policy(root / "policy.npz", nnx.state(Actor(nnx.Rngs(1), InputFeatures(), NUM_JOINTS)), False, policy_env_settings(ReachingEnv(2)))
    tasks = generate_chunk(GenerationSpec(count=4, arm_counts=(1, 2), mode="dynamic", seed=3, max_arms=2), 0)
    save_tasks(root / "tasks.npz", tasks)
    return root


def last_json(capsys) -> dict:
    return json.loads(capsys.readouterr().out.strip().splitlines()[-1])


@pytest.mark.slow
def test_benchmark_policy_and_birrt_tables(files, tmp_path, capsys):
    common = ["--tasks", str(files / "tasks.npz"), "--episode-steps", "10", "--json"]
    benchmark.main(["--checkpoint", str(files / "policy.npz"), "--out", str(tmp_path / "p"), *common])
    policy = last_json(capsys)
    assert set(policy["success"]) == {"1", "2"} and set(policy["success"]["2"]) == {"easy", "medium", "hard", "average"}
    assert policy["neighbour_radius"] == pytest.approx(1.7)  # the radius the file records
    assert policy["tasks"] == 4 and policy["success"]["1"]["average"] == 0.0  # random weights reach nothing in 10 steps
    assert policy["timeout_rate"] + policy["collision_rate"] == pytest.approx(1.0)
    assert set(policy["dynamic"]["success"]["1"]) == {"slow", "medium", "fast", "average"}
    for name in ("static.md", "static.csv", "dynamic.md", "dynamic.csv", "outcomes.csv", "summary.json"):
        assert (tmp_path / "p" / name).is_file()
    assert "| 1 |" in (tmp_path / "p" / "static.md").read_text() and "0.988" in (tmp_path / "p" / "static.md").read_text()

    benchmark.main(["--checkpoint", str(files / "policy.npz"), "--out", str(tmp_path / "s"), "--safe", "--arms", "2", *common])
    safe = last_json(capsys)
    assert safe["safe"] and not policy["safe"] and safe["collision_rate"] == 0.0 == safe["dynamic"]["collision_rate"]
    assert set(safe["success"]) == {"2"} and safe["tasks"] == 2  # --arms picks the 2-arm tasks of the file
    benchmark.main(["--checkpoint", str(files / "policy.npz"), "--out", str(tmp_path / "h"), "--safe", "--handover",
                    "--mode", "static", *common])
    hybrid = last_json(capsys)  # random weights stall; BiRRT takes every task over from where it stopped
    assert hybrid["handover"] and hybrid["success"]["1"]["average"] == 1.0 == hybrid["success"]["2"]["average"]
    assert hybrid["planned"] == 4 and hybrid["mean_plan_s"] > 0 and hybrid["steps_to_success"] > 10
    with pytest.raises(SystemExit, match="no task of 3 arms"):
        benchmark.main(["--checkpoint", str(files / "policy.npz"), "--arms", "3", *common])

    benchmark.main(["--planner", "birrt", "--mode", "static", "--out", str(tmp_path / "t"), *common])
    assert last_json(capsys)["timeout_rate"] > 0  # plans count within the episode's steps: not all fit in 10
    benchmark.main(["--planner", "birrt", "--mode", "static", "--out", str(tmp_path / "b"), *common, "--episode-steps", "500"])
    birrt = last_json(capsys)
    assert birrt["success"]["1"]["average"] == 1.0 and birrt["success"]["2"]["average"] == 1.0
    assert birrt["steps_to_success"] > 0 and "dynamic" not in birrt
    for result, won in ((policy, 0.0), (birrt, 1.0)):  # per team size: rates add up, arms reached follow success
        for team in ("1", "2"):
            row = result["by_team_size"][team]
            assert row["success_rate"] == won and row["tasks"] == 2
            assert row["success_rate"] + row["collision_rate"] + row["timeout_rate"] == pytest.approx(1.0)
            assert won <= row["arm_reach_rate"] <= 1.0 and (won == 1.0 or row["arm_reach_rate"] == 0.0)


def test_benchmark_bad_checkpoints(files, tmp_path):
    with pytest.raises(SystemExit, match="no such policy file"):
        benchmark.main(["--checkpoint", str(tmp_path / "none.npz"), "--tasks", str(files / "tasks.npz")])
    (tmp_path / "bad.npz").write_bytes(b"\x00" * 100)
    with pytest.raises(SystemExit, match="not a readable policy file"):
        benchmark.main(["--checkpoint", str(tmp_path / "bad.npz"), "--tasks", str(files / "tasks.npz")])


@pytest.mark.parametrize("flags, message", [
    (["--episode-steps", "0"], "--episode-steps must be >= 1, got 0"),
    (["--planner", "birrt", "--iterations", "0"], "--iterations must be >= 1, got 0"),
    (["--per-team", "0"], "--per-team must be >= 1, got 0"),
    (["--render", "-1"], "--render must be >= 0, got -1"),
])
def test_benchmark_refuses_values_that_cannot_run(files, flags, message):
    with pytest.raises(SystemExit, match=message):
        benchmark.main(["--checkpoint", str(files / "policy.npz"), *flags])


def test_benchmark_refuses_an_out_that_is_a_file_or_holds_results_and_an_empty_task_file(files, tmp_path):
    common = ["--checkpoint", str(files / "policy.npz"), "--tasks", str(files / "tasks.npz")]
    (tmp_path / "file").write_text("x")
    with pytest.raises(SystemExit, match="is a file; give a directory"):
        benchmark.main([*common, "--out", str(tmp_path / "file")])
    (tmp_path / "done").mkdir()
    (tmp_path / "done" / "summary.json").write_text("{}")
    with pytest.raises(SystemExit, match="already holds a benchmark's results"):
        benchmark.main([*common, "--out", str(tmp_path / "done")])
    with np.load(files / "tasks.npz") as data:  # a dataset file with every field but no task
        np.savez(tmp_path / "empty.npz", **{k: data[k][:0] if data[k].ndim else data[k] for k in data.files})
    with pytest.raises(SystemExit, match="holds no tasks"):
        benchmark.main(["--checkpoint", str(files / "policy.npz"), "--tasks", str(tmp_path / "empty.npz")])


def test_benchmark_neighbour_radius_overrides_the_policy_file(files, monkeypatch):
    tasks = TaskBank.from_tasks(generate_chunk(GenerationSpec(count=4, arm_counts=(2,), seed=5, max_arms=2), 0), 2).tasks
    visible = {}
    for radius in (None, 0.0):  # the file records ReachingEnv(2)'s radius, 1.7 m
        planner = Planner.load(files, radius)  # a run directory: its policy.npz
        start = jax.vmap(lambda task, env=planner.environment(2): env.reset(None, task))(tasks)
        visible[radius] = np.asarray(start.obs_mask).sum(-1)  # observed arms, per task and arm
    assert (visible[None] == 2).any() and (visible[0.0] == 1).all()  # neighbours within 1.7 m are seen, then none

    common = ["--checkpoint", str(files / "policy.npz"), "--tasks", str(files / "tasks.npz"), "--mode", "static"]
    with pytest.raises(SystemExit, match="neighbour_radius must be >= 0"):  # the flag reaches the planner
        benchmark.main([*common, "--neighbour-radius", "-1"])
    for flag in (["--neighbour-radius", "0"], ["--safe"], ["--handover"]):
        with pytest.raises(SystemExit, match="--planner policy only"):
            benchmark.main([*common, "--planner", "birrt", *flag])
    with pytest.raises(SystemExit, match="needs --mode static"):
        benchmark.main([*common[:-2], "--handover"])

    requested = []  # a radius of 0 is a value, not "unset": it must reach the planner (stopped before any rollout)
    def record(checkpoint, radius, safe):
        requested.append(radius)
        raise ValueError("planner recorded")
    monkeypatch.setattr(Planner, "load", staticmethod(record))
    with pytest.raises(SystemExit, match="planner recorded"):
        benchmark.main([*common, "--neighbour-radius", "0"])
    assert requested == [0.0]


@pytest.mark.slow
def test_latency_cli_reports_percentiles(files):
    out = subprocess.run([sys.executable, "-m", "eval.latency", "--checkpoint", str(files / "policy.npz"), "--calls", "5",
                          "--max-neighbours", "2", "--json"], capture_output=True, text=True, check=True).stdout
    result = json.loads(out.strip().splitlines()[-1])
    assert result["neighbours"] == [1, 2] and result["threads"] == 1
    for name in ("", "team_step_", "safe_step_"):
        assert all(0 < p50 <= p99 for p50, p99 in zip(result[f"{name}p50_ms"], result[f"{name}p99_ms"]))


@pytest.mark.slow
def test_render_frames_show_the_arms(files):
    planner = Planner.load(files / "policy.npz")
    tasks = generate_chunk(GenerationSpec(count=1, arm_counts=(2,), mode="static", seed=5, max_arms=2), 0)
    env = planner.environment(2, max_steps=3)
    task = jax.tree.map(lambda x: x[0], TaskBank.from_tasks(tasks, 2).tasks)
    trajectory = record_episode(env, planner.policy_fn(), planner.params, task)
    assert trajectory.joints.shape == (4, 2, 6)
    try:
        frames = render_episode(env, jax.device_get(task), trajectory, height=60, width=80)
    except RenderingUnavailable as error:
        pytest.skip(str(error))
    assert frames.shape == (4, 60, 80, 3) and frames.dtype == np.uint8
    assert frames.std() > 5  # not a blank image
