"""Actor-critic networks: shapes, masking, padding invariance, distributions."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from mjx_multiarm.env.observation import InputFeatures
from mjx_multiarm.geometry.robot import NUM_JOINTS
from models.networks import (
    FEW_SEQUENCES,
    VARIANCE_BOUNDS,
    Actor,
    Mixture,
    SequenceEncoder,
    TwinCritic,
    widened,
)


def _sequences(key, batch, length, valid):
    """Observation sequences [batch, length, 107] whose last ``valid`` elements are real."""
    obs = jax.random.normal(key, (batch, length, 107))
    mask = jnp.broadcast_to(jnp.arange(length) >= length - valid, (batch, length))
    return obs, mask


def test_padding_never_changes_the_encoding():
    encoder = SequenceEncoder(nnx.Rngs(0), InputFeatures())
    obs, mask = _sequences(jax.random.key(1), 3, 10, 4)
    garbage = obs.at[:, :6].set(1e3)  # masked elements hold anything
    np.testing.assert_array_equal(encoder(garbage, mask), encoder(obs, mask))
    short = encoder(obs[:, 6:], mask[:, 6:])  # the same 4 real elements without padding
    np.testing.assert_allclose(encoder(obs, mask), short, atol=1e-6)
    assert not np.allclose(encoder(obs, mask), encoder(obs, jnp.ones_like(mask)))  # real elements do count


def test_encoder_equals_flax_lstm_cell_from_the_zero_state():
    """The first element's skipped hidden matmul changes no value and no gradient (on a
    training-sized batch: the per-element input projections that training differentiates)."""
    encoder = SequenceEncoder(nnx.Rngs(0), InputFeatures())
    obs, mask = _sequences(jax.random.key(2), FEW_SEQUENCES + 4, 4, 3)
    mask = mask.at[0].set(True).at[1].set(jnp.array([False, False, False, True]))  # 4, 3 and 1 real elements

    def reference(encoder, obs, mask):
        carry = encoder.cell.initialize_carry(obs[:, 0].shape, nnx.Rngs(0))
        for t in range(obs.shape[1]):
            new, _ = encoder.cell(carry, obs[:, t])
            carry = tuple(jnp.where(mask[:, t, None], n, c) for n, c in zip(new, carry))
        return carry[1]

    np.testing.assert_array_equal(encoder(obs, mask), reference(encoder, obs, mask))
    loss = lambda f: nnx.grad(lambda e: jnp.sum(jnp.sin(f(e, obs, mask))))(encoder)  # noqa: E731
    fast, slow = loss(lambda e, o, m: e(o, m)), loss(reference)
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7), fast, slow)


def test_actor_and_critic_shapes_and_any_leading_dims():
    actor, critic = Actor(nnx.Rngs(0), InputFeatures(), NUM_JOINTS), TwinCritic(nnx.Rngs(1), InputFeatures(), NUM_JOINTS)
    obs = jax.random.normal(jax.random.key(0), (2, 5, 4, 4, 107))  # [devices?, envs, arms, seq, 107]
    mask = jnp.ones((2, 5, 4, 4), bool)
    action, log_prob = actor(obs, mask, jax.random.key(2))
    assert action.shape == (2, 5, 4, 6) and log_prob.shape == (2, 5, 4)
    q1, q2 = critic(obs, mask, action)
    assert q1.shape == q2.shape == (2, 5, 4) and not np.allclose(q1, q2)
    mean, _ = actor(obs, mask)
    assert np.all(np.abs(mean) <= 1.0)  # tanh-bounded mean, as the original


def test_log_probabilities_match_the_gaussian():
    actor = Actor(nnx.Rngs(0), InputFeatures(), NUM_JOINTS)
    obs, mask = _sequences(jax.random.key(3), 4, 3, 3)
    action, log_prob = actor(obs, mask, jax.random.key(4))
    np.testing.assert_allclose(actor.log_prob(obs, mask, action), log_prob, rtol=1e-4, atol=1e-4)
    dist = actor.distribution(obs, mask)
    mean, log_std = dist.mean[..., 0, :], dist.log_std[..., 0, :]
    variance = np.exp(2 * np.asarray(log_std))
    assert np.all(variance >= VARIANCE_BOUNDS[0] * (1 - 1e-4)) and np.all(variance <= VARIANCE_BOUNDS[1] * (1 + 1e-4))
    expected = -0.5 * ((action - mean) ** 2 / variance).sum(-1) - 0.5 * np.log(variance).sum(-1) - 3 * math.log(2 * math.pi)
    np.testing.assert_allclose(log_prob, expected, rtol=1e-4, atol=1e-3)
    squashed = Actor(nnx.Rngs(0), InputFeatures(), NUM_JOINTS, squash=True)
    sample, _ = squashed(obs, mask, jax.random.key(5))
    assert np.all(np.abs(sample) < 1.0)


def test_noise_schedule_shrinks_the_standard_deviation_bound():
    actor = Actor(nnx.Rngs(0), InputFeatures(), NUM_JOINTS)
    obs, mask = _sequences(jax.random.key(3), 4, 3, 3)
    mean, log_std, _ = (x[..., 0, :] for x in actor.distribution(obs, mask))
    narrow_mean, narrow_log_std, _ = (x[..., 0, :] for x in actor.distribution(obs, mask, std_scale=0.2))
    np.testing.assert_allclose(narrow_mean, mean)  # the schedule touches the noise alone
    assert np.all(np.exp(narrow_log_std) <= 0.2 * math.sqrt(VARIANCE_BOUNDS[1]) * (1 + 1e-4))
    assert np.all(narrow_log_std < log_std)
    action, log_prob = actor(obs, mask, jax.random.key(4), std_scale=0.2)
    z = (np.asarray(action) - np.asarray(mean)) / np.exp(np.asarray(narrow_log_std))
    expected = (-0.5 * z**2 - np.asarray(narrow_log_std) - 0.5 * math.log(2 * math.pi)).sum(-1)
    np.testing.assert_allclose(log_prob, expected, rtol=1e-4, atol=1e-3)


def test_rotation_features_are_continuous_and_blind_to_the_quaternion_sign():
    """Each quaternion of an element becomes the first two columns of its rotation matrix:
    q and -q give the same features (a sign-canonical quaternion flips at w = 0), every
    other component passes through in order, and the actor accepts the 107-D elements."""
    from mjx_multiarm.env.observation import (
        QUATERNIONS,
        InputFeatures,
        rotation_features,
    )
    from mjx_multiarm.geometry.transforms import quat_to_mat

    rng = np.random.default_rng(0)
    obs = rng.normal(size=(6, 3, 107)).astype(np.float32)
    for quat in QUATERNIONS:
        q = rng.normal(size=(6, 3, 4))
        obs[..., quat] = q / np.linalg.norm(q, axis=-1, keepdims=True)
    flipped = obs.copy()
    for quat in QUATERNIONS:
        flipped[..., quat] *= -1
    features = np.asarray(rotation_features(jnp.asarray(obs)))
    size = InputFeatures(rotations=True).size
    assert features.shape == (6, 3, size) and size == 117
    np.testing.assert_allclose(np.asarray(rotation_features(jnp.asarray(flipped))), features, atol=1e-6)
    kept = np.ones(107, bool)
    for quat in QUATERNIONS:
        kept[quat] = False
    first = QUATERNIONS[0]
    columns = np.asarray(quat_to_mat(jnp.asarray(obs[..., first])))[..., :, :2]
    np.testing.assert_allclose(features[..., first.start : first.start + 6], np.swapaxes(columns, -1, -2).reshape(6, 3, 6), atol=1e-6)
    passthrough = np.ones(size, bool)
    for i, quat in enumerate(QUATERNIONS):
        passthrough[quat.start + 2 * i : quat.start + 2 * i + 6] = False
    np.testing.assert_array_equal(features[..., passthrough], obs[..., kept])
    mean, _ = Actor(nnx.Rngs(0), InputFeatures(rotations=True), NUM_JOINTS)(jnp.asarray(obs), jnp.ones((6, 3), bool))
    assert mean.shape == (6, 6) and np.isfinite(np.asarray(mean)).all()


def test_goal_features_are_the_end_effector_error_to_its_target():
    """Position error scaled to 0.1 per cm, rotation error as a rotation vector in the end
    effector's frame (exact direction, small-angle magnitude), blind to quaternion signs;
    appended after the element (or its rotation features)."""
    from mjx_multiarm.env.observation import (
        EE_POSITION,
        EE_QUAT,
        TARGET_POSITION,
        TARGET_QUAT,
        InputFeatures,
        goal_features,
    )
    from mjx_multiarm.geometry.transforms import quat_mul

    rng = np.random.default_rng(1)
    obs = rng.normal(size=(5, 107)).astype(np.float32)
    ee = rng.normal(size=(5, 4))
    ee /= np.linalg.norm(ee, axis=-1, keepdims=True)
    axis = rng.normal(size=(5, 3))
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    angle = 0.05
    turn = np.concatenate([np.full((5, 1), np.cos(angle / 2)), np.sin(angle / 2) * axis], axis=-1)
    obs[:, EE_QUAT] = ee
    obs[:, TARGET_QUAT] = -np.asarray(quat_mul(jnp.asarray(ee), jnp.asarray(turn)))  # the target: ee turned, sign flipped
    obs[:, TARGET_POSITION] = obs[:, EE_POSITION] + np.array([0.02, 0.0, -0.01])
    features = np.asarray(goal_features(jnp.asarray(obs)))
    np.testing.assert_allclose(features[:, :3], np.tile([0.2, 0.0, -0.1], (5, 1)), atol=1e-5)
    np.testing.assert_allclose(features[:, 3:], angle * axis, rtol=1e-3, atol=1e-6)
    assert not np.asarray(goal_features(jnp.zeros((2, 107)))).any()  # masked elements stay zero
    both = np.asarray(InputFeatures(rotations=True, goal=True)(jnp.asarray(obs)))
    assert both.shape == (5, 123) and InputFeatures(goal=True).size == 113
    np.testing.assert_array_equal(both[:, -6:], features)
    mean, _ = Actor(nnx.Rngs(0), InputFeatures(goal=True), NUM_JOINTS)(jnp.asarray(obs[:, None]), jnp.ones((5, 1), bool))
    assert mean.shape == (5, 6) and np.isfinite(np.asarray(mean)).all()


def test_few_and_many_sequences_encode_alike():
    """A planner step's few sequences take one input projection for all elements, training
    batches one per element: the same encodings (to float32 rounding)."""
    encoder = SequenceEncoder(nnx.Rngs(0), InputFeatures(goal=True))
    obs, mask = _sequences(jax.random.key(3), 2 * FEW_SEQUENCES, 5, 3)
    many = encoder(obs, mask)
    few = jnp.concatenate([encoder(obs[:FEW_SEQUENCES], mask[:FEW_SEQUENCES]), encoder(obs[FEW_SEQUENCES:], mask[FEW_SEQUENCES:])])
    np.testing.assert_allclose(few, many, atol=1e-6)


def _two_modes(weights):
    """A two-component mixture per row: means -0.5 and +0.5 on every joint, narrow."""
    mean = jnp.broadcast_to(jnp.array([[-0.5] * 6, [0.5] * 6]), (4000, 2, 6))
    return Mixture(mean, jnp.full((4000, 2, 6), math.log(0.01)), jnp.broadcast_to(jnp.log(jnp.array(weights)), (4000, 2)))


def test_a_mixture_samples_its_components_by_weight_and_acts_with_the_heaviest():
    actor = Actor(nnx.Rngs(0), InputFeatures(), NUM_JOINTS, components=2)
    dist = _two_modes([0.2, 0.8])
    action, log_prob = actor.sample(dist, jax.random.key(1))
    upper = np.asarray(action[:, 0] > 0)
    assert abs(upper.mean() - 0.8) < 0.03  # 4,000 draws: 3 standard deviations is 0.019
    assert np.all(np.abs(np.asarray(action) - np.where(upper[:, None], 0.5, -0.5)) < 0.06)
    np.testing.assert_array_equal(actor.mode(dist), np.full((4000, 6), 0.5))
    np.testing.assert_array_equal(actor.mode(_two_modes([0.7, 0.3])), np.full((4000, 6), -0.5))
    # the density: a direct sum over the two components
    x = np.asarray(action, np.float64)
    gauss = [np.exp(-0.5 * (((x - m) / 0.01) ** 2).sum(-1)) / (0.01 * math.sqrt(2 * math.pi)) ** 6 for m in (-0.5, 0.5)]
    np.testing.assert_allclose(log_prob, np.log(0.2 * gauss[0] + 0.8 * gauss[1]), rtol=1e-5, atol=1e-3)


def test_component_samples_are_reparameterized_and_scored_by_the_whole_mixture():
    actor = Actor(nnx.Rngs(0), InputFeatures(), NUM_JOINTS, components=3)
    obs, mask = _sequences(jax.random.key(3), 5, 3, 2)
    dist = actor.distribution(obs, mask)
    assert dist.mean.shape == dist.log_std.shape == (5, 3, 6) and dist.log_weights.shape == (5, 3)
    np.testing.assert_allclose(jnp.exp(dist.log_weights).sum(-1), 1.0, rtol=1e-6)
    actions, log_probs = actor.component_samples(dist, jax.random.key(4))
    noise = jax.random.normal(jax.random.key(4), (5, 3, 6))
    np.testing.assert_allclose(actions, dist.mean + jnp.exp(dist.log_std) * noise, rtol=1e-6)
    for k in range(3):
        np.testing.assert_allclose(log_probs[:, k], actor.log_prob(obs, mask, actions[:, k]), rtol=1e-5, atol=1e-4)


def test_a_widened_actor_is_the_same_policy():
    """An equal mixture of copies of a Gaussian is that Gaussian: the same deterministic
    action and the same density everywhere."""
    actor = Actor(nnx.Rngs(0), InputFeatures(goal=True), NUM_JOINTS)
    wide = widened(actor, 4)
    assert wide.components == 4
    obs, mask = _sequences(jax.random.key(3), 6, 4, 3)
    np.testing.assert_allclose(wide(obs, mask)[0], actor(obs, mask)[0], atol=1e-6)
    action, log_prob = actor(obs, mask, jax.random.key(5))
    np.testing.assert_allclose(wide.log_prob(obs, mask, action), log_prob, rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(jnp.exp(wide.distribution(obs, mask).log_weights), 0.25)
    led = widened(actor, 3, first_weight=0.9)  # a dominant first copy: still the same policy
    np.testing.assert_allclose(jnp.exp(led.distribution(obs, mask).log_weights), np.broadcast_to([0.9, 0.05, 0.05], (6, 3)),
                               rtol=1e-6)
    np.testing.assert_allclose(led(obs, mask)[0], actor(obs, mask)[0], atol=1e-6)
    np.testing.assert_allclose(led.log_prob(obs, mask, action), log_prob, rtol=1e-5, atol=1e-4)
