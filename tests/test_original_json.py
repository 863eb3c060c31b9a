"""The original project's JSON task files: exact round trips, FK/difficulty checks, bad files."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from conftest import random_joints, random_padded_scenes

from mjx_multiarm import evaluate_arms
from mjx_multiarm.tasks.difficulty import task_difficulty
from mjx_multiarm.tasks.original_json import export_tasks, import_tasks, read_task_file
from mjx_multiarm.tasks.types import SCHEMA, Tasks

MAX_ARMS = 3
DYNAMIC = 3  # index of the dynamic task


@pytest.fixture(scope="module")
def tasks() -> Tasks:
    """Teams of 1, 2, 3 and 1 arms (the last one dynamic) with FK-consistent targets."""
    rng = np.random.default_rng(7)
    bases, joints, active = random_padded_scenes(rng, 4, MAX_ARMS)
    n = len(active)
    half = np.where(active, bases[..., 2], 0.0) / 2
    base_pos = np.concatenate([np.where(active[..., None], bases[..., :2], 0.0), np.zeros((n, MAX_ARMS, 1))], -1)
    base_quat = np.stack([np.cos(half), 0 * half, 0 * half, np.sin(half)], -1)  # wxyz; identity padding
    goal = np.where(active[..., None], joints, 0.0)
    fk = evaluate_arms(np.concatenate([base_pos, np.roll(base_quat, -1, -1)], -1), goal, active, max_arms=MAX_ARMS)
    target_quat = np.roll(np.asarray(fk.ee_quat, np.float64), 1, -1)
    target_quat /= np.linalg.norm(target_quat, axis=-1, keepdims=True)
    dynamic_start = goal.copy()
    dynamic_start[DYNAMIC] = np.where(active[DYNAMIC, :, None], random_joints(rng, (MAX_ARMS,)), 0.0)
    return Tasks(
        task_id=np.array([5, 17, 2**40, 123456789], np.int64),
        active=active,
        base_pos=base_pos,
        base_quat=base_quat,
        start_joints=np.where(active[..., None], random_joints(rng, (n, MAX_ARMS)), 0.0),
        goal_joints=goal,
        dynamic_start_joints=dynamic_start,
        target_pos=np.where(active[..., None], np.asarray(fk.ee_pos, np.float64), 0.0),
        target_quat=np.where(active[..., None], target_quat, [1.0, 0.0, 0.0, 0.0]),
        difficulty=task_difficulty(base_pos, active),
        speed=np.array([0.0, 0.0, 0.0, 0.05]),
    )


def test_export_import_round_trip_is_exact(tasks, tmp_path):
    paths = export_tasks(tasks, tmp_path)
    assert [p.name for p in paths] == [f"{i}.json" for i in tasks.task_id]
    imported, report = import_tasks(tmp_path, max_arms=MAX_ARMS)
    order = np.argsort([f"{i}.json" for i in tasks.task_id])  # a directory is read sorted by name
    for name in SCHEMA:
        assert np.array_equal(getattr(imported, name), getattr(tasks, name)[order]), name
        assert getattr(imported, name).dtype == SCHEMA[name][0], name
    assert report.count == 4 and report.arms_total == 7
    assert report.max_fk_position_error_m < 1e-5
    assert report.max_fk_rotation_error_rad < 1e-4
    assert report.max_difficulty_error < 1e-9
    np.testing.assert_allclose(report.difficulties, tasks.difficulty[order], atol=1e-9)


def test_static_and_dynamic_files_follow_the_original_format(tasks, tmp_path):
    paths = export_tasks(tasks, tmp_path, names=["a", "b", "c", "d"])
    static, dynamic = json.loads(paths[2].read_text()), json.loads(paths[DYNAMIC].read_text())
    assert static["start_goal_config"] is None and static["dynamic_speed"] is None
    assert len(static["base_poses"]) == 3 and len(static["target_eff_poses"][0][1]) == 4
    assert dynamic["dynamic_speed"] == 0.05 and len(dynamic["start_goal_config"]) == 1
    # the original's own static form (a null per arm) and its extra keys are accepted
    static.update(start_goal_config=[None] * 3, ur5_count=3, id="c", task_path="c.json")
    original = tmp_path / "original" / "c.json"
    original.parent.mkdir()
    original.write_text(json.dumps(static))
    record = read_task_file(original)
    assert np.array_equal(record["dynamic_start_joints"], record["goal_joints"]) and record["speed"] == 0.0
    assert record["task_id"] == read_task_file(paths[2])["task_id"]  # ids come from the stem


def test_slightly_off_quaternions_are_normalised(tmp_path):
    path = tmp_path / "1.json"
    path.write_text(json.dumps(_valid_task() | {"base_poses": [[[0, 0, 0], [0, 0, 0, 1.0005]], [[1, 0, 0], [0, 0, 0, 1]]]}))
    record = read_task_file(path)
    np.testing.assert_array_equal(record["base_quat"], [[1, 0, 0, 0], [1, 0, 0, 0]])


def test_duplicate_ids_name_both_files(tmp_path):
    for name in ("7", "007"):
        (tmp_path / f"{name}.json").write_text(json.dumps(_valid_task()))
    with pytest.raises(ValueError, match=r"007\.json and .*/7\.json have the same task id 7"):
        import_tasks(tmp_path)


def _valid_task() -> dict:
    """A well-formed 2-arm task (its targets need not match FK for parsing)."""
    return {
        "base_poses": [[[0, 0, 0], [0, 0, 0, 1]], [[1, 0, 0], [0, 0, 1, 0]]],
        "start_config": [[0.0] * 6, [0.1] * 6],
        "goal_config": [[0.2] * 6, [0.3] * 6],
        "start_goal_config": None,
        "target_eff_poses": [[[0.5, 0, 0.4], [0, 0, 0, 1]], [[0.5, 0, 0.4], [1, 0, 0, 0]]],
        "difficulty": 0.3,
        "dynamic_speed": None,
    }


def _edited(**changes) -> str:
    return json.dumps(_valid_task() | changes)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (json.dumps({k: v for k, v in _valid_task().items() if k != "goal_config"}), r"missing field\(s\) 'goal_config'"),
        (_edited(start_config=[[0.0] * 6] * 3), r"field 'start_config' has 3 arms but 'base_poses' has 2"),
        (_edited(goal_config=[[0.2] * 6, [0.3, float("nan"), 0, 0, 0, 0]]), r"field 'goal_config\[1\]\[1\]' is not finite"),
        (_edited(start_config=[[0.0] * 6, [0.1] * 5]), r"field 'start_config\[1\]' must be a list of 6 numbers"),
        (
            _edited(target_eff_poses=[[[0.5, 0, 0.4], [0, 0, 1]], [[0.5, 0, 0.4], [1, 0, 0, 0]]]),
            r"field 'target_eff_poses\[0\]\[1\]' must be a list of 4",
        ),
        (
            _edited(base_poses=[[[0, 0, 0], [0, 0, 0, 1.1]], [[1, 0, 0], [0, 0, 0, 1]]]),
            r"field 'base_poses\[0\]\[1\]' is not a unit quaternion",
        ),
        (_edited(difficulty="hard"), r"field 'difficulty' is not a number"),
        (_edited(dynamic_speed=-0.1), r"field 'dynamic_speed' must be >= 0"),
        ("[1, 2]", r"not a JSON object"),
        ('{"base_poses": [', r"invalid JSON"),
    ],
    ids=["missing-key", "arm-count", "nan", "joint-length", "quat-length", "non-unit-quat", "non-numeric",
         "negative-speed", "not-object", "invalid-json"],
)
def test_malformed_files_name_the_file_and_the_field(tmp_path, text, message):
    path = tmp_path / "bad.json"
    path.write_text(text)
    with pytest.raises(ValueError, match=re.escape(str(path)) + r": .*" + message):
        read_task_file(path)
    with pytest.raises(ValueError, match=re.escape(str(path))):
        import_tasks([path])


def test_more_arms_than_max_arms_is_rejected(tmp_path):
    path = tmp_path / "two.json"
    path.write_text(_edited())
    with pytest.raises(ValueError, match=re.escape(str(path)) + r": field 'base_poses' has 2 arms, more than max_arms=1"):
        import_tasks(tmp_path, max_arms=1)
