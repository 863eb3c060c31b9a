"""Trained policies as small standalone files: save, load, validate.

A policy file is a NumPy ``.npz`` archive holding the actor's parameters (one array per
parameter path, e.g. ``encoder/cell/ii/kernel``) and a ``__meta__`` entry: JSON with the
format version, the architecture (``squash``, the ``inputs`` features, the mixture
``components`` (absent in files before mixtures: one), every parameter's shape), the
environment settings the policy was trained for (action scale, neighbour radius, ...),
free-form training provenance, and a SHA-256 over the parameters. Loading checks all of it, so a
truncated or altered file, or one of another architecture, fails with a message that
says what is wrong instead of producing a silently broken planner.

Version 2 files may also carry the twin critics (parameters named ``critic:<path>``), what
fine-tuning (``python -m train.sac --init FILE``) needs beside the actor; the planner reads
only the actor. Version 1 files (the actor only) still load.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import pathlib
import zipfile

import jax
import numpy as np
from flax import nnx

from mjx_multiarm.env.observation import InputFeatures
from mjx_multiarm.geometry.robot import NUM_JOINTS
from models.networks import Actor, TwinCritic

FORMAT = "mjx-multiarm-policy"
VERSION = 2
READABLE_VERSIONS = (1, 2)
_META = "__meta__"
_CRITIC = "critic:"


def _name(path) -> str:
    """A parameter's name in the file: its path joined by '/' (e.g. ``encoder/cell/ii/kernel``)."""
    return "/".join(str(k) for k in path)


def _flat(state: nnx.State) -> dict[str, np.ndarray]:
    return {_name(path): np.asarray(value, np.float32) for path, value in nnx.to_flat_state(state)}


def _digest(arrays: dict[str, np.ndarray]) -> str:
    sha = hashlib.sha256()
    for name in sorted(arrays):
        sha.update(name.encode())
        sha.update(np.ascontiguousarray(arrays[name], np.float32).tobytes())
    return sha.hexdigest()


def _abstract_actor(squash: bool, inputs: InputFeatures, components: int) -> Actor:
    """An actor of this architecture, no weights materialized."""
    return nnx.eval_shape(lambda: Actor(nnx.Rngs(0), inputs, NUM_JOINTS, squash, components))


def _architecture(squash: bool, inputs: InputFeatures, components: int) -> dict[str, list[int]]:
    """Parameter shapes of a freshly built actor."""
    abstract = _abstract_actor(squash, inputs, components)
    return {_name(path): list(value.shape) for path, value in nnx.to_flat_state(nnx.state(abstract, nnx.Param))}


def _critic_architecture(inputs: InputFeatures) -> dict[str, list[int]]:
    """Parameter shapes of a freshly built twin critic, named as in the file."""
    abstract = nnx.eval_shape(lambda: TwinCritic(nnx.Rngs(0), inputs, NUM_JOINTS))
    return {_CRITIC + _name(path): list(value.shape) for path, value in nnx.to_flat_state(nnx.state(abstract, nnx.Param))}


def save_policy(path: str | os.PathLike, actor: nnx.State, squash: bool, env_settings: dict, provenance: dict | None = None,
                inputs: InputFeatures = InputFeatures(), critic: nnx.State | None = None, components: int = 1) -> None:
    """Write ``actor``'s parameters (an ``nnx.State`` of :class:`~models.networks.Actor`,
    built with ``squash``, ``inputs`` and ``components``) to ``path`` atomically. ``env_settings``
    records what the policy expects of the environment (``action_scale`` [6],
    ``neighbour_radius``, ``max_step`` [6]). ``critic``: the twin critics' parameters
    (:class:`~models.networks.TwinCritic`), stored for fine-tuning."""
    arrays = _flat(jax.device_get(actor))
    if critic is not None:
        arrays |= {_CRITIC + name: value for name, value in _flat(jax.device_get(critic)).items()}
    meta = {"format": FORMAT, "version": VERSION, "squash": bool(squash), "inputs": dataclasses.asdict(inputs),
            "components": int(components), "shapes": {k: list(v.shape) for k, v in arrays.items()},
            "sha256": _digest(arrays), "env": env_settings, "provenance": provenance or {}}
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "wb") as f:
        np.savez_compressed(f, **arrays, **{_META: np.frombuffer(json.dumps(meta).encode(), np.uint8)})
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


class LoadedPolicy:
    """A policy file's actor module (``actor``), its ``squash`` flag, input features, mixture
    ``components``, metadata, and the twin critics' parameters where the file carries them (``critic``,
    an ``nnx.State`` of :class:`~models.networks.TwinCritic`, else None)."""

    def __init__(self, actor: Actor, meta: dict, inputs: InputFeatures = InputFeatures(), critic: nnx.State | None = None):
        self.actor, self.meta, self.inputs, self.critic = actor, meta, inputs, critic
        self.squash, self.components = bool(meta["squash"]), actor.components

    @property
    def env(self) -> dict:
        return self.meta["env"]

    @property
    def provenance(self) -> dict:
        return self.meta.get("provenance", {})


def load_policy(path: str | os.PathLike) -> LoadedPolicy:
    """Read and validate a policy file (see the module docstring).

    Raises FileNotFoundError if ``path`` does not exist and ValueError if it is not a
    policy file, is corrupt, or holds another architecture than :class:`Actor`.
    """
    path = pathlib.Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such policy file")
    try:
        with np.load(path, allow_pickle=False) as data:
            contents = {name: data[name] for name in data.files}
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as error:
        raise ValueError(f"{path}: not a readable policy file ({error})") from error
    if _META not in contents:
        raise ValueError(f"{path}: not a policy file (no {_META} entry); train.sac writes one to RUN_DIR/policy.npz")
    try:
        meta = json.loads(contents.pop(_META).tobytes().decode())
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise ValueError(f"{path}: corrupt policy metadata ({error})") from error
    if meta.get("format") != FORMAT or meta.get("version") not in READABLE_VERSIONS:
        raise ValueError(f"{path}: format {meta.get('format')!r} version {meta.get('version')!r}, expected {FORMAT!r} version "
                         f"{' or '.join(map(str, READABLE_VERSIONS))}")
    if _digest(contents) != meta.get("sha256"):
        raise ValueError(f"{path}: parameter checksum mismatch (the file is corrupt or was modified)")
    try:  # files before the input options hold plain actors, files of one option "rotations"
        inputs = InputFeatures(**meta["inputs"]) if "inputs" in meta else InputFeatures(rotations=bool(meta.get("rotations", False)))
    except TypeError as error:
        raise ValueError(f"{path}: unknown input features {meta['inputs']} ({error})") from error
    components = meta.get("components", 1)  # files before mixtures hold one Gaussian
    if not isinstance(components, int) or components < 1:
        raise ValueError(f"{path}: mixture components {components!r}, expected an integer >= 1")
    expected = _architecture(bool(meta["squash"]), inputs, components)
    has_critic = any(name.startswith(_CRITIC) for name in contents)
    if has_critic:
        expected |= _critic_architecture(inputs)
    for name, shape in expected.items():
        if name not in contents:
            raise ValueError(f"{path}: parameter {name} missing: the file holds another architecture")
        if list(contents[name].shape) != shape:
            raise ValueError(f"{path}: parameter {name} has shape {list(contents[name].shape)}, this actor expects {shape}: "
                             "the file holds another architecture")
    unexpected = sorted(set(contents) - set(expected))
    if unexpected:
        raise ValueError(f"{path}: unexpected parameters {unexpected[:3]}: the file holds another architecture")
    graphdef, state = nnx.split(_abstract_actor(bool(meta["squash"]), inputs, components))
    critic = None
    if has_critic:
        _, critic_state = nnx.split(nnx.eval_shape(lambda: TwinCritic(nnx.Rngs(0), inputs, NUM_JOINTS)))
        critic = _filled(critic_state, contents, _CRITIC)
    return LoadedPolicy(nnx.merge(graphdef, _filled(state, contents)), meta, inputs, critic)


def _filled(abstract: nnx.State, contents: dict[str, np.ndarray], prefix: str = "") -> nnx.State:
    """``abstract``'s parameters with the file's arrays (named ``prefix`` + path)."""
    return nnx.from_flat_state([(path, nnx.Param(jax.numpy.asarray(contents[prefix + _name(path)])))
                                for path, _ in nnx.to_flat_state(abstract)])

