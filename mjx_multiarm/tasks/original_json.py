"""The original project's task files: one JSON object per task, read and written losslessly.

A file holds, per arm: ``base_poses`` and ``target_eff_poses`` as ``[[x, y, z], [qx, qy,
qz, qw]]``, ``start_config`` / ``goal_config`` / ``start_goal_config`` as 6 joint angles;
and per task ``difficulty`` and ``dynamic_speed`` (m/s). ``start_goal_config`` and
``dynamic_speed`` may be absent or null (static task); ``start_goal_config`` may also be a
per-arm list holding nulls, as the original writes for static tasks. A null start goal is
the goal itself and a null speed is 0 (see :mod:`mjx_multiarm.tasks.types` for the field
mapping). Other keys (``ur5_count``, ``id``, ``task_path``) are ignored.

A task's ``task_id`` comes from its file name: the stem itself where it is a plain
non-negative integer below 2**63, else a 63-bit blake2b hash of the stem.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import pathlib
import re
from collections.abc import Sequence

import numpy as np

from mjx_multiarm.files import atomic_write
from mjx_multiarm.geometry.evaluate import evaluate_arms
from mjx_multiarm.geometry.transforms import quat_angle
from mjx_multiarm.tasks.difficulty import task_difficulty
from mjx_multiarm.tasks.types import SCHEMA, Tasks, validate

#: Keys every task file must have.
REQUIRED_KEYS = ("base_poses", "start_config", "goal_config", "target_eff_poses", "difficulty")
#: Quaternions whose norm is off by more than this are rejected.
QUAT_NORM_LIMIT = 1e-3
#: Quaternions whose norm is off by more than this (types.validate's tolerance) are normalised;
#: nearer ones are kept bit for bit, so an export/import round trip is lossless.
QUAT_RENORMALISE = 1e-6


@dataclasses.dataclass(frozen=True, eq=False)
class ImportReport:
    """What :func:`import_tasks` read and how well the files agree with this code.

    Attributes:
      count: tasks read.
      arms_total: arms over all tasks.
      max_fk_position_error_m: largest distance between FK(goal_config) (float32) and the
        stored target position.
      max_fk_rotation_error_rad: largest rotation angle between FK(goal_config) and the
        stored target orientation.
      max_difficulty_error: largest |recomputed - stored| difficulty.
      difficulties: [count] recomputed :func:`~mjx_multiarm.tasks.difficulty.task_difficulty`.
    """

    count: int
    arms_total: int
    max_fk_position_error_m: float
    max_fk_rotation_error_rad: float
    max_difficulty_error: float
    difficulties: np.ndarray


def _field_error(path, field: str, message: str) -> ValueError:
    return ValueError(f"{path}: field '{field}' {message}")


def _preview(value) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _number(path, field: str, value) -> float:
    """A finite JSON number (not a bool)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise _field_error(path, field, f"is not a number: {_preview(value)}")
    try:
        value = float(value)
    except OverflowError:
        value = math.inf
    if not math.isfinite(value):
        raise _field_error(path, field, f"is not finite: {value!r}")
    return value


def _numbers(path, field: str, value, length: int) -> np.ndarray:
    """A list of ``length`` finite numbers as a float64 array."""
    if not isinstance(value, list) or len(value) != length:
        raise _field_error(path, field, f"must be a list of {length} numbers, got {_preview(value)}")
    return np.array([_number(path, f"{field}[{i}]", x) for i, x in enumerate(value)])


def _per_arm(path, data: dict, key: str, arms: int | None) -> list:
    """The per-arm list ``data[key]``, with ``arms`` entries where given."""
    value = data[key]
    if not isinstance(value, list) or not value:
        raise _field_error(path, key, f"must be a non-empty list with one entry per arm, got {_preview(value)}")
    if arms is not None and len(value) != arms:
        raise _field_error(path, key, f"has {len(value)} arms but 'base_poses' has {arms}")
    return value


def _joints(path, data: dict, key: str, arms: int) -> np.ndarray:
    return np.array([_numbers(path, f"{key}[{i}]", q, 6) for i, q in enumerate(_per_arm(path, data, key, arms))])


def _unit_quat_wxyz(path, field: str, value) -> np.ndarray:
    """An xyzw unit quaternion as wxyz, normalised where its norm is off by over QUAT_RENORMALISE."""
    quat = _numbers(path, field, value, 4)
    norm = np.linalg.norm(quat)
    if abs(norm - 1.0) > QUAT_NORM_LIMIT:
        raise _field_error(path, field, f"is not a unit quaternion (norm {norm:.6g})")
    quat = np.roll(quat, 1)
    return quat / norm if abs(norm - 1.0) > QUAT_RENORMALISE else quat


def _poses(path, data: dict, key: str, arms: int | None) -> tuple[np.ndarray, np.ndarray]:
    """Positions [k, 3] and wxyz quaternions [k, 4] of the per-arm poses ``data[key]``."""
    positions, quats = [], []
    for i, pose in enumerate(_per_arm(path, data, key, arms)):
        if not isinstance(pose, list) or len(pose) != 2:
            raise _field_error(path, f"{key}[{i}]", f"must be [[x, y, z], [qx, qy, qz, qw]], got {_preview(pose)}")
        positions.append(_numbers(path, f"{key}[{i}][0]", pose[0], 3))
        quats.append(_unit_quat_wxyz(path, f"{key}[{i}][1]", pose[1]))
    return np.array(positions), np.array(quats)


def _task_id(path) -> int:
    stem = pathlib.Path(path).stem
    if re.fullmatch(r"[0-9]+", stem) and int(stem) < 2**63:
        return int(stem)
    digest = hashlib.blake2b(stem.encode("utf-8", "surrogateescape"), digest_size=8).digest()
    return int.from_bytes(digest, "little") >> 1


def read_task_file(path: str | os.PathLike) -> dict:
    """Parse and check one task file.

    Returns:
      The task's :class:`~mjx_multiarm.tasks.types.Tasks` fields but ``active``, for its
      ``k`` arms (no padding): ``task_id`` (int), ``base_pos`` [k, 3], ``base_quat`` [k, 4]
      (wxyz), ``start_joints`` / ``goal_joints`` / ``dynamic_start_joints`` [k, 6],
      ``target_pos`` [k, 3], ``target_quat`` [k, 4] (wxyz), ``difficulty`` and ``speed``.

    Raises:
      ValueError: invalid JSON, not an object, a missing key, a wrong arm count or length,
        a non-numeric or non-finite value, a non-unit quaternion, a negative speed; the
        message names the file and the field.
    """
    path = pathlib.Path(path)
    try:
        data = json.loads(path.read_bytes())
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise ValueError(f"{path}: invalid JSON ({error})") from error
    if not isinstance(data, dict):
        raise ValueError(f"{path}: not a JSON object (got {type(data).__name__})")
    missing = [key for key in REQUIRED_KEYS if key not in data]
    if missing:
        raise ValueError(f"{path}: missing field(s) {', '.join(repr(key) for key in missing)}")
    base_pos, base_quat = _poses(path, data, "base_poses", None)
    arms = len(base_pos)
    target_pos, target_quat = _poses(path, data, "target_eff_poses", arms)
    goal = _joints(path, data, "goal_config", arms)
    dynamic_start = goal.copy()
    if data.get("start_goal_config") is not None:
        for i, q in enumerate(_per_arm(path, data, "start_goal_config", arms)):
            if q is not None:
                dynamic_start[i] = _numbers(path, f"start_goal_config[{i}]", q, 6)
    speed = data.get("dynamic_speed")
    speed = 0.0 if speed is None else _number(path, "dynamic_speed", speed)
    if speed < 0:
        raise _field_error(path, "dynamic_speed", f"must be >= 0, got {speed!r}")
    return {
        "task_id": _task_id(path),
        "base_pos": base_pos,
        "base_quat": base_quat,
        "start_joints": _joints(path, data, "start_config", arms),
        "goal_joints": goal,
        "dynamic_start_joints": dynamic_start,
        "target_pos": target_pos,
        "target_quat": target_quat,
        "difficulty": _number(path, "difficulty", data["difficulty"]),
        "speed": speed,
    }


def _task_files(paths) -> list[pathlib.Path]:
    if isinstance(paths, (str, os.PathLike)):
        directory = pathlib.Path(paths)
        if not directory.is_dir():
            raise ValueError(f"{directory}: not a directory (pass a directory or a list of files)")
        return sorted(directory.glob("*.json"))
    return [pathlib.Path(p) for p in paths]


def import_tasks(paths, max_arms: int | None = None) -> tuple[Tasks, ImportReport]:
    """Read task files into numpy :class:`Tasks` and check them against FK and difficulty.

    Args:
      paths: a directory (its ``*.json`` files, sorted by name) or a list of files.
      max_arms: arm slots (default: the largest team read).

    Raises:
      ValueError: no files, an invalid file (see :func:`read_task_file`), a team larger than
        ``max_arms``, or two files with the same task id (the message names both).
    """
    files = _task_files(paths)
    if not files:
        raise ValueError(f"{paths}: no task files")
    records = [read_task_file(f) for f in files]
    owners: dict[int, pathlib.Path] = {}
    for file, record in zip(files, records):
        if record["task_id"] in owners:
            raise ValueError(f"{owners[record['task_id']]} and {file} have the same task id {record['task_id']}")
        owners[record["task_id"]] = file
    teams = [len(record["base_pos"]) for record in records]
    max_arms = max(teams) if max_arms is None else max_arms
    for file, team in zip(files, teams):
        if team > max_arms:
            raise ValueError(f"{file}: field 'base_poses' has {team} arms, more than max_arms={max_arms}")

    fields = {
        name: np.zeros((len(records), *(max_arms if d == "A" else d for d in trailing)), dtype)
        for name, (dtype, trailing) in SCHEMA.items()
    }
    fields["base_quat"][..., 0] = fields["target_quat"][..., 0] = 1.0  # identity padding
    for i, (record, team) in enumerate(zip(records, teams)):
        fields["active"][i, :team] = True
        for name, value in record.items():
            if np.ndim(value):
                fields[name][i, :team] = value
            else:
                fields[name][i] = value
    tasks = validate(Tasks(**fields), str(paths))

    base_poses = np.concatenate([tasks.base_pos, np.roll(tasks.base_quat, -1, axis=-1)], axis=-1)
    fk = evaluate_arms(base_poses, tasks.goal_joints, tasks.active, max_arms=max_arms)
    fk_quat = np.roll(np.asarray(fk.ee_quat, np.float64), 1, axis=-1)
    position_error = np.linalg.norm(fk.ee_pos - tasks.target_pos, axis=-1)[tasks.active]
    rotation_error = np.asarray(quat_angle(fk_quat, tasks.target_quat), np.float64)[tasks.active]
    difficulties = task_difficulty(tasks.base_pos, tasks.active)
    return tasks, ImportReport(
        count=tasks.num_tasks,
        arms_total=sum(teams),
        max_fk_position_error_m=float(position_error.max()),
        max_fk_rotation_error_rad=float(rotation_error.max()),
        max_difficulty_error=float(np.abs(difficulties - tasks.difficulty).max()),
        difficulties=difficulties,
    )


def _poses_json(pos: np.ndarray, quat_wxyz: np.ndarray) -> list:
    return [[p.tolist(), np.roll(q, -1).tolist()] for p, q in zip(pos, quat_wxyz)]


def export_tasks(
    tasks: Tasks, directory: str | os.PathLike, names: Sequence[str] | None = None
) -> list[pathlib.Path]:
    """Write each task to ``directory/{name}.json`` (atomically) in the original format.

    ``names`` are file stems, one per task (default: the task ids, so that
    :func:`import_tasks` gives the ids back). ``start_goal_config`` is null where the
    dynamic start equals the goal and ``dynamic_speed`` is null where the speed is 0, so a
    round trip through :func:`import_tasks` is exact (padding aside). Returns the paths.
    """
    tasks = Tasks(**{name: np.asarray(getattr(tasks, name)) for name in SCHEMA})
    validate(tasks, "export_tasks")
    names = [str(i) for i in tasks.task_id] if names is None else list(names)
    if len(names) != tasks.num_tasks or len(set(names)) != len(names):
        raise ValueError(
            f"names: expected {tasks.num_tasks} distinct file stems, got {len(names)} ({len(set(names))} distinct)"
        )
    directory = pathlib.Path(directory)
    written = []
    for i, name in enumerate(names):
        arms = tasks.active[i]
        goal, dynamic_start = tasks.goal_joints[i][arms], tasks.dynamic_start_joints[i][arms]
        speed = float(tasks.speed[i])
        data = {
            "base_poses": _poses_json(tasks.base_pos[i][arms], tasks.base_quat[i][arms]),
            "start_config": tasks.start_joints[i][arms].tolist(),
            "goal_config": goal.tolist(),
            "start_goal_config": None if np.array_equal(dynamic_start, goal) else dynamic_start.tolist(),
            "target_eff_poses": _poses_json(tasks.target_pos[i][arms], tasks.target_quat[i][arms]),
            "difficulty": float(tasks.difficulty[i]),
            "dynamic_speed": speed if speed > 0 else None,
        }
        payload = json.dumps(data, indent=4, allow_nan=False).encode()
        path = directory / f"{name}.json"
        atomic_write(path, lambda f, payload=payload: f.write(payload))
        written.append(path)
    return written
