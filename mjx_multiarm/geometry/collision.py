"""Batched collision checking of padded multi-arm scenes in JAX: capsules and boxes.

Every collision geom is a capsule or a box (``assets/ur5.xml``), and every distance is
exact while the geoms are apart (what MuJoCo C's ``mj_geomDistance`` computes):

- capsule-capsule: segment-segment distance minus the two radii;
- capsule-box: segment-box distance (the convex, piecewise quadratic squared distance
  along the segment, minimized exactly from its breakpoints) minus the radius;
- box-box: apart (separating-axis test), the smallest of one box's 12 edges against the
  other box and the other box's 8 corners against the first; overlapping, the test's
  penetration;
- ground: the lowest capsule end minus the radius, the lowest box corner;
- static obstacles (boxes of the scene, :func:`mjx_multiarm.geometry.scene.build_scene`):
  as capsule-box and box-box, reported with the ground (``Contacts.ground``).

Distances are signed: negative means penetration (for a segment that enters a box, the
depth of the middle of its part inside). The pairs checked are those of
:class:`mjx_multiarm.geometry.scene.CollisionPairs`.

Two kernels compute these distances (:data:`KERNELS`): ``"xla"``, the JAX code below, for
any backend (coordinates as separate x/y/z arrays, so that XLA fuses each check into one
elementwise loop over all pairs of all scenes), and ``"numba"``, the same distances compiled
for the CPU with a broad phase (:func:`mjx_multiarm.geometry.compiled.batch_contacts`),
called from traced code through ``jax.pure_callback``. :func:`default_kernel` picks numba for
multi-arm scenes without obstacles on the CPU backend and XLA otherwise.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import math
import os
import threading

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from mjx_multiarm.geometry import compiled
from mjx_multiarm.geometry.kinematics import ArmFrames, forward_kinematics
from mjx_multiarm.geometry.scene import Scene

#: Default largest joint motion between two swept-collision checks (rad).
SWEEP_RESOLUTION = 0.05
#: Scenes per chunk of the capsule-capsule check between arms on CPU (measured best of
#: 16-256 for 4 and 10 arms).
CPU_CHUNK = 64
#: Scenes per chunk of the checks with boxes between arms on CPU, for scenes of fewer /
#: at least :data:`BOX_CHUNK_MIN_ARMS` arms (measured at batch 1024: 10 arms 261k -> 314k
#: arm-evaluations/s at chunks of 128-512; 4 arms are fastest at 1024, 694k vs 551-566k).
#: The self pairs and the ground take chunks of :data:`CPU_SELF_CHUNK`: every chunk size
#: bounds memory at large batches (a 2-million-scene swept check).
CPU_BOX_CHUNK = (1024, 256)
BOX_CHUNK_MIN_ARMS = 5
CPU_SELF_CHUNK = 1024
#: The collision kernels: the JAX code of this module, and its numba-compiled CPU twin.
KERNELS = ("xla", "numba")
#: Environment variable that overrides :func:`default_kernel` (one of :data:`KERNELS`).
KERNEL_VARIABLE = "MJX_MULTIARM_COLLISION_KERNEL"
#: ``max_distance`` that asks for contacts only: verdicts and penetration depths, every clear
#: arm at 0 (what a step, a task generator or a verdict needs; the fastest numba query).
CONTACTS_ONLY = 0.0


@struct.dataclass
class Contacts:
    """Per-arm collision result; every field has shape [..., max_arms].

    The distances are the smallest signed distance (m) over the capsule pairs of each kind;
    ``inf`` where an arm has no such pair (inactive slots, a lone arm's ``between_arms``).
    """

    between_arms: jnp.ndarray
    within_arm: jnp.ndarray  # non-adjacent links of the arm itself
    ground: jnp.ndarray  # the static scene: the ground and the scene's obstacle boxes

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


def _excess(x, h):
    """How far the coordinate x lies outside [-h, h] (signed, 0 inside)."""
    return x - jnp.clip(x, -h, h)


def _segment_aabb_distance(a, b, h):
    """Signed distance from the segment a + t b, t in [0, 1], to the box |x_k| <= h_k.

    ``a``, ``b``, ``h``: sequences of 3 arrays (the box's coordinates), broadcasting.
    The squared distance F(t) of the segment's point to the box is convex and piecewise
    quadratic in t, with breakpoints where a coordinate crosses a face plane; its slope is
    monotone and linear between breakpoints, so evaluating the slope at the breakpoints and
    the ends brackets the minimizer in one linear piece, where it is exact. Where the
    segment meets the box (slab clipping finds the part inside) the result is the
    non-positive signed distance of the middle of that part. Everything is elementwise
    (running extrema, no stacking), so XLA fuses it into one loop.
    """

    def slope(t):  # F'(t) / 2
        total = 0.0
        for k in range(3):
            total = total + b[k] * _excess(a[k] + t * b[k], h[k])
        return total

    zero = jnp.zeros_like(a[0] + b[0] + h[0])
    inf = jnp.asarray(jnp.inf, zero.dtype)
    candidates, enter, leave = [zero, zero + 1.0], zero, zero + 1.0
    for k in range(3):
        moving = jnp.abs(b[k]) > 1e-12
        inverse = 1.0 / jnp.where(moving, b[k], 1.0)
        t1, t2 = (-h[k] - a[k]) * inverse, (h[k] - a[k]) * inverse
        candidates += [jnp.where(moving, jnp.clip(t1, 0.0, 1.0), 0.0), jnp.where(moving, jnp.clip(t2, 0.0, 1.0), 0.0)]
        # The part of the segment inside slab k (all of it, or nothing, when parallel).
        within = jnp.abs(a[k]) <= h[k]
        enter = jnp.maximum(enter, jnp.where(moving, jnp.minimum(t1, t2), jnp.where(within, -inf, inf)))
        leave = jnp.minimum(leave, jnp.where(moving, jnp.maximum(t1, t2), jnp.where(within, inf, -inf)))
    # The slope is nondecreasing: bracket its zero by the last candidate with slope <= 0
    # and the first with slope >= 0.
    lo_t, lo_g, hi_t, hi_g = -inf, -inf, inf, inf
    for t in candidates:
        g = slope(t)
        lo_t, lo_g = jnp.where(g <= 0, jnp.maximum(lo_t, t), lo_t), jnp.where(g <= 0, jnp.maximum(lo_g, g), lo_g)
        hi_t, hi_g = jnp.where(g >= 0, jnp.minimum(hi_t, t), hi_t), jnp.where(g >= 0, jnp.minimum(hi_g, g), hi_g)
    plateau = hi_t <= lo_t  # F is flat on [hi_t, lo_t]
    linear = lo_t - lo_g * (hi_t - lo_t) / jnp.where(plateau, 1.0, hi_g - lo_g)
    best = jnp.where(plateau, hi_t, linear)
    best = jnp.where(jnp.isinf(lo_t), 0.0, jnp.where(jnp.isinf(hi_t), 1.0, best))
    outside = [_excess(a[k] + best * b[k], h[k]) for k in range(3)]
    distance = jnp.sqrt(sum(o * o for o in outside))
    middle = 0.5 * (enter + leave)
    depth = functools.reduce(jnp.maximum, [jnp.abs(a[k] + middle * b[k]) - h[k] for k in range(3)])
    return jnp.where(enter <= leave, jnp.minimum(depth, 0.0), distance)


def segment_box_distance(p, q, centre, axes, half):
    """Signed distance from segment [p, q] to a box; coordinates first.

    Args:
      p, q, centre: [3, ...]; axes: [3, 3, ...], ``axes[k]`` the box's unit axis k;
      half: [3, ...] half sizes along those axes.

    Exact while apart; negative where the segment enters the box (see
    :func:`_segment_aabb_distance`).
    """
    rel, d = p - centre, q - p
    return _segment_aabb_distance([_dot(rel, axes[k]) for k in range(3)], [_dot(d, axes[k]) for k in range(3)],
                                  [half[k] for k in range(3)])


def box_box_distance(centre_a, axes_a, half_a, centre_b, axes_b, half_b):
    """Signed distance between two boxes (coordinates first, as :func:`segment_box_distance`).

    Apart (no separating-axis test fails): exact, the smallest of A's 12 edges against B
    and B's 8 corners against A. The closest points of two separated boxes are an edge
    point of A, or a face point of A facing a corner of B or a B edge or face parallel to
    it, whose extreme points are B's corners or lie on A's edges. Overlapping: the
    separating-axis test's (negative) smallest penetration along the 15 axes.
    """
    # B in A's frame: rotation r[i][j] = a_i . b_j, centre offset t_i = a_i . (cB - cA).
    r = [[_dot(axes_a[i], axes_b[j]) for j in range(3)] for i in range(3)]
    t = [_dot(centre_b - centre_a, axes_a[i]) for i in range(3)]
    ha, hb = [half_a[i] for i in range(3)], [half_b[j] for j in range(3)]
    eps = 1e-6  # guards the near-parallel cross-product axes
    ar = [[jnp.abs(r[i][j]) + eps for j in range(3)] for i in range(3)]

    # Separating-axis test (Gottschalk et al. 1996): the largest gap over the 15 axes.
    gaps = []
    for i in range(3):  # A's face normals
        gaps.append(jnp.abs(t[i]) - ha[i] - sum(hb[j] * ar[i][j] for j in range(3)))
    for j in range(3):  # B's face normals
        gaps.append(jnp.abs(sum(t[i] * r[i][j] for i in range(3))) - hb[j] - sum(ha[i] * ar[i][j] for i in range(3)))
    for i, j in itertools.product(range(3), range(3)):  # a_i x b_j
        i1, i2 = (i + 1) % 3, (i + 2) % 3
        j1, j2 = (j + 1) % 3, (j + 2) % 3
        centre = jnp.abs(t[i2] * r[i1][j] - t[i1] * r[i2][j])
        extent = ha[i1] * ar[i2][j] + ha[i2] * ar[i1][j] + hb[j1] * ar[i][j2] + hb[j2] * ar[i][j1]
        length = jnp.sqrt(jnp.maximum(1.0 - r[i][j] ** 2, 0.0)) + eps
        gaps.append((centre - extent) / length)
    overlap_gap = functools.reduce(jnp.maximum, gaps)

    # A's edges against B, in B's frame: A's corners there are c + sum_i s_i h_i a_i with
    # c = -R^T t and a_i = row i of R.
    centre_in_b = [-sum(t[i] * r[i][j] for i in range(3)) for j in range(3)]
    nearest = None
    for k, s1, s2 in _BOX_EDGES:
        i1, i2 = [m for m in range(3) if m != k]
        start = [centre_in_b[j] + s1 * ha[i1] * r[i1][j] + s2 * ha[i2] * r[i2][j] - ha[k] * r[k][j] for j in range(3)]
        step = [2.0 * ha[k] * r[k][j] for j in range(3)]
        d = _segment_aabb_distance(start, step, hb)
        nearest = d if nearest is None else jnp.minimum(nearest, d)
    # B's corners against A, in A's frame: t + sum_j s_j h_j b_j, b_j = column j of R.
    for signs in itertools.product((-1.0, 1.0), repeat=3):
        corner = [t[i] + sum(signs[j] * hb[j] * r[i][j] for j in range(3)) for i in range(3)]
        excess = [_excess(c, ha[i]) for i, c in enumerate(corner)]
        nearest = jnp.minimum(nearest, jnp.sqrt(sum(e * e for e in excess)))
    return jnp.where(overlap_gap < 0.0, overlap_gap, nearest)


# The 12 edges of a box as (axis along the edge, signs of the two other axes).
_BOX_EDGES = [(k, s1, s2) for k in range(3) for s1 in (-1.0, 1.0) for s2 in (-1.0, 1.0)]


def _arm_pair_tables(max_arms: int):
    """Static arm pairs (i < j) and the [max_arms, npairs] incidence of arms in pairs."""
    first, second = np.triu_indices(max_arms, k=1)
    incidence = np.zeros((max_arms, len(first)), bool)
    incidence[first, np.arange(len(first))] = True
    incidence[second, np.arange(len(first))] = True
    return first, second, incidence


@dataclasses.dataclass(frozen=True)
class _Geoms:
    """Posed geoms of one type inside the kernel: coordinates first, then ``middle`` dims
    (arms, geoms, and broadcast axes added by :meth:`expand`), then scenes.

    Capsules: ``arrays`` = (p, q, radius); boxes: (centre, axes, half sizes); every array
    has all the middle dims (the sizes with length 1 along arms) and the scenes axis
    (length 1 for the sizes).
    """

    is_box: bool
    arrays: tuple
    middle: int = 2

    def _axis(self, x, axis: int) -> int:
        return x.ndim - self.middle - 1 + axis

    def take(self, axis: int, index) -> _Geoms:
        """Select along middle axis ``axis`` (0: arms, 1: geoms) with a numpy index array."""
        arrays = tuple(x if x.shape[self._axis(x, axis)] == 1 else jnp.take(x, index, axis=self._axis(x, axis))
                       for x in self.arrays)
        return _Geoms(self.is_box, arrays, self.middle)

    def expand(self, axis: int) -> _Geoms:
        """Insert a broadcast axis at middle position ``axis``."""
        arrays = tuple(jnp.expand_dims(x, self._axis(x, axis)) for x in self.arrays)
        return _Geoms(self.is_box, arrays, self.middle + 1)

    @property
    def count(self) -> int:
        """Geoms per arm (of an unexpanded set)."""
        return self.arrays[0].shape[-2]


def _pair_distance(a: _Geoms, b: _Geoms):
    """Signed distances of two broadcasting sets of posed geoms (any two types)."""
    if not (a.is_box or b.is_box):
        return segment_distance(*a.arrays[:2], *b.arrays[:2]) - (a.arrays[2] + b.arrays[2])
    if a.is_box and b.is_box:
        return box_box_distance(*a.arrays, *b.arrays)
    capsule, box = (a, b) if b.is_box else (b, a)
    return segment_box_distance(*capsule.arrays[:2], *box.arrays) - capsule.arrays[2]


def _type_blocks(types, checked):
    """The non-empty type blocks of a geom-pair mask [ngeom, ngeom] (capsules, then boxes):
    yields (ta, a, tb, b, mask) with ``mask`` the [Ga, Gb] part of types a and b."""
    offsets = np.cumsum([0] + [t.count for t in types])
    for (ta, a), (tb, b) in itertools.product(enumerate(types), repeat=2):
        mask = checked[offsets[ta]:offsets[ta + 1], offsets[tb]:offsets[tb + 1]]
        if mask.any():
            yield ta, a, tb, b, mask


def _between_arms(types, first, second, checked, boxes: bool) -> jnp.ndarray | None:
    """Per arm pair (first[i], second[i]), the smallest signed distance over the geom pairs
    marked in ``checked`` [ngeom, ngeom] (capsules, then boxes): [P, N], or None if none.

    ``boxes`` selects the blocks with a box, else the capsule-capsule block. Each block is
    a dense broadcast of one arm's geoms against the other's, masked by ``checked``.
    """
    result = None
    for ta, a, tb, b, mask in _type_blocks(types, checked):
        if (a.is_box or b.is_box) != boxes or ta > tb:
            continue
        d = _pair_distance(a.take(0, first).expand(2), b.take(0, second).expand(1))  # [P, Ga, Gb, N]
        d = jnp.where(mask[..., None], d, jnp.inf).min(axis=(1, 2))
        if ta != tb:  # the transposed block: b's geoms of the first arm, a's of the second
            t = _pair_distance(a.take(0, second).expand(2), b.take(0, first).expand(1))
            d = jnp.minimum(d, jnp.where(mask[..., None], t, jnp.inf).min(axis=(1, 2)))
        result = d if result is None else jnp.minimum(result, d)
    return result


def _self_pair_distances(types, pairs) -> jnp.ndarray:
    """Signed distance of each self pair [S, 2] (geom indices, capsules then boxes): [A, S, N].

    The pairs of each type combination are gathered and checked together.
    """
    offsets = np.cumsum([0] + [t.count for t in types])
    kind = np.searchsorted(offsets, pairs, side="right") - 1  # the type of each geom
    parts, rows = [], []
    for ta, tb in sorted(set(map(tuple, kind.tolist()))):
        chosen = np.nonzero((kind[:, 0] == ta) & (kind[:, 1] == tb))[0]
        a, b = types[ta].take(1, pairs[chosen, 0] - offsets[ta]), types[tb].take(1, pairs[chosen, 1] - offsets[tb])
        parts.append(_pair_distance(a, b))
        rows.append(chosen)
    return jnp.take(jnp.concatenate(parts, axis=1), np.argsort(np.concatenate(rows)), axis=1)


def ground_geoms(scene: Scene) -> np.ndarray:
    """The geoms checked against the ground and the obstacles, in the order of
    :func:`self_and_ground_distances`."""
    g, ncap = scene.pairs.ground, scene.arm.num_capsules
    return np.concatenate([g[g < ncap], g[g >= ncap]])


def _obstacle_geoms(scene: Scene, dtype) -> _Geoms:
    """The scene's static obstacle boxes in the kernel layout, broadcasting against arm geoms
    [.., A, G, 1, N] along a third middle axis: centre [3, 1, 1, K, 1], axes [3, 3, 1, 1, K, 1]."""
    frames = jnp.asarray(scene.obstacle_frames, dtype)  # [K, 4, 3]
    centre = frames[:, 0].T[:, None, None, :, None]
    axes = jnp.transpose(frames[:, 1:], (1, 2, 0))[:, :, None, None, :, None]
    half = jnp.asarray(scene.obstacle_half.T, dtype)[:, None, None, :, None]
    return _Geoms(True, (centre, axes, half), middle=3)


def _ground_distances(scene: Scene, types) -> jnp.ndarray:
    """Distance to the static scene of each geom of :func:`ground_geoms`: [A, G, N], the smaller
    of its height above the ground (a capsule's lowest end minus its radius, a box's lowest
    corner) and its signed distance to the nearest obstacle box."""
    g, ncap = scene.pairs.ground, scene.arm.num_capsules
    lowest = []
    for t in types:  # capsules, then boxes
        chosen = g[g >= ncap] - ncap if t.is_box else g[g < ncap]
        if not len(chosen):
            continue
        if t.is_box:
            centre, axes, half = t.arrays
            height = centre[2][:, chosen] - (half[:, :, chosen] * jnp.abs(axes[:, 2][:, :, chosen])).sum(axis=0)
        else:
            p, q, radius = t.arrays
            height = jnp.minimum(p[2][:, chosen], q[2][:, chosen]) - radius[0, chosen]
        if len(scene.obstacle_half):
            obstacles = _pair_distance(t.take(1, chosen).expand(2), _obstacle_geoms(scene, height.dtype))
            height = jnp.minimum(height, obstacles.min(axis=2))
        lowest.append(height)
    return jnp.concatenate(lowest, axis=1)


def _posed_types(arm, capsules, boxes) -> list[_Geoms]:
    """Kernel layout of a flat batch: capsules [N, A, C, 2, 3], boxes [N, A, B, 4, 3].

    Scenes go last, coordinates first: every operation of the kernel is elementwise over
    rows of scenes, which XLA vectorizes; reductions run over the leading (small) axes.
    """
    ends = jnp.moveaxis(capsules, (4, 3, 0), (0, 1, 4))  # [3, 2, A, C, N]
    frames = jnp.moveaxis(boxes, (4, 3, 0), (0, 1, 4))  # [3, 4, A, B, N]
    radius = jnp.asarray(arm.capsule_radius, capsules.dtype)[None, :, None]  # [1, C, 1]
    half = jnp.asarray(arm.box_half.T, boxes.dtype)[:, None, :, None]  # [3, 1, B, 1]
    types = [_Geoms(False, (ends[:, 0], ends[:, 1], radius)),
             _Geoms(True, (frames[:, 0], jnp.swapaxes(frames[:, 1:], 0, 1), half))]
    return [t for t in types if t.count]


def _flat_between(scene: Scene, boxes_only: bool, capsules, boxes) -> jnp.ndarray | None:
    """Per arm pair, the smallest distance on a flat batch: [P, N] (None: no such pairs).

    ``boxes_only`` selects the blocks with a box, else the capsule-capsule block.
    """
    first, second, _ = _arm_pair_tables(capsules.shape[1])
    if not len(first):
        return None
    return _between_arms(_posed_types(scene.arm, capsules, boxes), first, second, scene.pairs.between_arms, boxes_only)


def _flat_self_and_ground(scene: Scene, capsules, boxes) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Per arm, the smallest self and ground distances on a flat batch: [A, N] each."""
    pairs = scene.pairs
    types = _posed_types(scene.arm, capsules, boxes)
    shape = (capsules.shape[1], capsules.shape[0])
    self_dist = _self_pair_distances(types, pairs.self_pairs).min(axis=1) if len(pairs.self_pairs) else jnp.full(shape, jnp.inf)
    ground = _ground_distances(scene, types).min(axis=1) if len(pairs.ground) else jnp.full(shape, jnp.inf)
    return self_dist, ground


def self_and_ground_distances(scene: Scene, frames: ArmFrames) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Every self pair's signed distance [..., A, S] (``scene.pairs.self_pairs`` order) and every
    ground geom's height [..., A, G] (:func:`ground_geoms` order) of posed arms (XLA kernel)."""
    batch = frames.capsules.shape[:-4]
    flat = lambda x: x.reshape(-1, *x.shape[len(batch):])  # noqa: E731
    types = _posed_types(scene.arm, flat(frames.capsules), flat(frames.boxes))
    unflat = lambda x: jnp.moveaxis(x, -1, 0).reshape(*batch, *x.shape[:-1])  # noqa: E731  [A, K, N] -> [..., A, K]
    return unflat(_self_pair_distances(types, scene.pairs.self_pairs)), unflat(_ground_distances(scene, types))


def geom_clearances(scene: Scene, capsules, boxes, other_capsules, other_boxes) -> jnp.ndarray:
    """[..., ngeom] the signed distance from each collision geom of one arm (``capsules``
    [..., ncap, 2, 3], ``boxes`` [..., nbox, 4, 3], posed as ``ArmFrames``) to another arm
    (``other_*``, the same shapes): the smallest over the other arm's geoms, counting the
    geom pairs ``scene.pairs.between_arms`` checks (``inf`` for a geom with none). Their
    minimum is the two arms' ``between_arms`` distance of :func:`geom_contacts`."""
    batch = jnp.broadcast_shapes(capsules.shape[:-3], other_capsules.shape[:-3])

    def flat(mine, theirs):  # [N, 2, G, k, 3]: this arm, then the other
        pair = [jnp.broadcast_to(x, (*batch, *x.shape[-3:])) for x in (mine, theirs)]
        return jnp.stack(pair, axis=-4).reshape(-1, 2, *mine.shape[-3:])

    types = _posed_types(scene.arm, flat(capsules, other_capsules), flat(boxes, other_boxes))
    rows = [jnp.full((t.count, math.prod(batch)), jnp.inf, capsules.dtype) for t in types]
    for ta, a, _, b, mask in _type_blocks(types, scene.pairs.between_arms):
        d = _pair_distance(a.take(0, np.array([0])).expand(2), b.take(0, np.array([1])).expand(1))[0]  # [Ga, Gb, N]
        rows[ta] = jnp.minimum(rows[ta], jnp.where(mask[..., None], d, jnp.inf).min(axis=1))
    return jnp.concatenate(rows, axis=0).T.reshape(*batch, -1)


def default_kernel(scene: Scene) -> str:
    """``$MJX_MULTIARM_COLLISION_KERNEL`` if set (read when a function is traced), else
    ``"numba"`` for multi-arm scenes without obstacles on the CPU backend and ``"xla"``
    otherwise: with one arm there are no pairs between arms to skip, and the XLA kernel was
    faster (2.5x on the core benchmark, ``benchmarks/RESULTS.md``); the numba kernel has no
    obstacles (a scene with them runs the XLA kernel)."""
    numba_wins = jax.default_backend() == "cpu" and scene.max_arms > 1 and not len(scene.obstacle_half)
    return _checked_kernel(scene, os.environ.get(KERNEL_VARIABLE) or ("numba" if numba_wins else "xla"))


def kernel_jit(*static_argnames: str):
    """``jax.jit`` with these static arguments, compiled once per value of
    ``$MJX_MULTIARM_COLLISION_KERNEL`` (which :func:`default_kernel` reads when tracing): one
    compiled program for an eager call instead of one per operation."""

    def wrap(fn):
        per_kernel = {}

        @functools.wraps(fn)
        def call(*args, **kwargs):
            key = os.environ.get(KERNEL_VARIABLE)
            if key not in per_kernel:
                per_kernel[key] = jax.jit(fn, static_argnames=static_argnames)
            return per_kernel[key](*args, **kwargs)

        return call

    return wrap


def _checked_kernel(scene: Scene, kernel: str) -> str:
    if kernel not in KERNELS:
        raise ValueError(f"collision kernel {kernel!r} ({KERNEL_VARIABLE} or kernel=): expected one of {KERNELS}")
    if kernel == "numba" and len(scene.obstacle_half):
        raise ValueError(f"the numba collision kernel has no static obstacles, and this scene has {len(scene.obstacle_half)}: "
                         "use kernel='xla'")
    return kernel


def geom_contacts(scene: Scene, capsules, boxes, active, chunk: int | None = None, kernel: str | None = None,
                  max_distance: float = math.inf) -> Contacts:
    """Signed distances of posed collision geoms.

    Args:
      scene: the padded scene.
      capsules: [..., max_arms, ncap, 2, 3] world capsule segments (``ArmFrames.capsules``).
      boxes: [..., max_arms, nbox, 4, 3] world box frames (``ArmFrames.boxes``).
      active: [..., max_arms] bool; inactive slots never collide and never affect others.
      chunk: XLA kernel: scenes per chunk of the capsule-capsule check between arms (a
        sequential ``lax.map`` over chunks). Default: :data:`CPU_CHUNK` for multi-arm scenes
        on the CPU backend (2-3x faster at large batches: the working set stays in cache),
        the whole batch at once otherwise.
      kernel: one of :data:`KERNELS`; default :func:`default_kernel`. Both return the same
        distances up to float32 rounding (the numba kernel computes in float64).
      max_distance: distances above it come back as it (MuJoCo's ``distmax``); the numba
        kernel skips the pairs that cannot come within it, so 0 (contacts only: the
        verdicts and penetration depths, every clear arm at 0) is the fastest.

    Under ``jax.vmap`` the mapped axes join the leading dims: the kernel always sees the
    whole batch of scenes at once (vectorized over scenes, chunked on CPU), however it is
    called.
    """
    kernel = default_kernel(scene) if kernel is None else _checked_kernel(scene, kernel)
    return _batched_kernel(scene, chunk, kernel, max_distance=float(max_distance))(capsules, boxes, active)


def frame_contacts(scene: Scene, frames: ArmFrames, active, chunk: int | None = None, kernel: str | None = None,
                   max_distance: float = math.inf) -> Contacts:
    """:func:`geom_contacts` of arms already posed by :func:`forward_kinematics`."""
    return geom_contacts(scene, frames.capsules, frames.boxes, active, chunk, kernel, max_distance)


@functools.cache
def _batched_kernel(scene: Scene, chunk: int | None, kernel_name: str, swept: bool = False, max_distance: float = math.inf):
    """The kernel on posed geoms, batched as :func:`_folding_batch` describes.

    ``swept``: the posed geoms carry a configurations axis before the arms ([..., S, A, ...]),
    and the result is each arm's smallest distance over them (numba kernel only).
    """
    geom_dims = 5 if swept else 4

    def flat(capsules, boxes, active):
        if kernel_name == "numba":
            steps = (capsules, boxes) if swept else (capsules[:, None], boxes[:, None])
            return _numba_contacts(scene, *steps, active, max_distance)
        return _contacts(scene, capsules, boxes, active, chunk, max_distance)

    return _folding_batch(flat, (geom_dims, geom_dims, 1))


@functools.cache
def _joint_kernel(scene: Scene, max_distance: float = math.inf):
    """The numba kernel on joints (base_pos [..., A, 3], base_quat [..., A, 4], joints
    [..., S, A, 6], active [..., A]): it poses the arms itself, and each arm's distances are
    the smallest over the S configurations."""
    return _folding_batch(functools.partial(_numba_joint_contacts, scene, max_distance=max_distance), (2, 2, 3, 1))


def _folding_batch(flat, trailing: tuple[int, ...]):
    """``flat`` (inputs with one batch axis, :class:`Contacts` [N, A] out) on inputs with any
    leading dims, broadcast together; input k has ``trailing[k]`` dims after them. Under
    ``jax.vmap`` the mapped axes join the leading dims, so ``flat`` always sees the whole
    batch of scenes at once (vectorized over scenes, chunked on CPU), however it is called."""

    @jax.custom_batching.custom_vmap
    def kernel(*inputs):
        cores = [x.shape[x.ndim - dims:] for x, dims in zip(inputs, trailing)]
        batch = jnp.broadcast_shapes(*(x.shape[:x.ndim - dims] for x, dims in zip(inputs, trailing)))
        contacts = flat(*(jnp.broadcast_to(x, (*batch, *core)).reshape(-1, *core) for x, core in zip(inputs, cores)))
        return jax.tree.map(lambda x: x.reshape(*batch, x.shape[-1]), contacts)

    @kernel.def_vmap
    def fold_batch(axis_size, in_batched, *args):
        args = [x if batched else jnp.broadcast_to(x, (axis_size, *x.shape)) for x, batched in zip(args, in_batched)]
        contacts = kernel(*args)
        return contacts, jax.tree.map(lambda _: True, contacts)

    return kernel


#: One numba kernel call at a time: XLA may run independent callbacks concurrently, and
#: numba's default threading layer does not allow concurrent parallel launches.
_NUMBA_LOCK = threading.Lock()


@functools.cache
def _numba_constants(scene: Scene) -> tuple:
    """The collision model as :func:`compiled.batch_contacts` takes it; the self pairs
    nearest first over 64 random configurations in the joint ranges (fixed seed)."""
    arm, pairs = scene.arm, scene.pairs
    radius, box_half = arm.capsule_radius.astype(np.float64), arm.box_half.astype(np.float64)
    joints = np.random.default_rng(0).uniform(arm.joint_range[:, 0], arm.joint_range[:, 1], (64, 6))
    self_pairs = compiled.nearest_first(compiled.arm_constants(arm), radius, box_half, pairs.self_pairs.astype(np.int64), joints)
    return radius, box_half, self_pairs, pairs.between_arms, pairs.ground.astype(np.int64)


def _numba_callback(batch, constants: tuple, inputs: tuple, max_distance: float) -> Contacts:
    """``batch(*constants, *inputs, max_distance)`` (a :mod:`compiled` batch kernel) through a
    host callback; the last input is ``active`` [N, A], and the outputs take the first input's dtype."""
    dtype = inputs[0].dtype

    def host(*arrays):
        with _NUMBA_LOCK:
            out = batch(*constants, *(np.asarray(x) for x in arrays), max_distance)
        return tuple(x.astype(dtype, copy=False) for x in out)

    shape = jax.ShapeDtypeStruct(inputs[-1].shape, dtype)
    return Contacts(*jax.pure_callback(host, (shape,) * 3, *inputs))


def _numba_contacts(scene: Scene, capsules, boxes, active, max_distance: float) -> Contacts:
    """:func:`compiled.batch_contacts` on a flat batch [N, S, A, ...] (min over S)."""
    return _numba_callback(compiled.batch_contacts, _numba_constants(scene), (capsules, boxes, active), max_distance)


def _numba_joint_contacts(scene: Scene, base_pos, base_quat, joints, active, max_distance: float) -> Contacts:
    """:func:`compiled.batch_joint_contacts` on a flat batch (joints [N, S, A, 6], min over S)."""
    constants = (compiled.arm_constants(scene.arm), *_numba_constants(scene))
    dtype = joints.dtype
    return _numba_callback(compiled.batch_joint_contacts, constants,
                           (base_pos.astype(dtype), base_quat.astype(dtype), joints, active), max_distance)


def _contacts(scene: Scene, capsules, boxes, active, chunk: int | None, max_distance: float) -> Contacts:
    """The XLA kernel on a flat batch: capsules [N, A, ncap, 2, 3], boxes [N, A, nbox, 4, 3], active [N, A]."""
    num_arms = capsules.shape[-4]
    n = capsules.shape[0]
    cpu = jax.default_backend() == "cpu"
    if chunk is None:
        chunk = CPU_CHUNK if cpu and num_arms > 1 else n
    box_chunk = CPU_BOX_CHUNK[num_arms >= BOX_CHUNK_MIN_ARMS] if cpu else n
    # The capsule-capsule block between arms has the largest working set: chunked on CPU
    # (cache). The blocks with boxes are long elementwise chains that XLA splits into a
    # few loops: per chunk they pay overhead, so they take larger chunks, as do the self
    # pairs and the ground.
    parts = [_chunked(functools.partial(_flat_between, scene, False), chunk, capsules, boxes),
             _chunked(functools.partial(_flat_between, scene, True), box_chunk, capsules, boxes)]
    parts = [x for x in parts if x is not None]
    first, second, incidence = _arm_pair_tables(num_arms)
    inf = jnp.asarray(jnp.inf, capsules.dtype)
    if parts:
        act = active.T
        pair_dist = jnp.where(act[first] & act[second], functools.reduce(jnp.minimum, parts), inf)  # [P, N]
        between = jnp.where(incidence[..., None], pair_dist[None], inf).min(axis=1)  # [A, N]
    else:
        between = jnp.full((num_arms, n), inf)
    self_dist, ground = _chunked(functools.partial(_flat_self_and_ground, scene), CPU_SELF_CHUNK if cpu else n,
                                 capsules, boxes)

    def per_arm(x):  # [A, N] -> [N, A], inactive arms at +inf, then at most max_distance
        return jnp.minimum(jnp.where(active, x.T, inf), max_distance)

    return Contacts(between_arms=per_arm(between), within_arm=per_arm(self_dist), ground=per_arm(ground))


def _chunked(kernel, chunk: int, *inputs):
    """``kernel`` (flat batch in, [..., N] out) over sequential chunks of scenes (``lax.map``)."""
    n = inputs[0].shape[0]
    if n <= chunk:
        return kernel(*inputs)
    pad = -n % chunk  # padded scenes are inactive

    def split(x):
        x = jnp.pad(x, ((0, pad),) + ((0, 0),) * (x.ndim - 1))
        return x.reshape(-1, chunk, *x.shape[1:])

    out = jax.lax.map(lambda xs: kernel(*xs), tuple(split(x) for x in inputs))
    return jax.tree.map(lambda x: jnp.moveaxis(x, 0, -2).reshape(*x.shape[1:-1], -1)[..., :n], out)


@kernel_jit("scene", "max_distance")
def scene_contacts(scene: Scene, base_pos, base_quat, joints, active, max_distance: float = math.inf) -> Contacts:
    """Kinematics + collision of padded scenes at one configuration.

    Args:
      base_pos: [..., max_arms, 3]; base_quat: [..., max_arms, 4] (wxyz);
      joints: [..., max_arms, 6]; active: [..., max_arms] bool.
      max_distance: as :func:`geom_contacts`'s.
    """
    if default_kernel(scene) == "numba":  # the kernel poses the arms itself
        joints = jnp.asarray(joints)
        return _joint_kernel(scene, float(max_distance))(jnp.asarray(base_pos), jnp.asarray(base_quat),
                                                         joints[..., None, :, :], active)
    return frame_contacts(scene, forward_kinematics(scene.arm, base_pos, base_quat, joints), active, max_distance=max_distance)


def num_substeps(joints_from, joints_to, resolution: float = SWEEP_RESOLUTION) -> int:
    """Substeps so that no joint moves more than ``resolution`` between checks (concrete inputs)."""
    largest = float(np.max(np.abs(np.asarray(joints_to) - np.asarray(joints_from)), initial=0.0))
    return max(1, math.ceil(largest / resolution - 1e-9))


@kernel_jit("scene", "substeps", "max_distance")
def swept_contacts(scene: Scene, base_pos, base_quat, joints_from, joints_to, active, substeps: int,
                   end_frames: ArmFrames | None = None, max_distance: float = math.inf) -> Contacts:
    """Collision along the straight joint-space motion ``joints_from -> joints_to``.

    Checks the configurations at fractions k / substeps, k = 1..substeps (the start is
    assumed checked already), and returns per arm the smallest distance over them. Pick
    ``substeps`` with :func:`num_substeps`, or as ``ceil(max_step / resolution)`` for a
    known largest joint step; it is static under ``jit``. A caller that already posed the
    arms at ``joints_to`` passes those ``ArmFrames`` as ``end_frames`` so the end
    configuration's kinematics is not computed twice (the XLA kernel; the numba kernel
    poses every configuration itself). ``max_distance``: as :func:`geom_contacts`'s.
    """
    inner = substeps if end_frames is None else substeps - 1
    fractions = jnp.arange(1, inner + 1, dtype=jnp.result_type(joints_from)) / substeps

    def joints_at(fraction):
        return joints_from + fraction * (joints_to - joints_from)

    if default_kernel(scene) == "numba":  # one call that poses every configuration: each one's distances bound the next's
        shape = jnp.broadcast_shapes(jnp.shape(joints_from), jnp.shape(joints_to))
        configs = [jnp.moveaxis(jax.vmap(joints_at)(fractions), 0, -3)] if inner else []
        if end_frames is not None:  # the end configuration as given (the kernel poses it again: cheaper than its geoms)
            configs.append(jnp.broadcast_to(jnp.asarray(joints_to, fractions.dtype), shape)[..., None, :, :])
        return _joint_kernel(scene, float(max_distance))(jnp.asarray(base_pos), jnp.asarray(base_quat),
                                                         jnp.concatenate(configs, axis=-3), active)

    def at(fraction):
        return scene_contacts(scene, base_pos, base_quat, joints_at(fraction), active, max_distance)

    per_step = [jax.tree.map(lambda x: x.min(axis=0), jax.vmap(at)(fractions))] if inner else []
    if end_frames is not None:
        per_step.append(frame_contacts(scene, end_frames, active, max_distance=max_distance))
    return jax.tree.map(lambda *x: functools.reduce(jnp.minimum, x), *per_step)
