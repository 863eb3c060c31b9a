"""Multi-arm reaching tasks.

- :mod:`.types`: the padded ``Tasks`` pytree, its schema and validation, difficulty/speed bins.
- :mod:`.difficulty`: workspace-overlap difficulty.
- :mod:`.generate`: stratified, chunked, resumable, multi-process generation; named datasets.
- :mod:`.dynamic`: moving targets of dynamic tasks.
- :mod:`.dataset`: versioned ``.npz`` datasets.
- :mod:`.select`: detour tasks and training subsets with a chosen share of them.
- :mod:`.original_json`: the original project's per-task JSON import/export.

``python -m mjx_multiarm.tasks --help`` lists the command-line tools.
"""

from mjx_multiarm.tasks.dataset import load_tasks, save_tasks
from mjx_multiarm.tasks.difficulty import task_difficulty
from mjx_multiarm.tasks.types import DIFFICULTY_BINS, SPEED_BINS, Tasks

__all__ = ["DIFFICULTY_BINS", "SPEED_BINS", "Tasks", "load_tasks", "save_tasks", "task_difficulty"]
