"""The collision model compiled for the planner: single configurations and straight motions.

The planner asks one question at a time (is this configuration free? is this edge free?),
which the batched JAX kernel (:mod:`mjx_multiarm.geometry.collision`) answers only through a
dispatch of 100-200 microseconds, after compiling for every batch shape. This module evaluates the same geometry (the capsules and
boxes of ``assets/ur5.xml``, the pairs of :class:`mjx_multiarm.geometry.scene.CollisionPairs`, the
same exact distance formulas) as numba-compiled scalar code with early exits: bounding
spheres of each arm and each geom skip pairs that cannot touch, and the first contact ends
the query. Verdicts agree with the JAX kernel (``tests/test_expert_checker.py``) except
within float rounding of contact: the kernel runs in float32, this code in float64.

Compiled functions are cached on disk by numba (``cache=True``), so worker processes do
not compile again.
"""

from __future__ import annotations

import functools
import math

import mujoco
import numba
import numpy as np

from mjx_multiarm.geometry.robot import NUM_JOINTS, load_arm
from mjx_multiarm.geometry.scene import build_scene

_jit = numba.njit(cache=True, nogil=True)
#: Clearance (m) that an expert's replayed steps must keep, so that the environment's
#: float32 kernel (errors ~1e-6 m) sees no contact where this float64 code saw none. Small,
#: because task goals may lie this close to contact (generated tasks: 1 in 1,000 within 0.1 mm).
REPLAY_MARGIN = 1e-5


@_jit
def _dot(u, v):
    return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]


@_jit
def _transform(pos, rot, local, out):
    """out = pos + rot @ local (3-vectors; written out: no BLAS call for 3 x 3)."""
    for i in range(3):
        out[i] = pos[i] + rot[i, 0] * local[0] + rot[i, 1] * local[1] + rot[i, 2] * local[2]


@_jit
def _matmul3(a, b, out):
    for i in range(3):
        for j in range(3):
            out[i, j] = a[i, 0] * b[0, j] + a[i, 1] * b[1, j] + a[i, 2] * b[2, j]


@_jit
def _rotation(axis, angle):
    """Rotation matrix of ``angle`` about the unit ``axis`` (Rodrigues)."""
    c, s = math.cos(angle), math.sin(angle)
    x, y, z = axis[0], axis[1], axis[2]
    t = 1.0 - c
    out = np.empty((3, 3))
    out[0, 0], out[0, 1], out[0, 2] = t * x * x + c, t * x * y - s * z, t * x * z + s * y
    out[1, 0], out[1, 1], out[1, 2] = t * x * y + s * z, t * y * y + c, t * y * z - s * x
    out[2, 0], out[2, 1], out[2, 2] = t * x * z - s * y, t * y * z + s * x, t * z * z + c
    return out


@_jit
def _pose_arm(base_pos, base_rot, joints, body_pos, body_rot, body_joint, joint_axis,
              capsule_body, capsule_ends, box_body, box_frame, capsules, boxes):
    """World capsule ends [ncap, 2, 3] and box frames [nbox, 4, 3] of one arm (written in place)."""
    nbody = body_pos.shape[0]
    pos = np.empty((nbody, 3))
    rot = np.empty((nbody, 3, 3))
    fixed = np.empty((3, 3))
    zero = np.zeros(3)
    pos[0] = base_pos
    rot[0] = base_rot
    for b in range(1, nbody):
        _transform(pos[b - 1], rot[b - 1], body_pos[b], pos[b])
        j = body_joint[b]
        if j >= 0:
            _matmul3(rot[b - 1], body_rot[b], fixed)
            _matmul3(fixed, _rotation(joint_axis[j], joints[j]), rot[b])
        else:
            _matmul3(rot[b - 1], body_rot[b], rot[b])
    for c in range(capsule_body.shape[0]):
        b = capsule_body[c]
        for e in range(2):
            _transform(pos[b], rot[b], capsule_ends[c, e], capsules[c, e])
    for x in range(box_body.shape[0]):
        b = box_body[x]
        _transform(pos[b], rot[b], box_frame[x, 0], boxes[x, 0])
        for k in range(1, 4):
            _transform(zero, rot[b], box_frame[x, k], boxes[x, k])


@_jit
def _segment_distance(p1, q1, p2, q2):
    """Distance between segments (Ericson 5.1.9, as :func:`mjx_multiarm.geometry.collision.segment_distance`)."""
    a = e = b = c = f = 0.0
    for i in range(3):
        d1, d2, r = q1[i] - p1[i], q2[i] - p2[i], p1[i] - p2[i]
        a, e, b, c, f = a + d1 * d1, e + d2 * d2, b + d1 * d2, c + d1 * r, f + d2 * r
    denom = a * e - b * b
    s = min(max((b * f - c * e) / denom, 0.0), 1.0) if denom > 1e-12 * a * e else 0.0
    t = (b * s + f) / e
    if t < 0.0:
        s = min(max(-c / a, 0.0), 1.0)
    elif t > 1.0:
        s = min(max((b - c) / a, 0.0), 1.0)
    t = min(max(t, 0.0), 1.0)
    total = 0.0
    for i in range(3):
        gap = p1[i] - p2[i] + (q1[i] - p1[i]) * s - (q2[i] - p2[i]) * t
        total += gap * gap
    return math.sqrt(total)


@_jit
def _excess(x, h):
    """How far x lies outside [-h, h] (signed, 0 inside)."""
    return x - h if x > h else (x + h if x < -h else 0.0)


@_jit
def _segment_aabb_distance(a, b, h):
    """Signed distance from the segment a + t b (t in [0, 1]) to the box |x_k| <= h_k: the
    breakpoint-bracketed minimum of the convex piecewise-quadratic squared distance, or the
    depth of the middle of the part inside (as the JAX kernel's ``_segment_aabb_distance``)."""
    enter, leave = 0.0, 1.0
    lo_t, lo_g, hi_t, hi_g = -np.inf, -np.inf, np.inf, np.inf
    for c in range(8):
        if c < 2:
            t = float(c)
        else:
            k, face = (c - 2) // 2, h[(c - 2) // 2] if c % 2 else -h[(c - 2) // 2]
            t = 0.0 if abs(b[k]) <= 1e-12 else min(max((face - a[k]) / b[k], 0.0), 1.0)
        g = 0.0
        for k in range(3):
            g += b[k] * _excess(a[k] + t * b[k], h[k])
        if g <= 0.0:
            lo_t, lo_g = max(lo_t, t), max(lo_g, g)
        if g >= 0.0:
            hi_t, hi_g = min(hi_t, t), min(hi_g, g)
    for k in range(3):
        if abs(b[k]) > 1e-12:
            t1, t2 = (-h[k] - a[k]) / b[k], (h[k] - a[k]) / b[k]
            enter, leave = max(enter, min(t1, t2)), min(leave, max(t1, t2))
        elif abs(a[k]) > h[k]:
            enter = np.inf
    if enter <= leave:
        middle, depth = 0.5 * (enter + leave), -np.inf
        for k in range(3):
            depth = max(depth, abs(a[k] + middle * b[k]) - h[k])
        return min(depth, 0.0)
    if np.isinf(lo_t):
        best = 0.0
    elif np.isinf(hi_t):
        best = 1.0
    elif hi_t <= lo_t:
        best = hi_t
    else:
        best = lo_t - lo_g * (hi_t - lo_t) / (hi_g - lo_g)
    total = 0.0
    for k in range(3):
        o = _excess(a[k] + best * b[k], h[k])
        total += o * o
    return math.sqrt(total)


@_jit
def _segment_box_distance(p, q, box, half):
    """Signed distance from segment [p, q] to a box (frame [4, 3]: centre, unit axes)."""
    a, b = np.empty(3), np.empty(3)
    for k in range(3):
        axis = box[k + 1]
        a[k] = (p[0] - box[0, 0]) * axis[0] + (p[1] - box[0, 1]) * axis[1] + (p[2] - box[0, 2]) * axis[2]
        b[k] = (q[0] - p[0]) * axis[0] + (q[1] - p[1]) * axis[1] + (q[2] - p[2]) * axis[2]
    return _segment_aabb_distance(a, b, half)


@_jit
def _box_box_distance(box_a, half_a, box_b, half_b):
    """Signed distance between boxes (as :func:`mjx_multiarm.geometry.collision.box_box_distance`):
    separating-axis penetration when they overlap, else A's 12 edges and B's 8 corners."""
    r = np.empty((3, 3))
    t = np.empty(3)
    for i in range(3):
        t[i] = 0.0
        for m in range(3):
            t[i] += (box_b[0, m] - box_a[0, m]) * box_a[i + 1, m]
        for j in range(3):
            r[i, j] = _dot(box_a[i + 1], box_b[j + 1])
    ar = np.abs(r) + 1e-6
    gap = -np.inf
    for i in range(3):
        gap = max(gap, abs(t[i]) - half_a[i] - (half_b[0] * ar[i, 0] + half_b[1] * ar[i, 1] + half_b[2] * ar[i, 2]))
    for j in range(3):
        gap = max(gap, abs(t[0] * r[0, j] + t[1] * r[1, j] + t[2] * r[2, j]) - half_b[j]
                  - (half_a[0] * ar[0, j] + half_a[1] * ar[1, j] + half_a[2] * ar[2, j]))
    for i in range(3):
        i1, i2 = (i + 1) % 3, (i + 2) % 3
        for j in range(3):
            j1, j2 = (j + 1) % 3, (j + 2) % 3
            centre = abs(t[i2] * r[i1, j] - t[i1] * r[i2, j])
            extent = half_a[i1] * ar[i2, j] + half_a[i2] * ar[i1, j] + half_b[j1] * ar[i, j2] + half_b[j2] * ar[i, j1]
            gap = max(gap, (centre - extent) / (math.sqrt(max(1.0 - r[i, j] ** 2, 0.0)) + 1e-6))
    if gap < 0.0:
        return gap
    nearest = np.inf
    centre_in_b = np.empty(3)
    for j in range(3):
        centre_in_b[j] = -(t[0] * r[0, j] + t[1] * r[1, j] + t[2] * r[2, j])
    start, step = np.empty(3), np.empty(3)
    for k in range(3):
        i1, i2 = (k + 1) % 3, (k + 2) % 3
        for s1 in (-1.0, 1.0):
            for s2 in (-1.0, 1.0):
                for j in range(3):
                    start[j] = (centre_in_b[j] + s1 * half_a[i1] * r[i1, j] + s2 * half_a[i2] * r[i2, j]
                                - half_a[k] * r[k, j])
                    step[j] = 2.0 * half_a[k] * r[k, j]
                nearest = min(nearest, _segment_aabb_distance(start, step, half_b))
    for s0 in (-1.0, 1.0):
        for s1 in (-1.0, 1.0):
            for s2 in (-1.0, 1.0):
                total = 0.0
                for i in range(3):
                    o = _excess(t[i] + s0 * half_b[0] * r[i, 0] + s1 * half_b[1] * r[i, 1] + s2 * half_b[2] * r[i, 2], half_a[i])
                    total += o * o
                nearest = min(nearest, math.sqrt(total))
    return nearest


@_jit
def _geom_distance(capsules_a, boxes_a, ga, capsules_b, boxes_b, gb, radius, box_half):
    """Signed distance of geom ``ga`` of arm A and geom ``gb`` of arm B (capsules, then boxes)."""
    ncap = radius.shape[0]
    if ga < ncap and gb < ncap:
        return _segment_distance(capsules_a[ga, 0], capsules_a[ga, 1], capsules_b[gb, 0], capsules_b[gb, 1]) \
            - radius[ga] - radius[gb]
    if ga >= ncap and gb >= ncap:
        return _box_box_distance(boxes_a[ga - ncap], box_half[ga - ncap], boxes_b[gb - ncap], box_half[gb - ncap])
    if ga < ncap:
        return _segment_box_distance(capsules_a[ga, 0], capsules_a[ga, 1], boxes_b[gb - ncap], box_half[gb - ncap]) - radius[ga]
    return _segment_box_distance(capsules_b[gb, 0], capsules_b[gb, 1], boxes_a[ga - ncap], box_half[ga - ncap]) - radius[gb]


@_jit
def _bounding_spheres(capsules, boxes, radius, box_half, centres, radii):
    """Per geom, a bounding sphere (written in place)."""
    ncap = radius.shape[0]
    for c in range(ncap):
        length2 = 0.0
        for i in range(3):
            centres[c, i] = 0.5 * (capsules[c, 0, i] + capsules[c, 1, i])
            length2 += (capsules[c, 1, i] - capsules[c, 0, i]) ** 2
        radii[c] = 0.5 * math.sqrt(length2) + radius[c]
    for x in range(boxes.shape[0]):
        centres[ncap + x] = boxes[x, 0]
        radii[ncap + x] = math.sqrt(_dot(box_half[x], box_half[x]))


@_jit
def _spheres_apart(centres_a, radii_a, a, centres_b, radii_b, b, margin):
    d2 = 0.0
    for i in range(3):
        d2 += (centres_a[a, i] - centres_b[b, i]) ** 2
    reach = radii_a[a] + radii_b[b] + margin
    return d2 > reach * reach


@_jit
def _collides(joints, margin, base_pos, base_rot, body_pos, body_rot, body_joint, joint_axis, capsule_body,
              capsule_ends, radius, box_body, box_frame, box_half, self_pairs, between_pairs, ground):
    """Any contact (signed distance < ``margin``) among the arms at ``joints`` [k, 6]."""
    k, ncap, nbox = joints.shape[0], radius.shape[0], box_half.shape[0]
    capsules = np.empty((k, ncap, 2, 3))
    boxes = np.empty((k, nbox, 4, 3))
    centres = np.empty((k, ncap + nbox, 3))
    radii = np.empty((k, ncap + nbox))
    arm_radius = np.empty(k)  # about the base: all of an arm lies within it
    for i in range(k):
        _pose_arm(base_pos[i], base_rot[i], joints[i], body_pos, body_rot, body_joint, joint_axis,
                  capsule_body, capsule_ends, box_body, box_frame, capsules[i], boxes[i])
        for g in ground:  # the lowest capsule end minus the radius, the lowest box corner
            if g < ncap:
                low = min(capsules[i, g, 0, 2], capsules[i, g, 1, 2]) - radius[g]
            else:
                x = g - ncap
                low = boxes[i, x, 0, 2]
                for a in range(3):
                    low -= box_half[x, a] * abs(boxes[i, x, a + 1, 2])
            if low < margin:
                return True
        _bounding_spheres(capsules[i], boxes[i], radius, box_half, centres[i], radii[i])
        arm_radius[i] = 0.0
        for g in range(ncap + nbox):
            d2 = 0.0
            for m in range(3):
                d2 += (centres[i, g, m] - base_pos[i, m]) ** 2
            arm_radius[i] = max(arm_radius[i], math.sqrt(d2) + radii[i, g])
    for i in range(k):
        for j in range(i + 1, k):
            d2 = 0.0
            for m in range(3):
                d2 += (base_pos[i, m] - base_pos[j, m]) ** 2
            reach = arm_radius[i] + arm_radius[j] + margin
            if d2 <= reach * reach and _pairs_touch(between_pairs, i, j, capsules, boxes, centres, radii, radius,
                                                    box_half, margin):
                return True
    for i in range(k):
        if _pairs_touch(self_pairs, i, i, capsules, boxes, centres, radii, radius, box_half, margin):
            return True
    return False


@_jit
def _pairs_touch(pairs, i, j, capsules, boxes, centres, radii, radius, box_half, margin):
    """Whether any geom pair (a of arm i, b of arm j) of ``pairs`` [P, 2] is within ``margin``."""
    for p in range(pairs.shape[0]):
        a, b = pairs[p, 0], pairs[p, 1]
        if _spheres_apart(centres[i], radii[i], a, centres[j], radii[j], b, margin):
            continue
        if _geom_distance(capsules[i], boxes[i], a, capsules[j], boxes[j], b, radius, box_half) < margin:
            return True
    return False


@_jit
def _any_collides(configs, margin, *model):
    """Whether any of the composite configurations [n, k, 6] collides (in order, first hit wins)."""
    for n in range(configs.shape[0]):
        if _collides(configs[n], margin, *model):
            return True
    return False


@_jit
def _motion_collides(start, end, steps, margin, *model):
    """Whether the straight motion start -> end [k, 6] collides at fractions s / steps,
    s = 1..steps, checked coarse to fine (halving strides) so that a blocked edge fails early."""
    stride = 1
    while stride * 2 <= steps:
        stride *= 2
    seen = np.zeros(steps + 1, np.bool_)
    while stride >= 1:
        for s in range(stride, steps + 1, stride):
            if not seen[s]:
                seen[s] = True
                if _collides(start + (end - start) * (s / steps), margin, *model):
                    return True
        stride //= 2
    return False


class CollisionChecker:
    """Collision queries of one task's arms on composite vectors [..., 6k] (numpy, float64).

    Args:
      base_pos: [k, 3] and base_quat: [k, 4] (wxyz) base poses of the task's arms.
      joint_range: [6, 2] joint limits.
      resolution: largest joint motion (rad) between two checks of an edge.
      margin: signed distance below which two geoms count as touching (0: the model's
        contact; a small positive value keeps clear of float32 rounding).
    """

    def __init__(self, base_pos, base_quat, joint_range, resolution: float, margin: float = 0.0):
        base_pos = np.asarray(base_pos, np.float64).reshape(-1, 3)
        base_quat = np.asarray(base_quat, np.float64).reshape(-1, 4)
        if len(base_pos) != len(base_quat) or not len(base_pos):
            raise ValueError(f"base_pos {base_pos.shape} and base_quat {base_quat.shape} must describe the same k >= 1 arms")
        self.num_arms = len(base_pos)
        self.lower = np.tile(joint_range[:, 0], self.num_arms)
        self.upper = np.tile(joint_range[:, 1], self.num_arms)
        self.resolution = resolution
        self.margin = float(margin)
        self._model = (base_pos, _quat_to_rot(base_quat), *_arm_constants())

    def collided(self, configs) -> np.ndarray:
        """[n] bool for composite configurations [n, 6k]."""
        configs = self._arms(configs)
        return np.array([_any_collides(c[None], self.margin, *self._model) for c in configs], bool)

    def state_free(self, config) -> bool:
        """Whether the composite configuration [6k] is collision-free."""
        return not _collides(np.asarray(config, np.float64).reshape(self.num_arms, NUM_JOINTS), self.margin, *self._model)

    def any_collides(self, configs, margin: float | None = None) -> bool:
        """Whether any of the composite configurations [n, 6k] collides (stops at the first);
        ``margin`` overrides the checker's."""
        return bool(_any_collides(self._arms(configs), self.margin if margin is None else margin, *self._model))

    def in_bounds(self, config) -> bool:
        return bool(np.all(config >= self.lower) and np.all(config <= self.upper))

    def steps_free(self, start, deltas, substeps: int, margin: float = REPLAY_MARGIN) -> bool:
        """Executing ``deltas`` [T, 6k] from ``start`` as the environment does (float32 joints,
        joint limits, ``substeps`` checks per step) never comes within ``margin`` of contact
        (the default covers the environment's float32 arithmetic)."""
        joints = [np.asarray(start, np.float32)]
        for delta in np.asarray(deltas, np.float32):
            joints.append(np.clip(joints[-1] + delta, self.lower, self.upper).astype(np.float32))
        joints = np.stack(joints)
        fractions = (np.arange(1, substeps + 1, dtype=np.float32) / substeps)[:, None, None]
        configs = joints[:-1] + fractions * (joints[1:] - joints[:-1])
        return not self.any_collides(np.swapaxes(configs, 0, 1).reshape(-1, joints.shape[-1]), margin)

    def motion_free(self, start, end) -> bool:
        """The straight motion start -> end (start assumed valid) is collision-free."""
        start, end = np.asarray(start, np.float64), np.asarray(end, np.float64)
        steps = max(1, math.ceil(float(np.max(np.abs(end - start))) / self.resolution - 1e-9))
        shape = (self.num_arms, NUM_JOINTS)
        return not _motion_collides(start.reshape(shape), end.reshape(shape), steps, self.margin, *self._model)

    def _arms(self, configs) -> np.ndarray:
        configs = np.asarray(configs, np.float64)
        if configs.ndim != 2 or configs.shape[1] != self.num_arms * NUM_JOINTS:
            raise ValueError(f"configs: expected [n, {self.num_arms * NUM_JOINTS}], got {configs.shape}")
        return configs.reshape(len(configs), self.num_arms, NUM_JOINTS)


def _quat_to_rot(quat) -> np.ndarray:
    """Rotation matrices [n, 3, 3] of wxyz quaternions [n, 4] (normalized first; MuJoCo C)."""
    out = np.empty((len(quat), 9))
    for q, rot in zip(quat, out):
        mujoco.mju_quat2Mat(rot, q / np.linalg.norm(q))
    return out.reshape(-1, 3, 3)


@functools.cache
def _arm_constants() -> tuple:
    """The arm's geometry and pair lists as the compiled functions take them (read once)."""
    arm, pairs = load_arm(), build_scene(2).pairs
    return (
        arm.body_pos.astype(np.float64), _quat_to_rot(arm.body_quat), np.asarray(arm.body_joint, np.int64),
        arm.joint_axis.astype(np.float64), arm.capsule_body.astype(np.int64), arm.capsule_ends.astype(np.float64),
        arm.capsule_radius.astype(np.float64), arm.box_body.astype(np.int64), arm.box_frame.astype(np.float64),
        arm.box_half.astype(np.float64), pairs.self_pairs.astype(np.int64),
        np.argwhere(pairs.between_arms).astype(np.int64), pairs.ground.astype(np.int64),
    )
