"""The collision model compiled for the planner: single configurations and straight motions.

The planner asks one question at a time (is this configuration free? is this edge free?),
which the batched JAX kernel (:mod:`mjx_multiarm.geometry.collision`) answers only through a
dispatch of 100-200 microseconds, after compiling for every batch shape. This module poses
the arms and evaluates the same geometry (the capsules and boxes of ``assets/ur5.xml``, the
pairs of :class:`mjx_multiarm.geometry.scene.CollisionPairs`, the kinematics and exact
distances of :mod:`mjx_multiarm.geometry.compiled`) as numba-compiled scalar code with early
exits: bounding spheres of each arm and each geom skip pairs that cannot touch, and the
first contact ends the query. Verdicts agree with the JAX kernel
(``tests/test_expert_checker.py``) except within float rounding of contact: the XLA kernel
poses the arms in float32, this code in float64.

Compiled functions are cached on disk by numba (``cache=True``), so worker processes do
not compile again.
"""

from __future__ import annotations

import functools
import math

import numba
import numpy as np

from mjx_multiarm.geometry import compiled
from mjx_multiarm.geometry.certified import (
    MAX_EVALUATIONS,
    SMALLEST_STEP,
    geom_reach,
    pair_tables,
)
from mjx_multiarm.geometry.compiled import (
    bounding_spheres,
    centre_distance2,
    geom_distance,
    ground_distance,
    pose_arm,
)
from mjx_multiarm.geometry.robot import NUM_JOINTS, load_arm
from mjx_multiarm.geometry.scene import build_scene

_jit = numba.njit(cache=True, nogil=True)
#: Clearance (m) that an expert's replayed steps must keep (:func:`mjx_multiarm.expert.solve.replay_free`),
#: so that float32 rounding (errors ~1e-6 m) cannot turn a graze into a contact. Small,
#: because task goals may lie this close to contact (generated tasks: 1 in 1,000 within 0.1 mm).
REPLAY_MARGIN = 1e-5


@_jit
def _spheres_apart(centres, radii, i, a, j, b, margin):
    reach = radii[i, a] + radii[j, b] + margin
    return centre_distance2(centres, i, a, j, b) > reach * reach


@_jit
def _collides(joints, margin, base_pos, base_rot, arm, radius, box_half, self_pairs, between_pairs, ground):
    """Any contact (signed distance < ``margin``) among the arms at ``joints`` [k, 6]."""
    k, ncap, nbox = joints.shape[0], radius.shape[0], box_half.shape[0]
    capsules = np.empty((k, ncap, 2, 3))
    boxes = np.empty((k, nbox, 4, 3))
    centres = np.empty((k, ncap + nbox, 3))
    radii = np.empty((k, ncap + nbox))
    arm_radius = np.empty(k)  # about the base: all of an arm lies within it
    for i in range(k):
        pose_arm(base_pos, base_rot, joints, i, arm, capsules, boxes)
        if ground_distance(capsules, boxes, i, radius, box_half, ground) < margin:
            return True
        bounding_spheres(capsules, boxes, i, radius, box_half, centres, radii)
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
        if _spheres_apart(centres, radii, i, a, j, b, margin):
            continue
        if geom_distance(capsules, boxes, i, a, j, b, radius, box_half) < margin:
            return True
    return False


@_jit
def _pair_certified(start, end, i, a, j, b, rate, margin, smallest, max_evaluations, base_pos, base_rot, arm, radius,
                    box_half, capsules, boxes):
    """Conservative advancement of one geom pair (a of arm i, b of arm j; ``b < 0``: a's height
    above the ground) along start -> end [k, 6], whose distance shrinks by at most ``rate`` per
    unit of the motion: whether it keeps ``margin`` all along (see mjx_multiarm.geometry.certified)."""
    ncap, s = radius.shape[0], 0.0
    joints = start.copy()
    for _ in range(max_evaluations):
        for m in range(6):
            joints[i, m] = start[i, m] + s * (end[i, m] - start[i, m])
            joints[j, m] = start[j, m] + s * (end[j, m] - start[j, m])
        pose_arm(base_pos, base_rot, joints, i, arm, capsules, boxes)
        if j != i:
            pose_arm(base_pos, base_rot, joints, j, arm, capsules, boxes)
        if b >= 0:
            d = geom_distance(capsules, boxes, i, a, j, b, radius, box_half)
        elif a < ncap:
            d = min(capsules[i, a, 0, 2], capsules[i, a, 1, 2]) - radius[a]
        else:
            d = boxes[i, a - ncap, 0, 2]
            for m in range(3):
                d -= box_half[a - ncap, m] * abs(boxes[i, a - ncap, m + 1, 2])
        if d < margin:
            return False
        if rate <= 0.0 or (d - margin) >= rate * (1.0 - s):
            return True
        step = (d - margin) / rate
        if step < smallest:
            return False
        s += step
    return False


@_jit
def _step_certified(start, end, margin, smallest, max_evaluations, base_pos, base_rot, arm, radius, box_half, self_pairs,
                    between_pairs, ground, reach, self_joints, self_outer):
    """Whether the team motion start -> end [k, 6] is certified to keep ``margin`` everywhere:
    every between-arm, self and ground pair by its own conservative advancement, after a
    bounding-sphere test at the start that certifies the pairs far enough apart."""
    k, ncap, nbox = start.shape[0], radius.shape[0], box_half.shape[0]
    ngeom = ncap + nbox
    capsules = np.empty((k, ncap, 2, 3))
    boxes = np.empty((k, nbox, 4, 3))
    centres = np.empty((k, ngeom, 3))
    radii = np.empty((k, ngeom))
    speed = np.zeros((k, ngeom))  # how far each geom can move along the motion
    for i in range(k):
        pose_arm(base_pos, base_rot, start, i, arm, capsules, boxes)
        bounding_spheres(capsules, boxes, i, radius, box_half, centres, radii)
        for g in range(ngeom):
            for m in range(6):
                speed[i, g] += abs(end[i, m] - start[i, m]) * reach[m, g]
    for i in range(k):
        for g in ground:
            if not _pair_certified(start, end, i, g, i, -1, speed[i, g], margin, smallest, max_evaluations, base_pos,
                                   base_rot, arm, radius, box_half, capsules, boxes):
                return False
        for p in range(self_pairs.shape[0]):
            rate = 0.0
            for m in range(6):
                if self_joints[m, p]:
                    rate += abs(end[i, m] - start[i, m]) * reach[m, self_outer[p]]
            if not _pair_certified(start, end, i, self_pairs[p, 0], i, self_pairs[p, 1], rate, margin, smallest,
                                   max_evaluations, base_pos, base_rot, arm, radius, box_half, capsules, boxes):
                return False
        for j in range(i + 1, k):
            for p in range(between_pairs.shape[0]):
                a, b = between_pairs[p, 0], between_pairs[p, 1]
                rate = speed[i, a] + speed[j, b]
                gap = math.sqrt(centre_distance2(centres, i, a, j, b)) - radii[i, a] - radii[j, b]
                if gap - margin >= rate:
                    continue
                if not _pair_certified(start, end, i, a, j, b, rate, margin, smallest, max_evaluations, base_pos, base_rot,
                                       arm, radius, box_half, capsules, boxes):
                    return False
    return True


@_jit
def _steps_certified(joints, margin, smallest, max_evaluations, *model):
    """Whether every motion joints[t] -> joints[t + 1] of [T + 1, k, 6] is certified free."""
    for t in range(joints.shape[0] - 1):
        if not _step_certified(joints[t], joints[t + 1], margin, smallest, max_evaluations, *model):
            return False
    return True


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
        self.base_pos, self.base_quat = base_pos, base_quat
        self.lower = np.tile(joint_range[:, 0], self.num_arms)
        self.upper = np.tile(joint_range[:, 1], self.num_arms)
        self.resolution = resolution
        self.margin = float(margin)
        self._model = (base_pos, compiled.rotations(base_quat), *_arm_constants())

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

    def steps_certified(self, joints, margin: float = REPLAY_MARGIN) -> bool:
        """Whether every straight motion between consecutive team configurations ``joints``
        [T + 1, k, 6] keeps ``margin`` all along (certified: :mod:`mjx_multiarm.geometry.certified`'s
        guarantee, pair by pair, with its step and evaluation limits)."""
        joints = np.asarray(joints, np.float64)
        if joints.ndim != 3 or joints.shape[1:] != (self.num_arms, NUM_JOINTS):
            raise ValueError(f"joints: expected [T + 1, {self.num_arms}, {NUM_JOINTS}], got {joints.shape}")
        return bool(_steps_certified(joints, float(margin), SMALLEST_STEP, MAX_EVALUATIONS, *self._model, *_reach_constants()))

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


def team_checker(base_pos, base_quat, resolution: float) -> CollisionChecker:
    """The collision checker of a team of UR5s with bases ``base_pos`` [k, 3], ``base_quat`` [k, 4] (wxyz)."""
    return CollisionChecker(base_pos, base_quat, load_arm().joint_range, resolution)


@functools.cache
def _reach_constants() -> tuple:
    """The certified check's tables: the geoms' reach from each joint's axis [6, ngeom], the
    joints between each self pair's bodies [6, S] and its outer geom [S]."""
    scene = build_scene(2)
    _, outer, between, _ = pair_tables(scene)
    return geom_reach(scene.arm), between, outer.astype(np.int64)


@functools.cache
def _arm_constants() -> tuple:
    """The arm's kinematics, geometry and pair lists as the compiled functions take them (read once)."""
    arm, pairs = load_arm(), build_scene(2).pairs
    return (
        compiled.arm_constants(arm), arm.capsule_radius.astype(np.float64), arm.box_half.astype(np.float64),
        pairs.self_pairs.astype(np.int64), np.argwhere(pairs.between_arms).astype(np.int64), pairs.ground.astype(np.int64),
    )
