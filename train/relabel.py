"""Expert relabelling of collisions (DAgger-style, beyond the paper), the host half.

The training iteration queues every state where a team collided (the joints before the
colliding step, :class:`~train.trainer.TrainState` ``collisions``). Between iterations
:class:`CollisionRelabeller` takes the oldest queued states (one per task among them), plans
the whole team from each to the task's goal configuration with the BiRRT expert
(:func:`mjx_multiarm.expert.solve.solve_team`, whose steps pass the environment's swept
check), and hands the plans to the next iteration as :class:`~train.trainer.Relabelled`
demonstrations: the policy learns what the expert does in the states its own actions led to
(Ross et al. 2011), not only from the tasks' starts.
"""

from __future__ import annotations

import time

import jax
import numpy as np

from mjx_multiarm.expert.planner import SOLVED, PlannerConfig
from mjx_multiarm.expert.solve import solve_team
from train.trainer import Relabelled, Trainer, TrainState

#: Queued states read per plan wanted: consecutive collisions of one episode share a task,
#: and one state per task is planned.
READ_PER_PLAN = 4


class CollisionRelabeller:
    """Plans demonstrations from a trainer's queued collision states (``trainer.config.relabel``
    per call, at most ``relabel_seconds`` each)."""

    def __init__(self, trainer: Trainer, seed: int = 0):
        config = trainer.config
        if not config.relabel:
            raise ValueError("CollisionRelabeller needs a trainer with TrainConfig.relabel > 0")
        self.plans, self.env, self.seed = config.relabel, trainer.env, seed
        self.steps = trainer.demos.max_steps
        self.planner = PlannerConfig(time_limit=config.relabel_seconds, attempts=2)
        self.tasks = jax.device_get(trainer.bank.tasks)
        self.task_ids = trainer.bank.task_ids
        read = self.plans * READ_PER_PLAN
        self._pop = jax.jit(lambda queue: queue.pop(read))

    def empty(self) -> Relabelled:
        """A batch with nothing to replay (the shapes every batch has)."""
        slots = self.env.max_arms
        return Relabelled(np.zeros(self.plans, np.int32), np.zeros((self.plans, slots, 6), np.float32),
                          np.zeros((self.plans, self.steps, slots, 6), np.float32), np.zeros(self.plans, np.int32))

    def __call__(self, state: TrainState, iteration: int) -> tuple[TrainState, Relabelled, dict]:
        """(``state`` with the states it took popped from its queue, the plans, statistics:
        states planned, plans solved, planning seconds)."""
        clock = time.perf_counter()
        queue, (rows, joints), valid = self._pop(state.collisions)
        rows, joints, valid = jax.device_get((rows, joints, valid))
        _, first = np.unique(rows[valid], return_index=True)
        chosen = np.flatnonzero(valid)[np.sort(first)][: self.plans]
        batch = self.empty()
        solved = 0
        for row, joints_before in zip(rows[chosen], joints[chosen], strict=True):
            arms = int(self.tasks.active[row].sum())
            result = solve_team(self.tasks.base_pos[row][:arms], self.tasks.base_quat[row][:arms], joints_before[:arms],
                                self.tasks.goal_joints[row][:arms], self.planner, self.seed + iteration, int(self.task_ids[row]))
            if result.status != SOLVED or len(result.deltas) == 0:
                continue
            length = min(len(result.deltas), self.steps)
            batch.rows[solved], batch.start[solved], batch.lengths[solved] = row, joints_before, length
            batch.actions[solved, :length, :arms] = self.env.joint_deltas_to_actions(result.deltas[:length])
            solved += 1
        stats = {"relabel_planned": len(chosen), "relabel_solved": solved, "relabel_seconds": time.perf_counter() - clock}
        return state.replace(collisions=queue), batch, stats
