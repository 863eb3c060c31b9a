"""The collision model as numba-compiled scalar code: arm kinematics, exact geom distances,
and a batched kernel with a broad phase for the CPU.

The distance formulas are those of :mod:`mjx_multiarm.geometry.collision` (capsule-capsule,
capsule-box, box-box, signed where geoms overlap), evaluated one pair at a time in float64;
:func:`pose_arm` is :func:`~mjx_multiarm.geometry.kinematics.forward_kinematics` for one arm
in float64. They serve two callers:

- the expert planner's checker (:mod:`mjx_multiarm.geometry.checker`), which asks about one
  configuration at a time;
- :func:`batch_contacts` and :func:`batch_joint_contacts`, the CPU kernel behind
  :func:`~mjx_multiarm.geometry.collision.geom_contacts` (posed geoms in) and
  ``scene_contacts`` / ``swept_contacts`` (joints in: it poses the arms itself): the same
  per-arm smallest distances as the JAX kernel (float32 distances out) for a batch of
  scenes, in parallel over scenes. Unlike the JAX kernel, which must evaluate every geom
  pair of every scene (XLA has no cheap per-scene branch), it skips the pairs that cannot
  change a result: bounding spheres per geom and boxes per arm, arm pairs visited nearest
  first, a pair evaluated only while its sphere gap is below the distance still to beat,
  which starts at ``max_distance`` (0: contacts only). Every distance it returns is exact.

Compiled functions are cached on disk by numba (``cache=True``), so worker processes do
not compile again.
"""

from __future__ import annotations

import math

import numba
import numpy as np

_jit = numba.njit(cache=True, nogil=True, error_model="numpy")


@_jit
def centre_distance2(centres, i, a, j, b):
    """Squared distance between centre ``a`` of arm ``i`` and centre ``b`` of arm ``j`` (``centres`` [arms, ngeom, 3])."""
    return ((centres[i, a, 0] - centres[j, b, 0]) ** 2 + (centres[i, a, 1] - centres[j, b, 1]) ** 2
            + (centres[i, a, 2] - centres[j, b, 2]) ** 2)


@_jit
def segment_distance(capsules, i, ga, j, gb):
    """Distance between the axes of capsule ``ga`` of arm ``i`` and capsule ``gb`` of arm ``j``
    (``capsules`` [arms, ncap, 2, 3]; Ericson 5.1.9, as
    :func:`mjx_multiarm.geometry.collision.segment_distance`). Reads scalars: no array views
    on the hot path (each costs reference counting)."""
    p1 = (capsules[i, ga, 0, 0], capsules[i, ga, 0, 1], capsules[i, ga, 0, 2])
    q1 = (capsules[i, ga, 1, 0], capsules[i, ga, 1, 1], capsules[i, ga, 1, 2])
    p2 = (capsules[j, gb, 0, 0], capsules[j, gb, 0, 1], capsules[j, gb, 0, 2])
    q2 = (capsules[j, gb, 1, 0], capsules[j, gb, 1, 1], capsules[j, gb, 1, 2])
    a = e = b = c = f = 0.0
    for k in range(3):
        d1, d2, r = q1[k] - p1[k], q2[k] - p2[k], p1[k] - p2[k]
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
    for k in range(3):
        gap = p1[k] - p2[k] + (q1[k] - p1[k]) * s - (q2[k] - p2[k]) * t
        total += gap * gap
    return math.sqrt(total)


@_jit
def _excess(x, h):
    """How far x lies outside [-h, h] (signed, 0 inside; h >= 0). Branch-free: this runs
    eight times per segment-box distance, where a branch on the sign is a coin toss."""
    return max(x - h, 0.0) + min(x + h, 0.0)


@_jit
def segment_aabb_distance(a, b, h):
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
def segment_box_distance(capsules, i, a, boxes, j, x, half):
    """Signed distance from the axis of capsule ``a`` of arm ``i`` to box ``x`` of arm ``j``
    (frames [arms, nbox, 4, 3]: centre, unit axes) of half sizes ``half`` [3]."""
    a0 = a1 = a2 = b0 = b1 = b2 = 0.0
    for m in range(3):
        rel, d = capsules[i, a, 0, m] - boxes[j, x, 0, m], capsules[i, a, 1, m] - capsules[i, a, 0, m]
        a0, a1, a2 = a0 + rel * boxes[j, x, 1, m], a1 + rel * boxes[j, x, 2, m], a2 + rel * boxes[j, x, 3, m]
        b0, b1, b2 = b0 + d * boxes[j, x, 1, m], b1 + d * boxes[j, x, 2, m], b2 + d * boxes[j, x, 3, m]
    return segment_aabb_distance((a0, a1, a2), (b0, b1, b2), (half[0], half[1], half[2]))


@_jit
def _axes_dot(boxes, i, x, k, j, y, n):
    """Axis ``k`` of box ``x`` of arm ``i`` dotted with axis ``n`` of box ``y`` of arm ``j``."""
    return (boxes[i, x, k + 1, 0] * boxes[j, y, n + 1, 0] + boxes[i, x, k + 1, 1] * boxes[j, y, n + 1, 1]
            + boxes[i, x, k + 1, 2] * boxes[j, y, n + 1, 2])


@_jit
def box_box_distance(boxes, i, x, j, y, box_half):
    """Signed distance between box ``x`` of arm ``i`` (A) and box ``y`` of arm ``j`` (B)
    (frames [arms, nbox, 4, 3]: centre, unit axes; half sizes ``box_half`` [nbox, 3]), as
    :func:`mjx_multiarm.geometry.collision.box_box_distance`: separating-axis penetration
    when they overlap, else A's 12 edges and B's 8 corners. Works on scalars and tuples
    (no temporary arrays: this runs inside the pair loops)."""
    ha, hb = (box_half[x, 0], box_half[x, 1], box_half[x, 2]), (box_half[y, 0], box_half[y, 1], box_half[y, 2])
    d0, d1, d2 = boxes[j, y, 0, 0] - boxes[i, x, 0, 0], boxes[j, y, 0, 1] - boxes[i, x, 0, 1], boxes[j, y, 0, 2] - boxes[i, x, 0, 2]
    t = (d0 * boxes[i, x, 1, 0] + d1 * boxes[i, x, 1, 1] + d2 * boxes[i, x, 1, 2],  # B's centre in A's frame
         d0 * boxes[i, x, 2, 0] + d1 * boxes[i, x, 2, 1] + d2 * boxes[i, x, 2, 2],
         d0 * boxes[i, x, 3, 0] + d1 * boxes[i, x, 3, 1] + d2 * boxes[i, x, 3, 2])
    r = ((_axes_dot(boxes, i, x, 0, j, y, 0), _axes_dot(boxes, i, x, 0, j, y, 1), _axes_dot(boxes, i, x, 0, j, y, 2)),
         (_axes_dot(boxes, i, x, 1, j, y, 0), _axes_dot(boxes, i, x, 1, j, y, 1), _axes_dot(boxes, i, x, 1, j, y, 2)),
         (_axes_dot(boxes, i, x, 2, j, y, 0), _axes_dot(boxes, i, x, 2, j, y, 1), _axes_dot(boxes, i, x, 2, j, y, 2)))
    ar = ((abs(r[0][0]) + 1e-6, abs(r[0][1]) + 1e-6, abs(r[0][2]) + 1e-6),
          (abs(r[1][0]) + 1e-6, abs(r[1][1]) + 1e-6, abs(r[1][2]) + 1e-6),
          (abs(r[2][0]) + 1e-6, abs(r[2][1]) + 1e-6, abs(r[2][2]) + 1e-6))
    c = (-(t[0] * r[0][0] + t[1] * r[1][0] + t[2] * r[2][0]),  # A's centre in B's frame
         -(t[0] * r[0][1] + t[1] * r[1][1] + t[2] * r[2][1]),
         -(t[0] * r[0][2] + t[1] * r[1][2] + t[2] * r[2][2]))
    gap = -np.inf
    for a in range(3):
        gap = max(gap, abs(t[a]) - ha[a] - (hb[0] * ar[a][0] + hb[1] * ar[a][1] + hb[2] * ar[a][2]))
    for b in range(3):
        gap = max(gap, abs(c[b]) - hb[b] - (ha[0] * ar[0][b] + ha[1] * ar[1][b] + ha[2] * ar[2][b]))
    for a in range(3):
        a1, a2 = (a + 1) % 3, (a + 2) % 3
        for b in range(3):
            b1, b2 = (b + 1) % 3, (b + 2) % 3
            centre = abs(t[a2] * r[a1][b] - t[a1] * r[a2][b])
            extent = ha[a1] * ar[a2][b] + ha[a2] * ar[a1][b] + hb[b1] * ar[a][b2] + hb[b2] * ar[a][b1]
            gap = max(gap, (centre - extent) / (math.sqrt(max(1.0 - r[a][b] ** 2, 0.0)) + 1e-6))
    if gap < 0.0:
        return gap
    nearest = np.inf
    for k in range(3):  # A's edges along axis k, in B's frame
        k1, k2 = (k + 1) % 3, (k + 2) % 3
        step = (2.0 * ha[k] * r[k][0], 2.0 * ha[k] * r[k][1], 2.0 * ha[k] * r[k][2])
        for s1 in (-1.0, 1.0):
            for s2 in (-1.0, 1.0):
                start = (c[0] + s1 * ha[k1] * r[k1][0] + s2 * ha[k2] * r[k2][0] - ha[k] * r[k][0],
                         c[1] + s1 * ha[k1] * r[k1][1] + s2 * ha[k2] * r[k2][1] - ha[k] * r[k][1],
                         c[2] + s1 * ha[k1] * r[k1][2] + s2 * ha[k2] * r[k2][2] - ha[k] * r[k][2])
                nearest = min(nearest, segment_aabb_distance(start, step, hb))
    for s0 in (-1.0, 1.0):  # B's corners, in A's frame
        for s1 in (-1.0, 1.0):
            for s2 in (-1.0, 1.0):
                total = 0.0
                for a in range(3):
                    o = _excess(t[a] + s0 * hb[0] * r[a][0] + s1 * hb[1] * r[a][1] + s2 * hb[2] * r[a][2], ha[a])
                    total += o * o
                nearest = min(nearest, math.sqrt(total))
    return nearest


@_jit
def geom_distance(capsules, boxes, i, ga, j, gb, radius, box_half):
    """Signed distance of geom ``ga`` of arm ``i`` and geom ``gb`` of arm ``j`` (capsules,
    then boxes; ``capsules`` [arms, ncap, 2, 3], ``boxes`` [arms, nbox, 4, 3])."""
    ncap = radius.shape[0]
    if ga < ncap and gb < ncap:
        return segment_distance(capsules, i, ga, j, gb) - radius[ga] - radius[gb]
    if ga >= ncap and gb >= ncap:
        return box_box_distance(boxes, i, ga - ncap, j, gb - ncap, box_half)
    if ga < ncap:
        return segment_box_distance(capsules, i, ga, boxes, j, gb - ncap, box_half[gb - ncap]) - radius[ga]
    return segment_box_distance(capsules, j, gb, boxes, i, ga - ncap, box_half[ga - ncap]) - radius[gb]


@_jit
def bounding_spheres(capsules, boxes, i, radius, box_half, centres, radii):
    """Per geom of arm ``i``, a bounding sphere centred inside the geom (written in place
    to ``centres[i]``, ``radii[i]``)."""
    ncap = radius.shape[0]
    for c in range(ncap):
        length2 = 0.0
        for m in range(3):
            centres[i, c, m] = 0.5 * (capsules[i, c, 0, m] + capsules[i, c, 1, m])
            length2 += (capsules[i, c, 1, m] - capsules[i, c, 0, m]) ** 2
        radii[i, c] = 0.5 * math.sqrt(length2) + radius[c]
    for x in range(boxes.shape[1]):
        for m in range(3):
            centres[i, ncap + x, m] = boxes[i, x, 0, m]
        radii[i, ncap + x] = math.sqrt(box_half[x, 0] ** 2 + box_half[x, 1] ** 2 + box_half[x, 2] ** 2)


@_jit
def ground_distance(capsules, boxes, i, radius, box_half, ground):
    """The lowest point of arm ``i``'s ground-checked geoms: capsule ends minus the radius, box corners."""
    ncap, low = radius.shape[0], np.inf
    for g in ground:
        if g < ncap:
            low = min(low, min(capsules[i, g, 0, 2], capsules[i, g, 1, 2]) - radius[g])
        else:
            x = g - ncap
            corner = boxes[i, x, 0, 2]
            for a in range(3):
                corner -= box_half[x, a] * abs(boxes[i, x, a + 1, 2])
            low = min(low, corner)
    return low


@_jit
def quat_rotation(quat, i, rot):
    """``rot[i]`` = the rotation matrix of the wxyz quaternion ``quat[i]``, normalized first."""
    norm = math.sqrt(quat[i, 0] ** 2 + quat[i, 1] ** 2 + quat[i, 2] ** 2 + quat[i, 3] ** 2)
    w, x, y, z = quat[i, 0] / norm, quat[i, 1] / norm, quat[i, 2] / norm, quat[i, 3] / norm
    rot[i, 0, 0], rot[i, 0, 1], rot[i, 0, 2] = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
    rot[i, 1, 0], rot[i, 1, 1], rot[i, 1, 2] = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
    rot[i, 2, 0], rot[i, 2, 1], rot[i, 2, 2] = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)


@_jit
def _times(r, q):
    """The product of two 3x3 matrices held as row-major 9-tuples."""
    return (r[0] * q[0] + r[1] * q[3] + r[2] * q[6], r[0] * q[1] + r[1] * q[4] + r[2] * q[7],
            r[0] * q[2] + r[1] * q[5] + r[2] * q[8],
            r[3] * q[0] + r[4] * q[3] + r[5] * q[6], r[3] * q[1] + r[4] * q[4] + r[5] * q[7],
            r[3] * q[2] + r[4] * q[5] + r[5] * q[8],
            r[6] * q[0] + r[7] * q[3] + r[8] * q[6], r[6] * q[1] + r[7] * q[4] + r[8] * q[7],
            r[6] * q[2] + r[7] * q[5] + r[8] * q[8])


@_jit
def _placed(p, r, u, v, w):
    """The point (u, v, w) of the frame (p, r) (r a row-major 9-tuple) in world coordinates."""
    return p[0] + r[0] * u + r[1] * v + r[2] * w, p[1] + r[3] * u + r[4] * v + r[5] * w, p[2] + r[6] * u + r[7] * v + r[8] * w


@_jit
def pose_arm(base_pos, base_rot, joints, i, arm, capsules, boxes):
    """Forward kinematics of arm ``i``: its world capsule ends ``capsules[i]`` [ncap, 2, 3] and
    box frames ``boxes[i]`` [nbox, 4, 3] (centre, unit axes), from its base ``base_pos[i]``,
    ``base_rot[i]`` and ``joints[i]``, all float64. ``arm``: the tuple of :func:`arm_constants`.

    The body frames are chained in tuples (registers, not arrays that the compiler must
    assume alias the outputs), and each body's geoms are placed as the chain reaches it."""
    body_pos, body_rot, body_turns, body_joint, joint_axis, capsule_body, capsule_ends, box_body, box_frame = arm
    g = x = 0  # the next capsule and box to place (ordered by body)
    p = (base_pos[i, 0], base_pos[i, 1], base_pos[i, 2])
    r = (base_rot[i, 0, 0], base_rot[i, 0, 1], base_rot[i, 0, 2], base_rot[i, 1, 0], base_rot[i, 1, 1],
         base_rot[i, 1, 2], base_rot[i, 2, 0], base_rot[i, 2, 1], base_rot[i, 2, 2])
    for b in range(body_pos.shape[0]):
        if b > 0:  # body 0 is the base frame itself
            p = _placed(p, r, body_pos[b, 0], body_pos[b, 1], body_pos[b, 2])
            if body_turns[b]:  # the parent frame times the body's fixed rotation
                r = _times(r, (body_rot[b, 0, 0], body_rot[b, 0, 1], body_rot[b, 0, 2], body_rot[b, 1, 0],
                               body_rot[b, 1, 1], body_rot[b, 1, 2], body_rot[b, 2, 0], body_rot[b, 2, 1],
                               body_rot[b, 2, 2]))
            j = body_joint[b]
            if j >= 0:  # times the joint's rotation about its axis (Rodrigues)
                c, s = math.cos(joints[i, j]), math.sin(joints[i, j])
                u, v, w = joint_axis[j, 0], joint_axis[j, 1], joint_axis[j, 2]
                t = 1.0 - c
                r = _times(r, (t * u * u + c, t * u * v - s * w, t * u * w + s * v,
                               t * u * v + s * w, t * v * v + c, t * v * w - s * u,
                               t * u * w - s * v, t * v * w + s * u, t * w * w + c))
        while g < capsule_body.shape[0] and capsule_body[g] == b:
            for e in range(2):
                capsules[i, g, e, 0], capsules[i, g, e, 1], capsules[i, g, e, 2] = _placed(
                    p, r, capsule_ends[g, e, 0], capsule_ends[g, e, 1], capsule_ends[g, e, 2])
            g += 1
        while x < box_body.shape[0] and box_body[x] == b:
            for k in range(4):  # the centre, then the axes (directions: not translated)
                boxes[i, x, k, 0], boxes[i, x, k, 1], boxes[i, x, k, 2] = _placed(
                    p if k == 0 else (0.0, 0.0, 0.0), r, box_frame[x, k, 0], box_frame[x, k, 1], box_frame[x, k, 2])
            x += 1


def rotations(quat) -> np.ndarray:
    """Rotation matrices [n, 3, 3] (float64) of wxyz quaternions [n, 4], normalized first."""
    quat = np.asarray(quat, np.float64).reshape(-1, 4)
    out = np.empty((len(quat), 3, 3))
    for i in range(len(quat)):
        quat_rotation(quat, i, out)
    return out


def arm_constants(arm) -> tuple:
    """The arm's kinematics as :func:`pose_arm` takes it (float64 / int64 / bool arrays): body
    offsets, fixed rotations and whether each is one (not the identity), joint of each body
    (-1: none) and joint axes, capsule and box bodies (in body order) with their ends and
    frames in the body frame. ``arm``: a :class:`mjx_multiarm.geometry.robot.ArmModel`."""
    if np.any(np.diff(arm.capsule_body) < 0) or np.any(np.diff(arm.box_body) < 0):
        raise ValueError("arm_constants: the arm's capsules and boxes must be listed in body order")
    turns = rotations(arm.body_quat)
    return (arm.body_pos.astype(np.float64), turns, ~np.all(turns == np.eye(3), axis=(1, 2)), np.asarray(arm.body_joint, np.int64),
            arm.joint_axis.astype(np.float64), arm.capsule_body.astype(np.int64), arm.capsule_ends.astype(np.float64),
            arm.box_body.astype(np.int64), arm.box_frame.astype(np.float64))


@_jit
def _self_distance(i, capsules, boxes, centres, radii, radius, box_half, pairs, best):
    """The smaller of ``best`` and the smallest distance over arm ``i``'s self pairs,
    measuring only the pairs whose sphere gap is below the distance to beat (with no bound
    yet, the first pair is measured: :func:`nearest_first` orders them)."""
    for p in range(pairs.shape[0]):
        a, b = pairs[p, 0], pairs[p, 1]
        reach = max(best, 0.0) + radii[i, a] + radii[i, b]
        if centre_distance2(centres, i, a, i, b) < reach * reach:
            best = min(best, geom_distance(capsules, boxes, i, a, i, b, radius, box_half))
    return best


def nearest_first(arm, radius, box_half, pairs, joints) -> np.ndarray:
    """``pairs`` [n, 2] (geom pairs within one arm) ordered by their mean distance over the
    arm's configurations ``joints`` [k, 6], nearest first: the kernel's self check measures
    the first pair and prunes the others by it, so the first should usually be close."""
    k = len(joints)
    capsules, boxes = np.empty((k, len(radius), 2, 3)), np.empty((k, len(box_half), 4, 3))
    base_pos, base_rot = np.zeros((k, 3)), np.tile(np.eye(3), (k, 1, 1))
    joints = np.asarray(joints, np.float64)
    for i in range(k):
        pose_arm(base_pos, base_rot, joints, i, arm, capsules, boxes)
    mean = [np.mean([geom_distance(capsules, boxes, i, a, i, b, radius, box_half) for i in range(k)]) for a, b in pairs]
    return pairs[np.argsort(mean, kind="stable")]


@_jit
def _between_pair(i, j, capsules, boxes, centres, radii, lo, hi, radius, box_half, mask, bi, bj, near_i, near_j,
                  keys_i, keys_j):
    """Arm i's and arm j's bests ``bi``, ``bj``, each lowered to the two arms' distance where that is smaller.

    A geom pair is measured only when its sphere gap is below the larger of the two arms'
    current bests: a pair beyond it lowers neither. One pass measures each geom's centre
    against the other arm's box [lo, hi]; while one of the arms has no best yet, the pair of
    each arm's geom nearest the other arm's box is measured first, and that distance bounds
    which geoms (those whose sphere comes within it of the other arm's box) take part.
    """
    ga = gb = -1
    da = db = np.inf
    for g in range(radii.shape[1]):  # squared distances of the geom centres to the other arm's box
        ea = eb = 0.0
        for m in range(3):
            ea += max(lo[j, m] - centres[i, g, m], centres[i, g, m] - hi[j, m], 0.0) ** 2
            eb += max(lo[i, m] - centres[j, g, m], centres[j, g, m] - hi[i, m], 0.0) ** 2
        keys_i[g], keys_j[g] = ea, eb
        if ea < da:
            ga, da = g, ea
        if eb < db:
            gb, db = g, eb
    if max(bi, bj) == np.inf and mask[ga, gb]:
        d = geom_distance(capsules, boxes, i, ga, j, gb, radius, box_half)
        bi, bj = min(bi, d), min(bj, d)
    else:
        ga = gb = -1  # no pair measured yet
    reach = max(bi, bj, 0.0)
    ni = nj = 0
    for g in range(radii.shape[1]):
        if keys_i[g] <= (reach + radii[i, g]) ** 2:
            near_i[ni] = g
            ni += 1
        if keys_j[g] <= (reach + radii[j, g]) ** 2:
            near_j[nj] = g
            nj += 1
    for x in range(ni):
        a = near_i[x]
        ax, ay, az, ra = centres[i, a, 0], centres[i, a, 1], centres[i, a, 2], radii[i, a]
        for y in range(nj):
            b = near_j[y]
            limit = max(bi, bj, 0.0) + ra + radii[j, b]
            dx, dy, dz = ax - centres[j, b, 0], ay - centres[j, b, 1], az - centres[j, b, 2]
            if dx * dx + dy * dy + dz * dz < limit * limit and mask[a, b] and (a != ga or b != gb):
                d = geom_distance(capsules, boxes, i, a, j, b, radius, box_half)
                bi, bj = min(bi, d), min(bj, d)
    return bi, bj


@_jit
def _scene_contacts(capsules, boxes, active, radius, box_half, self_pairs, mask, ground, best,
                    centres, radii, lo, hi, near_i, near_j, keys_i, keys_j, gaps, first, second):
    """Lower ``best`` [3, A] (per arm: between arms, within the arm, to the ground) to one
    posed scene's smallest distances where they are smaller; inactive arms are left as they
    are. The arguments after it are work arrays. Pairs that cannot lower a value are
    skipped, so a caller that wants the minimum over several configurations passes the
    running minimum."""
    num_arms = capsules.shape[0]
    pairs = 0
    for i in range(num_arms):
        if not active[i]:
            continue
        bounding_spheres(capsules, boxes, i, radius, box_half, centres, radii)
        for m in range(3):  # the arm's box, in locals: the stores cannot alias the loads
            low, high = np.inf, -np.inf
            for g in range(radii.shape[1]):
                low, high = min(low, centres[i, g, m] - radii[i, g]), max(high, centres[i, g, m] + radii[i, g])
            lo[i, m], hi[i, m] = low, high
        best[2, i] = min(best[2, i], ground_distance(capsules, boxes, i, radius, box_half, ground))
        if self_pairs.shape[0]:
            best[1, i] = _self_distance(i, capsules, boxes, centres, radii, radius, box_half, self_pairs, best[1, i])
        for j in range(i):  # arm pairs, kept in order of the squared gap of the arms' boxes
            if active[j]:
                gap2 = 0.0
                for m in range(3):
                    gap2 += max(lo[j, m] - hi[i, m], lo[i, m] - hi[j, m], 0.0) ** 2
                o = pairs
                while o > 0 and gaps[o - 1] > gap2:  # insertion: no array allocated per scene
                    first[o], second[o], gaps[o] = first[o - 1], second[o - 1], gaps[o - 1]
                    o -= 1
                first[o], second[o], gaps[o] = j, i, gap2
                pairs += 1
    for o in range(pairs):  # nearest first: every arm soon has a finite distance to beat
        i, j = first[o], second[o]
        bound = max(best[0, i], best[0, j])
        if gaps[o] > 0.0 and gaps[o] >= max(bound, 0.0) ** 2:
            continue
        best[0, i], best[0, j] = _between_pair(i, j, capsules, boxes, centres, radii, lo, hi, radius, box_half, mask,
                                               best[0, i], best[0, j], near_i, near_j, keys_i, keys_j)


@_jit
def _work_arrays(num_arms, ngeom):
    """The work arrays of :func:`_scene_contacts` after its outputs (allocated once per chunk of scenes)."""
    return (np.empty((num_arms, ngeom, 3)), np.empty((num_arms, ngeom)), np.empty((num_arms, 3)),
            np.empty((num_arms, 3)), np.empty(ngeom, np.int64), np.empty(ngeom, np.int64), np.empty(ngeom), np.empty(ngeom),
            np.empty(num_arms * num_arms), np.empty(num_arms * num_arms, np.int64),
            np.empty(num_arms * num_arms, np.int64))


@numba.njit(cache=True, parallel=True, error_model="numpy")
def _batch(capsules, boxes, active, radius, box_half, self_pairs, mask, ground, max_distance):
    n, steps, num_arms = capsules.shape[0], capsules.shape[1], capsules.shape[2]
    out = np.empty((3, n, num_arms), np.float32)
    chunks = min(n, 64)
    for c in numba.prange(chunks):  # work arrays once per chunk of scenes
        best = np.empty((3, num_arms))
        posed_capsules, posed_boxes = np.empty(capsules.shape[2:]), np.empty(boxes.shape[2:])  # float64
        work = _work_arrays(num_arms, radius.shape[0] + boxes.shape[3])
        for s in range(c * n // chunks, (c + 1) * n // chunks):
            best[:] = max_distance  # pairs that cannot come within it are skipped
            for k in range(steps):  # the running minimum over the configurations prunes the later ones
                posed_capsules[:], posed_boxes[:] = capsules[s, k], boxes[s, k]
                _scene_contacts(posed_capsules, posed_boxes, active[s], radius, box_half, self_pairs, mask, ground, best,
                                *work)
            out[:, s] = best
    return out[0], out[1], out[2]


@numba.njit(cache=True, parallel=True, error_model="numpy")
def _batch_joints(base_pos, base_quat, joints, active, arm, radius, box_half, self_pairs, mask, ground, max_distance):
    n, steps, num_arms = joints.shape[0], joints.shape[1], joints.shape[2]
    ncap, nbox = radius.shape[0], box_half.shape[0]
    out = np.empty((3, n, num_arms), np.float32)
    chunks = min(n, 64)
    for c in numba.prange(chunks):
        best = np.empty((3, num_arms))
        capsules, boxes = np.empty((num_arms, ncap, 2, 3)), np.empty((num_arms, nbox, 4, 3))
        place, turn, config = np.empty((num_arms, 3)), np.empty((num_arms, 3, 3)), np.empty((num_arms, joints.shape[3]))
        work = _work_arrays(num_arms, ncap + nbox)
        for s in range(c * n // chunks, (c + 1) * n // chunks):  # element copies: no array views per scene
            best[:] = max_distance  # pairs that cannot come within it are skipped
            quat = base_quat[s]
            for i in range(num_arms):
                if active[s, i]:  # padded slots may hold no valid quaternion
                    for m in range(3):
                        place[i, m] = base_pos[s, i, m]
                    quat_rotation(quat, i, turn)
            for k in range(steps):
                for i in range(num_arms):
                    if active[s, i]:
                        for m in range(config.shape[1]):
                            config[i, m] = joints[s, k, i, m]
                        pose_arm(place, turn, config, i, arm, capsules, boxes)
                _scene_contacts(capsules, boxes, active[s], radius, box_half, self_pairs, mask, ground, best, *work)
            for q in range(3):
                for i in range(num_arms):
                    out[q, s, i] = best[q, i]
    return out[0], out[1], out[2]


def batch_contacts(radius, box_half, self_pairs, between_mask, ground, capsules, boxes, active, max_distance=np.inf):
    """Per-arm smallest signed distances of posed scenes, each over one or more of its
    configurations (the substeps of a swept check), in parallel over scenes.

    Args:
      radius: [ncap] capsule radii; box_half: [nbox, 3] box half sizes.
      self_pairs: [nself, 2] int geom pairs within an arm; between_mask: [ngeom, ngeom]
        symmetric bool, the geom pairs checked between two arms; ground: [nground] int geoms.
      capsules: [N, S, A, ncap, 2, 3] world capsule ends of N scenes in S configurations;
        boxes: [N, S, A, nbox, 4, 3] world box frames (centre, unit axes); active: [N, A] bool.

    Returns:
      (between_arms, within_arm, ground), each [N, A] float32: the smallest over the S
      configurations; ``inf`` where an arm has no such pair (inactive slots, a lone arm's
      ``between_arms``). Distances above ``max_distance`` come back as ``max_distance``
      (as MuJoCo's ``mj_geomDistance`` with ``distmax``), and pairs that cannot come
      within it are skipped: 0 asks for the contacts only, the fastest.
    """
    return _batch(capsules, boxes, active, radius, box_half, self_pairs, between_mask, ground, float(max_distance))


def batch_joint_contacts(arm, radius, box_half, self_pairs, between_mask, ground, base_pos, base_quat, joints, active,
                         max_distance=np.inf):
    """:func:`batch_contacts` of arms posed here from their joints (float64 kinematics,
    :func:`pose_arm`), so the caller need not pose them.

    Args:
      arm: :func:`arm_constants`; the next five and ``max_distance`` as in :func:`batch_contacts`.
      base_pos: [N, A, 3]; base_quat: [N, A, 4] (wxyz); joints: [N, S, A, 6], S configurations
        per scene; active: [N, A] bool.
    """
    return _batch_joints(base_pos, base_quat, joints, active, arm, radius, box_half, self_pairs, between_mask, ground,
                         float(max_distance))
