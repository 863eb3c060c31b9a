"""Soft Actor-Critic updates of the shared decentralized actor-critic, as pure functions.

The networks (:mod:`models.networks`) are Flax NNX modules; their parameters live in an
:class:`Agent` pytree (with optimizer states and target critics) and the modules are
rebuilt inside jitted functions with ``nnx.merge``, so a whole update is one compiled
function. The original's choices are the default: fixed entropy temperature 0.001, the
bounded-variance Gaussian without tanh squashing; ``squash=True, learn_alpha=True`` gives
standard SAC (tanh-squashed samples, temperature tuned to a target entropy of -6).
``expert_bc > 0`` adds a Q-filtered behaviour-cloning term on the buffer's expert
transitions to the actor loss (:func:`expert_bc_loss`; ``expert_bc_filter=False`` drops the
filter). ``components`` = K > 1 makes the actor a mixture of K Gaussians: its loss is the
exact expectation over the components (one reparameterized sample of each, weighted by the
mixture weights), and cloning an action is winner-takes-all (:func:`cloning_error`).
``bc_start`` = N > 0 gives a
behaviour-cloned start: for the first N updates the actor step regresses the mean action
onto the batch's expert actions (the critics learn as usual meanwhile, so SAC takes over
from a cloned actor with a critic of it). ``actor_freeze`` = N > 0 leaves the actor and its
optimizer unchanged for the first N updates while the critics learn (the critic warm-up of
a fine-tune, :mod:`train.finetune`). ``policy_average > 0`` keeps a Polyak
average of the actor's parameters (``Agent.average_actor``), the policy that evaluation and
exported policy files use; 0 deploys the latest actor, as the original.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import optax
from flax import nnx, struct

from mjx_multiarm.env.observation import InputFeatures
from mjx_multiarm.geometry.robot import NUM_JOINTS
from mjx_multiarm.options import option
from models.networks import Actor, Mixture, TwinCritic
from train.replay import Transitions


#: Share of a mixture's cloning error carried by the components that are not the nearest
#: to the target action (relaxed winner-takes-all, :func:`cloning_error`).
LOSER_SHARE = 0.1


@dataclasses.dataclass(frozen=True)
class SACConfig:
    """SAC hyperparameters (defaults: the paper's appendix and the original code)."""

    actor_lr: float = option(5e-4, "actor learning rate")
    critic_lr: float = option(1e-3, "critic learning rate")
    gamma: float = option(0.99, "discount factor")
    tau: float = option(1e-3, "Polyak rate of the target critics")
    alpha: float = option(1e-3, "entropy temperature (fixed, or the initial value of a learned one)")
    learn_alpha: bool = option(False, "learn the temperature toward --target-entropy (standard SAC)")
    squash: bool = option(False, "tanh-squashed samples (standard SAC) instead of the original's bounded-variance Gaussian")
    alpha_lr: float = option(3e-4, "learning rate of a learned temperature")
    target_entropy: float = option(-float(NUM_JOINTS), "target policy entropy of a learned temperature")
    bc_lr: float = option(1e-3, "learning rate of the behaviour-cloning ablation")
    expert_bc: float = option(0.0, "weight of a behaviour-cloning term on the expert transitions in the actor loss, applied "
                                   "where the critic rates the expert's action above the policy's (Nair et al. 2018; 0: the "
                                   "original's pure SAC)")
    expert_bc_filter: bool = option(True, "apply the expert behaviour-cloning term only where the critic rates the "
                                          "expert's action above the policy's (0: on every expert transition)")
    policy_average: float = option(0.0, "deploy (evaluate and export) a Polyak average of the actor's parameters, updated at "
                                        "this rate per gradient update (0: the latest actor, as the original)")
    inputs: InputFeatures = InputFeatures()
    bc_start: int = option(0, "the first N updates train the actor by cloning the batch's expert transitions (the critics "
                              "learn meanwhile), then SAC takes over (0: none)")
    actor_freeze: int = option(0, "the first N updates leave the actor as it is while the critics learn (the critic warm-up "
                                  "of a fine-tune, --init; 0: none)")
    components: int = option(1, "mixture components of the actor's action distribution (1: the original's Gaussian; a "
                                "one-component --init policy is widened into a mixture of copies of itself)")
    widen_weight: float = option(0.0, "the weight of the first copy when --init widens a one-component policy into "
                                      "--components copies (0: equal weights)")

    def __post_init__(self):
        for name in ("actor_lr", "critic_lr", "alpha", "alpha_lr", "bc_lr"):
            if not getattr(self, name) > 0:
                raise ValueError(f"SACConfig.{name} must be > 0, got {getattr(self, name)}")
        if not 0 < self.gamma <= 1:
            raise ValueError(f"SACConfig.gamma must be in (0, 1], got {self.gamma}")
        if not 0 < self.tau <= 1:
            raise ValueError(f"SACConfig.tau must be in (0, 1], got {self.tau}")
        if self.expert_bc < 0:
            raise ValueError(f"SACConfig.expert_bc must be >= 0, got {self.expert_bc}")
        if not 0 <= self.policy_average <= 1:
            raise ValueError(f"SACConfig.policy_average must be in [0, 1], got {self.policy_average}")
        for name in ("bc_start", "actor_freeze"):
            if getattr(self, name) < 0:
                raise ValueError(f"SACConfig.{name} must be >= 0, got {getattr(self, name)}")
        if self.components < 1:
            raise ValueError(f"SACConfig.components must be >= 1, got {self.components}")
        if not 0 <= self.widen_weight < 1:
            raise ValueError(f"SACConfig.widen_weight must be in [0, 1), got {self.widen_weight}")


@struct.dataclass
class Agent:
    """Parameters, target critics and optimizer states; the graph definitions are static."""

    actor: nnx.State
    average_actor: nnx.State  # the deployed policy's parameters (SACConfig.policy_average)
    critic: nnx.State
    target_critic: nnx.State
    actor_opt: optax.OptState
    critic_opt: optax.OptState
    log_alpha: jnp.ndarray
    alpha_opt: optax.OptState
    updates: jnp.ndarray
    actor_def: nnx.GraphDef = struct.field(pytree_node=False)
    critic_def: nnx.GraphDef = struct.field(pytree_node=False)

    def policy(self) -> Actor:
        """The actor module with this agent's parameters."""
        return nnx.merge(self.actor_def, self.actor)

    def with_actor(self, actor: nnx.State, config: SACConfig) -> Agent:
        """This agent with updated actor parameters, its average following them."""
        average = optax.incremental_update(actor, self.average_actor, config.policy_average) if config.policy_average else actor
        return self.replace(actor=actor, average_actor=average)

    def critics(self) -> TwinCritic:
        return nnx.merge(self.critic_def, self.critic)


def _optimizers(config: SACConfig):
    return optax.adam(config.actor_lr), optax.adam(config.critic_lr), optax.adam(config.alpha_lr)


def create_agent(key, config: SACConfig = SACConfig()) -> Agent:
    """Freshly initialized networks (weights as the original) and optimizers."""
    actor_key, critic_key = jax.random.split(key)
    actor_def, actor = nnx.split(Actor(nnx.Rngs(actor_key), config.inputs, NUM_JOINTS, config.squash, config.components))
    critic_def, critic = nnx.split(TwinCritic(nnx.Rngs(critic_key), config.inputs, NUM_JOINTS))
    actor_opt, critic_opt, alpha_opt = _optimizers(config)
    log_alpha = jnp.asarray(math.log(config.alpha), jnp.float32)
    return Agent(actor, actor, critic, critic, actor_opt.init(actor), critic_opt.init(critic), log_alpha,
                 alpha_opt.init(log_alpha), jnp.zeros((), jnp.int32), actor_def, critic_def)


def agent_from_parameters(key, config: SACConfig, actor: nnx.State, critic: nnx.State | None = None) -> Agent:
    """An agent whose actor (and its average) start from ``actor`` and whose critics (and
    target critics) start from ``critic`` (fresh where None), with fresh optimizers: the
    start of a fine-tune."""
    agent = create_agent(key, config)
    critic = agent.critic if critic is None else critic
    actor_opt, critic_opt, _ = _optimizers(config)
    return agent.replace(actor=actor, average_actor=actor, critic=critic, target_critic=critic, actor_opt=actor_opt.init(actor),
                         critic_opt=critic_opt.init(critic))


def td_target(agent: Agent, batch: Transitions, key, config: SACConfig = SACConfig(), std_scale=1.0) -> jnp.ndarray:
    """Soft TD target [N]: r + gamma (1 - terminal) (min target Q(s', a') - alpha log pi(a'|s'))."""
    next_action, next_log_prob = agent.policy()(batch.next_obs, batch.next_mask, key, std_scale)
    target_q = jnp.minimum(*nnx.merge(agent.critic_def, agent.target_critic)(batch.next_obs, batch.next_mask, next_action))
    continuing = 1.0 - batch.terminal.astype(jnp.float32)
    return jax.lax.stop_gradient(batch.reward + config.gamma * continuing * (target_q - jnp.exp(agent.log_alpha) * next_log_prob))


def critic_loss(agent: Agent, critic: nnx.State, batch: Transitions, target) -> tuple[jnp.ndarray, tuple]:
    """(twin-critic TD loss of parameters ``critic`` against ``target``, (q1, q2, encodings)):
    the critics' encodings of ``batch.obs`` come back so that the actor loss, which values
    its own actions with the same critics, does not encode the observations again."""
    critics = nnx.merge(agent.critic_def, critic)
    encodings = critics.encode(batch.obs, batch.mask)
    q1, q2 = critics.values(encodings, batch.action)
    return jnp.mean((q1 - target) ** 2) + jnp.mean((q2 - target) ** 2), (q1, q2, encodings)


def cloning_error(actor: Actor, dist: Mixture, target) -> jnp.ndarray:
    """How far the policy ``dist`` is from the actions ``target`` [N, 6], per row [N].

    One Gaussian: the squared error of its mean. A mixture: relaxed winner-takes-all, the
    squared error of the nearest component's mean (and :data:`LOSER_SHARE` of the other
    components', so that none drifts off unanchored) plus the cross-entropy of the weights
    against the nearest component, so the heaviest component, whose mean is the
    deterministic action, learns to be the one that imitates (a multimodal target is not
    averaged)."""
    errors = jnp.sum((actor.component_modes(dist) - target[..., None, :]) ** 2, axis=-1)  # [N, K]
    nearest = jax.nn.one_hot(jnp.argmin(errors, axis=-1), errors.shape[-1], dtype=errors.dtype)
    share = nearest if errors.shape[-1] == 1 else (1 - LOSER_SHARE) * nearest + LOSER_SHARE * (1 - nearest) / (errors.shape[-1] - 1)
    return jnp.sum(share * errors - nearest * dist.log_weights, axis=-1)


def expert_bc_loss(error, batch: Transitions, q_data, q_policy, filtered: bool = True) -> tuple[jnp.ndarray, jnp.ndarray]:
    """(behaviour-cloning loss, fraction of the batch it applies to), Q-filtered as Nair et
    al. 2018 ("Overcoming exploration in RL with demonstrations").

    The policy's :func:`cloning_error` ``error`` [N] against the stored actions counts on
    the batch's expert transitions where the critic values the expert's action above the
    policy's (``q_data`` > ``q_policy``, both [N]), so the policy imitates the expert only
    where the expert is still the better choice; ``filtered=False``: on every expert
    transition."""
    applies = batch.expert & (q_data > q_policy) if filtered else batch.expert
    return jnp.sum(jnp.where(applies, error, 0.0)) / jnp.maximum(applies.sum(), 1), jnp.mean(applies)


def sac_update(agent: Agent, batch: Transitions, key, config: SACConfig = SACConfig(), std_scale=1.0) -> tuple[Agent, dict]:
    """One gradient step of the critics, the actor (and the temperature if learned).

    ``std_scale``: the policy's noise bound at this point of training (see ``Actor``)."""
    next_key, actor_key = jax.random.split(key)
    alpha = jnp.exp(agent.log_alpha)
    target = td_target(agent, batch, next_key, config, std_scale)

    (c_loss, (q1, q2, encodings)), c_grads = jax.value_and_grad(lambda p: critic_loss(agent, p, batch, target), has_aux=True)(agent.critic)
    encodings = jax.lax.stop_gradient(encodings)  # the actor's gradient reaches the critics through the action only

    def actor_loss(params):
        actor = nnx.merge(agent.actor_def, params)
        dist = actor.distribution(batch.obs, batch.mask, std_scale)
        actions, log_probs = actor.component_samples(dist, actor_key)  # [N, K, 6], [N, K]
        per_action = tuple(jnp.broadcast_to(e[..., None, :], actions.shape[:-1] + e.shape[-1:]) for e in encodings)
        weights = jnp.exp(dist.log_weights)  # the expectation over components, exact
        q = jnp.sum(weights * jnp.minimum(*agent.critics().values(per_action, actions)), axis=-1)
        log_prob = jnp.sum(weights * log_probs, axis=-1)
        loss = jnp.mean(alpha * log_prob - q)
        bc, bc_share = jnp.zeros(()), jnp.zeros(())
        if config.expert_bc or config.bc_start:
            error = cloning_error(actor, dist, batch.action)
        if config.expert_bc:
            bc, bc_share = expert_bc_loss(error, batch, jnp.minimum(q1, q2), q, config.expert_bc_filter)
        loss = loss + config.expert_bc * bc
        if config.bc_start:  # behaviour-cloned start: imitate the batch's expert rows
            cloning = jnp.sum(jnp.where(batch.expert, error, 0.0)) / jnp.maximum(batch.expert.sum(), 1)
            loss = jnp.where(agent.updates < config.bc_start, cloning, loss)
        return loss, (log_prob, bc, bc_share)

    (a_loss, (log_prob, bc, bc_share)), a_grads = jax.value_and_grad(actor_loss, has_aux=True)(agent.actor)
    actor_opt, critic_opt, alpha_opt = _optimizers(config)
    c_updates, critic_state = critic_opt.update(c_grads, agent.critic_opt, agent.critic)
    a_updates, actor_state = actor_opt.update(a_grads, agent.actor_opt, agent.actor)
    critic = optax.apply_updates(agent.critic, c_updates)
    actor = optax.apply_updates(agent.actor, a_updates)
    if config.actor_freeze:  # critic warm-up: the actor and its optimizer stay as they are
        moves = agent.updates >= config.actor_freeze
        actor, actor_state = jax.tree.map(lambda new, old: jnp.where(moves, new, old), (actor, actor_state),
                                          (agent.actor, agent.actor_opt))
    log_alpha, alpha_state = agent.log_alpha, agent.alpha_opt
    if config.learn_alpha:
        entropy_gap = jax.lax.stop_gradient(jnp.mean(log_prob) + config.target_entropy)
        alpha_updates, alpha_state = alpha_opt.update(-entropy_gap, agent.alpha_opt, agent.log_alpha)
        log_alpha = optax.apply_updates(agent.log_alpha, alpha_updates)
    target_critic = optax.incremental_update(critic, agent.target_critic, config.tau)
    new = agent.with_actor(actor, config).replace(critic=critic, target_critic=target_critic, actor_opt=actor_state,
                        critic_opt=critic_state, log_alpha=log_alpha, alpha_opt=alpha_state, updates=agent.updates + 1)
    metrics = {"critic_loss": c_loss, "actor_loss": a_loss, "q": jnp.mean(q1), "entropy": -jnp.mean(log_prob), "alpha": alpha}
    if config.expert_bc:
        metrics |= {"expert_bc_loss": bc, "expert_bc_share": bc_share}
    return new, metrics


def bc_update(agent: Agent, batch: Transitions, config: SACConfig = SACConfig()) -> tuple[Agent, dict]:
    """Behaviour cloning (the paper's ablation): regress the actor's mean onto the actions
    (:func:`cloning_error`)."""

    def loss(params):
        actor = nnx.merge(agent.actor_def, params)
        return jnp.mean(cloning_error(actor, actor.distribution(batch.obs, batch.mask), batch.action))

    value, grads = jax.value_and_grad(loss)(agent.actor)
    optimizer = optax.adam(config.bc_lr)
    updates, state = optimizer.update(grads, agent.actor_opt, agent.actor)
    new = agent.with_actor(optax.apply_updates(agent.actor, updates), config)
    return new.replace(actor_opt=state, updates=agent.updates + 1), {"bc_loss": value}
