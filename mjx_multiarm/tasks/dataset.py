"""Task datasets on disk: one compressed ``.npz`` file per split, versioned and validated.

Why ``.npz``: numpy-native (no extra dependency), compressed, loads field by field, and
holds the fixed-shape padded arrays of :class:`~mjx_multiarm.tasks.types.Tasks` as they
are. Beside the task fields a file stores ``schema_version`` and ``metadata`` (a JSON
string: generator arguments, counts). Writes are atomic: a temporary file in the same
folder, then a rename.
"""

from __future__ import annotations

import json
import os
import pathlib
import zipfile

import numpy as np

from mjx_multiarm.files import atomic_write
from mjx_multiarm.tasks.types import SCHEMA, Tasks, validate

SCHEMA_VERSION = 1


def save_tasks(path: str | os.PathLike, tasks: Tasks, metadata: dict | None = None) -> None:
    """Validate and write ``tasks`` (with JSON-serialisable ``metadata``) to ``path`` atomically;
    ValueError for an empty set (a dataset holds at least one task)."""
    validate(tasks, str(path))
    if not tasks.num_tasks:
        raise ValueError(f"{path}: refusing to write a task dataset with no tasks")
    arrays = {name: np.asarray(getattr(tasks, name), dtype) for name, (dtype, _) in SCHEMA.items()}
    arrays["schema_version"] = np.array(SCHEMA_VERSION)
    arrays["metadata"] = np.array(json.dumps(metadata or {}, sort_keys=True))
    atomic_write(path, lambda f: np.savez_compressed(f, **arrays))


def load_tasks(path: str | os.PathLike) -> tuple[Tasks, dict]:
    """Read and validate a dataset file: returns (tasks, metadata).

    Raises:
      FileNotFoundError: no such file.
      ValueError: not a task dataset, another schema version, invalid fields (the message
        names the file and the field), or no tasks.
    """
    path = pathlib.Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such task dataset")
    if not zipfile.is_zipfile(path):
        raise ValueError(f"{path}: unreadable or corrupt task dataset (not a valid .npz archive)")
    try:
        with np.load(path, allow_pickle=False) as data:
            if "schema_version" not in data:
                raise ValueError(f"{path}: not a task dataset (no 'schema_version')")
            version = int(data["schema_version"])
            if version != SCHEMA_VERSION:
                raise ValueError(f"{path}: schema version {version}, this code reads version {SCHEMA_VERSION}")
            missing = [name for name in SCHEMA if name not in data]
            if missing:
                raise ValueError(f"{path}: missing field(s) {', '.join(missing)}")
            tasks = Tasks(**{name: data[name] for name in SCHEMA})
            metadata = json.loads(str(data["metadata"])) if "metadata" in data else {}
    except (zipfile.BadZipFile, OSError, EOFError) as error:
        raise ValueError(f"{path}: unreadable or corrupt task dataset ({error})") from error
    tasks = validate(tasks, str(path))
    if not tasks.num_tasks:
        raise ValueError(f"{path}: the task dataset holds no tasks")
    return tasks, metadata
