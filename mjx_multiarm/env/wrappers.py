"""Batched use of :class:`~mjx_multiarm.env.reaching.ReachingEnv`: task banks on device, auto-reset,
episode statistics, and replaying stored action sequences (expert demonstrations).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from mjx_multiarm.env.reaching import ReachingEnv, State
from mjx_multiarm.tasks.types import SCHEMA, Tasks, validate, with_slots


def batched_step(env: ReachingEnv):
    """``(states [B], actions [B, max_arms, 6]) -> states``: ``env.step`` over a batch.

    ``vmap``, except with safe execution on a CPU: there the teams step one after another
    (``lax.map``), so that each team's certified checks take their own number of evaluations,
    where under ``vmap`` every team waits for the slowest of the batch (3.5-3.7x faster at 4 and
    10 arms on 2 cores, same joints: benchmarks/RESULTS.md, "Certified safe execution, second
    session"). Accelerators keep ``vmap``.
    """
    if env.config.safe and jax.default_backend() == "cpu":
        return lambda states, actions: jax.lax.map(lambda pair: env.step(*pair), (states, actions))
    return jax.vmap(env.step)


@struct.dataclass
class TaskBank:
    """Tasks held on device, padded to the environment's slots, float32.

    On device ``tasks.task_id`` is the row of each task in the bank (JAX keeps 32-bit
    integers); the dataset's own int64 ids stay on the host in ``task_ids``.
    """

    tasks: Tasks  # [N, max_arms]
    task_ids: np.ndarray = struct.field(pytree_node=False)

    @classmethod
    def from_tasks(cls, tasks: Tasks, max_arms: int, source: str = "tasks") -> TaskBank:
        """Validate numpy ``tasks``, fit them to ``max_arms`` slots and move them to device.

        Raises ValueError for malformed tasks or a team larger than ``max_arms``.
        """
        tasks = with_slots(validate(tasks, source), max_arms, source)
        if tasks.num_tasks == 0:
            raise ValueError(f"{source}: the task bank needs at least one task")

        def to_device(name):
            value = np.asarray(getattr(tasks, name))
            if name == "task_id":
                return jnp.arange(len(value), dtype=jnp.int32)
            return jnp.asarray(value, jnp.float32 if value.dtype.kind == "f" else value.dtype)

        return cls(tasks=Tasks(**{name: to_device(name) for name in SCHEMA}), task_ids=np.asarray(tasks.task_id))

    @property
    def size(self) -> int:
        return int(self.tasks.active.shape[0])

    def take(self, index) -> Tasks:
        """The tasks at device indices ``index`` [...]."""
        return jax.tree.map(lambda x: x[index], self.tasks)


@struct.dataclass
class EpisodeStats:
    """Counts of finished episodes per team size (index = number of arms, 0 unused)."""

    episodes: jnp.ndarray
    successes: jnp.ndarray
    collisions: jnp.ndarray
    timeouts: jnp.ndarray
    success_steps: jnp.ndarray  # sum of episode lengths of successful episodes
    arms_reached: jnp.ndarray  # sum over episodes of the arms within tolerance when the episode ended

    @classmethod
    def zeros(cls, max_arms: int) -> EpisodeStats:
        return cls(*(jnp.zeros(max_arms + 1, jnp.int32) for _ in range(6)))

    def add(self, finished: State) -> EpisodeStats:
        """Count the episodes of a batch of stepped states that ended at this step."""
        ended = finished.done
        team = finished.task.active.sum(axis=-1)

        def count(flag):
            return jnp.zeros_like(self.episodes).at[team].add(flag.astype(jnp.int32))

        collided = finished.collided.any(axis=-1)
        return EpisodeStats(
            episodes=self.episodes + count(ended),
            successes=self.successes + count(ended & finished.success),
            collisions=self.collisions + count(ended & collided),
            timeouts=self.timeouts + count(ended & finished.truncated),
            success_steps=self.success_steps + jnp.zeros_like(self.episodes).at[team].add(jnp.where(ended & finished.success, finished.step, 0)),
            arms_reached=self.arms_reached + jnp.zeros_like(self.episodes).at[team].add(jnp.where(ended, finished.reached.sum(-1), 0)),
        )

    def summary(self) -> dict:
        """Host-side rates per team size with at least one episode, and over all of them;
        ``arm_reach_rate``: the share of arms within tolerance when their episode ended."""
        counts = {name: np.asarray(getattr(self, name))
                  for name in ("episodes", "successes", "collisions", "timeouts", "success_steps", "arms_reached")}
        arms = counts["episodes"] * np.arange(len(counts["episodes"]))

        def rates(sel):
            n = int(counts["episodes"][sel].sum())
            won = int(counts["successes"][sel].sum())
            return {
                "episodes": n,
                "success_rate": won / n if n else float("nan"),
                "collision_rate": int(counts["collisions"][sel].sum()) / n if n else float("nan"),
                "timeout_rate": int(counts["timeouts"][sel].sum()) / n if n else float("nan"),
                "mean_steps_to_success": int(counts["success_steps"][sel].sum()) / won if won else float("nan"),
                "arm_reach_rate": int(counts["arms_reached"][sel].sum()) / int(arms[sel].sum()) if n else float("nan"),
            }

        by_team = {int(k): rates(k) for k in np.flatnonzero(counts["episodes"])}
        return {"all": rates(slice(None)), "by_team_size": by_team}


@struct.dataclass
class BatchState:
    """A batch of environments with auto-reset: ``env`` has leading dim [B]."""

    env: State
    rng: jax.Array
    cursor: jnp.ndarray  # next bank row in sequential order
    tolerance: jnp.ndarray  # [max_arms, 2] used by the next resets, row k - 1 for k-arm tasks; a curriculum sets it
    stats: EpisodeStats


class AutoReset:
    """Steps a batch of environments and restarts finished ones with tasks from a bank.

    ``order="uniform"`` draws each new task uniformly at random; ``"sequential"`` walks the
    bank in order (wrapping around), so B environments cover the bank once every N episodes.
    """

    def __init__(self, env: ReachingEnv, bank: TaskBank, order: str = "uniform"):
        if order not in ("uniform", "sequential"):
            raise ValueError(f"order must be 'uniform' or 'sequential', got {order!r}")
        if bank.tasks.active.shape[1] != env.max_arms:
            raise ValueError(f"task bank has {bank.tasks.active.shape[1]} slots, the environment {env.max_arms}")
        self.env, self.bank, self.order = env, bank, order

    def _next_rows(self, rng, cursor, wanted):
        """Bank rows for the environments flagged in ``wanted`` [B], and the new cursor."""
        if self.order == "uniform":
            return jax.random.randint(rng, wanted.shape, 0, self.bank.size), cursor
        offset = jnp.cumsum(wanted) - 1
        return (cursor + offset) % self.bank.size, (cursor + wanted.sum()) % self.bank.size

    def _reset_rows(self, rows, tolerance) -> State:
        tasks = self.bank.take(rows)
        team_index = tasks.active.sum(axis=-1) - 1
        return jax.vmap(lambda task, team: self.env.reset(None, task, tolerance[team]))(tasks, team_index)

    def reset(self, rng, batch: int, tolerance=None) -> BatchState:
        """``batch`` fresh environments. ``tolerance``: (eps_p, eps_r) for every task, or
        [max_arms, 2], row k - 1 for tasks of k arms (default: the environment's)."""
        tolerance = self.tolerance_table(self.env.config.tolerance if tolerance is None else tolerance)
        rng, key = jax.random.split(rng)
        rows, cursor = self._next_rows(key, jnp.zeros((), jnp.int32), jnp.ones(batch, bool))
        return BatchState(self._reset_rows(rows, tolerance), rng, cursor, tolerance, EpisodeStats.zeros(self.env.max_arms))

    def tolerance_table(self, tolerance) -> jnp.ndarray:
        """[max_arms, 2] tolerances by team size from [2] (the same for all) or [max_arms, 2]."""
        tolerance = jnp.asarray(tolerance, jnp.float32)
        if tolerance.shape not in ((2,), (self.env.max_arms, 2)):
            raise ValueError(f"tolerance must have shape (2,) or ({self.env.max_arms}, 2), got {tolerance.shape}")
        return jnp.broadcast_to(tolerance, (self.env.max_arms, 2))

    def step(self, state: BatchState, actions) -> tuple[BatchState, State]:
        """Step every environment with ``actions`` [B, max_arms, 6].

        Returns ``(next, stepped)``: ``stepped`` holds the states right after the step (their
        observations, rewards and done flags are the transitions to learn from); in ``next``
        the environments that finished have been reset with new tasks.
        """
        stepped = batched_step(self.env)(state.env, actions)
        rng, key = jax.random.split(state.rng)
        rows, cursor = self._next_rows(key, state.cursor, stepped.done)
        fresh = self._reset_rows(rows, state.tolerance)
        env = jax.tree.map(lambda f, s: jnp.where(_expand(stepped.done, f), f, s), fresh, stepped)
        return BatchState(env, rng, cursor, state.tolerance, state.stats.add(stepped)), stepped


def _expand(flag, like):
    """``flag`` [B] reshaped to broadcast against ``like`` [B, ...]."""
    return flag.reshape(flag.shape + (1,) * (like.ndim - flag.ndim))


def replay_actions(env: ReachingEnv, state: State, actions, length) -> tuple[State, jnp.ndarray]:
    """Execute a stored action sequence from ``state`` (the expert-replay hook).

    Args:
      actions: [T, max_arms, 6] actions, padded beyond ``length`` (their values are unused).
      length: number of valid actions (traced; the compiled shape depends only on T).

    Returns:
      (states [T], valid [T]): the state after each action, and whether that step is part of
      the demonstration (within ``length`` and not after the episode ended). Steps beyond
      ``length`` hold the arms still. Batch it with ``vmap``.
    """

    def one(current, inputs):
        t, action = inputs
        action = jnp.where(t < length, action, 0.0)
        valid = (t < length) & ~current.done
        nxt = env.step(current, action)
        return nxt, (nxt, valid)

    steps = jnp.arange(actions.shape[0])
    _, (states, valid) = jax.lax.scan(one, state, (steps, actions))
    return states, valid


#: Progress (m) of a team's summed end-effector distance to its targets that restarts the
#: stall count of :func:`make_episodes` (``stall_steps``).
STALL_PROGRESS = 0.01


def make_episodes(env: ReachingEnv, policy, steps: int, stall_steps: int = 0):
    """A jitted function running a batch of tasks from their start for ``steps`` control steps.

    ``policy(states, params) -> actions [B, max_arms, 6]`` sees the batched states; the
    returned function maps (tasks [B], params) to the final states (finished episodes stay
    frozen at their end, see :class:`~mjx_multiarm.env.reaching.ReachingEnv`). Stepping
    stops once every episode of the batch has ended (the states would not change).

    With ``stall_steps`` > 0 an episode also ends, as a timeout, once its team's summed
    end-effector distance to its targets has not shrunk by :data:`STALL_PROGRESS` in that
    many steps: a deadlock detector (the hybrid planner hands such a team over at once).
    """

    def team_error(states):
        error = jnp.linalg.norm(states.arms.ee_pos - states.arms.target_pos, axis=-1)
        return jnp.where(states.task.active, error, 0.0).sum(axis=-1)

    step_all = batched_step(env)

    @jax.jit
    def episodes(tasks: Tasks, params):
        start = jax.vmap(lambda task: env.reset(None, task))(tasks)

        def running(carry):
            t, states, _, _ = carry
            return (t < steps) & ~states.done.all()

        def step(carry):
            t, states, best, since = carry
            states = step_all(states, policy(states, params))
            if stall_steps:
                error = team_error(states)
                progress = error <= best - STALL_PROGRESS
                best, since = jnp.where(progress, error, best), jnp.where(progress, 0, since + 1)
                stalled = (since >= stall_steps) & ~states.done
                states = states.replace(done=states.done | stalled, truncated=states.truncated | stalled)
            return t + 1, states, best, since

        carry = (jnp.zeros((), jnp.int32), start, team_error(start), jnp.zeros(start.done.shape, jnp.int32))
        return jax.lax.while_loop(running, step, carry)[1]

    return episodes


@dataclasses.dataclass
class Outcomes:
    """Per-task results of finished episodes (numpy, [N] each)."""

    team: np.ndarray  # arms in the task
    success: np.ndarray
    collision: np.ndarray
    timeout: np.ndarray  # neither success nor collision within the episode
    steps: np.ndarray  # control steps the episode lasted
    reached: np.ndarray  # arms within tolerance when the episode ended

    @classmethod
    def of(cls, final: State) -> Outcomes:
        """The outcomes of finished episodes' final states (numpy, [N] leading)."""
        collision = final.collided.any(axis=-1)
        return cls(final.task.active.sum(axis=-1), final.success, collision & ~final.success, ~final.success & ~collision,
                   final.step, final.reached.sum(axis=-1))

    @classmethod
    def concatenate(cls, parts: list[Outcomes]) -> Outcomes:
        return cls(*(np.concatenate([getattr(p, f.name) for p in parts]) for f in dataclasses.fields(cls)))

    def select(self, mask) -> Outcomes:
        return Outcomes(*(getattr(self, f.name)[mask] for f in dataclasses.fields(self)))

    def stats(self, max_arms: int) -> EpisodeStats:
        """The same counts as an :class:`EpisodeStats` (for its ``summary()``)."""

        def count(weights):
            return jnp.asarray(np.bincount(self.team, weights=weights, minlength=max_arms + 1).astype(np.int32))

        return EpisodeStats(count(np.ones(len(self.team))), count(self.success), count(self.collision), count(self.timeout),
                            count(np.where(self.success, self.steps, 0)), count(self.reached))


def run_episodes(env: ReachingEnv, policy, params, bank: TaskBank, steps: int | None = None, batch: int = 256) -> Outcomes:
    """Every task of ``bank`` run once from its start for ``steps`` control steps (default:
    the episode length); ``policy(states, params)`` as in :func:`make_episodes`."""
    return episode_outcomes(make_episodes(env, policy, env.config.max_steps if steps is None else steps), params, bank, batch)


def episode_outcomes(episodes, params, bank: TaskBank, batch: int = 256) -> Outcomes:
    """Every task of ``bank`` run once by ``episodes`` (from :func:`make_episodes`; reuse it
    to compile once), ``batch`` tasks per call (the last batch is padded by repeating tasks)."""
    return Outcomes.of(final_states(episodes, params, bank, batch))


def final_states(episodes, params, bank: TaskBank, batch: int = 256) -> State:
    """The final states (numpy, [N] leading) of every task of ``bank`` run once by ``episodes``,
    ``batch`` tasks per call, as :func:`episode_outcomes` runs them."""
    size = min(batch, bank.size)
    parts = []
    for start in range(0, bank.size, size):
        rows = np.arange(start, start + size) % bank.size
        keep = min(size, bank.size - start)
        parts.append(jax.tree.map(lambda x, k=keep: x[:k], jax.device_get(episodes(bank.take(rows), params))))
    return jax.tree.map(lambda *x: np.concatenate(x), *parts)
