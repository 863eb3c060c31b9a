"""The multi-arm reaching environment (paper sections 4.2-4.3) as pure JAX functions.

:class:`ReachingEnv`: ``reset(rng, task)`` and ``step(state, actions)`` are pure functions
of pytrees, so ``jax.vmap`` runs thousands of environments at once and ``jax.jit`` wraps
whole ``lax.scan`` rollouts (Brax's ``Env`` and JaxMARL's ``MultiAgentEnv`` views of it:
:mod:`mjx_multiarm.env.brax_env`, :mod:`mjx_multiarm.env.jaxmarl_env`). One compiled
function serves every team size: a task occupies the first of the scene's ``max_arms`` slots
and the rest are masked.

Control (kinematic position control of an industrial arm): every 0.05 s control step each
arm receives a 6-D action, a delta-joint command. The joint motion is
``clip(action * action_scale, -v_max * dt, v_max * dt)``, then the joint limits; by default
``action_scale = v_max * dt``, so an action of +-1 is full speed. The motion is checked for
collision along the way: by the sampled sweep (substeps no further apart than 0.05 rad of
any joint; training and the paper's metric), or, with ``EnvConfig.safe``, by the certified
motion check (:mod:`mjx_multiarm.geometry.certified`: no configuration along it touches).

Rules (documented here once):

- Non-finite action components are replaced by 0 (that joint holds still) and flagged per
  arm in ``state.metrics["nonfinite_action"]``; actions of the wrong shape raise
  ``ValueError`` when traced. Actions of inactive slots are ignored.
- Rewards per arm add up: ``collision`` if the arm collided during the step, ``reach``
  while it is within tolerance of its target, ``team`` to every arm when all arms are
  within tolerance at once (success). Presets: :data:`REWARDS`. With
  ``EnvConfig.shaping`` = k > 0 every active arm also gets Phi(s') - Phi(s), a
  potential-based shaping term (Ng et al. 1999) with Phi = -k (position error in m +
  :data:`SHAPING_METRES_PER_RADIAN` x orientation error in rad) against the target of each
  state: it pays for progress, sums over an episode to k times the error removed, so it
  gives no reason to end an episode early by colliding.
- An episode ends on success, on any collision (a failure for the whole team), or after
  ``max_steps`` steps (a failure; ``truncated`` marks it for bootstrapping). Stepping a
  finished episode returns it unchanged, with zero reward. With
  ``EnvConfig.end_on_collision=False`` (a training option, as RoboBallet's) a collision
  does not end the episode: every arm that collided is put back where it was before the
  step (its last collision-free pose) and receives the ``collision`` reward; the others
  keep their motion. Success still needs a step without any collision. With
  ``EnvConfig.collisions_end_at`` = t > 0 as well, collisions end the episodes whose
  position tolerance is at most t (m), so a tolerance curriculum turns restoring into the
  paper's rule once it reaches t.
- With ``EnvConfig.safe`` (deployment, beyond the paper) the motion of a step is first
  shielded (:mod:`mjx_multiarm.env.shield`): arms whose motions are not certified free step
  away from the others or hold, so that a step never collides anywhere along it; its
  failures are timeouts. A contact between a moving arm and one that holds still is
  reported for the moving arm.
- Tolerances (eps_p m, eps_r rad) live in the state, so a curriculum changes them without
  recompiling. Reaching counts against the target of that step (moving targets move first).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from mjx_multiarm.env.observation import (
    NEIGHBOUR_RADIUS,
    ArmSnapshot,
    observe,
    retarget,
)
from mjx_multiarm.env.shield import PROPOSED, shielded_joints
from mjx_multiarm.geometry.collision import (
    CONTACTS_ONLY,
    SWEEP_RESOLUTION,
    num_substeps,
    swept_contacts,
)
from mjx_multiarm.geometry.kinematics import ArmFrames, forward_kinematics
from mjx_multiarm.geometry.robot import NUM_JOINTS, ArmModel
from mjx_multiarm.geometry.scene import Obstacle, Scene, build_scene
from mjx_multiarm.geometry.transforms import quat_angle
from mjx_multiarm.options import option
from mjx_multiarm.tasks.dynamic import PATH_SAMPLES, path_lengths, target_at
from mjx_multiarm.tasks.types import Tasks

#: Seconds per control step (the paper's action interval).
CONTROL_PERIOD = 0.05
#: Evaluation tolerances: 2 cm, 0.1 rad.
EVAL_TOLERANCE = (0.02, 0.1)


@dataclasses.dataclass(frozen=True)
class Rewards:
    """Per-arm reward terms (they add up)."""

    team: float  # every arm, when all arms are within tolerance at once
    reach: float  # an arm within tolerance of its target
    collision: float  # an arm that collided during the step


#: Weight of the orientation error in the shaping potential: 0.2 m per rad, the ratio of the
#: evaluation tolerances (2 cm, 0.1 rad).
SHAPING_METRES_PER_RADIAN = EVAL_TOLERANCE[0] / EVAL_TOLERANCE[1]


#: ``team``: the paper's cooperative reward; ``selfish``: its ablation without team reward.
REWARDS = {"team": Rewards(team=1.0, reach=0.01, collision=-0.05), "selfish": Rewards(team=0.0, reach=0.1, collision=-0.05)}


@dataclasses.dataclass(frozen=True)
class EnvConfig:
    """Static settings of the environment (changing one means recompiling).

    Attributes:
      max_steps: episode length in control steps (paper 500; original benchmark code 400).
      action_scale: radians of joint motion per unit of action (one number, or one per
        joint); None means each joint's velocity limit times the control period (an action
        of +-1 is full speed).
      neighbour_radius: bases within this distance (m) are observed; 1.7 as in the original
        code, 0.85 as in the paper text, 0 for the individualistic ablation (self only).
      reward: a key of :data:`REWARDS`.
      collision_penalty: replaces that reward's collision term (the paper's -0.05) when set.
      shaping: k of the potential-based shaping term (module rules); 0, the paper's
        reward, adds nothing.
      dynamic_targets: targets of tasks with a speed move along their paths
        (:mod:`mjx_multiarm.tasks.dynamic`); otherwise every target is static.
      tolerance: default (eps_p m, eps_r rad) at reset.
      sweep_resolution: largest joint motion (rad) between two collision checks of a step.
      end_on_collision: a collision ends the episode (the paper's rule, and evaluation's);
        False restores the colliding arms instead (module rules).
      collisions_end_at: with ``end_on_collision`` False, collisions still end the episodes
        whose position tolerance is at most this (m); 0: never (module rules).
      safe: every team step goes through :func:`mjx_multiarm.env.shield.shielded_joints`
        (collision-free execution; ``metrics["shielded"]`` marks the arms that stepped away
        or held instead of their proposed motion). Off for the paper's metric.
    """

    max_steps: int = option(500, "episode length in control steps", flag="episode_steps")
    action_scale: float | tuple[float, ...] | None = option(None, "radians of joint motion per unit of action (one number or "
                                                                  "one per joint; none: full speed at +-1)")
    neighbour_radius: float = option(NEIGHBOUR_RADIUS, "bases within this distance (m) are observed (0: individualistic)")
    reward: str = option("team", "reward terms (selfish: the paper's ablation)", choices=tuple(REWARDS))
    collision_penalty: float | None = option(None, "reward of an arm that collides in a step, <= 0 (none: the reward's, -0.05)")
    shaping: float = option(0.0, "potential-based reward shaping: every step pays K x the decrease of (position error in m "
                                 "+ 0.2 x orientation error in rad) (Ng et al. 1999; 0: the paper's reward)")
    dynamic_targets: bool = option(False, "targets of tasks with a speed move along their paths")
    tolerance: tuple[float, float] = option(EVAL_TOLERANCE, "(eps_p m, eps_r rad) at reset without a curriculum")
    sweep_resolution: float = option(SWEEP_RESOLUTION, "largest joint motion (rad) between two collision checks of a step")
    end_on_collision: bool = option(True, "a collision ends the episode (the paper; evaluation always ends it); 0: the "
                                          "colliding arms are put back with the collision penalty and the episode goes on")
    collisions_end_at: float = option(0.0, "with collisions restored: they end the episode once its position tolerance is at "
                                           "most this (m; a curriculum reaches it), 0: never")
    safe: bool = option(False, "safe execution (deployment, beyond the paper): every team step is shielded so that it never "
                               "collides (mjx_multiarm.env.shield: colliding arms step away from the others or hold)")

    def __post_init__(self):
        if self.max_steps < 1:
            raise ValueError(f"EnvConfig.max_steps must be >= 1, got {self.max_steps}")
        if self.action_scale is not None and (np.shape(self.action_scale) not in ((), (NUM_JOINTS,))
                                              or not np.all(np.asarray(self.action_scale) > 0)):
            raise ValueError(f"EnvConfig.action_scale must be None, a number > 0 or {NUM_JOINTS} of them, got {self.action_scale}")
        if not self.neighbour_radius >= 0:
            raise ValueError(f"EnvConfig.neighbour_radius must be >= 0, got {self.neighbour_radius}")
        if self.reward not in REWARDS:
            raise ValueError(f"EnvConfig.reward must be one of {sorted(REWARDS)}, got {self.reward!r}")
        if self.collision_penalty is not None and not self.collision_penalty <= 0:
            raise ValueError(f"EnvConfig.collision_penalty must be <= 0, got {self.collision_penalty}")
        if not self.shaping >= 0:
            raise ValueError(f"EnvConfig.shaping must be >= 0, got {self.shaping}")
        if len(self.tolerance) != 2 or not all(t > 0 for t in self.tolerance):
            raise ValueError(f"EnvConfig.tolerance must be (eps_p > 0, eps_r > 0), got {self.tolerance}")
        if not self.collisions_end_at >= 0 or (self.collisions_end_at and self.end_on_collision):
            raise ValueError(f"EnvConfig.collisions_end_at must be >= 0 and needs end_on_collision=False, got "
                             f"{self.collisions_end_at} with end_on_collision={self.end_on_collision}")
        if not self.sweep_resolution > 0:
            raise ValueError(f"EnvConfig.sweep_resolution must be > 0, got {self.sweep_resolution}")


@struct.dataclass
class State:
    """One environment (add leading batch dims with ``vmap``); ``A`` = max_arms slots.

    Attributes:
      task: the episode's task (one row of a device task bank).
      joints: [A, 6] joint angles.
      arms: world-frame snapshot of the arms at this step (next step's history frame).
      obs: [A, A, 107] every arm's observation sequence; obs_mask: [A, A] (see
        :func:`mjx_multiarm.env.observation.observe`).
      reward: [A] reward of the last step.
      reached: [A] arm within tolerance of its target (inactive slots False).
      collided: [A] arm collided during the last step.
      success: all arms within tolerance at once, no collision (ends the episode).
      done: the episode has ended (success, collision or timeout).
      truncated: it ended by timeout only.
      step: control steps taken.
      tolerance: [2] (eps_p m, eps_r rad).
      target_lengths: [A, samples] arc-length tables of moving targets ([A, 1] zeros when static).
      metrics: ``min_distance`` [A] smallest signed distance (m) during the last step where
        it is negative (a contact), else 0 (the step asks the collision kernel for contacts
        only: :data:`~mjx_multiarm.geometry.collision.CONTACTS_ONLY`); ``nonfinite_action`` [A] the arm's action held a NaN or inf.
    """

    task: Tasks
    joints: jnp.ndarray
    arms: ArmSnapshot
    obs: jnp.ndarray
    obs_mask: jnp.ndarray
    reward: jnp.ndarray
    reached: jnp.ndarray
    collided: jnp.ndarray
    success: jnp.ndarray
    done: jnp.ndarray
    truncated: jnp.ndarray
    step: jnp.ndarray
    tolerance: jnp.ndarray
    target_lengths: jnp.ndarray
    metrics: dict


def step_limits(arm: ArmModel, resolution: float = SWEEP_RESOLUTION) -> tuple[np.ndarray, int]:
    """([6] largest joint motion per control step, swept-check substeps per step)."""
    max_step = (arm.velocity_limit * CONTROL_PERIOD).astype(np.float32)
    return max_step, num_substeps(np.zeros(NUM_JOINTS), max_step, resolution)


class ReachingEnv:
    """Multi-arm reaching in a padded scene of ``max_arms`` slots."""

    def __init__(self, max_arms: int = 10, config: EnvConfig = EnvConfig(), arm_xml: str | None = None,
                 obstacles: tuple[Obstacle, ...] = ()):
        """``arm_xml`` and ``obstacles`` change the collision model (:func:`build_scene`: an arm
        carrying a tool, a bin): the arms' verdicts and the shield see them, the observation
        does not (the policy observes the arms' link points and targets only)."""
        self.config = config
        self.scene: Scene = build_scene(max_arms, arm_xml, obstacles)
        self.max_arms = max_arms
        arm = self.scene.arm
        self.rewards = REWARDS[config.reward]
        if config.collision_penalty is not None:
            self.rewards = dataclasses.replace(self.rewards, collision=config.collision_penalty)
        #: [6] largest joint motion per control step (rad), swept-check substeps per step.
        self.max_step, self.substeps = step_limits(arm, config.sweep_resolution)
        #: [6] radians of joint motion per unit of action.
        self.action_scale = self.max_step if config.action_scale is None else np.full(NUM_JOINTS, config.action_scale, np.float32)
        self.joint_range = arm.joint_range.astype(np.float32)

    @property
    def action_shape(self) -> tuple[int, int]:
        return (self.max_arms, NUM_JOINTS)

    def joint_deltas_to_actions(self, deltas):
        """Actions that move the joints by ``deltas`` [..., 6] (each within the per-step limit)."""
        return deltas / self.action_scale

    def next_joints(self, joints, actions, active):
        """Joint angles [..., A, 6] after ``actions`` [..., A, 6]: scaled, clipped to the
        per-step and joint limits; non-finite components and inactive arms hold still."""
        delta = jnp.clip(jnp.where(jnp.isfinite(actions), actions, 0.0) * self.action_scale, -self.max_step, self.max_step)
        delta = jnp.where(active[..., None], delta, 0.0)
        return jnp.clip(joints + delta, self.joint_range[:, 0], self.joint_range[:, 1])

    def shield(self, base_pos, base_quat, joints, proposed, active):
        """:func:`~mjx_multiarm.env.shield.shielded_joints` of one team with this environment's
        joint and step limits: (next joints, motion, certified verdict of the executed step)."""
        return shielded_joints(self.scene, base_pos, base_quat, joints, proposed, active, self.joint_range, self.max_step)

    def _check_task(self, task: Tasks) -> None:
        if task.active.shape != (self.max_arms,):
            raise ValueError(
                f"task has slots of shape {task.active.shape}, the environment expects one task of "
                f"{self.max_arms} slots: pad tasks with mjx_multiarm.tasks.types.with_slots and pass one row"
            )

    def _targets(self, task: Tasks, lengths, step):
        """Target poses [A, 3], [A, 4] at control step ``step``."""
        if not self.config.dynamic_targets:
            return task.target_pos, task.target_quat
        distance = task.speed * CONTROL_PERIOD * step
        pos, quat, _ = target_at(self.scene.arm, task.base_pos, task.base_quat, task.dynamic_start_joints, task.goal_joints, lengths, distance)
        return pos, quat

    def _snapshot(self, task: Tasks, joints, frames: ArmFrames, lengths, step) -> ArmSnapshot:
        target_pos, target_quat = self._targets(task, lengths, step)
        return ArmSnapshot(joints, frames.ee_pos, frames.ee_quat, target_pos, target_quat, frames.points)

    def _pose(self, task: Tasks, joints) -> ArmFrames:
        return forward_kinematics(self.scene.arm, task.base_pos, task.base_quat, joints)

    @staticmethod
    def _errors(arms: ArmSnapshot):
        """Per arm (position error m, orientation error rad) against its target."""
        return jnp.linalg.norm(arms.ee_pos - arms.target_pos, axis=-1), quat_angle(arms.ee_quat, arms.target_quat)

    def _reached(self, task: Tasks, arms: ArmSnapshot, tolerance):
        position, angle = self._errors(arms)
        return task.active & (position < tolerance[0]) & (angle < tolerance[1])

    def _potential(self, arms: ArmSnapshot):
        """The shaping potential Phi [A] of each arm (module rules)."""
        position, angle = self._errors(arms)
        return -self.config.shaping * (position + SHAPING_METRES_PER_RADIAN * angle)

    def _observe(self, task: Tasks, prev: ArmSnapshot, now: ArmSnapshot):
        return observe(task.base_pos, task.base_quat, task.active, prev, now, self.config.neighbour_radius)

    def reset(self, rng, task: Tasks, tolerance=None) -> State:
        """The state at the start of ``task`` (one row of a device task bank).

        A task fixes its episode, so reset draws nothing from ``rng``; the standard interfaces
        (:mod:`mjx_multiarm.env.brax_env`, :mod:`mjx_multiarm.env.jaxmarl_env`) draw the task
        from a bank with theirs. ``tolerance`` (eps_p, eps_r) defaults to ``config.tolerance``.
        """
        del rng
        self._check_task(task)
        tolerance = jnp.asarray(self.config.tolerance if tolerance is None else tolerance, jnp.float32)
        if self.config.dynamic_targets:
            lengths = path_lengths(self.scene.arm, task.base_pos, task.base_quat, task.dynamic_start_joints, task.goal_joints, PATH_SAMPLES)
        else:
            lengths = jnp.zeros((self.max_arms, 1), jnp.float32)  # unused; not empty, so checkpoints can hold it
        step = jnp.zeros((), jnp.int32)
        arms = self._snapshot(task, task.start_joints, self._pose(task, task.start_joints), lengths, step)
        obs, obs_mask = self._observe(task, arms, arms)
        no = jnp.zeros(self.max_arms, bool)
        return State(
            task=task,
            joints=task.start_joints,
            arms=arms,
            obs=obs,
            obs_mask=obs_mask,
            reward=jnp.zeros(self.max_arms, jnp.float32),
            reached=self._reached(task, arms, tolerance),
            collided=no,
            success=jnp.zeros((), bool),
            done=jnp.zeros((), bool),
            truncated=jnp.zeros((), bool),
            step=step,
            tolerance=tolerance,
            target_lengths=lengths,
            metrics={"min_distance": jnp.zeros(self.max_arms, jnp.float32), "nonfinite_action": no}
            | ({"shielded": no} if self.config.safe else {}),
        )

    def step(self, state: State, actions) -> State:
        """Apply ``actions`` [max_arms, 6] for one control step (see the module rules)."""
        actions = jnp.asarray(actions)
        if actions.shape != self.action_shape:
            raise ValueError(f"actions have shape {actions.shape}, expected {self.action_shape} (max_arms, joints)")
        task = state.task
        finite = jnp.isfinite(actions)
        # An ended episode holds still (its step is discarded below; a shield then certifies it at once).
        joints = self.next_joints(state.joints, jnp.where(state.done, 0.0, actions), task.active)
        metrics = {}
        if self.config.safe:
            joints, motion, contacts = self.shield(task.base_pos, task.base_quat, state.joints, joints, task.active)
            frames = self._pose(task, joints)
            metrics["shielded"] = motion != PROPOSED
        else:
            frames = self._pose(task, joints)
            contacts = swept_contacts(self.scene, task.base_pos, task.base_quat, state.joints, joints, task.active,
                                      self.substeps, end_frames=frames, max_distance=CONTACTS_ONLY)
        collided = contacts.collided & task.active
        if not self.config.end_on_collision:  # training option: the colliding arms go back
            joints = jnp.where((collided & ~self._collisions_end(state.tolerance))[:, None], state.joints, joints)
            frames = self._pose(task, joints)

        step = state.step + 1
        arms = self._snapshot(task, joints, frames, state.target_lengths, step)
        obs, obs_mask = self._observe(task, state.arms, arms)
        stepped = State(
            task=task,
            joints=joints,
            arms=arms,
            obs=obs,
            obs_mask=obs_mask,
            collided=collided,
            step=step,
            tolerance=state.tolerance,
            target_lengths=state.target_lengths,
            metrics={"min_distance": jnp.minimum(contacts.min_distance, 0.0), "nonfinite_action": task.active & ~finite.all(axis=-1), **metrics},
            **self._outcome(task, state.arms, arms, collided, state.tolerance, step),
        )
        finished = state.replace(reward=jnp.zeros_like(state.reward))
        return jax.tree.map(lambda old, new: jnp.where(state.done, old, new), finished, stepped)

    def _collisions_end(self, tolerance) -> jnp.ndarray:
        """Whether a collision ends an episode of ``tolerance`` (eps_p, eps_r) (module rules)."""
        return jnp.asarray(self.config.end_on_collision) | (tolerance[0] <= self.config.collisions_end_at)

    def _outcome(self, task: Tasks, before: ArmSnapshot, arms: ArmSnapshot, collided, tolerance, step) -> dict:
        """The fields ``reached``, ``success``, ``reward``, ``done`` and ``truncated`` of a step
        from the arms at ``before`` to ``arms`` (see the module rules)."""
        reached = self._reached(task, arms, tolerance)
        any_collision = collided.any()
        success = jnp.all(reached | ~task.active) & ~any_collision
        terms = self.rewards
        reward = terms.collision * collided + terms.reach * reached + terms.team * success
        if self.config.shaping:
            reward = reward + self._potential(arms) - self._potential(before)
        timeout = step >= self.config.max_steps
        ends = any_collision & self._collisions_end(tolerance)
        return {"reached": reached, "success": success, "reward": jnp.where(task.active, reward, 0.0).astype(jnp.float32),
                "done": success | ends | timeout, "truncated": timeout & ~success & ~ends}

    def with_achieved_targets(self, before: State, after: State, goal: State) -> State:
        """Hindsight relabelling (Andrychowicz et al. 2017): the state ``after``, stepped from
        ``before``, as if every arm's target had been the end-effector pose that arm holds in
        ``goal``, a later state of the same episode. Targets, observations, reached, success,
        reward and the done flags are recomputed; collisions stay. Static targets only."""
        if self.config.dynamic_targets:
            raise ValueError("hindsight targets replace static targets; this environment moves its targets (dynamic_targets=True)")
        retargeted = [s.arms.replace(target_pos=goal.arms.ee_pos, target_quat=goal.arms.ee_quat) for s in (before, after)]
        return after.replace(arms=retargeted[1], obs=retarget(after.obs, goal.obs),
                             **self._outcome(after.task, *retargeted, after.collided, after.tolerance, after.step))
