"""The jitted SAC training iteration with expert demonstrations on failure and a curriculum.

One call of :meth:`Trainer.iteration` (compiled once) does, in the style of Brax's SAC:

1. ``rollout_steps`` steps of ``num_envs`` auto-resetting environments with actions sampled
   from the shared policy (every arm of every environment in one forward pass); every
   active arm's transition enters the replay buffer;
2. every episode that ends is recorded for the curriculum (which tightens the tolerance of
   new episodes when the policy graduates); every failed episode whose task has an expert
   joins a queue of failed tasks;
3. up to ``expert_replays`` queued failed tasks are re-run from their start with the
   expert's stored actions (:func:`mjx_multiarm.env.wrappers.replay_actions`) and the expert's
   experience, with the environment's rewards, enters the buffer beside the failed attempt;
4. with ``hindsight`` = C > 0, C copies of every policy transition of the rollout enter the
   buffer relabelled with hindsight goals (:func:`hindsight_transitions`);
5. ``updates_per_iteration`` SAC updates on uniform batches from the buffer once it holds
   ``warmup`` transitions (behaviour cloning on expert transitions only with ``bc=True``).

With ``relabel`` = N > 0 (beyond the paper; DAgger-style, Ross et al. 2011) every step
where a team collided queues the team's joints before that step; between iterations up to N
of them are planned by BiRRT to the task's goal configuration (:mod:`train.relabel`) and
the next iteration replays the plans from those states as expert demonstrations.

With ``shield_teacher`` = f > 0 (shield distillation, DAgger-style with safe execution as
the teacher) the first f of the environments run every step through the shield
(:mod:`mjx_multiarm.env.shield`); where it replaced an arm's motion (stepping away or
holding), the executed motion is stored as that arm's action, flagged as an expert's, so
the Q-filtered behaviour cloning (``sac.expert_bc``) teaches each arm from its own
observation what the shield knew; those episodes do not count toward the curriculum.

Options beyond the paper: ``curriculum_by_team`` gives every team size its own curriculum
level (:class:`~train.curriculum.GroupedCurriculum`); ``expert_share`` = f > 0 keeps the
expert transitions in a buffer of their own (``expert_buffer`` rows) and draws a fixed
fraction f of every batch from it (as RLPD's symmetric sampling), so demonstrations stay
in the batches however many policy transitions arrive.

Everything stays on device; the host only reads metrics between iterations.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from mjx_multiarm.env.observation import retarget
from mjx_multiarm.env.reaching import ReachingEnv, State
from mjx_multiarm.env.shield import PROPOSED
from mjx_multiarm.env.wrappers import AutoReset, BatchState, TaskBank, replay_actions
from mjx_multiarm.expert.store import ExpertStore
from mjx_multiarm.options import option
from train.agent import Agent, SACConfig, bc_update, create_agent, sac_update
from train.curriculum import LEVELS, GroupedCurriculum
from train.replay import ReplayBuffer, Transitions, ring_write


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Sizes of the training loop (see the module docstring)."""

    num_envs: int = option(64, "environments stepped in parallel")
    rollout_steps: int = option(16, "environment steps per iteration")
    updates_per_iteration: int = option(16, "SAC updates per iteration")
    batch_size: int = option(256, "transitions per SAC update")
    buffer_size: int = option(50_000, "replay buffer rows (arm transitions)")
    warmup: int = option(2_000, "transitions in the buffer before the first update")
    expert: bool = option(True, "replay the expert's demonstration of every failed task (the paper)")
    expert_replays: int = option(8, "failed tasks replayed with their expert per iteration")
    expert_steps: int = option(64, "longest expert sequence kept (longer ones are cut)")
    failed_queue: int = option(256, "failed tasks waiting for their expert replay")
    bc: bool = option(False, "behaviour cloning on the expert data only (the paper's ablation; see --bc)")
    curriculum: bool = option(True, "tolerance curriculum from 10 cm / 0.2 rad down to 1 cm / 0.05 rad "
                                    "(--no-curriculum: 2 cm / 0.1 rad from the start)")
    start_level: int = option(0, "first curriculum level")
    noise_decay: float = option(0.0, "shrink the policy's standard-deviation bound with the curriculum: x (eps_p / 10 cm) ** P "
                                     "(0: the original's fixed bound)")
    hindsight: int = option(0, "copies of every policy transition relabelled with a hindsight goal (the pose an arm reached "
                               "later in the episode; Andrychowicz et al. 2017; 0: the original's replay)")
    curriculum_by_team: bool = option(False, "every team size has its own curriculum level, graduating on its own episodes "
                                             "(0: one level for all, the original)")
    expert_share: float = option(0.0, "fraction of every batch drawn from a separate buffer of expert transitions "
                                      "(0: one buffer for all, the original)")
    expert_buffer: int = option(50_000, "rows of the expert buffer of --expert-share", flag="expert_buffer_size")
    expert_prefill: int = option(0, "replay the experts of this many random training tasks into the buffer before the "
                                    "first iteration (0: none, as the original)")
    relabel: int = option(0, "expert relabelling of collisions (DAgger-style, beyond the paper): every iteration up to N "
                             "states where a team collided are planned by BiRRT from the step before the collision to the "
                             "task's goal configuration, and the plans are replayed as demonstrations (0: off)")
    relabel_queue: int = option(256, "collision states waiting for --relabel")
    relabel_seconds: float = option(0.5, "BiRRT time cap (s) of one --relabel plan")
    shield_teacher: float = option(0.0, "shield distillation (DAgger with safe execution as the teacher): this fraction of the "
                                        "environments runs every step through the shield, and where it replaced an arm's "
                                        "motion the executed motion is stored as an expert transition (0: off)")
    sac: SACConfig = SACConfig()

    def __post_init__(self):
        for name in ("num_envs", "rollout_steps", "updates_per_iteration", "batch_size", "buffer_size", "expert_replays", "expert_steps",
                     "failed_queue", "relabel_queue"):
            if getattr(self, name) < 1:
                raise ValueError(f"TrainConfig.{name} must be >= 1, got {getattr(self, name)}")
        if self.bc and not self.expert:
            raise ValueError("behaviour cloning (bc) learns from expert demonstrations: it needs expert=True")
        if self.hindsight < 0:
            raise ValueError(f"TrainConfig.hindsight must be >= 0, got {self.hindsight}")
        if self.hindsight and self.bc:
            raise ValueError("hindsight relabels the policy's own transitions; behaviour cloning (bc) stores none")
        if self.noise_decay < 0:
            raise ValueError(f"TrainConfig.noise_decay must be >= 0, got {self.noise_decay}")
        if not 0 <= self.expert_share < 1:
            raise ValueError(f"TrainConfig.expert_share must be in [0, 1), got {self.expert_share}")
        if self.expert_share and (self.bc or not self.expert):
            raise ValueError("expert_share samples expert transitions beside the policy's: it needs expert=True and bc=False")
        if self.expert_share and self.expert_buffer < 1:
            raise ValueError(f"TrainConfig.expert_buffer must be >= 1, got {self.expert_buffer}")
        if self.expert_prefill < 0:
            raise ValueError(f"TrainConfig.expert_prefill must be >= 0, got {self.expert_prefill}")
        if self.expert_prefill and (self.bc or not self.expert):
            raise ValueError("expert_prefill replays expert demonstrations: it needs expert=True and bc=False")
        if self.sac.bc_start and (self.bc or not self.expert):
            raise ValueError("bc_start clones expert transitions before SAC: it needs expert=True and bc=False")
        if self.relabel < 0 or not self.relabel_seconds > 0:
            raise ValueError(f"TrainConfig.relabel must be >= 0 and relabel_seconds > 0, got {self.relabel}, {self.relabel_seconds}")
        if self.relabel and (self.bc or not self.expert):
            raise ValueError("relabel replays planned demonstrations beside the policy's transitions: it needs expert=True and bc=False")
        if not 0 <= self.shield_teacher <= 1:
            raise ValueError(f"TrainConfig.shield_teacher must be in [0, 1], got {self.shield_teacher}")
        if self.shield_teacher and self.bc:
            raise ValueError("shield_teacher labels the policy's own rollouts; behaviour cloning (bc) runs none")
        if self.sac.expert_bc and (self.bc or not self.expert):
            raise ValueError("expert_bc adds behaviour cloning of expert demonstrations to SAC: it needs expert=True and bc=False")


@struct.dataclass
class Demonstrations:
    """Expert actions of the bank's tasks on device, packed back to back.

    ``actions`` [S, max_arms, 6] holds every task's sequence in turn (task ``i`` at
    ``offsets[i]``, ``lengths[i]`` steps, 0 where it has no expert), so memory grows with
    the planned steps (~20 per task), not with ``max_steps``: 100,000 four-slot tasks take
    ~0.2 GB where a padded [N, 128, 4, 6] table took 1.2 GB.
    """

    actions: jnp.ndarray
    offsets: jnp.ndarray
    lengths: jnp.ndarray
    max_steps: int = struct.field(pytree_node=False)

    @classmethod
    def from_store(cls, store: ExpertStore, bank: TaskBank, env: ReachingEnv, max_steps: int) -> Demonstrations:
        """The experts of the bank's tasks (length 0 where a task has none or it failed)."""
        solved = set(int(t) for t in store.task_ids[store.solved])
        ids = [int(t) for t in bank.task_ids]
        rows = [i for i, t in enumerate(ids) if t in solved]
        deltas, offsets, lengths = store.packed([ids[i] for i in rows], max_steps, env.max_arms)
        all_offsets, all_lengths = np.zeros(len(ids), np.int64), np.zeros(len(ids), np.int32)
        all_offsets[rows], all_lengths[rows] = offsets, lengths
        deltas = np.concatenate([deltas, np.zeros((1, *deltas.shape[1:]), np.float32)])  # never empty
        if len(deltas) >= 2**31:  # device offsets are int32
            raise ValueError(f"{store.path}: {len(deltas)} expert steps exceed the 2**31 a task bank can index")
        return cls(jnp.asarray(env.joint_deltas_to_actions(deltas)), jnp.asarray(all_offsets, jnp.int32),
                   jnp.asarray(all_lengths), max_steps)

    def take(self, rows) -> tuple[jnp.ndarray, jnp.ndarray]:
        """(actions [B, max_steps, max_arms, 6], lengths [B]) of bank rows [B]; actions
        beyond a task's length are padding (their values are unused)."""
        steps = jnp.arange(self.max_steps)
        index = jnp.minimum(self.offsets[rows][:, None] + steps, self.actions.shape[0] - 1)
        return self.actions[index], self.lengths[rows]


@struct.dataclass
class Queue:
    """A bounded FIFO ring of items (a pytree of [size, ...] arrays): failed tasks waiting
    for their expert replay, collision states waiting for their relabelling plan."""

    items: object
    head: jnp.ndarray
    count: jnp.ndarray

    @classmethod
    def create(cls, size: int, like=None) -> Queue:
        """An empty queue of ``size`` items shaped like ``like`` (default: one int32 row index)."""
        zero = jnp.zeros((), jnp.int32)
        like = zero if like is None else like
        return cls(jax.tree.map(lambda x: jnp.zeros((size, *jnp.shape(x)), jnp.asarray(x).dtype), like), zero, zero)

    @property
    def size(self) -> int:
        return jax.tree.leaves(self.items)[0].shape[0]

    def push(self, flags, items) -> Queue:
        """Append ``items`` [B, ...] where ``flags`` [B]; the oldest entries are overwritten when full."""
        queued = jax.tree.map(lambda ring, new: ring_write(ring, new, flags, self.head + self.count)[0], self.items, items)
        new = flags.astype(bool).sum().astype(jnp.int32)
        overflow = jnp.maximum(self.count + new - self.size, 0)
        return Queue(queued, (self.head + overflow) % self.size, jnp.minimum(self.count + new, self.size))

    def pop(self, n: int) -> tuple[Queue, object, jnp.ndarray]:
        """(queue, items [n, ...], valid [n]): the ``n`` oldest entries (fewer may be valid)."""
        take = jnp.minimum(self.count, n)
        index = (self.head + jnp.arange(n)) % self.size
        items = jax.tree.map(lambda x: x[index], self.items)
        return Queue(self.items, (self.head + take) % self.size, self.count - take), items, jnp.arange(n) < take


@struct.dataclass
class Relabelled:
    """Demonstrations planned from collision states (:mod:`train.relabel`), replayed by the
    next iteration: bank ``rows`` [R], their ``start`` joints [R, A, 6], ``actions``
    [R, T, A, 6] and ``lengths`` [R] (0: nothing to replay)."""

    rows: jnp.ndarray
    start: jnp.ndarray
    actions: jnp.ndarray
    lengths: jnp.ndarray


@struct.dataclass
class TrainState:
    """Everything a training run carries from one iteration to the next (checkpointed)."""

    agent: Agent
    envs: BatchState
    buffer: ReplayBuffer
    expert_buffer: ReplayBuffer | None  # with TrainConfig.expert_share > 0
    curriculum: GroupedCurriculum
    failed: Queue  # bank rows of failed tasks
    collisions: Queue | None  # with TrainConfig.relabel: (bank row, joints [A, 6] before the colliding step)
    rng: jax.Array
    env_steps: jnp.ndarray
    expert_steps: jnp.ndarray


def arm_transitions(before_obs, before_mask, actions, after: State, expert) -> tuple[Transitions, jnp.ndarray]:
    """Per-arm transitions of a batch of stepped environments, flattened over [..., arms].

    ``before_obs`` [..., A, A, 107] / ``before_mask`` [..., A, A] are the observations the
    actions [..., A, 6] were taken from; ``after`` the stepped states; ``expert``: the
    actions are an expert's (a bool, or [..., A] per arm). Returns the transitions and their
    validity (active arms).
    """
    terminal = jnp.broadcast_to((after.done & ~after.truncated)[..., None], after.reward.shape)

    def flat(x, trailing):
        return x.reshape(-1, *x.shape[x.ndim - trailing :])

    transitions = Transitions(
        obs=flat(before_obs, 2), mask=flat(before_mask, 1), action=flat(actions, 1), reward=after.reward.reshape(-1),
        next_obs=flat(after.obs, 2), next_mask=flat(after.obs_mask, 1), terminal=terminal.reshape(-1),
        expert=jnp.broadcast_to(jnp.asarray(expert), after.reward.shape).reshape(-1),
    )
    return transitions, after.task.active.reshape(-1)


def hindsight_transitions(env: ReachingEnv, before: State, actions, stepped: State, copies: int, key) -> tuple[Transitions, jnp.ndarray]:
    """Policy transitions of a rollout relabelled with hindsight goals ("future" strategy of
    Andrychowicz et al. 2017, within the rollout).

    ``before`` / ``stepped`` [T, B] are the states before and after ``actions`` [T, B, A, 6]
    at each of T consecutive steps of B auto-resetting environments. Each transition gets
    ``copies`` goals: the arms' end-effector poses after a step drawn uniformly from that
    step to the last of its episode within the rollout. Returns flattened transitions
    [copies * T * B * A] and their validity, as :func:`arm_transitions`.
    """
    steps, batch = actions.shape[:2]
    t = jnp.arange(steps)[:, None]
    last = jax.lax.cummin(jnp.where(stepped.done, t, steps - 1), axis=0, reverse=True)  # [T, B]: the episode's last step here
    draw = jax.random.uniform(key, (copies, steps, batch))
    goal_step = jnp.minimum(t + jnp.floor(draw * (last - t + 1)).astype(jnp.int32), last)
    goal = jax.tree.map(lambda x: x[goal_step, jnp.arange(batch)], stepped)
    repeat = lambda tree: jax.tree.map(lambda x: jnp.broadcast_to(x, (copies, *x.shape)), tree)  # noqa: E731
    relabelled = jax.vmap(jax.vmap(jax.vmap(env.with_achieved_targets)))(repeat(before), repeat(stepped), goal)
    before_obs = retarget(repeat(before.obs), goal.obs)
    return arm_transitions(before_obs, repeat(before.obs_mask), repeat(actions), relabelled, expert=False)


class Trainer:
    """Builds and runs the training iteration for one environment, task bank and expert set."""

    def __init__(self, env: ReachingEnv, bank: TaskBank, demonstrations: Demonstrations | None, config: TrainConfig = TrainConfig(),
                 devices=None):
        """``devices``: data-parallel over these (default: one device). The environments are
        split along their batch axis across the devices and the SAC batches too; parameters,
        optimizer states and the replay buffer are replicated, and XLA inserts the
        gradient all-reduce."""
        if config.hindsight and env.config.dynamic_targets:
            raise ValueError("hindsight relabelling needs static targets; the environment has dynamic_targets=True")
        relabelled = config.hindsight * config.rollout_steps * config.num_envs * env.max_arms
        if relabelled > config.buffer_size:
            raise ValueError(f"hindsight={config.hindsight} relabels {relabelled} arm transitions per iteration, more than the "
                             f"replay buffer holds ({config.buffer_size}): raise buffer_size or lower hindsight")
        if config.expert and demonstrations is None:
            raise ValueError("expert demonstrations are enabled but none were given")
        devices = list(devices) if devices is not None else jax.devices()[:1]
        for name in ("num_envs", "batch_size"):
            if getattr(config, name) % len(devices):
                raise ValueError(f"TrainConfig.{name}={getattr(config, name)} must be divisible by the {len(devices)} devices")
        if config.expert_share and config.expert_replays * demonstrations.max_steps * env.max_arms > config.expert_buffer:
            raise ValueError(f"expert_buffer={config.expert_buffer} is smaller than one iteration's expert replays "
                             f"({config.expert_replays} x {demonstrations.max_steps} steps x {env.max_arms} arms)")
        self.env, self.bank, self.demos, self.config = env, bank, demonstrations, config
        teams = np.unique(np.asarray(bank.tasks.active.sum(axis=-1)))
        #: Curriculum group of each team size (index k - 1), and the groups the bank's tasks use.
        self.team_group = np.arange(env.max_arms) if config.curriculum_by_team else np.zeros(env.max_arms, np.int64)
        self.groups_used = np.unique(self.team_group[teams - 1])
        self.teams = teams
        self.mesh = Mesh(np.array(devices), ("data",))
        self.autoreset = AutoReset(env, bank)
        #: Environments whose steps go through the shield teacher (the first ones), as a count and a mask.
        self.teacher_count = max(1, round(config.shield_teacher * config.num_envs)) if config.shield_teacher else 0
        self._teacher_envs = jnp.arange(config.num_envs) < self.teacher_count
        self.iteration = jax.jit(self._iteration, donate_argnums=0)  # the buffers are updated in place, not copied

    def place(self, state: TrainState) -> TrainState:
        """``state`` laid out over the devices: environments split, everything else replicated,
        every leaf its own buffer (``iteration`` donates the state it is given)."""
        seen = set()

        def own_buffer(x):
            buffers = tuple(shard.data.unsafe_buffer_pointer() for shard in x.addressable_shards)
            if seen.intersection(buffers):
                return jnp.copy(x)
            seen.update(buffers)
            return x

        return jax.tree.map(own_buffer, jax.device_put(state, self._shardings(state)))

    def _shardings(self, state: TrainState):
        replicated, split = NamedSharding(self.mesh, PartitionSpec()), NamedSharding(self.mesh, PartitionSpec("data"))
        shardings = jax.tree.map(lambda _: replicated, state)
        return shardings.replace(envs=shardings.envs.replace(env=jax.tree.map(lambda _: split, state.envs.env)))

    def init(self, key) -> TrainState:
        """A fresh run: networks, environments at curriculum level ``start_level``, empty buffer."""
        agent_key, env_key, key = jax.random.split(key, 3)
        config = self.config
        curriculum = GroupedCurriculum.start(config.num_envs, int(self.team_group.max()) + 1, config.start_level)
        tolerance = self._tolerances(curriculum) if config.curriculum else jnp.asarray(self.env.config.tolerance, jnp.float32)
        envs = jax.jit(self.autoreset.reset, static_argnums=1)(env_key, config.num_envs, tolerance)
        buffer = ReplayBuffer.create(config.buffer_size, self.env.max_arms)
        expert_buffer = ReplayBuffer.create(config.expert_buffer, self.env.max_arms) if config.expert_share else None
        zero = jnp.zeros((), jnp.int32)
        state = TrainState(create_agent(agent_key, config.sac), envs, buffer, expert_buffer, curriculum,
                           Queue.create(config.failed_queue), self._collision_queue(), key, zero, zero)
        return self.place(state)

    def _collision_queue(self) -> Queue | None:
        if not self.config.relabel:
            return None
        return Queue.create(self.config.relabel_queue, (jnp.zeros((), jnp.int32), jnp.zeros((self.env.max_arms, 6), jnp.float32)))

    def _rollout(self, state: TrainState, key) -> tuple[TrainState, dict]:
        config = self.config

        def one_step(carry, step_key):
            state = carry
            envs = state.envs
            actions, _ = state.agent.policy()(envs.env.obs, envs.env.obs_mask, step_key, self.std_scale(state))
            actions, shielded = self._shielded(envs.env, actions)
            envs, stepped = self.autoreset.step(envs, actions)
            buffer, expert_buffer = state.buffer, state.expert_buffer
            if not config.bc:
                transitions, valid = arm_transitions(state.envs.env.obs, state.envs.env.obs_mask, actions, stepped, expert=shielded)
                buffer = buffer.insert(transitions, valid)
                if config.shield_teacher and config.expert_share:  # the teacher's motions are demonstrations too
                    expert_buffer = expert_buffer.insert(transitions, valid & shielded.reshape(-1))
            ended = stepped.done
            failed = state.failed
            if config.expert:
                rows = stepped.task.task_id
                failed = failed.push(ended & ~stepped.success & (self.demos.lengths[rows] > 0), rows)
            collisions = state.collisions
            if config.relabel:
                collisions = collisions.push(stepped.collided.any(-1), (stepped.task.task_id, state.envs.env.joints))
            curriculum = state.curriculum
            if config.curriculum:  # shielded episodes are the teacher's: they do not count toward graduation
                group = jnp.asarray(self.team_group)[stepped.task.active.sum(-1) - 1]
                curriculum = curriculum.record(ended & ~self._teacher_envs, stepped.success, group)
                envs = envs.replace(tolerance=self._tolerances(curriculum))
            active = stepped.task.active.sum(-1)
            trajectory = (state.envs.env, actions, stepped) if config.hindsight else None
            state = state.replace(envs=envs, buffer=buffer, expert_buffer=expert_buffer, failed=failed, collisions=collisions,
                                  curriculum=curriculum, env_steps=state.env_steps + config.num_envs)
            return state, ({"ended": ended.sum(), "successes": (ended & stepped.success).sum(), "arm_steps": active.sum(),
                            "shielded_arm_steps": shielded.sum()}, trajectory)

        state, (stats, trajectory) = jax.lax.scan(one_step, state, jax.random.split(key, config.rollout_steps))
        if config.hindsight:
            transitions, valid = hindsight_transitions(self.env, *trajectory, config.hindsight, jax.random.fold_in(key, 1))
            state = state.replace(buffer=state.buffer.insert(transitions, valid))
        return state, jax.tree.map(jnp.sum, stats)

    def _shielded(self, envs: State, actions) -> tuple[jnp.ndarray, jnp.ndarray]:
        """The actions [B, A, 6] executed and which arms the shield teacher replaced [B, A]:
        in the first ``shield_teacher`` share of the environments every team step goes
        through safe execution (:mod:`mjx_multiarm.env.shield`), and an arm whose motion it
        replaced (stepped away or held) executes the replacement, as an action."""
        none = jnp.zeros(actions.shape[:-1], bool)
        if not self.config.shield_teacher:
            return actions, none
        n = self.teacher_count
        env, teacher = self.env, jax.tree.map(lambda x: x[:n], envs)
        proposed = env.next_joints(teacher.joints, actions[:n], teacher.task.active)
        task = teacher.task
        executed, motion, _ = jax.vmap(env.shield)(task.base_pos, task.base_quat, teacher.joints, proposed, task.active)
        replaced = (motion != PROPOSED) & task.active & ~teacher.done[:, None]
        replacement = (executed - teacher.joints) / env.action_scale
        return actions.at[:n].set(jnp.where(replaced[..., None], replacement, actions[:n])), none.at[:n].set(replaced)

    def _expert_replays(self, state: TrainState) -> TrainState:
        failed, rows, valid_task = state.failed.pop(self.config.expert_replays)
        return self._replay(state, rows, valid_task).replace(failed=failed)

    def prefill(self, state: TrainState, count: int, seed: int = 0, chunk: int = 64) -> TrainState:
        """``state`` with the experts of ``count`` bank tasks (drawn without replacement among
        those with an expert) replayed into the buffer that holds expert transitions: a
        stock of demonstrations before the first iteration (e.g. for a behaviour-cloned start)."""
        if self.demos is None:
            raise ValueError("prefilling needs expert demonstrations")
        solved = np.flatnonzero(np.asarray(self.demos.lengths) > 0)
        if count > len(solved):
            raise ValueError(f"cannot prefill {count} expert demonstrations: the task bank has {len(solved)}")
        rows = np.random.default_rng(seed).choice(solved, count, replace=False)
        target = state.expert_buffer if self.config.expert_share else state.buffer
        chunk = max(1, min(chunk, target.capacity // (self.demos.max_steps * self.env.max_arms)))
        padded = np.resize(rows, -(-count // chunk) * chunk).reshape(-1, chunk)
        valid = (np.arange(padded.size) < count).reshape(padded.shape)

        @jax.jit
        def run(state, rows, valid):
            return jax.lax.scan(lambda s, x: (self._replay(s, *x), None), state, (rows, valid))[0]

        return run(state, jnp.asarray(padded, jnp.int32), jnp.asarray(valid))

    def _replay(self, state: TrainState, rows, valid_task) -> TrainState:
        """``state`` with the experts of bank rows ``rows`` [R] (where ``valid_task``) replayed
        from their start and their transitions stored."""
        actions, lengths = self.demos.take(rows)
        return self._replay_actions(state, self.bank.take(rows), actions, jnp.where(valid_task, lengths, 0))

    def _replay_actions(self, state: TrainState, tasks, actions, lengths) -> TrainState:
        """``state`` with ``actions`` [R, T, A, 6] (the first ``lengths`` [R] steps) replayed from
        the start of ``tasks`` [R] and their transitions stored as expert transitions."""
        tolerance = state.envs.tolerance[tasks.active.sum(-1) - 1]
        start = jax.vmap(lambda task, tol: self.env.reset(None, task, tol))(tasks, tolerance)
        states, valid = jax.vmap(lambda s, a, n: replay_actions(self.env, s, a, n))(start, actions, lengths)
        before_obs = jnp.concatenate([start.obs[:, None], states.obs[:, :-1]], axis=1)
        before_mask = jnp.concatenate([start.obs_mask[:, None], states.obs_mask[:, :-1]], axis=1)
        transitions, arm_valid = arm_transitions(before_obs, before_mask, actions, states, expert=True)
        arm_valid = arm_valid & jnp.repeat(valid.reshape(-1), self.env.max_arms)
        if self.config.expert_share:
            state = state.replace(expert_buffer=state.expert_buffer.insert(transitions, arm_valid))
        else:
            state = state.replace(buffer=state.buffer.insert(transitions, arm_valid))
        return state.replace(expert_steps=state.expert_steps + valid.sum().astype(jnp.int32))

    def _tolerances(self, curriculum: GroupedCurriculum) -> jnp.ndarray:
        """[max_arms, 2] reset tolerances by team size at the curriculum's levels."""
        return curriculum.tolerance[jnp.asarray(self.team_group)]

    def level(self, curriculum: GroupedCurriculum) -> jnp.ndarray:
        """The lowest level among the groups the bank's tasks use (the run's progress)."""
        return jnp.min(curriculum.level[jnp.asarray(self.groups_used)])

    def std_scale(self, state: TrainState) -> jnp.ndarray:
        """The policy's noise bound at the current curriculum level (1 without a schedule)."""
        if not self.config.noise_decay:
            return jnp.ones((), jnp.float32)
        return (jnp.asarray(LEVELS)[self.level(state.curriculum), 0] / LEVELS[0, 0]) ** self.config.noise_decay

    def _sample(self, state: TrainState, key, updates) -> Transitions:
        """A training batch: uniform from the buffer, or with ``expert_share`` that fraction
        drawn from the expert buffer (from the main buffer while the expert buffer is empty);
        during a behaviour-cloned start (``updates`` < ``bc_start``) all of it."""
        config = self.config
        if not config.expert_share:
            return state.buffer.sample(key, config.batch_size)
        expert_rows = round(config.expert_share * config.batch_size)
        if config.sac.bc_start:
            expert_rows = jnp.where(updates < config.sac.bc_start, config.batch_size, expert_rows)
        main_key, expert_key, fallback_key = jax.random.split(key, 3)
        expert = jax.lax.cond(state.expert_buffer.size > 0, lambda: state.expert_buffer.sample(expert_key, config.batch_size),
                              lambda: state.buffer.sample(fallback_key, config.batch_size))
        from_expert = jnp.arange(config.batch_size) >= config.batch_size - expert_rows
        main = state.buffer.sample(main_key, config.batch_size)
        return jax.tree.map(lambda m, e: jnp.where(from_expert.reshape(-1, *(1,) * (m.ndim - 1)), e, m), main, expert)

    def _updates(self, state: TrainState, key) -> tuple[TrainState, dict]:
        config = self.config
        std_scale = self.std_scale(state)

        def update(agent, update_key):
            sample_key, sac_key = jax.random.split(update_key)
            batch = self._sample(state, sample_key, agent.updates)
            batch = jax.lax.with_sharding_constraint(batch, NamedSharding(self.mesh, PartitionSpec("data")))
            if config.bc:
                return bc_update(agent, batch, config.sac)
            return sac_update(agent, batch, sac_key, config.sac, std_scale)

        def run(agent):
            agent, metrics = jax.lax.scan(update, agent, jax.random.split(key, config.updates_per_iteration))
            return agent, jax.tree.map(jnp.mean, metrics)

        shapes = jax.eval_shape(run, state.agent)[1]
        skip = lambda agent: (agent, jax.tree.map(lambda s: jnp.full(s.shape, jnp.nan, s.dtype), shapes))  # noqa: E731
        agent, metrics = jax.lax.cond(state.buffer.size >= config.warmup, run, skip, state.agent)
        return state.replace(agent=agent), metrics

    def _iteration(self, state: TrainState, relabelled: Relabelled | None = None) -> tuple[TrainState, dict]:
        rng, rollout_key, update_key = jax.random.split(state.rng, 3)
        state, rollout = self._rollout(state.replace(rng=rng), rollout_key)
        if self.config.expert:
            state = self._expert_replays(state)
        if relabelled is not None:
            tasks = self.bank.take(relabelled.rows).replace(start_joints=relabelled.start)
            state = self._replay_actions(state, tasks, relabelled.actions, relabelled.lengths)
        state, learning = self._updates(state, update_key)
        state = jax.lax.with_sharding_constraint(state, self._shardings(state))
        groups = jnp.asarray(self.groups_used)
        per_team = {}
        if self.config.curriculum_by_team:
            per_team = {name: value for team in self.teams for name, value in
                        ((f"level_{team}", state.curriculum.level[team - 1]), (f"window_success_{team}", state.curriculum.success_rate[team - 1]))}
        return state, {**rollout, **learning, "level": self.level(state.curriculum),
                       "window_success": jnp.mean(state.curriculum.success_rate[groups]), **per_team,
                       "buffer": state.buffer.size, "queued_failures": state.failed.count,
                       **({"queued_collisions": state.collisions.count} if self.config.relabel else {})}
