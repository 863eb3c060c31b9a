"""Training checkpoints with Orbax: the whole :class:`~train.trainer.TrainState` and metadata.

A checkpoint holds the networks, optimizer states, target critics, the environments'
states, the curriculum, the failed-task queue, the RNG keys, the step counters and (by
default) the replay buffer, so a resumed run continues bit for bit where the saved one
stopped. Orbax writes each checkpoint to a temporary directory and renames it when
complete, so a kill never leaves a half-written checkpoint; only the latest ``keep`` are
kept. JSON metadata (the run's configuration, counters, level) sits beside the arrays.
A checkpoint damaged afterwards (a truncated file) is set aside on restore and the newest
intact one is used instead.
"""

from __future__ import annotations

import os
import pathlib
import shutil

import jax
import orbax.checkpoint as ocp

from train.replay import ReplayBuffer
from train.trainer import TrainState


def _is_key(x) -> bool:
    return hasattr(x, "dtype") and jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)


class _Mismatch(ValueError):
    """A checkpoint that reads back but holds another configuration's state."""


def _structure_differs(step_dir: pathlib.Path, error: Exception) -> bool:
    """Whether a restore failed because the saved tree differs from the template (rather
    than because the checkpoint's files are damaged)."""
    text = str(error).lower()
    return any(word in text for word in ("shape", "structure", "mismatch", "dtype", "missing")) and (step_dir / "state").is_dir()


def _storable(state: TrainState, with_buffer: bool):
    """The state with PRNG keys as raw data (and without the buffer unless ``with_buffer``)."""
    if not with_buffer:
        state = state.replace(buffer=None)
    return jax.tree.map(lambda x: jax.random.key_data(x) if _is_key(x) else x, state)


class Checkpoints:
    """Periodic checkpoints of a training run in ``directory`` (created if needed)."""

    def __init__(self, directory: str | os.PathLike, keep: int = 3, with_buffer: bool = True):
        self.directory = pathlib.Path(directory).absolute()
        self.with_buffer = with_buffer
        self.options = ocp.CheckpointManagerOptions(max_to_keep=keep, create=True, enable_async_checkpointing=False)
        self.manager = ocp.CheckpointManager(self.directory, options=self.options, item_names=("state", "meta"))

    def save(self, step: int, state: TrainState, metadata: dict) -> None:
        """Write checkpoint ``step`` (blocking until it is complete on disk)."""
        args = ocp.args.Composite(state=ocp.args.StandardSave(_storable(state, self.with_buffer)), meta=ocp.args.JsonSave(metadata))
        self.manager.save(step, args=args, force=True)
        self.manager.wait_until_finished()

    @staticmethod
    def exist(directory: str | os.PathLike) -> bool:
        """Whether ``directory`` holds a checkpoint (complete or not) to resume from."""
        directory = pathlib.Path(directory)
        return directory.is_dir() and any(p.name.isdigit() for p in directory.iterdir())

    def latest(self) -> int | None:
        return self.manager.latest_step()

    def restore(self, template: TrainState, step: int | None = None, warn=None) -> tuple[TrainState, dict]:
        """The saved state (shaped like ``template``, e.g. a fresh ``Trainer.init``) and metadata,
        from checkpoint ``step`` or, by default, the newest one that reads back intact: an
        unreadable checkpoint (truncated, its files damaged) is set aside as ``<step>.corrupt``
        with a warning to ``warn`` and the next older one is tried.

        Raises FileNotFoundError when the directory holds no checkpoint, ValueError when the
        checkpoint does not fit the template (another architecture or configuration) or none
        reads back.
        """
        if step is not None:
            return self._restore(template, step)
        steps = sorted(self.manager.all_steps(), reverse=True)
        if not steps:
            raise FileNotFoundError(f"{self.directory}: no checkpoint to resume from")
        for i, step in enumerate(steps):
            try:
                return self._restore(template, step)
            except _Mismatch:
                raise
            except Exception as error:  # noqa: BLE001 - orbax raises many kinds for a damaged checkpoint
                summary = str(error).strip().splitlines()[0][:200] if str(error).strip() else type(error).__name__
                if i == len(steps) - 1:
                    raise ValueError(f"{self.directory}: no checkpoint reads back; the oldest, {step}, fails with: {summary}") from None
                (warn or print)(f"warning: checkpoint {step} in {self.directory} does not read back ({summary}); set aside as "
                                f"{step}.corrupt, trying checkpoint {steps[i + 1]}")
                self._set_aside(step)
        raise AssertionError("unreachable")

    def _set_aside(self, step: int) -> None:
        """Rename checkpoint ``step`` out of the manager's sight (``<step>.corrupt``)."""
        self.manager.close()
        source = self.directory / str(step)
        target = self.directory / f"{step}.corrupt"
        if target.exists():
            shutil.rmtree(target)
        source.rename(target)
        self.manager = ocp.CheckpointManager(self.directory, options=self.options, item_names=("state", "meta"))

    def _restore(self, template: TrainState, step: int) -> tuple[TrainState, dict]:
        meta = self.manager.restore(step, args=ocp.args.Composite(meta=ocp.args.JsonRestore()))["meta"]
        if not isinstance(meta, dict) or "iteration" not in meta:
            raise ValueError(f"checkpoint {step}: metadata unreadable")
        with_buffer = bool(meta.get("with_buffer", True))
        target = jax.tree.map(ocp.utils.to_shape_dtype_struct, _storable(template, with_buffer))
        try:
            saved = self.manager.restore(step, args=ocp.args.Composite(state=ocp.args.StandardRestore(target)))["state"]
        except (ValueError, KeyError, TypeError) as error:
            if _structure_differs(self.directory / str(step), error):
                raise _Mismatch(f"{self.directory}: checkpoint {step} does not match this configuration ({error})") from error
            raise
        keys = jax.tree.map(_is_key, template)
        saved_full = saved if with_buffer else saved.replace(buffer=template.buffer)
        restored = jax.tree.map(lambda is_key, x: jax.random.wrap_key_data(x) if is_key else x, keys, saved_full)
        if not with_buffer:
            restored = restored.replace(buffer=ReplayBuffer.create(template.buffer.capacity, template.buffer.data.mask.shape[1]))
        return restored, meta

    def close(self) -> None:
        self.manager.close()
