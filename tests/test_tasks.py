"""Task generation, difficulty, datasets and the task CLI."""

from __future__ import annotations

import json
import pathlib
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mjx_multiarm import scene_contacts
from mjx_multiarm.expert.planner import PlannerConfig
from mjx_multiarm.geometry.collision import frame_contacts
from mjx_multiarm.geometry.ik import solve_positions
from mjx_multiarm.geometry.kinematics import forward_kinematics
from mjx_multiarm.geometry.robot import REACH, load_arm
from mjx_multiarm.geometry.scene import build_scene
from mjx_multiarm.tasks import __main__ as cli
from mjx_multiarm.tasks import generate as generation
from mjx_multiarm.tasks import load_tasks, save_tasks, task_difficulty
from mjx_multiarm.tasks.generate import (
    MIN_BASE_SPACING,
    ORIGINAL_MAX_OFFSET,
    GenerationSpec,
    generate_chunk,
    generate_dataset,
    sample_bases_original,
    spec_record,
)
from mjx_multiarm.tasks.select import detour_rows, straight_motion_free
from mjx_multiarm.tasks.types import (
    DIFFICULTY_BINS,
    SPEED_BINS,
    bin_index,
    take,
    with_slots,
)


def test_generated_tasks_are_valid(generated):
    tasks, arm, scene = generated, load_arm(), build_scene(10)
    active = tasks.active
    assert sorted(set(tasks.num_arms.tolist())) == list(range(1, 11))
    for field in ("start_joints", "goal_joints", "dynamic_start_joints"):
        joints = getattr(tasks, field)
        contacts = scene_contacts(scene, tasks.base_pos, tasks.base_quat, jnp.asarray(joints, jnp.float32), active)
        assert not np.asarray(contacts.collided).any(), field
        within = (joints >= arm.joint_range[:, 0]) & (joints <= arm.joint_range[:, 1])
        assert within[active].all(), field
    frames = forward_kinematics(arm, tasks.base_pos, tasks.base_quat, jnp.asarray(tasks.goal_joints))
    assert np.abs(np.asarray(frames.ee_pos) - tasks.target_pos)[active].max() < 1e-5
    quat = np.asarray(frames.ee_quat)
    sign_free = np.minimum(np.abs(quat - tasks.target_quat).max(-1), np.abs(quat + tasks.target_quat).max(-1))
    assert sign_free[active].max() < 1e-6
    gaps = np.linalg.norm(tasks.base_pos[:, :, None] - tasks.base_pos[:, None], axis=-1)
    both = active[:, :, None] & active[:, None] & ~np.eye(10, dtype=bool)
    assert gaps[both].min() >= MIN_BASE_SPACING
    np.testing.assert_allclose(task_difficulty(tasks.base_pos, active), tasks.difficulty, atol=1e-6)
    assert (bin_index(tasks.difficulty, DIFFICULTY_BINS) >= 0).all()
    assert (bin_index(tasks.speed, SPEED_BINS) >= 0).all()
    assert (tasks.difficulty[tasks.num_arms == 1] == 0).all()
    assert np.abs(tasks.base_pos[..., 2]).max() == 0 and not tasks.base_pos[~active].any()


def test_every_bin_is_populated_for_teams(generated):
    summary = cli.summarize(generated)
    for team in range(2, 11):
        row = summary["by_team_size"][str(team)]
        assert all(row["difficulty"][name] > 0 for name in DIFFICULTY_BINS), (team, row)
        assert row["difficulty"]["outside"] == 0


def test_original_layout_walks_bases_and_reaches_past_the_paper_bins():
    teams = np.repeat([1, 2, 3, 4], 500)
    base_pos, yaw, difficulty = sample_bases_original(np.random.default_rng(0), teams, 4)
    active = np.arange(4) < teams[:, None]
    assert not base_pos[~active].any() and not base_pos[..., 2].any() and yaw.shape == (2000, 4)
    steps = np.abs(np.diff(base_pos[..., :2], axis=1))  # each base within 1 m (per axis) of the previous one
    assert steps[active[:, 1:]].max() <= ORIGINAL_MAX_OFFSET
    gaps = np.linalg.norm(base_pos[:, :, None] - base_pos[:, None], axis=-1)
    assert gaps[active[:, :, None] & active[:, None] & ~np.eye(4, dtype=bool)].min() > MIN_BASE_SPACING
    np.testing.assert_allclose(difficulty, task_difficulty(base_pos, active), atol=1e-6)
    assert (difficulty[teams == 1] == 0).all()
    four = difficulty[teams == 4]
    assert 0.2 < (four > 0.5).mean() and four.max() > 0.85  # beyond the paper's last bin, as the original's tasks


@pytest.mark.slow
def test_original_layout_tasks_are_valid_and_deterministic():
    spec = GenerationSpec(count=8, arm_counts=(1, 2, 3, 4), seed=5, chunk_size=8, layout="original")
    tasks = generate_chunk(spec, 0)
    scene = build_scene(4)
    for joints in (tasks.start_joints, tasks.goal_joints):
        assert not np.asarray(scene_contacts(scene, tasks.base_pos, tasks.base_quat, jnp.asarray(joints, jnp.float32),
                                             tasks.active).collided).any()
    np.testing.assert_allclose(task_difficulty(tasks.base_pos, tasks.active), tasks.difficulty, atol=1e-6)
    np.testing.assert_array_equal(generate_chunk(spec, 0).base_pos, tasks.base_pos)
    with pytest.raises(ValueError, match="layout"):
        GenerationSpec(count=8, arm_counts=(2,), layout="circle")


def test_a_cell_fixes_the_bases_of_every_task(tmp_path, capsys):
    cell = [[-0.35, 0.0, 1.5708], [0.35, 0.0, -1.5708], [0.0, 0.6, 0.0]]
    path = tmp_path / "cell.json"
    path.write_text(json.dumps(cell))
    cli.main(["generate", "--cell", str(path), "--count", "6", "--seed", "3", "--max-arms", "4", "--out", str(tmp_path / "c.npz"),
              "--workers", "1", "--quiet"])
    tasks, meta = load_tasks(tmp_path / "c.npz")
    assert (tasks.num_arms == 3).all() and tasks.max_arms == 4 and meta["generator"]["cell"] == cell
    np.testing.assert_allclose(tasks.base_pos[:, :3, :2], np.broadcast_to(np.asarray(cell)[:, :2], (6, 3, 2)))
    yaw = 2 * np.arctan2(tasks.base_quat[:, :3, 3], tasks.base_quat[:, :3, 0])
    np.testing.assert_allclose(yaw, np.broadcast_to(np.asarray(cell)[:, 2], (6, 3)), atol=1e-6)
    np.testing.assert_allclose(tasks.difficulty, task_difficulty(tasks.base_pos, tasks.active), atol=1e-6)
    assert len(np.unique(tasks.goal_joints.round(6), axis=0)) == 6  # the same cell, new configurations
    scene = build_scene(4)
    for joints in (tasks.start_joints, tasks.goal_joints):
        assert not np.asarray(scene_contacts(scene, tasks.base_pos, tasks.base_quat, jnp.asarray(joints, jnp.float32),
                                             tasks.active).collided).any()


@pytest.mark.parametrize("content, message", [
    ("not json", "not JSON"),
    ('{"bases": []}', "a list of \\[x, y, yaw\\]"),
    ("[[0, 0]]", "a list of \\[x, y, yaw\\]"),
    ("[[0, 0, 0], [0.2, 0, 0]]", "bases 0 and 1 are 0.200 m apart"),
])
def test_a_malformed_cell_file_is_refused_with_a_clear_error(tmp_path, capsys, content, message):
    path = tmp_path / "cell.json"
    path.write_text(content)
    with pytest.raises(SystemExit) as exit_:
        cli.main(["generate", "--cell", str(path), "--count", "4", "--out", str(tmp_path / "c.npz")])
    assert "--cell" in str(exit_.value) or "bases" in str(exit_.value)
    assert re.search(message, str(exit_.value)), exit_.value


def test_a_cell_takes_its_own_team_size_and_no_layout():
    cell = ((0.0, 0.0, 0.0), (0.7, 0.0, 0.0))
    with pytest.raises(ValueError, match="2-arm tasks only"):
        GenerationSpec(count=4, arm_counts=(1, 2), cell=cell)
    with pytest.raises(ValueError, match="no layout"):
        GenerationSpec(count=4, arm_counts=(2,), cell=cell, layout="original")
    with pytest.raises(ValueError, match="finite"):
        GenerationSpec(count=4, arm_counts=(2,), cell=((0.0, 0.0, float("nan")), (0.7, 0.0, 0.0)))
    assert spec_record(GenerationSpec(count=4, arm_counts=(2,), cell=cell))["cell"] == [[0.0, 0.0, 0.0], [0.7, 0.0, 0.0]]
    line = cli.read_cell(pathlib.Path(__file__).resolve().parents[1] / "benchmarks/cells/line4.json")  # the README's example cell
    assert len(line) == 4 and {base[1:] for base in line} == {(0.0, np.pi / 2)}


@pytest.mark.slow
def test_generation_is_deterministic_and_resumable(tmp_path, monkeypatch):
    spec = GenerationSpec(count=12, arm_counts=(1, 2, 3), mode="static", seed=11, chunk_size=5)
    reference = generate_dataset(spec, tmp_path / "straight.npz")

    calls = []

    def interrupted(spec, chunk):  # one worker: chunks are made in this process
        if len(calls) == 1:
            raise KeyboardInterrupt  # killed while making the second chunk
        calls.append(chunk)
        return generate_chunk(spec, chunk)

    out = tmp_path / "resumed.npz"
    monkeypatch.setattr(generation, "generate_chunk", interrupted)
    with pytest.raises(KeyboardInterrupt):
        generate_dataset(spec, out)
    assert not out.exists() and len(list((tmp_path / "resumed.npz.partial").glob("chunk_*.npz"))) == 1
    monkeypatch.setattr(generation, "generate_chunk", generate_chunk)
    resumed = generate_dataset(spec, out)
    for name in ("task_id", "base_pos", "start_joints", "goal_joints", "target_quat", "difficulty"):
        np.testing.assert_array_equal(getattr(resumed, name), getattr(reference, name), err_msg=name)
    assert not (tmp_path / "resumed.npz.partial").exists()
    other = GenerationSpec(count=12, arm_counts=(1, 2, 3), mode="static", seed=12, chunk_size=5)
    (tmp_path / "x.npz.partial").mkdir()
    (tmp_path / "x.npz.partial" / "spec.json").write_text(json.dumps(spec_record(spec)))
    with pytest.raises(ValueError, match="other arguments"):
        generate_dataset(other, tmp_path / "x.npz")


def test_cli_info_and_json_round_trip(tmp_path, capsys, generated):
    path = tmp_path / "tasks.npz"
    save_tasks(path, take(generated, np.arange(20)))
    cli.main(["info", str(path), "--json"])
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["count"] == 20 and sum(r["count"] for r in summary["by_team_size"].values()) == 20
    cli.main(["export-json", str(path), "--out", str(tmp_path / "json")])
    cli.main(["import-json", str(tmp_path / "json"), "--out", str(tmp_path / "back.npz"), "--max-arms", "10", "--json"])
    report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert report["count"] == 20 and report["max_fk_position_error_m"] < 1e-5 and report["max_difficulty_error"] < 1e-9
    back, _ = load_tasks(tmp_path / "back.npz")
    np.testing.assert_array_equal(back.goal_joints, take(generated, np.arange(20)).goal_joints)


def test_cli_merge_joins_datasets_padded_to_the_most_slots(tmp_path, capsys, generated):
    small = take(generated, generated.num_arms <= 2)
    five = with_slots(take(small, np.arange(6)), 5)
    two = with_slots(take(small, np.arange(6, small.num_tasks)), 2)
    save_tasks(tmp_path / "a.npz", five, {"source": "a"})
    save_tasks(tmp_path / "b.npz", two)
    cli.main(["merge", str(tmp_path / "a.npz"), str(tmp_path / "b.npz"), "--out", str(tmp_path / "ab.npz")])
    merged, meta = load_tasks(tmp_path / "ab.npz")
    assert merged.max_arms == 5 and merged.num_tasks == small.num_tasks
    np.testing.assert_array_equal(merged.task_id, small.task_id)
    np.testing.assert_array_equal(merged.goal_joints[:, :2], small.goal_joints[:, :2])
    assert [(m["count"], m["metadata"]) for m in meta["merged_from"]] == [(6, {"source": "a"}), (small.num_tasks - 6, {})]
    with pytest.raises(SystemExit, match="duplicate ids"):  # the same tasks twice
        cli.main(["merge", str(tmp_path / "a.npz"), str(tmp_path / "a.npz"), "--out", str(tmp_path / "aa.npz")])
    assert not (tmp_path / "aa.npz").exists()


# --- difficulty ---------------------------------------------------------------------------


def _two_arms(distance):
    return np.array([[0.0, 0.0, 0.0], [distance, 0.0, 0.0]]), np.ones(2, bool)


def test_difficulty_analytic_cases():
    assert task_difficulty(np.zeros((1, 3)), np.ones(1, bool)) == 0.0
    for distance in (1.7, 2.5):
        assert task_difficulty(*_two_arms(distance)) == 0.0
    assert task_difficulty(*_two_arms(0.01)) > 0.98
    for distance in np.linspace(0.05, 1.65, 9):  # two equal balls: exact lens volume
        x = distance / REACH
        exact = (4 + x) * (2 - x) ** 2 / 16
        assert abs(task_difficulty(*_two_arms(distance)) - exact) < 0.003, distance


def test_difficulty_matches_independent_monte_carlo():
    rng = np.random.default_rng(0)
    for team in (3, 5, 8):
        bases = np.zeros((team, 3))
        bases[:, :2] = rng.uniform(-0.8, 0.8, (team, 2))
        samples = rng.normal(size=(200_000, 3))
        samples[:, 2] = np.abs(samples[:, 2])
        samples *= REACH * rng.uniform(size=(200_000, 1)) ** (1 / 3) / np.linalg.norm(samples, axis=1, keepdims=True)
        fractions = []
        for i in range(team):
            points = bases[i] + samples
            others = np.delete(bases, i, axis=0)
            inside = (np.linalg.norm(points[:, None] - others[None], axis=-1) <= REACH).any(axis=1)
            fractions.append(inside.mean())
        assert abs(task_difficulty(bases, np.ones(team, bool)) - max(fractions)) < 0.01, team


def test_bins_include_only_the_last_upper_edge():
    np.testing.assert_array_equal(bin_index([0.0, 0.35, 0.4499, 0.45, 0.5, 0.5001, -0.1], DIFFICULTY_BINS), [0, 1, 1, 2, 2, -1, -1])


def test_difficulty_ignores_padding():
    bases = np.array([[0.0, 0.0, 0.0], [0.6, 0.0, 0.0], [0.1, 0.0, 0.0]])
    assert task_difficulty(bases, np.array([True, True, False])) == task_difficulty(bases[:2], np.ones(2, bool))


# --- IK -----------------------------------------------------------------------------------


def test_ik_reaches_reachable_targets():
    rng = np.random.default_rng(1)
    arm = load_arm()
    truth = arm.home + rng.normal(0, 0.8, (256, 6))
    targets = forward_kinematics(arm, jnp.zeros(3), jnp.array([1.0, 0, 0, 0]), jnp.asarray(truth, jnp.float32)).ee_pos
    initial = arm.home + rng.normal(0, 0.3, (256, 6))
    _, error = solve_positions(arm, targets, jnp.asarray(initial, jnp.float32))
    assert (np.asarray(error) < 1e-3).mean() > 0.95


# --- dataset files ------------------------------------------------------------------------


def test_dataset_round_trip_and_corruption(tmp_path, generated):
    tasks = take(generated, np.arange(10))
    path = tmp_path / "d.npz"
    save_tasks(path, tasks, {"note": "x"})
    loaded, metadata = load_tasks(path)
    assert metadata == {"note": "x"}
    for name in ("task_id", "active", "base_quat", "dynamic_start_joints", "speed"):
        np.testing.assert_array_equal(getattr(loaded, name), getattr(tasks, name))
    path.write_bytes(path.read_bytes()[:200])
    with pytest.raises(ValueError, match="d.npz: unreadable or corrupt"):
        load_tasks(path)
    with pytest.raises(FileNotFoundError, match="missing.npz"):
        load_tasks(tmp_path / "missing.npz")
    (tmp_path / "text.npz").write_text("not a dataset")
    with pytest.raises(ValueError, match="text.npz: unreadable or corrupt"):
        load_tasks(tmp_path / "text.npz")
    np.savez(tmp_path / "old.npz", schema_version=np.array(0))
    with pytest.raises(ValueError, match="schema version 0"):
        load_tasks(tmp_path / "old.npz")


def test_invalid_tasks_are_never_written(tmp_path, generated):
    bad = take(generated, np.arange(3))
    bad = bad.replace(start_joints=np.where(bad.active[..., None], np.nan, bad.start_joints))
    with pytest.raises(ValueError, match="field 'start_joints' has a non-finite value"):
        save_tasks(tmp_path / "bad.npz", bad)
    assert not list(tmp_path.iterdir())


# --- dynamic targets ----------------------------------------------------------------------


def test_dynamic_target_moves_at_constant_speed_and_stops_at_the_goal(generated):
    from mjx_multiarm.tasks.dynamic import path_lengths, target_at

    arm = load_arm()
    tasks = take(generated, np.arange(8))
    args = [jnp.asarray(x, jnp.float32) for x in (tasks.base_pos, tasks.base_quat, tasks.dynamic_start_joints, tasks.goal_joints)]
    lengths = path_lengths(arm, *args)
    speed = jnp.asarray(tasks.speed, jnp.float32)[:, None]
    positions = np.stack([np.asarray(target_at(arm, *args, lengths, speed * t)[0]) for t in (0.0, 0.05)])
    start = forward_kinematics(arm, args[0], args[1], args[2])
    np.testing.assert_allclose(positions[0], np.asarray(start.ee_pos), atol=1e-5)
    # Per control step, each moving target advances speed * 0.05 s along its path (up to the
    # chord-vs-arc difference of one small step).
    step = np.linalg.norm(positions[1] - positions[0], axis=-1)
    moving = np.asarray(tasks.active) & (np.asarray(lengths[..., -1]) > speed * 0.1)
    np.testing.assert_allclose(step[moving], np.broadcast_to(tasks.speed[:, None] * 0.05, step.shape)[moving], rtol=0.02)
    end_pos, end_quat, s = target_at(arm, *args, lengths, speed * 1e3)
    np.testing.assert_allclose(np.asarray(end_pos)[tasks.active], tasks.target_pos[tasks.active], atol=1e-5)
    assert np.all(np.asarray(s) == 1.0)


# --- detour tasks -------------------------------------------------------------------------


def test_straight_motion_free_matches_the_xla_kernel_along_the_motion(generated):
    """The expert checker's straight-motion verdict (numba, float64) against the XLA kernel
    evaluated at the same configurations (float32), on the generated 1-5-arm teams in 5
    slots; near-contact paths are left out."""
    generated = with_slots(take(generated, generated.num_arms <= 5), 5)
    free = straight_motion_free(generated)
    start, goal = np.asarray(generated.start_joints, np.float64), np.asarray(generated.goal_joints, np.float64)
    active = np.asarray(generated.active)
    steps = np.maximum(1, np.ceil(np.max(np.abs(goal - start) * active[..., None], axis=(1, 2)) / PlannerConfig.resolution - 1e-9))
    task = np.repeat(np.arange(len(steps)), steps.astype(int))  # every checked configuration of every task, once
    fraction = np.concatenate([np.arange(1, n + 1) / n for n in steps])
    joints = start[task] + fraction[:, None, None] * (goal - start)[task]
    scene = build_scene(generated.max_arms)

    @jax.jit
    def min_distance(base_pos, base_quat, joints, active):
        frames = forward_kinematics(scene.arm, base_pos, base_quat, joints)
        return frame_contacts(scene, frames, active, kernel="xla").min_distance

    per_step = np.asarray(min_distance(generated.base_pos[task].astype(np.float32), generated.base_quat[task].astype(np.float32),
                                       joints.astype(np.float32), active[task]))
    distance = np.full(len(steps), np.inf)
    np.minimum.at(distance, task, np.where(active[task], per_step, np.inf).min(axis=1))
    clear = np.abs(distance) > 1e-4
    assert clear.mean() > 0.9
    np.testing.assert_array_equal(free[clear], distance[clear] > 0)
    assert (~free[generated.num_arms >= 2]).sum() >= 10  # the set holds detour tasks


def test_detour_rows_take_the_share_where_there_are_enough():
    num_arms = np.repeat([1, 2, 3], 100)
    free = np.ones(300, bool)
    free[100:130] = False  # 30 detour tasks of 2 arms
    free[200:290] = False  # 90 of 3 arms
    rows = detour_rows(num_arms, free, per_team=40, detour_share=0.5, seed=3)
    assert len(rows) == 120 and len(np.unique(rows)) == 120 and np.all(np.diff(rows) > 0)
    counts = {k: (int((num_arms[rows] == k).sum()), int(((num_arms[rows] == k) & ~free[rows]).sum())) for k in (1, 2, 3)}
    assert counts == {1: (40, 0), 2: (40, 20), 3: (40, 30)}  # 3 arms: 10 straight tasks, the rest detours
    assert int((~free[detour_rows(num_arms, free, 40, 0.9)] & (num_arms[detour_rows(num_arms, free, 40, 0.9)] == 2)).sum()) == 30
    three = detour_rows(num_arms, free, 20, 0.0)  # 3 arms: only 10 straight tasks, filled with detour tasks
    assert int(((num_arms[three] == 3) & free[three]).sum()) == 10
    np.testing.assert_array_equal(detour_rows(num_arms, free, 40, 0.5, seed=3), rows)
    with pytest.raises(ValueError, match="fewer than per_team"):
        detour_rows(num_arms, free, 101, 0.5)
    with pytest.raises(ValueError, match="detour_share"):
        detour_rows(num_arms, free, 10, 1.5)


def test_cli_select_writes_the_subset_with_its_provenance(tmp_path, capsys, generated):
    small = take(generated, generated.num_arms <= 3)
    save_tasks(tmp_path / "a.npz", small, {"source": "a"})
    per_team = int(np.bincount(small.num_arms)[1:].min())
    cli.main(["select", str(tmp_path / "a.npz"), "--per-team", str(per_team), "--detour-share", "1", "--out", str(tmp_path / "s.npz")])
    subset, meta = load_tasks(tmp_path / "s.npz")
    assert subset.num_tasks == 3 * per_team and set(subset.task_id) <= set(small.task_id)
    assert meta["source_metadata"] == {"source": "a"} and meta["detour_share"] == 1.0
    free = straight_motion_free(subset)
    assert meta["detours_by_team"] == {str(k): int(((subset.num_arms == k) & ~free).sum()) for k in (1, 2, 3)}
    assert "detour tasks by team size" in capsys.readouterr().out


def test_cli_refuses_outputs_of_the_wrong_kind_and_empty_subsets(tmp_path, generated):
    save_tasks(tmp_path / "a.npz", take(generated, np.arange(8)))
    with pytest.raises(SystemExit, match="is a directory; give the .npz file"):
        cli.main(["merge", str(tmp_path / "a.npz"), "--out", str(tmp_path)])
    with pytest.raises(SystemExit, match="is a file; export-json writes a folder"):
        cli.main(["export-json", str(tmp_path / "a.npz"), "--out", str(tmp_path / "a.npz")])
    with pytest.raises(SystemExit, match="per_team=0"):
        cli.main(["select", str(tmp_path / "a.npz"), "--per-team", "0", "--detour-share", "0.5", "--out", str(tmp_path / "s.npz")])
    assert not (tmp_path / "s.npz").exists()
    with pytest.raises(ValueError, match="no tasks"):
        save_tasks(tmp_path / "e.npz", take(generated, np.arange(0)))
