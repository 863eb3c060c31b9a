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
  [-20, 2], and samples are squashed by tanh. With ``components`` = K > 1 the policy is a
  mixture of K such Gaussians (a multimodal head for detours that may go either way): the
  last layer gives 12 numbers per component and a linear layer from the 64 features gives
  the mixture's logits; the deterministic action is the heaviest component's mean.
  :func:`widened` turns a one-component actor into an equal mixture of copies of it (the
  same policy), the start of a mixture fine-tune.
- :class:`Critic`: encoder, the action concatenated to its output, MLP -> 128 -> 64 -> 1.
  :class:`TwinCritic` holds two independent ones.

Linear layers start as PyTorch's (and the original's): weights uniform in
+-1/sqrt(fan_in), biases zero.
"""

from __future__ import annotations

import math
from typing import NamedTuple, Protocol

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
        x = self.layers[-1](self.features(x))
        return jnp.tanh(x) if self.final_tanh else x

    def features(self, x):
        """The last layer's input: every layer but the last, each followed by tanh."""
        for layer in self.layers[:-1]:
            x = jnp.tanh(layer(x))
        return x


class Mixture(NamedTuple):
    """A policy's action distribution at each observation: a mixture of diagonal Gaussians
    (one component for the original's Gaussian), before any tanh squashing."""

    mean: jnp.ndarray  # [..., K, 6]
    log_std: jnp.ndarray  # [..., K, 6]
    log_weights: jnp.ndarray  # [..., K], normalized


def _gaussian_log_density(x, dist: Mixture):
    """log N(x; mean_k, std_k) of every component [..., K] at ``x`` [..., 6]."""
    z = (x[..., None, :] - dist.mean) * jnp.exp(-dist.log_std)
    return jnp.sum(-0.5 * z**2 - dist.log_std - 0.5 * math.log(2 * math.pi), axis=-1)


class Actor(nnx.Module):
    """Gaussian (or Gaussian-mixture) policy over delta-joint actions."""

    def __init__(self, rngs: nnx.Rngs, inputs: ElementFeatures, actions: int, squash: bool = False, components: int = 1):
        if components < 1:
            raise ValueError(f"an actor needs at least one mixture component, got {components}")
        self.squash, self.actions, self.components = squash, actions, components
        self.encoder = SequenceEncoder(rngs, inputs)
        self.head = MLP((HIDDEN, *MLP_LAYERS, 2 * actions * components), rngs, final_tanh=not squash)
        if components > 1:
            self.logits = _linear(MLP_LAYERS[-1], components, rngs)

    def distribution(self, obs, mask, std_scale=1.0) -> Mixture:
        """The action distribution at each observation.

        ``std_scale`` (<= 1, may be traced) shrinks the upper bound of the standard deviation
        (a noise schedule; 1: the fixed bounds)."""
        features = self.head.features(self.encoder(obs, mask))
        out = self.head.layers[-1](features)
        out = (out if self.squash else jnp.tanh(out)).reshape(*out.shape[:-1], self.components, 2 * self.actions)
        mean, raw = jnp.split(out, 2, axis=-1)
        if self.components > 1:
            log_weights = jax.nn.log_softmax(self.logits(features), axis=-1)
        else:
            log_weights = jnp.zeros(out.shape[:-1], out.dtype)
        log_scale = jnp.log(std_scale)
        if self.squash:
            return Mixture(mean, jnp.clip(raw, LOG_STD_BOUNDS[0], LOG_STD_BOUNDS[1] + log_scale), log_weights)
        low, high = (math.log(v) for v in VARIANCE_BOUNDS)
        log_variance = low + (raw + 1.0) * 0.5 * (high + 2.0 * log_scale - low)
        return Mixture(mean, 0.5 * log_variance, log_weights)

    def __call__(self, obs, mask, key=None, std_scale=1.0):
        """(action, log-probability); the deterministic action (:meth:`mode`) when ``key`` is None."""
        return self.sample(self.distribution(obs, mask, std_scale), key)

    def mode(self, dist: Mixture):
        """The deterministic action [..., 6]: the heaviest component's mean (squashed if so)."""
        heaviest = jnp.argmax(dist.log_weights, axis=-1)
        mean = jnp.take_along_axis(dist.mean, heaviest[..., None, None], axis=-2)[..., 0, :]
        return jnp.tanh(mean) if self.squash else mean

    def component_modes(self, dist: Mixture):
        """Every component's mean [..., K, 6] (squashed if so)."""
        return jnp.tanh(dist.mean) if self.squash else dist.mean

    def sample(self, dist: Mixture, key=None):
        """(action, log-probability) drawn from ``dist``; (:meth:`mode`, 0) when ``key`` is None."""
        if key is None:
            action = self.mode(dist)
            return action, jnp.zeros(action.shape[:-1], action.dtype)
        if self.components > 1:
            key, pick = jax.random.split(key)
            chosen = jax.random.categorical(pick, dist.log_weights)[..., None, None]
            mean, log_std = (jnp.take_along_axis(x, chosen, axis=-2)[..., 0, :] for x in (dist.mean, dist.log_std))
        else:
            mean, log_std = dist.mean[..., 0, :], dist.log_std[..., 0, :]
        sample = mean + jnp.exp(log_std) * jax.random.normal(key, mean.shape, mean.dtype)
        return self._squashed(sample, self._log_density(sample, dist))

    def component_samples(self, dist: Mixture, key):
        """(actions [..., K, 6], log-probabilities [..., K]): one reparameterized sample of
        every component, each with its density under the whole mixture, so that
        ``sum_k w_k f(a_k)`` is an exact expectation over the components (the actor loss)."""
        samples = dist.mean + jnp.exp(dist.log_std) * jax.random.normal(key, dist.mean.shape, dist.mean.dtype)
        log_prob = jax.vmap(self._log_density, in_axes=(-2, None), out_axes=-1)(samples, dist)
        return self._squashed(samples, log_prob)

    def _log_density(self, x, dist: Mixture):
        """The mixture's log-density at ``x`` [..., 6] (before squashing) [...]."""
        if self.components == 1:
            return _gaussian_log_density(x, dist)[..., 0]
        return jax.nn.logsumexp(dist.log_weights + _gaussian_log_density(x, dist), axis=-1)

    def _squashed(self, sample, log_prob):
        if self.squash:
            action = jnp.tanh(sample)
            return action, log_prob - jnp.sum(jnp.log1p(-(action**2) + 1e-6), axis=-1)
        return sample, log_prob

    def log_prob(self, obs, mask, action):
        """Log-density of ``action`` (unsquashed policies only: behaviour cloning)."""
        return self._log_density(action, self.distribution(obs, mask))


def widened(actor: Actor, components: int, first_weight: float | None = None) -> Actor:
    """``actor`` (one component) as a mixture of ``components`` copies of its Gaussian, with
    equal weights, or ``first_weight`` on the first copy and the rest shared equally: the
    same policy either way (density, samples' distribution, deterministic action), whose
    copies the gradient then pulls apart. The start of a mixture fine-tune of a trained actor."""
    if actor.components != 1:
        raise ValueError(f"only a one-component actor can be widened, this one has {actor.components}")
    if first_weight is not None and not 0 < first_weight < 1:
        raise ValueError(f"the first copy's weight must be in (0, 1), got {first_weight}")
    rest = (1 - first_weight) / (components - 1) if first_weight is not None else 1.0
    logits_bias = jnp.log(jnp.array([first_weight or 1.0] + [rest] * (components - 1)))
    wide = nnx.eval_shape(lambda: Actor(nnx.Rngs(0), actor.encoder.inputs, actor.actions, actor.squash, components))
    graphdef, state = nnx.split(wide)
    params = dict(nnx.to_flat_state(nnx.state(actor, nnx.Param)))
    last = ("head", "layers", len(MLP_LAYERS))

    def value(path, abstract):
        if path[:3] == last:  # the mean and variance outputs, once per component
            return jnp.tile(params[path][...], (1,) * (abstract.ndim - 1) + (components,))
        if path[0] == "logits":  # the weights from the bias alone
            return logits_bias.astype(abstract.dtype) if path[-1] == "bias" else jnp.zeros(abstract.shape, abstract.dtype)
        return params[path][...]

    flat = [(path, nnx.Param(value(path, abstract))) for path, abstract in nnx.to_flat_state(state)]
    return nnx.merge(graphdef, nnx.from_flat_state(flat))


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
