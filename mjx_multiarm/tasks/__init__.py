"""Multi-arm reaching tasks: the task type, difficulty, generation, datasets, original JSON.

``python -m mjx_multiarm.tasks --help`` lists the command-line tools.
"""

from mjx_multiarm.tasks.dataset import load_tasks, save_tasks
from mjx_multiarm.tasks.difficulty import task_difficulty
from mjx_multiarm.tasks.types import DIFFICULTY_BINS, SPEED_BINS, Tasks

__all__ = ["DIFFICULTY_BINS", "SPEED_BINS", "Tasks", "load_tasks", "save_tasks", "task_difficulty"]
