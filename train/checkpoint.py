"""Training checkpoints with Orbax: the whole :class:`~train.trainer.TrainState` and metadata.

A checkpoint holds the networks, optimizer states, target critics, the environments'
states, the curriculum, the failed-task queue, the RNG keys, the step counters and (by
default) the replay buffer, so a resumed run continues bit for bit where the saved one
stopped. Orbax writes each checkpoint to a temporary directory and renames it when
complete, so a kill never leaves a half-written checkpoint; only the latest ``keep`` are
kept. JSON metadata (the run's configuration, counters, level) sits beside the arrays.
"""

from __future__ import annotations

import os
import pathlib

import jax
import orbax.checkpoint as ocp

from train.replay import ReplayBuffer
from train.trainer import TrainState


def _is_key(x) -> bool:
    return hasattr(x, "dtype") and jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)


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
        options = ocp.CheckpointManagerOptions(max_to_keep=keep, create=True, enable_async_checkpointing=False)
        self.manager = ocp.CheckpointManager(self.directory, options=options, item_names=("state", "meta"))

    def save(self, step: int, state: TrainState, metadata: dict) -> None:
        """Write checkpoint ``step`` (blocking until it is complete on disk)."""
        args = ocp.args.Composite(state=ocp.args.StandardSave(_storable(state, self.with_buffer)), meta=ocp.args.JsonSave(metadata))
        self.manager.save(step, args=args, force=True)
        self.manager.wait_until_finished()

    def latest(self) -> int | None:
        return self.manager.latest_step()

    def restore(self, template: TrainState, step: int | None = None) -> tuple[TrainState, dict]:
        """The saved state (shaped like ``template``, e.g. a fresh ``Trainer.init``) and metadata.

        Raises FileNotFoundError when the directory holds no checkpoint, ValueError when the
        checkpoint does not fit the template (another architecture or configuration).
        """
        step = self.latest() if step is None else step
        if step is None:
            raise FileNotFoundError(f"{self.directory}: no checkpoint to resume from")
        meta = self.manager.restore(step, args=ocp.args.Composite(meta=ocp.args.JsonRestore()))["meta"]
        with_buffer = bool(meta.get("with_buffer", True))
        target = jax.tree.map(ocp.utils.to_shape_dtype_struct, _storable(template, with_buffer))
        try:
            saved = self.manager.restore(step, args=ocp.args.Composite(state=ocp.args.StandardRestore(target)))["state"]
        except (ValueError, KeyError, TypeError) as error:
            raise ValueError(f"{self.directory}: checkpoint {step} does not match this configuration ({error})") from error
        keys = jax.tree.map(_is_key, template)
        saved_full = saved if with_buffer else saved.replace(buffer=template.buffer)
        restored = jax.tree.map(lambda is_key, x: jax.random.wrap_key_data(x) if is_key else x, keys, saved_full)
        if not with_buffer:
            restored = restored.replace(buffer=ReplayBuffer.create(template.buffer.capacity, template.buffer.data.mask.shape[1]))
        return restored, meta

    def close(self) -> None:
        self.manager.close()
