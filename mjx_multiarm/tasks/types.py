"""The task type: one multi-arm reaching task per row, padded to ``max_arms`` slots.

A :class:`Tasks` holds a batch of tasks as arrays with a leading task axis (numpy on disk,
JAX on device: it is a pytree). Quaternions are wxyz (see :mod:`mjx_multiarm.geometry.transforms`).

Every task starts at ``start_joints``. In static mode the targets are the end-effector
poses ``FK(goal_joints)``, stored as ``target_pos`` / ``target_quat``. In dynamic mode the
targets start at ``FK(dynamic_start_joints)`` and move along
``FK(interp(dynamic_start_joints -> goal_joints))`` at ``speed`` m/s, ending at the static
targets (:mod:`mjx_multiarm.tasks.dynamic`). In the paper's words (section 4.1) q1 = start,
q2 = dynamic start, q3 = goal; in the original JSON files ``start_config``,
``start_goal_config`` and ``goal_config``.
Tasks generated without a dynamic mode have ``speed`` 0 and dynamic start = goal.
"""

from __future__ import annotations

import numpy as np
from flax import struct

#: Difficulty bins of static tasks: [lower, upper) (the last bin includes 0.5).
DIFFICULTY_BINS = {"easy": (0.0, 0.35), "medium": (0.35, 0.45), "hard": (0.45, 0.5)}
#: Target-speed bins of dynamic tasks (m/s): [lower, upper).
SPEED_BINS = {"slow": (0.01, 0.05), "medium": (0.05, 0.10), "fast": (0.10, 0.15)}


@struct.dataclass
class Tasks:
    """A batch of padded tasks; ``N`` tasks, ``A`` = max_arms slots.

    Attributes:
      task_id: [N] int64, stable identifier (unique within a dataset).
      active: [N, A] bool, the arms of each task occupy the first slots.
      base_pos: [N, A, 3] base positions (m; z = 0 for planar layouts).
      base_quat: [N, A, 4] base orientations (wxyz).
      start_joints: [N, A, 6] where the arms start.
      goal_joints: [N, A, 6] the configuration whose end-effector poses are the targets.
      dynamic_start_joints: [N, A, 6] where moving targets start (dynamic mode).
      target_pos: [N, A, 3] FK(goal_joints) end-effector positions.
      target_quat: [N, A, 4] FK(goal_joints) end-effector orientations (wxyz).
      difficulty: [N] in [0, 1]: see :mod:`mjx_multiarm.tasks.difficulty`.
      speed: [N] dynamic-mode target speed (m/s); 0 for tasks without a dynamic mode.
    """

    task_id: np.ndarray
    active: np.ndarray
    base_pos: np.ndarray
    base_quat: np.ndarray
    start_joints: np.ndarray
    goal_joints: np.ndarray
    dynamic_start_joints: np.ndarray
    target_pos: np.ndarray
    target_quat: np.ndarray
    difficulty: np.ndarray
    speed: np.ndarray

    @property
    def num_tasks(self) -> int:
        return self.active.shape[0]

    @property
    def max_arms(self) -> int:
        return self.active.shape[1]

    @property
    def num_arms(self):
        """[N] arms per task."""
        return self.active.sum(axis=-1)

    @property
    def has_dynamic_mode(self):
        """[N] bool: the task has a moving-target mode."""
        return self.speed > 0


#: Per-field (dtype, trailing shape with "A" for the arm slots) of a :class:`Tasks`.
SCHEMA = {
    "task_id": (np.int64, ()),
    "active": (np.bool_, ("A",)),
    "base_pos": (np.float64, ("A", 3)),
    "base_quat": (np.float64, ("A", 4)),
    "start_joints": (np.float64, ("A", 6)),
    "goal_joints": (np.float64, ("A", 6)),
    "dynamic_start_joints": (np.float64, ("A", 6)),
    "target_pos": (np.float64, ("A", 3)),
    "target_quat": (np.float64, ("A", 4)),
    "difficulty": (np.float64, ()),
    "speed": (np.float64, ()),
}


def validate(tasks: Tasks, source: str = "tasks") -> Tasks:
    """Check shapes, dtypes, finiteness and padding of numpy tasks; raise ValueError naming the field."""
    n = np.shape(tasks.task_id)[0] if np.ndim(tasks.task_id) else None
    if n is None:
        raise ValueError(f"{source}: field 'task_id' must be 1-D [N], got shape {np.shape(tasks.task_id)}")
    arms = np.shape(tasks.active)[1] if np.ndim(tasks.active) == 2 else None
    if arms is None:
        raise ValueError(f"{source}: field 'active' must be [N, max_arms], got shape {np.shape(tasks.active)}")
    for name, (dtype, trailing) in SCHEMA.items():
        value = np.asarray(getattr(tasks, name))
        expected = (n, *(arms if d == "A" else d for d in trailing))
        if value.shape != expected:
            raise ValueError(f"{source}: field '{name}' has shape {value.shape}, expected {expected}")
        if not np.can_cast(value.dtype, dtype, casting="same_kind"):
            raise ValueError(f"{source}: field '{name}' has dtype {value.dtype}, expected {np.dtype(dtype)}")
        if value.dtype.kind == "f" and not np.isfinite(value).all():
            raise ValueError(f"{source}: field '{name}' has a non-finite value at {tuple(np.argwhere(~np.isfinite(value))[0])}")
    active = np.asarray(tasks.active)
    if n and not active[:, 0].all():
        raise ValueError(f"{source}: field 'active': every task needs at least one arm, in slot 0")
    if np.any(active[:, 1:] & ~active[:, :-1]):
        raise ValueError(f"{source}: field 'active': a task's arms must occupy its first slots")
    if len(np.unique(tasks.task_id)) != n:
        raise ValueError(f"{source}: field 'task_id' has duplicate ids")
    for name in ("base_quat", "target_quat"):
        norm = np.linalg.norm(np.asarray(getattr(tasks, name))[active], axis=-1)
        if np.any(np.abs(norm - 1.0) > 1e-6):
            raise ValueError(f"{source}: field '{name}' holds a non-unit quaternion")
    if np.any(np.asarray(tasks.speed) < 0):
        raise ValueError(f"{source}: field 'speed' must be >= 0")
    return tasks


def concatenate(parts: list[Tasks]) -> Tasks:
    """Join task batches along the task axis (same max_arms)."""
    return Tasks(**{name: np.concatenate([getattr(p, name) for p in parts]) for name in SCHEMA})


def take(tasks: Tasks, index) -> Tasks:
    """The tasks at ``index`` (numpy fancy index or mask)."""
    return Tasks(**{name: np.asarray(getattr(tasks, name))[index] for name in SCHEMA})


def bin_index(values, bins: dict[str, tuple[float, float]]) -> np.ndarray:
    """Index into ``bins`` of the bin holding each value, -1 outside every bin.

    Bins are [lower, upper); the last one also includes its upper edge.
    """
    values = np.asarray(values, np.float64)
    index = np.full(values.shape, -1)
    bounds = list(bins.values())
    for i, (lower, upper) in enumerate(bounds):
        last = i == len(bounds) - 1
        index[(values >= lower) & ((values < upper) | (last & (values == upper)))] = i
    return index


def with_slots(tasks: Tasks, max_arms: int, source: str = "tasks") -> Tasks:
    """The same tasks padded (or trimmed) to ``max_arms`` arm slots.

    Empty slots hold zeros and identity quaternions. Raises ValueError naming the first
    task whose team is larger than ``max_arms``.
    """
    too_big = np.flatnonzero(np.asarray(tasks.active)[:, max_arms:].any(axis=-1))
    if len(too_big):
        first = int(too_big[0])
        raise ValueError(
            f"{source}: task {int(tasks.task_id[first])} has {int(tasks.num_arms[first])} arms, "
            f"more than the {max_arms} slots ({len(too_big)} such tasks)"
        )

    def resized(name: str, per_arm: bool):
        value = np.asarray(getattr(tasks, name))
        if not per_arm:
            return value
        value = value[:, :max_arms]
        fill = np.zeros((value.shape[0], max_arms - value.shape[1], *value.shape[2:]), value.dtype)
        if name.endswith("quat"):
            fill[..., 0] = 1.0
        return np.concatenate([value, fill], axis=1)

    return Tasks(**{name: resized(name, bool(trailing)) for name, (_, trailing) in SCHEMA.items()})
