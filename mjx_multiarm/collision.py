"""Batched capsule collision checking of padded multi-arm scenes in JAX.

Every collision geom is a capsule, so every check is a segment-segment distance minus the
two radii (exactly what MuJoCo C's capsule-capsule test computes), and the ground test is
the lowest segment end's height minus the radius. Distances are signed: negative means
penetration. The pairs checked are those of :class:`mjx_multiarm.scene.CollisionPairs`.

Coordinates are handled as separate x/y/z arrays inside the kernel so that XLA fuses each
check into one elementwise loop over all pairs of all scenes.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from mjx_multiarm.kinematics import forward_kinematics
from mjx_multiarm.scene import Scene

#: Default largest joint motion between two swept-collision checks (rad).
SWEEP_RESOLUTION = 0.05
#: Scenes per collision chunk on CPU (measured best of 16-256 for 4 and 10 arms).
CPU_CHUNK = 64


@struct.dataclass
class Contacts:
    """Per-arm collision result; every field has shape [..., max_arms].

    The distances are the smallest signed distance (m) over the capsule pairs of each kind;
    ``inf`` where an arm has no such pair (inactive slots, a lone arm's ``between_arms``).
    """

    between_arms: jnp.ndarray
    within_arm: jnp.ndarray  # non-adjacent links of the arm itself
    ground: jnp.ndarray

    @property
    def min_distance(self) -> jnp.ndarray:
        return jnp.minimum(jnp.minimum(self.between_arms, self.within_arm), self.ground)

    @property
    def collided(self) -> jnp.ndarray:
        return self.min_distance < 0.0


def _dot(u, v):
    """Dot product of coordinates-first vectors, written out (XLA fuses it elementwise)."""
    return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]


def segment_distance(p1, q1, p2, q2):
    """Distance between segments [p1, q1] and [p2, q2]; coordinates first: [3, ...].

    Closest points by clamped parameters (Ericson, Real-Time Collision Detection 5.1.9);
    segments must have positive length.
    """
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a, e, b = _dot(d1, d1), _dot(d2, d2), _dot(d1, d2)
    c, f = _dot(d1, r), _dot(d2, r)
    denom = a * e - b * b
    s = jnp.where(denom > 1e-12 * a * e, jnp.clip((b * f - c * e) / denom, 0.0, 1.0), 0.0)
    t = (b * s + f) / e
    s = jnp.where(t < 0.0, jnp.clip(-c / a, 0.0, 1.0), jnp.where(t > 1.0, jnp.clip((b - c) / a, 0.0, 1.0), s))
    t = jnp.clip(t, 0.0, 1.0)
    gap = r + d1 * s - d2 * t
    return jnp.sqrt(_dot(gap, gap))


def _arm_pair_tables(max_arms: int):
    """Static arm pairs (i < j) and the [max_arms, npairs] incidence of arms in pairs."""
    first, second = np.triu_indices(max_arms, k=1)
    incidence = np.zeros((max_arms, len(first)), bool)
    incidence[first, np.arange(len(first))] = True
    incidence[second, np.arange(len(first))] = True
    return first, second, incidence


def _flat_contacts(scene: Scene, capsules, active) -> Contacts:
    """The kernel on a flat batch: capsules [N, A, C, 2, 3], active [N, A] -> fields [N, A]."""
    pairs, radius = scene.pairs, scene.arm.capsule_radius
    num_arms = capsules.shape[1]
    # Scenes go last, coordinates first: every operation below is elementwise over rows of
    # scenes, which XLA vectorizes; reductions run over the leading (small) axes.
    ends = jnp.moveaxis(capsules, (4, 3, 0), (0, 1, 4))
    p, q = ends[:, 0], ends[:, 1]  # [3, A, C, N]
    act = active.T  # [A, N]
    inf = jnp.asarray(jnp.inf, capsules.dtype)

    # Between arms: every capsule pair of every arm pair (i < j).
    first, second, incidence = _arm_pair_tables(num_arms)
    if len(first):
        pi, qi = p[:, first, :, None], q[:, first, :, None]  # [3, P, C, 1, N]
        pj, qj = p[:, second, None, :], q[:, second, None, :]  # [3, P, 1, C, N]
        reach = jnp.asarray(radius[:, None] + radius[None, :], capsules.dtype)[..., None]
        dist = segment_distance(pi, qi, pj, qj) - reach
        dist = jnp.where(pairs.between_arms[..., None], dist, inf).min(axis=(1, 2))  # [P, N]
        dist = jnp.where(act[first] & act[second], dist, inf)
        between = jnp.where(incidence[..., None], dist[None], inf).min(axis=1)  # [A, N]
    else:
        between = jnp.full(act.shape, inf)

    # Self: non-adjacent capsule pairs of one arm.
    a, b = pairs.self_pairs[:, 0], pairs.self_pairs[:, 1]
    reach = jnp.asarray(radius[a] + radius[b], capsules.dtype)[:, None]
    self_dist = segment_distance(p[:, :, a], q[:, :, a], p[:, :, b], q[:, :, b]) - reach  # [A, S, N]
    self_dist = self_dist.min(axis=1, initial=jnp.inf)

    # Ground: lowest end point of each capsule above z = 0.
    g = pairs.ground
    lowest = jnp.minimum(p[2][:, g], q[2][:, g]) - jnp.asarray(radius[g], capsules.dtype)[:, None]
    ground = lowest.min(axis=1, initial=jnp.inf)

    def per_arm(x):  # [A, N] -> [N, A], inactive arms at +inf
        return jnp.where(act, x, inf).T

    return Contacts(between_arms=per_arm(between), within_arm=per_arm(self_dist), ground=per_arm(ground))


def capsule_contacts(scene: Scene, capsules, active, chunk: int | None = None) -> Contacts:
    """Signed distances of posed capsules.

    Args:
      scene: the padded scene.
      capsules: [..., max_arms, ncap, 2, 3] world capsule segments (``ArmFrames.capsules``).
      active: [..., max_arms] bool; inactive slots never collide and never affect others.
      chunk: scenes checked at a time (a sequential ``lax.map`` over chunks). Default:
        :data:`CPU_CHUNK` for multi-arm scenes on the CPU backend (2-3x faster at large
        batches: the working set stays in cache), the whole batch at once otherwise.

    Under ``jax.vmap`` the mapped axes join the leading dims: the kernel always sees the
    whole batch of scenes at once (vectorized over scenes, chunked on CPU), however it is
    called.
    """
    return _batched_kernel(scene, chunk)(capsules, active)


@functools.cache
def _batched_kernel(scene: Scene, chunk: int | None):
    """:func:`_contacts` with a batching rule that folds vmapped axes into its batch."""

    @jax.custom_batching.custom_vmap
    def kernel(capsules, active):
        return _contacts(scene, capsules, active, chunk)

    @kernel.def_vmap
    def fold_batch(axis_size, in_batched, capsules, active):
        capsules_batched, active_batched = in_batched
        if not capsules_batched:
            capsules = jnp.broadcast_to(capsules, (axis_size, *capsules.shape))
        if not active_batched:
            active = jnp.broadcast_to(active, (axis_size, *active.shape))
        contacts = kernel(capsules, active)
        return contacts, jax.tree.map(lambda _: True, contacts)

    return kernel


def _contacts(scene: Scene, capsules, active, chunk: int | None) -> Contacts:
    batch = capsules.shape[:-4]
    num_arms, num_caps = capsules.shape[-4:-2]
    capsules = capsules.reshape(-1, num_arms, num_caps, 2, 3)
    active = jnp.broadcast_to(active, (*batch, num_arms)).reshape(-1, num_arms)
    n = capsules.shape[0]
    if chunk is None:
        chunk = CPU_CHUNK if jax.default_backend() == "cpu" and num_arms > 1 else n
    if n > chunk:
        pad = -n % chunk  # padded scenes are inactive
        capsules = jnp.pad(capsules, ((0, pad), (0, 0), (0, 0), (0, 0), (0, 0)))
        active = jnp.pad(active, ((0, pad), (0, 0)))
        chunks = (capsules.reshape(-1, chunk, *capsules.shape[1:]), active.reshape(-1, chunk, num_arms))
        contacts = jax.lax.map(lambda xs: _flat_contacts(scene, *xs), chunks)
        contacts = jax.tree.map(lambda x: x.reshape(-1, num_arms)[:n], contacts)
    else:
        contacts = _flat_contacts(scene, capsules, active)
    return jax.tree.map(lambda x: x.reshape(*batch, num_arms), contacts)


def scene_contacts(scene: Scene, base_pos, base_quat, joints, active) -> Contacts:
    """Kinematics + collision of padded scenes at one configuration.

    Args:
      base_pos: [..., max_arms, 3]; base_quat: [..., max_arms, 4] (wxyz);
      joints: [..., max_arms, 6]; active: [..., max_arms] bool.
    """
    frames = forward_kinematics(scene.arm, base_pos, base_quat, joints)
    return capsule_contacts(scene, frames.capsules, active)


def num_substeps(joints_from, joints_to, resolution: float = SWEEP_RESOLUTION) -> int:
    """Substeps so that no joint moves more than ``resolution`` between checks (concrete inputs)."""
    largest = float(np.max(np.abs(np.asarray(joints_to) - np.asarray(joints_from)), initial=0.0))
    return max(1, math.ceil(largest / resolution - 1e-9))


def swept_contacts(scene: Scene, base_pos, base_quat, joints_from, joints_to, active, substeps: int,
                   end_capsules=None) -> Contacts:
    """Collision along the straight joint-space motion ``joints_from -> joints_to``.

    Checks the configurations at fractions k / substeps, k = 1..substeps (the start is
    assumed checked already), and returns per arm the smallest distance over them. Pick
    ``substeps`` with :func:`num_substeps`, or as ``ceil(max_step / resolution)`` for a
    known largest joint step; it is static under ``jit``. A caller that already posed the
    arms at ``joints_to`` passes their ``ArmFrames.capsules`` as ``end_capsules`` so the
    end configuration's kinematics is not computed twice.
    """
    inner = substeps if end_capsules is None else substeps - 1
    fractions = jnp.arange(1, inner + 1, dtype=jnp.result_type(joints_from)) / substeps

    def at(fraction):
        joints = joints_from + fraction * (joints_to - joints_from)
        return scene_contacts(scene, base_pos, base_quat, joints, active)

    per_step = [jax.tree.map(lambda x: x.min(axis=0), jax.vmap(at)(fractions))] if inner else []
    if end_capsules is not None:
        per_step.append(capsule_contacts(scene, end_capsules, active))
    return jax.tree.map(lambda *x: functools.reduce(jnp.minimum, x), *per_step)
