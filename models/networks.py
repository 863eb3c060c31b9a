"""The decentralized actor-critic (paper appendix), in Flax NNX.

Every arm is evaluated by the same networks on its own observation: the sequence of 107-D
elements of the arms it sees (masked elements first, itself last; see
:mod:`mjx_multiarm.env.observation`). One forward pass takes any leading batch dims
(environments, arms), so all arms of all environments go through at once.

- :class:`SequenceEncoder`: a one-layer LSTM (107 -> 256, zero initial state) over the
  sequence; masked elements leave the state untouched, and since they come first the
  state is still exactly zero when the first real element arrives, so padding never
  changes the encoding.
- :class:`Actor`: encoder, then MLP 256 -> 128 -> 64 -> 12 with tanh after every layer: the
  mean (6) and the log-variance (6, mapped from [-1, 1] onto [log 1e-8, log 0.1]) of a
  diagonal Gaussian over the 6 delta-joint actions, as the original code. With
  ``squash=True`` (standard SAC) the last layer is linear, the log-std is clipped to
  [-20, 2], and samples are squashed by tanh.
- :class:`Critic`: encoder, the action concatenated to its output, MLP -> 128 -> 64 -> 1.
  :class:`TwinCritic` holds two independent ones.

Linear layers start as PyTorch's (and the original's): weights uniform in
+-1/sqrt(fan_in), biases zero.
"""

from __future__ import annotations

import math
from typing import Protocol

import jax
import jax.numpy as jnp
from flax import nnx

HIDDEN = 256
MLP_LAYERS = (128, 64)
#: The original's bounds on the action variance.
VARIANCE_BOUNDS = (1e-8, 0.1)
LOG_STD_BOUNDS = (-20.0, 2.0)
#: Up to this many sequences (a planner step: one per arm) the LSTM's input projections of
#: all elements are one matrix product; more (training batches) take one product per element.
FEW_SEQUENCES = 16


class ElementFeatures(Protocol):
    """What the encoder computes from each observation element before its LSTM: ``size``
    numbers per element (the library's :class:`mjx_multiarm.env.observation.InputFeatures`)."""

    size: int

    def __call__(self, obs): ...


def _linear(inputs: int, outputs: int, rngs: nnx.Rngs) -> nnx.Linear:
    init = jax.nn.initializers.variance_scaling(1.0 / 3.0, "fan_in", "uniform")
    return nnx.Linear(inputs, outputs, kernel_init=init, bias_init=jax.nn.initializers.zeros, rngs=rngs)


class SequenceEncoder(nnx.Module):
    """LSTM encoding of a masked observation sequence: [..., L, 107], [..., L] -> [..., 256].

    ``inputs`` says what the LSTM sees of each element (:class:`ElementFeatures`)."""

    def __init__(self, rngs: nnx.Rngs, inputs: ElementFeatures, hidden: int = HIDDEN):
        self.hidden, self.inputs = hidden, inputs
        self.cell = nnx.OptimizedLSTMCell(inputs.size, hidden, rngs=rngs)

    def __call__(self, obs, mask):
        cell, carry = self.cell, None  # None: the zero state, untouched so far
        inputs = self.inputs(obs)
        if math.prod(obs.shape[:-2]) <= FEW_SEQUENCES:
            # Every element's input projection in one matrix product: the weights are read
            # once, not once per element (most of a planner step's forward pass).
            projected = cell.dense_i(jnp.moveaxis(inputs, -2, 0))
        else:  # per element: faster for training batches on XLA CPU (benchmarks/RESULTS.md)
            projected = [cell.dense_i(inputs[..., t, :]) for t in range(obs.shape[-2])]
        for t in range(obs.shape[-2]):  # short sequences (max_arms): unrolled
            gates = projected[t]
            # From the zero state the hidden projection is its bias alone: skipping that
            # matmul at the first element changes no number and saves 18 % of the FLOPs of
            # a 4-element encoding, 70 % of a 1-element one.
            gates = gates + (cell.dense_h.bias[...] if carry is None else cell.dense_h(carry[1]))
            i, f, g, o = jnp.split(gates, 4, axis=-1)
            i, f, g, o = cell.gate_fn(i), cell.gate_fn(f), cell.activation_fn(g), cell.gate_fn(o)
            c = i * g if carry is None else f * carry[0] + i * g
            previous = carry or (0.0, 0.0)
            carry = tuple(jnp.where(mask[..., t, None], new, old) for new, old in zip((c, o * cell.activation_fn(c)), previous))
        return carry[1]


class MLP(nnx.Module):
    """Linear layers with tanh between them (and after the last one if ``final_tanh``)."""

    def __init__(self, sizes: tuple[int, ...], rngs: nnx.Rngs, final_tanh: bool):
        self.layers = nnx.List([_linear(a, b, rngs) for a, b in zip(sizes[:-1], sizes[1:])])
        self.final_tanh = final_tanh

    def __call__(self, x):
        for i, layer in enumerate(self.layers):
            x = layer(x)
            if i < len(self.layers) - 1 or self.final_tanh:
                x = jnp.tanh(x)
        return x


class Actor(nnx.Module):
    """Gaussian policy over delta-joint actions."""

    def __init__(self, rngs: nnx.Rngs, inputs: ElementFeatures, actions: int, squash: bool = False):
        self.squash = squash
        self.encoder = SequenceEncoder(rngs, inputs)
        self.head = MLP((HIDDEN, *MLP_LAYERS, 2 * actions), rngs, final_tanh=not squash)

    def distribution(self, obs, mask, std_scale=1.0):
        """(mean [..., 6], log-std [..., 6]).

        ``std_scale`` (<= 1, may be traced) shrinks the upper bound of the standard deviation
        (a noise schedule; 1: the fixed bounds)."""
        out = self.head(self.encoder(obs, mask))
        mean, raw = jnp.split(out, 2, axis=-1)
        log_scale = jnp.log(std_scale)
        if self.squash:
            return mean, jnp.clip(raw, LOG_STD_BOUNDS[0], LOG_STD_BOUNDS[1] + log_scale)
        low, high = (math.log(v) for v in VARIANCE_BOUNDS)
        log_variance = low + (raw + 1.0) * 0.5 * (high + 2.0 * log_scale - low)
        return mean, 0.5 * log_variance

    def __call__(self, obs, mask, key=None, std_scale=1.0):
        """(action, log-probability); the mean action (squashed if so) when ``key`` is None."""
        return self.sample(*self.distribution(obs, mask, std_scale), key)

    def sample(self, mean, log_std, key=None):
        """(action, log-probability) of the distribution (mean, log_std); see ``__call__``."""
        if key is None:
            action = jnp.tanh(mean) if self.squash else mean
            return action, jnp.zeros(action.shape[:-1], action.dtype)
        noise = jax.random.normal(key, mean.shape, mean.dtype)
        sample = mean + jnp.exp(log_std) * noise
        log_prob = jnp.sum(-0.5 * noise**2 - log_std - 0.5 * math.log(2 * math.pi), axis=-1)
        if self.squash:
            action = jnp.tanh(sample)
            return action, log_prob - jnp.sum(jnp.log1p(-(action**2) + 1e-6), axis=-1)
        return sample, log_prob

    def log_prob(self, obs, mask, action):
        """Log-density of ``action`` (unsquashed policies only: behaviour cloning)."""
        mean, log_std = self.distribution(obs, mask)
        z = (action - mean) * jnp.exp(-log_std)
        return jnp.sum(-0.5 * z**2 - log_std - 0.5 * math.log(2 * math.pi), axis=-1)


class Critic(nnx.Module):
    """Q(observation, action) -> [...]."""

    def __init__(self, rngs: nnx.Rngs, inputs: ElementFeatures, actions: int):
        self.encoder = SequenceEncoder(rngs, inputs)
        self.head = MLP((HIDDEN + actions, *MLP_LAYERS, 1), rngs, final_tanh=False)

    def __call__(self, obs, mask, action):
        return self.value(self.encoder(obs, mask), action)

    def value(self, encoding, action):
        """Q from an observation's ``encoding`` [..., 256] (e.g. reused across actions)."""
        return self.head(jnp.concatenate([encoding, action], axis=-1))[..., 0]


class TwinCritic(nnx.Module):
    """Two independent critics: (q1, q2)."""

    def __init__(self, rngs: nnx.Rngs, inputs: ElementFeatures, actions: int):
        self.q1, self.q2 = Critic(rngs, inputs, actions), Critic(rngs, inputs, actions)

    def __call__(self, obs, mask, action):
        return self.values(self.encode(obs, mask), action)

    def encode(self, obs, mask):
        """Both critics' encodings of the observations: (e1, e2)."""
        return self.q1.encoder(obs, mask), self.q2.encoder(obs, mask)

    def values(self, encodings, action):
        """(q1, q2) of ``action`` from the critics' ``encodings`` (as :meth:`encode` returns)."""
        return self.q1.value(encodings[0], action), self.q2.value(encodings[1], action)
