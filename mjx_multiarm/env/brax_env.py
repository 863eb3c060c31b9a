"""The reaching environment behind Brax's ``Env`` interface, for Brax's wrappers and trainers.

    from brax.envs.wrappers.training import wrap
    from brax.training.agents.ppo.train import train as ppo

    env = BraxReaching(TaskBank.from_tasks(tasks, max_arms=1))
    make_policy, params, metrics = ppo(env, num_timesteps=..., episode_length=200, ...)

One Brax agent drives the whole team (a centralized view of the decentralized task):
``reset(rng)`` draws a task uniformly from the bank; the observation is every slot's
observation sequence and mask flattened into one vector (``observation_size`` =
max_arms x max_arms x 108), the action every slot's 6 delta-joint commands
(``action_size`` = max_arms x 6, actions of inactive slots are ignored), the reward the sum
over the team's arms, ``done`` the episode's end (success, collision or timeout). The
:class:`~mjx_multiarm.env.reaching.State` travels as ``pipeline_state``; ``metrics`` hold
``success`` and ``collision`` of the step. Brax's ``AutoResetWrapper`` restarts a finished
episode from that environment's first state (the same task); the decentralized trainer's
:class:`~mjx_multiarm.env.wrappers.AutoReset` draws a new task instead.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from brax.envs.base import Env
from brax.envs.base import State as BraxState

from mjx_multiarm.env.observation import ELEMENT_SIZE
from mjx_multiarm.env.reaching import EnvConfig, ReachingEnv, State
from mjx_multiarm.env.wrappers import TaskBank
from mjx_multiarm.geometry.robot import NUM_JOINTS


class BraxReaching(Env):
    """:class:`ReachingEnv` on the tasks of ``bank`` as a Brax ``Env`` (module docstring).

    ``config``: the environment's settings (default :class:`EnvConfig`: 2 cm / 0.1 rad,
    500 steps); ``tolerance``: (eps_p, eps_r) of every episode (default ``config.tolerance``).
    """

    def __init__(self, bank: TaskBank, config: EnvConfig = EnvConfig(), tolerance=None):
        max_arms = bank.tasks.active.shape[-1]
        self.env, self.bank = ReachingEnv(max_arms, config), bank
        self.tolerance = jnp.asarray(config.tolerance if tolerance is None else tolerance, jnp.float32)

    @property
    def observation_size(self) -> int:
        return self.env.max_arms * self.env.max_arms * (ELEMENT_SIZE + 1)

    @property
    def action_size(self) -> int:
        return self.env.max_arms * NUM_JOINTS

    @property
    def backend(self) -> str:
        return "jax"

    def _obs(self, state: State) -> jax.Array:
        return jnp.concatenate([state.obs.reshape(-1), state.obs_mask.reshape(-1).astype(jnp.float32)])

    def _brax_state(self, state: State, reward, metrics: dict) -> BraxState:
        return BraxState(pipeline_state=state, obs=self._obs(state), reward=reward, done=state.done.astype(jnp.float32),
                         metrics=metrics, info={})

    def reset(self, rng: jax.Array) -> BraxState:
        """A task drawn uniformly from the bank, at its start."""
        row = jax.random.randint(rng, (), 0, self.bank.size)
        state = self.env.reset(rng, self.bank.take(row), self.tolerance)
        zero = jnp.zeros((), jnp.float32)
        return self._brax_state(state, zero, {"success": zero, "collision": zero})

    def step(self, state: BraxState, action: jax.Array) -> BraxState:
        """One control step of every arm; ``action`` [action_size]."""
        stepped = self.env.step(state.pipeline_state, action.reshape(self.env.action_shape))
        reward = jnp.sum(jnp.where(stepped.task.active, stepped.reward, 0.0))
        metrics = {**state.metrics, "success": stepped.success.astype(jnp.float32),
                   "collision": stepped.collided.any().astype(jnp.float32)}  # wrappers may have added their own keys
        return self._brax_state(stepped, reward, metrics).replace(info=state.info)
