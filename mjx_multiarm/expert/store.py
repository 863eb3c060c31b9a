"""Expert files: delta-joint step sequences keyed by task id, read without loading them all.

One file holds, for N tasks, a small index (task id, status, arms, steps, row offset,
planning time, iterations, attempts, a CRC-32 of the task's steps) and one float32 array of
rows [R, 6] with every solved task's [steps, arms, 6] block. The file is a little header
(magic, version, JSON describing where each array lies, a CRC of the index) followed by
the raw arrays, so :class:`ExpertStore` memory-maps it: opening costs the index only, and
reading a task reads its block (and checks its CRC). Writes are atomic.
"""

from __future__ import annotations

import dataclasses
import json
import os
import pathlib
import struct
import zlib
from collections.abc import Iterable

import numpy as np

from mjx_multiarm.expert.planner import SOLVED, STATUSES
from mjx_multiarm.files import atomic_write

MAGIC = b"MJXEXPRT"
VERSION = 1
_ALIGN = 64
#: Index fields and their dtypes (one value per task).
INDEX = {
    "task_id": np.int64,
    "status": np.int8,
    "arms": np.int8,
    "steps": np.int32,
    "offset": np.int64,
    "plan_s": np.float64,
    "iterations": np.int64,
    "attempts": np.int16,
    "crc": np.uint32,
}


@dataclasses.dataclass
class ExpertTable:
    """Experts in memory: index arrays [N] and one [T, k, 6] block per task."""

    index: dict[str, np.ndarray]
    blocks: list[np.ndarray]

    @classmethod
    def from_results(cls, results) -> ExpertTable:
        """From :class:`~mjx_multiarm.expert.solve.ExpertResult` objects."""
        blocks = [np.ascontiguousarray(r.deltas, np.float32) for r in results]
        index = {
            "task_id": [r.task_id for r in results],
            "status": [r.status for r in results],
            "arms": [b.shape[1] for b in blocks],
            "steps": [len(b) for b in blocks],
            "plan_s": [r.plan_s for r in results],
            "iterations": [r.iterations for r in results],
            "attempts": [r.attempts for r in results],
        }
        return cls({name: np.asarray(index[name], INDEX[name]) for name in index}, blocks)


def _header_and_layout(index: dict[str, np.ndarray], rows: int, metadata: dict) -> tuple[bytes, dict]:
    arrays = {name: (np.dtype(INDEX[name]).str, [len(index["task_id"])]) for name in INDEX}
    arrays["deltas"] = (np.dtype(np.float32).str, [rows, 6])
    layout, position = {}, 0
    for name, (dtype, shape) in arrays.items():
        layout[name] = {"dtype": dtype, "shape": shape, "offset": position}
        position += -(-int(np.prod(shape)) * np.dtype(dtype).itemsize // _ALIGN) * _ALIGN
    index_crc = 0
    for name in INDEX:
        index_crc = zlib.crc32(np.ascontiguousarray(index[name], INDEX[name]).tobytes(), index_crc)
    header = json.dumps({"arrays": layout, "index_crc": index_crc, "metadata": metadata}, sort_keys=True).encode()
    prefix = MAGIC + struct.pack("<IQ", VERSION, len(header)) + header
    prefix += b"\0" * (-len(prefix) % _ALIGN)
    return prefix, layout


def _write(path, index: dict[str, np.ndarray], rows: int, blocks: Iterable[np.ndarray], metadata: dict) -> None:
    """Write an expert file from its index and its delta blocks (streamed, in index order)."""
    index = dict(index)
    prefix, layout = _header_and_layout(index, rows, metadata)

    def write(f):
        f.write(prefix)
        for name in INDEX:
            data = np.ascontiguousarray(index[name], INDEX[name]).tobytes()
            f.write(data + b"\0" * (-len(data) % _ALIGN))
        written = 0
        for block in blocks:
            data = np.ascontiguousarray(block, np.float32).tobytes()
            f.write(data)
            written += len(data)
        if written != rows * 24:
            raise ValueError(f"expert blocks hold {written // 24} rows, the index says {rows}")

    atomic_write(path, write)


def save_experts(path: str | os.PathLike, table: ExpertTable, metadata: dict | None = None) -> None:
    """Write ``table`` to ``path`` atomically."""
    index = dict(table.index)
    sizes = np.array([b.size // 6 for b in table.blocks], np.int64)
    index["offset"] = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
    index["crc"] = np.array([zlib.crc32(b.tobytes()) for b in table.blocks], np.uint32)
    _write(path, index, int(sizes.sum()), table.blocks, metadata or {})


class ExpertStore:
    """A memory-mapped expert file.

    Raises ValueError on open when the file is not an expert file, has another version, is
    truncated, or its index is corrupt; :meth:`deltas` checks each task's CRC when read.
    """

    def __init__(self, path: str | os.PathLike):
        self.path = pathlib.Path(path)
        if not self.path.is_file():
            raise FileNotFoundError(f"{self.path}: no such expert file")
        size = self.path.stat().st_size
        with open(self.path, "rb") as f:
            head = f.read(len(MAGIC) + 12)
            if len(head) < len(MAGIC) + 12 or head[: len(MAGIC)] != MAGIC:
                raise ValueError(f"{self.path}: not an expert file (bad magic)")
            version, length = struct.unpack("<IQ", head[len(MAGIC) :])
            if version != VERSION:
                raise ValueError(f"{self.path}: expert file version {version}, this code reads version {VERSION}")
            try:
                header = json.loads(f.read(length))
                layout = header["arrays"]
            except (ValueError, KeyError) as error:
                raise ValueError(f"{self.path}: corrupt expert file header ({error})") from error
        start = len(MAGIC) + 12 + length
        start += -start % _ALIGN
        arrays = {}
        for name, spec in layout.items():
            dtype, shape = np.dtype(spec["dtype"]), tuple(spec["shape"])
            end = start + spec["offset"] + int(np.prod(shape)) * dtype.itemsize
            if end > size:
                raise ValueError(f"{self.path}: truncated expert file (array '{name}' needs {end} bytes, the file has {size})")
            arrays[name] = np.memmap(self.path, dtype, "r", start + spec["offset"], shape) if np.prod(shape) else np.zeros(shape, dtype)
        missing = [name for name in (*INDEX, "deltas") if name not in arrays]
        if missing:
            raise ValueError(f"{self.path}: expert file lacks array(s) {', '.join(missing)}")
        self.index = {name: np.asarray(arrays[name]) for name in INDEX}
        crc = 0
        for name in INDEX:
            crc = zlib.crc32(self.index[name].tobytes(), crc)
        if crc != header.get("index_crc"):
            raise ValueError(f"{self.path}: corrupt expert file (index checksum mismatch)")
        self._rows = arrays["deltas"]
        self.metadata = header.get("metadata", {})
        self._position = {int(t): i for i, t in enumerate(self.index["task_id"])}

    def __len__(self) -> int:
        return len(self.index["task_id"])

    @property
    def task_ids(self) -> np.ndarray:
        return self.index["task_id"]

    @property
    def solved(self) -> np.ndarray:
        """[N] bool."""
        return self.index["status"] == SOLVED

    def position(self, task_id: int) -> int:
        try:
            return self._position[int(task_id)]
        except KeyError:
            raise KeyError(f"{self.path}: no expert for task {task_id}") from None

    def _block(self, i: int) -> np.ndarray:
        steps, arms, offset = (int(self.index[name][i]) for name in ("steps", "arms", "offset"))
        return self._rows[offset : offset + steps * arms]

    def deltas(self, task_id: int) -> np.ndarray:
        """[T, k, 6] joint steps of a task's k arms (T = 0 unless solved)."""
        i = self.position(task_id)
        block = np.asarray(self._block(i))
        if zlib.crc32(block.tobytes()) != int(self.index["crc"][i]):
            raise ValueError(f"{self.path}: corrupt expert data for task {int(task_id)} (checksum mismatch)")
        return block.reshape(int(self.index["steps"][i]), int(self.index["arms"][i]), 6)

    def packed(self, task_ids, max_steps: int, max_arms: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(deltas [S, max_arms, 6], offsets [B], lengths [B]): the tasks' step sequences
        back to back (task b's steps are ``deltas[offsets[b] : offsets[b] + lengths[b]]``),
        cut at ``max_steps``; empty arm slots are zero. Memory grows with the steps actually
        planned, not with ``max_steps`` per task."""
        blocks = [self.deltas(task_id)[:max_steps] for task_id in task_ids]
        lengths = np.array([len(b) for b in blocks], np.int32)
        offsets = np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(np.int64)
        out = np.zeros((int(lengths.sum()), max_arms, 6), np.float32)
        for block, offset in zip(blocks, offsets):
            out[offset : offset + len(block), : block.shape[1]] = block
        return out, offsets, lengths

    def padded(self, task_ids, max_steps: int, max_arms: int) -> tuple[np.ndarray, np.ndarray]:
        """(deltas [B, max_steps, max_arms, 6], lengths [B]) for a batch of task ids.

        Sequences longer than ``max_steps`` are cut (their length says so); empty arm slots
        and steps beyond a sequence are zero.
        """
        out = np.zeros((len(task_ids), max_steps, max_arms, 6), np.float32)
        lengths = np.zeros(len(task_ids), np.int32)
        for b, task_id in enumerate(task_ids):
            deltas = self.deltas(task_id)[:max_steps]
            out[b, : len(deltas), : deltas.shape[1]] = deltas
            lengths[b] = len(deltas)
        return out, lengths

    def verify(self) -> None:
        """Check every task's CRC (reads the whole file)."""
        for task_id in self.task_ids:
            self.deltas(task_id)

    def summary(self) -> dict:
        """Counts per status and planning-time percentiles of solved tasks."""
        status, solved = self.index["status"], self.solved
        times = self.index["plan_s"][solved]
        return {
            "tasks": len(self),
            "solved": int(solved.sum()),
            "status": {STATUSES[s]: int((status == s).sum()) for s in np.unique(status)},
            "median_plan_s": float(np.median(times)) if len(times) else float("nan"),
            "p95_plan_s": float(np.percentile(times, 95)) if len(times) else float("nan"),
        }


def merge_experts(path: str | os.PathLike, parts: list[str | os.PathLike], metadata: dict | None = None) -> None:
    """Concatenate expert files into one, verifying every part first. One part is open at a
    time (a 100,000-task precompute leaves thousands of chunk files)."""
    indexes, sizes = [], []
    for part in parts:
        store = ExpertStore(part)
        store.verify()
        indexes.append({name: np.array(store.index[name]) for name in INDEX})
        sizes.append(len(store._rows))
    index = {name: np.concatenate([i[name] for i in indexes]) if indexes else np.zeros(0, INDEX[name]) for name in INDEX}
    if len(np.unique(index["task_id"])) != len(index["task_id"]):
        raise ValueError(f"{path}: the parts hold duplicate task ids")
    shift = np.cumsum([0] + sizes)
    if indexes:
        index["offset"] = np.concatenate([i["offset"] + shift[k] for k, i in enumerate(indexes)])
    rows = (np.array(ExpertStore(part)._rows) for part in parts)
    _write(path, index, int(shift[-1]), rows, metadata or {})
