"""A trained decentralized policy as a closed-loop motion planner for any team of UR5 arms.

    from mjx_multiarm import Planner

    planner = Planner.load()                      # the policy shipped with the package
    next_joints = planner.step(joints, base_poses, targets)           # numpy in, numpy out
    path = planner.rollout(joints, base_poses, targets, steps=200)    # waypoints until reached
    safe = Planner.load(safe=True)                # every team step shielded: never collides

Each call evaluates every arm's policy on its own decentralized observation (its
neighbours within the policy's radius) and returns the next joint waypoint of every arm
(one control step of 50 ms, within the velocity and joint limits). With ``safe=True`` each
team step is first checked with the certified motion check, and arms whose motions would
collide step away from the others or hold (:mod:`mjx_multiarm.env.shield`): the waypoints never collide in the
model (given a collision-free start). The model is the arms' collision geometry and the
ground, or what ``arm_xml`` and ``obstacles`` give (a tool on the arm, a bin). Arms may stand anywhere
and there may be any number of them: the observation is built for exactly the arms given.
:meth:`Planner.batched` is the jittable JAX path for batches of teams.

Inputs (numpy, float): ``joints`` [n, 6] (rad); ``base_poses`` [n, 3] planar (x, y, yaw)
or [n, 7] (x, y, z, qx, qy, qz, qw); ``targets`` [n, 7] end-effector poses (x, y, z, qx,
qy, qz, qw) in the world frame. Quaternions are xyzw, as in the original's task files.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx, struct

from mjx_multiarm.env.observation import ArmSnapshot, observe
from mjx_multiarm.env.reaching import EVAL_TOLERANCE, EnvConfig, ReachingEnv
from mjx_multiarm.expert.planner import SOLVED, PlannerConfig
from mjx_multiarm.expert.solve import solve_team
from mjx_multiarm.geometry.certified import certified_contacts
from mjx_multiarm.geometry.collision import scene_contacts
from mjx_multiarm.geometry.evaluate import base_pose_arrays, check_finite, evaluate_arms
from mjx_multiarm.geometry.kinematics import forward_kinematics
from mjx_multiarm.geometry.robot import NUM_JOINTS
from mjx_multiarm.geometry.scene import Obstacle
from mjx_multiarm.geometry.transforms import quat_angle, xyzw_to_wxyz
from mjx_multiarm.planner.policy_file import LoadedPolicy, load_policy

#: The policy shipped with the package (trained by the command in benchmarks/RESULTS.md).
SHIPPED_POLICY = pathlib.Path(__file__).parents[1] / "assets" / "policy.npz"


@struct.dataclass
class PlannedPath:
    """Result of :meth:`Planner.rollout` (numpy).

    Attributes:
      waypoints: [T + 1, n, 6] joint angles, the start first; T <= steps (the rollout stops
        once every arm is within tolerance).
      reached: bool, every arm within tolerance at the last waypoint.
      position_error: [n] end-effector distance to the target (m) at the last waypoint.
      angle_error: [n] orientation error (rad) at the last waypoint.
      min_distance: [n] each arm's smallest signed distance (m) to the other arms, itself
        and the ground at the configurations checked along the path (the start, and those
        the certified motion check evaluated between waypoints); negative where it collides.
      collided: bool, the start collides or some motion between waypoints is not certified
        free (:mod:`mjx_multiarm.geometry.certified`: no configuration along it touches).
      handed_over: waypoints at the end planned by BiRRT from where the policy stopped
        (``rollout(..., goal_joints=...)``; 0 where the policy did it all).
    """

    waypoints: np.ndarray
    reached: np.ndarray
    position_error: np.ndarray
    angle_error: np.ndarray
    min_distance: np.ndarray
    collided: np.ndarray
    handed_over: int = 0


def policy_env_settings(env: ReachingEnv) -> dict:
    """What a policy file records of its training environment (read back by :class:`Planner`)."""
    return {"action_scale": np.asarray(env.action_scale).tolist(), "neighbour_radius": env.config.neighbour_radius}


class Planner:
    """Closed-loop planner from a policy file (see the module docstring)."""

    def __init__(self, policy: LoadedPolicy, neighbour_radius: float | None = None, safe: bool = False,
                 arm_xml: str | None = None, obstacles: tuple[Obstacle, ...] = ()):
        """``neighbour_radius`` (m) replaces the radius the policy file records (0 blinds the
        policy to its neighbours, as the individualistic ablation); ``safe`` shields every
        team step (module docstring); ``arm_xml`` and ``obstacles`` give the collision model
        the arm as it is equipped and the static scene (:class:`ReachingEnv`): the shield and
        the reported collisions see them, the policy's observation does not."""
        self.policy = policy
        self._collision_model = (arm_xml, tuple(obstacles))
        env = policy.env
        action_scale = np.asarray(env["action_scale"], np.float64)
        if action_scale.shape != (NUM_JOINTS,):
            raise ValueError(f"policy file: env.action_scale has shape {action_scale.shape}, expected ({NUM_JOINTS},)")
        #: The environment settings the policy was trained with (or the radius given).
        radius = float(env["neighbour_radius"]) if neighbour_radius is None else neighbour_radius
        self.env_config = EnvConfig(action_scale=tuple(action_scale.tolist()), neighbour_radius=radius, safe=safe)
        self._actor_def, self._actor = nnx.split(policy.actor)
        self._compiled: dict = {}

    @classmethod
    def load(cls, path: str | os.PathLike | None = None, neighbour_radius: float | None = None, safe: bool = False,
             arm_xml: str | None = None, obstacles: tuple[Obstacle, ...] = ()) -> Planner:
        """The planner of policy file ``path``, or of a run directory's ``policy.npz`` (default:
        the shipped policy); the other arguments as the constructor's."""
        path = pathlib.Path(SHIPPED_POLICY if path is None else path)
        return cls(load_policy(path / "policy.npz" if path.is_dir() else path), neighbour_radius, safe, arm_xml, obstacles)

    def environment(self, num_arms: int, **settings) -> ReachingEnv:
        """An environment of ``num_arms`` slots with the policy's action scale and neighbour
        radius (and ``settings``, :class:`EnvConfig` fields, e.g. ``dynamic_targets=True``)."""
        return ReachingEnv(num_arms, dataclasses.replace(self.env_config, **settings), *self._collision_model)

    def _env(self, num_arms: int) -> ReachingEnv:
        if ("env", num_arms) not in self._compiled:
            self._compiled["env", num_arms] = self.environment(num_arms)
        return self._compiled["env", num_arms]

    def policy_fn(self):
        """``policy(states, params) -> mean actions`` for :func:`mjx_multiarm.env.wrappers.make_episodes`
        (``params``: :attr:`params`)."""
        actor_def = self._actor_def
        return lambda states, params: nnx.merge(actor_def, params)(states.obs, states.obs_mask)[0]

    @property
    def params(self):
        return self._actor

    def batched(self, num_arms: int):
        """The jitted JAX step for teams of ``num_arms`` arms, over any leading batch dims:
        ``step(base_pos, base_quat, prev_joints, joints, prev_target_pos, prev_target_quat,
        target_pos, target_quat) -> next joints`` with positions [..., n, 3], quaternions
        **wxyz** [..., n, 4] and joints [..., n, 6] (JAX arrays, float32)."""
        if ("step", num_arms) not in self._compiled:
            env, actor_def = self._env(num_arms), self._actor_def

            def step(params, base_pos, base_quat, prev_joints, joints, prev_target_pos, prev_target_quat, target_pos, target_quat):
                one = functools.partial(_policy_joints, env, nnx.merge(actor_def, params))
                for _ in range(joints.ndim - 2):  # leading batch dims
                    one = jax.vmap(one)
                return one(base_pos, base_quat, prev_joints, joints, (prev_target_pos, prev_target_quat), (target_pos, target_quat))

            self._compiled["step", num_arms] = jax.jit(step)
        return functools.partial(self._compiled["step", num_arms], self._actor)

    def _rollout(self, num_arms: int, steps: int):
        if ("rollout", num_arms, steps) not in self._compiled:
            env, actor_def = self._env(num_arms), self._actor_def

            def rollout(params, base_pos, base_quat, start, target_pos, target_quat):
                actor, targets = nnx.merge(actor_def, params), (target_pos, target_quat)

                active = jnp.ones(start.shape[:-1], bool)

                def body(carry, _):
                    prev, joints = carry
                    following = _policy_joints(env, actor, base_pos, base_quat, prev, joints, targets, targets)
                    verdict = certified_contacts(env.scene, base_pos, base_quat, joints, following, active)
                    return (joints, following), (following, verdict.min_distance, verdict.collided)

                _, (path, distance, collided) = jax.lax.scan(body, (start, start), None, length=steps)
                waypoints = jnp.concatenate([start[None], path])
                at_start = scene_contacts(env.scene, base_pos, base_quat, start, active)
                distance = jnp.concatenate([at_start.min_distance[None], distance])
                collided = jnp.concatenate([at_start.collided[None], collided])
                frames = jax.vmap(lambda q: forward_kinematics(env.scene.arm, base_pos, base_quat, q))(waypoints)
                return (waypoints, jnp.linalg.norm(frames.ee_pos - target_pos, axis=-1), quat_angle(frames.ee_quat, target_quat),
                        distance, collided)

            self._compiled["rollout", num_arms, steps] = jax.jit(rollout)
        return functools.partial(self._compiled["rollout", num_arms, steps], self._actor)

    def _inputs(self, joints, base_poses, targets, previous_joints, previous_targets):
        joints = np.asarray(joints, np.float64)
        if joints.ndim != 2 or joints.shape[1] != NUM_JOINTS or joints.shape[0] < 1:
            raise ValueError(f"joints: expected shape (n_arms, {NUM_JOINTS}), got {joints.shape}")
        n = joints.shape[0]
        base_poses = np.asarray(base_poses, np.float64)
        if base_poses.shape not in ((n, 3), (n, 7)):
            raise ValueError(f"base_poses: expected shape ({n}, 3) (x, y, yaw) or ({n}, 7) (x, y, z, qx, qy, qz, qw) "
                             f"for {n} arms, got {base_poses.shape}")
        checked = {"joints": joints, "base_poses": base_poses}
        for name, value, shape in (("targets", targets, (n, 7)), ("previous_targets", previous_targets, (n, 7)),
                                   ("previous_joints", previous_joints, (n, NUM_JOINTS))):
            if value is not None:
                value = np.asarray(value, np.float64)
                if value.shape != shape:
                    raise ValueError(f"{name}: expected shape {shape} for {n} arms, got {value.shape}")
                checked[name] = value
        for name, value in checked.items():
            check_finite(name, value)
        base_pos, base_quat = base_pose_arrays(base_poses)
        now = base_pose_arrays(checked["targets"], "targets")
        before = base_pose_arrays(checked["previous_targets"], "previous_targets") if "previous_targets" in checked else now
        prev_joints = checked.get("previous_joints", joints)
        as32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
        return n, [as32(x) for x in (base_pos, base_quat, prev_joints, joints, *before, *now)]

    def step(self, joints, base_poses, targets, previous_joints=None, previous_targets=None) -> np.ndarray:
        """The next joint waypoint [n, 6] of every arm (numpy in, numpy out).

        ``previous_joints`` / ``previous_targets`` are the arms' joints and targets one
        control step (50 ms) earlier; the policy observes this history (default: the same
        as now, as at the start of an episode).
        """
        n, inputs = self._inputs(joints, base_poses, targets, previous_joints, previous_targets)
        return np.asarray(self.batched(n)(*inputs), np.float64)

    def rollout(self, joints, base_poses, targets, steps: int = 200, tolerance=EVAL_TOLERANCE, goal_joints=None,
                handover: PlannerConfig = PlannerConfig()) -> PlannedPath:
        """Run the policy from ``joints`` toward static ``targets`` for at most ``steps``
        control steps, stopping once every arm is within ``tolerance``; the path's collisions
        (the start, and every motion by the certified motion check) are reported in
        :class:`PlannedPath` (with ``safe=True`` the motions are certified collision-free).

        ``goal_joints`` [n, 6] (configurations at the targets) makes it a hybrid planner
        (:mod:`mjx_multiarm.planner.handover`): where the policy stops short without a
        collision, BiRRT (``handover`` settings) plans the team from its last waypoint to
        them, and the plan's waypoints (its motions certified by the expert's replay check) are
        appended; their ``min_distance`` is measured at the waypoints.
        """
        if steps < 1:
            raise ValueError(f"steps must be >= 1, got {steps}")
        n, (base_pos, base_quat, _, start, _, _, target_pos, target_quat) = self._inputs(joints, base_poses, targets, None, None)
        if goal_joints is not None:
            goal_joints = np.asarray(goal_joints, np.float64)
            if goal_joints.shape != (n, NUM_JOINTS):
                raise ValueError(f"goal_joints: expected shape ({n}, {NUM_JOINTS}) for {n} arms, got {goal_joints.shape}")
            check_finite("goal_joints", goal_joints)
        outputs = self._rollout(n, steps)(base_pos, base_quat, start, target_pos, target_quat)
        waypoints, position, angle, distance = (np.asarray(x, np.float64) for x in outputs[:4])
        reached = (position < tolerance[0]) & (angle < tolerance[1])
        done = np.flatnonzero(reached.all(axis=1))
        last = int(done[0]) if done.size else steps
        min_distance = distance[: last + 1].min(axis=0)
        path = PlannedPath(waypoints[: last + 1], bool(reached[last].all()), position[last], angle[last], min_distance,
                           bool(np.asarray(outputs[4])[: last + 1].any()))
        if goal_joints is None or path.reached or path.collided:
            return path
        result = solve_team(base_pos, base_quat, path.waypoints[-1], goal_joints, handover)
        if result.status != SOLVED or not len(result.deltas):
            return path
        plan = path.waypoints[-1] + np.cumsum(result.deltas.astype(np.float64), axis=0)
        base_poses = np.asarray(base_poses, np.float64)
        at = evaluate_arms(np.broadcast_to(base_poses, (len(plan), *base_poses.shape)), plan)
        position = np.linalg.norm(at.ee_pos[-1] - np.asarray(targets, np.float64)[:, :3], axis=-1)
        angle = np.asarray(quat_angle(xyzw_to_wxyz(at.ee_quat[-1]), target_quat), np.float64)
        return PlannedPath(np.concatenate([path.waypoints, plan]), bool(((position < tolerance[0]) & (angle < tolerance[1])).all()),
                           position, angle, np.minimum(min_distance, at.min_distance.min(axis=0)), path.collided, len(plan))


def _policy_joints(env: ReachingEnv, actor, base_pos, base_quat, prev_joints, joints, prev_targets, targets):
    """Every arm's next joints under the policy's mean action (one team; any batch dims)."""
    active = jnp.ones(joints.shape[:-1], bool)

    def snapshot(q, target):
        frames = forward_kinematics(env.scene.arm, base_pos, base_quat, q)
        return ArmSnapshot(q, frames.ee_pos, frames.ee_quat, *target, frames.points)

    obs, mask = observe(base_pos, base_quat, active, snapshot(prev_joints, prev_targets), snapshot(joints, targets),
                        env.config.neighbour_radius)
    mean, _ = actor(obs, mask)
    following = env.next_joints(joints, mean, active)
    if env.config.safe:
        shield = env.shield
        for _ in range(joints.ndim - 2):  # leading batch dims
            shield = jax.vmap(shield)
        following = shield(base_pos, base_quat, joints, following, active)[0]
    return following
