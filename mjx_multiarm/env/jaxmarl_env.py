"""The reaching environment as a JaxMARL ``MultiAgentEnv``: one agent per arm.

    env = MultiArmReaching(TaskBank.from_tasks(two_arm_tasks, max_arms=2))
    obs, state = env.reset(key)                       # {"arm_0": [...], "arm_1": [...]}
    obs, state, rewards, dones, infos = env.step(key, state, {"arm_0": a0, "arm_1": a1})

The JaxMARL convention: observations, actions, rewards and dones are dicts keyed by agent
(``arm_0`` ... ``arm_{k-1}``), ``dones["__all__"]`` ends the episode and ``step``
restarts it with a new task drawn from the bank (``reset`` draws uniformly). Each arm
observes its own decentralized observation (the sequence of the arms within the neighbour
radius, itself last, and its mask, flattened: ``k x 108`` numbers) and acts with its 6
delta-joint commands in [-1, 1]; its reward is its own term of the paper's reward (team,
reach and collision parts). All tasks of the bank must have the same team size k, the
environment's ``max_arms``, so every agent is an arm.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxmarl.environments.multi_agent_env import MultiAgentEnv
from jaxmarl.environments.spaces import Box

from mjx_multiarm.env.observation import ELEMENT_SIZE
from mjx_multiarm.env.reaching import EnvConfig, ReachingEnv, State
from mjx_multiarm.env.wrappers import TaskBank
from mjx_multiarm.geometry.robot import NUM_JOINTS


class MultiArmReaching(MultiAgentEnv):
    """:class:`ReachingEnv` on the tasks of ``bank`` (all of one team size) as a JaxMARL
    environment (module docstring). ``config`` and ``tolerance`` as :class:`ReachingEnv`'s."""

    def __init__(self, bank: TaskBank, config: EnvConfig = EnvConfig(), tolerance=None):
        teams = np.unique(np.asarray(bank.tasks.active.sum(-1)))
        slots = bank.tasks.active.shape[-1]
        if len(teams) != 1 or teams[0] != slots:
            raise ValueError(f"MultiArmReaching needs tasks of one team size filling every slot; the bank has team sizes "
                             f"{teams.tolist()} in {slots} slots (TaskBank.from_tasks(tasks, max_arms=k) of k-arm tasks)")
        super().__init__(num_agents=slots)
        self.env, self.bank = ReachingEnv(slots, config), bank
        self.tolerance = jnp.asarray(config.tolerance if tolerance is None else tolerance, jnp.float32)
        self.agents = [f"arm_{i}" for i in range(slots)]
        size = slots * (ELEMENT_SIZE + 1)
        self.observation_spaces = {a: Box(-jnp.inf, jnp.inf, (size,)) for a in self.agents}
        self.action_spaces = {a: Box(-1.0, 1.0, (NUM_JOINTS,)) for a in self.agents}

    def reset(self, key: jax.Array) -> tuple[dict, State]:
        """A task drawn uniformly from the bank, at its start."""
        row = jax.random.randint(key, (), 0, self.bank.size)
        state = self.env.reset(key, self.bank.take(row), self.tolerance)
        return self.get_obs(state), state

    def step_env(self, key: jax.Array, state: State, actions: dict) -> tuple[dict, State, dict, dict, dict]:
        """One control step of every arm (no reset; :meth:`step` adds it)."""
        stepped = self.env.step(state, jnp.stack([actions[a] for a in self.agents]))
        rewards = {a: stepped.reward[i] for i, a in enumerate(self.agents)}
        dones = {a: stepped.done for a in self.agents} | {"__all__": stepped.done}
        infos = {"success": stepped.success, "collided": stepped.collided}
        return self.get_obs(stepped), stepped, rewards, dones, infos

    def get_obs(self, state: State) -> dict:
        """Each arm's observation sequence and mask, flattened."""
        flat = jnp.concatenate([state.obs.reshape(self.num_agents, -1), state.obs_mask.astype(jnp.float32)], axis=-1)
        return {a: flat[i] for i, a in enumerate(self.agents)}

    def get_avail_actions(self, state: State) -> dict:
        """Every action is available to every arm (continuous actions)."""
        return {a: jnp.ones(NUM_JOINTS, bool) for a in self.agents}

    @property
    def agent_classes(self) -> dict:
        return {"arm": self.agents}
