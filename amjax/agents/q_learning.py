"""What Dueling DQN (dqn.py) and DRQN (drqn.py) share: their base config, the epsilon schedule and epsilon-greedy
action, the optimiser, n-step double-Q targets and the target-network update. PQN and recurrent PQN (pqn.py,
pqn_rnn.py) take from here the epsilon schedule, the epsilon-greedy action, their Q(lambda) targets and the greedy
policies (feed-forward: Dueling DQN's; recurrent: DRQN's acting and test policies).

Both algorithms are siblings of `QLearningConfig`: each adds only its own fields (DRQN: the sequence length, burn-in
and recurrent core) and its own defaults.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, ClassVar

import jax
import jax.numpy as jnp
import optax
from flax import struct

from amjax import strategy
from amjax.agents.config import AgentConfig, static
from amjax.agents.networks import VECTOR_TORSO, RecurrentQNetwork, Torso, check_activation, zero_carry
from amjax.agents.optim import clipped_adam
from amjax.agents.rollout import EnvBatch, Transition
from amjax.agents.setup import Setup
from amjax.agents.training import Policy, greedy_policy
from amjax.batching import uniform_cond, update_where
from amjax.validation import check_positive_int


@struct.dataclass
class QLearningConfig(AgentConfig):
    """Fields of every Q-learning agent (defaults: Dueling DQN's)."""

    num_envs: int = static(1)
    buffer_size: int = static(100_000)  # transitions (DRQN: sequences)
    batch_size: int = static(64)  # transitions (DRQN: sequences) per gradient step
    learning_starts: int = static(1_000)  # env steps taken before the first gradient step
    train_freq: int = static(4)  # steps per env between gradient phases
    gradient_steps: int = static(1)
    target_update_interval: int = static(2_000)  # env steps between target updates
    hidden: Sequence[int] = static((64, 64))
    activation: str = static("relu")
    dueling: bool = static(True)
    double_q: bool = static(True)
    n_step: int = static(10)  # multi-step returns (1 = one-step); see dqn.py
    anneal_lr: bool = static(True)  # linear decay of the learning rate to 0 over training
    learning_rate: float = 1e-3
    gamma: float = 0.99
    tau: float = 1.0  # target update rate (1 = hard copy)
    epsilon_start: float = 1.0
    epsilon_end: float = 0.05
    exploration_fraction: float = 0.3  # fraction of training over which epsilon decays linearly
    max_grad_norm: float = 10.0
    reward_scale: float = 1.0  # rewards (measurement costs included) are stored multiplied by this

    WIDTH_FIELDS: ClassVar[tuple[str, ...]] = ("hidden",)
    TRACED_BOUNDS: ClassVar[dict[str, str]] = {
        "learning_rate": "positive",
        "gamma": "unit",
        "tau": "unit",
        "epsilon_start": "unit",
        "epsilon_end": "unit",
        "exploration_fraction": "unit",
        "max_grad_norm": "positive",
        "reward_scale": "positive",
    }

    def steps_per_update(self) -> int:
        return self.num_envs * self.train_freq

    def check_fields(self) -> None:
        for name in (
            "num_envs",
            "buffer_size",
            "batch_size",
            "train_freq",
            "gradient_steps",
            "target_update_interval",
            "n_step",
        ):
            check_positive_int(name, getattr(self, name))
        check_positive_int("learning_starts", self.learning_starts, minimum=0)
        check_activation(self.activation)
        super().check_fields()


def make_optimizer(config: QLearningConfig) -> optax.GradientTransformation:
    num_updates = config.total_timesteps // config.steps_per_update()
    return clipped_adam(
        config.learning_rate,
        config.max_grad_norm,
        total_steps=num_updates * config.gradient_steps,
        anneal=config.anneal_lr,
    )


def epsilon(config: QLearningConfig, env_steps: jax.Array) -> jax.Array:
    """Linear decay from epsilon_start to epsilon_end over exploration_fraction of training."""
    decay_steps = jnp.maximum(config.exploration_fraction * config.total_timesteps, 1.0)
    progress = jnp.minimum(env_steps / decay_steps, 1.0)
    return config.epsilon_start + progress * (config.epsilon_end - config.epsilon_start)


def epsilon_greedy(q: jax.Array, key: jax.Array, eps: jax.Array) -> jax.Array:
    """argmax_a q[..., a], or with probability `eps` a uniformly random action."""
    explore_key, random_key = jax.random.split(key)
    greedy_action = jnp.argmax(q, -1)
    random_action = jax.random.randint(random_key, greedy_action.shape, 0, q.shape[-1])
    explore = jax.random.uniform(explore_key, greedy_action.shape) < eps
    return jnp.where(explore, random_action, greedy_action)


def greedy(config: AgentConfig, setup: Setup, params: Any, num_envs: int) -> Policy:
    """The test policy of a feed-forward Q-network (Dueling DQN, PQN): argmax_a Q(obs, a)."""
    return greedy_policy(lambda obs: setup.network.apply(params, obs))


def recurrent_q_network(
    config: AgentConfig, action_space: Any, torso: Torso = VECTOR_TORSO, layer_norm: bool = False
) -> RecurrentQNetwork:
    """The recurrent Q-network of a config with DRQN's network fields (`hidden`, `rnn_size`, `cell`, `activation`,
    `dueling`) for `action_space`."""
    return RecurrentQNetwork(
        action_space.n,
        tuple(config.hidden),
        config.rnn_size,
        config.cell,
        config.activation,
        config.dueling,
        config.factored_masks,
        torso,
        layer_norm=layer_norm,
    )


def epsilon_greedy_act(setup: Setup, params: Any, eps: jax.Array, greedy_values: bool = False) -> Callable:
    """The epsilon-greedy act function of a feed-forward Q-network (Dueling DQN, PQN), for `rollout`; with
    `greedy_values`, its extras are max_a Q(obs, a) of the observations it acted on (PQN's `bootstrap_values`)."""

    def act(batch: EnvBatch, carry: Any, key: jax.Array):
        q = setup.network.apply(params, batch.obs)
        return epsilon_greedy(q, key, eps), carry, q.max(-1) if greedy_values else None

    return act


def recurrent_epsilon_greedy(setup: Setup, params: Any, eps: jax.Array) -> Callable:
    """The epsilon-greedy act function of a recurrent Q-network (DRQN, recurrent PQN), carrying its hidden state;
    its extras are the hidden state before each step and the step's `first` flag (what a learner re-unrolls from)."""

    def act(batch: EnvBatch, carry: Any, key: jax.Array):
        new_carry, q = setup.network.apply(params, carry, batch.obs, batch.first)
        return epsilon_greedy(q, key, eps), new_carry, (carry, batch.first)

    return act


def recurrent_greedy(config: AgentConfig, setup: Setup, params: Any, num_envs: int) -> tuple[Callable, Any]:
    """The test policy of a recurrent Q-network (config fields `cell`, `rnn_size`): the greedy action, carrying the
    hidden state; and a zero hidden state for `num_envs` test envs."""
    act = recurrent_epsilon_greedy(setup, params, jnp.float32(0.0))

    def greedy_act(batch: EnvBatch, carry: Any, key: jax.Array):
        action, carry, _ = act(batch, carry, key)
        return action, carry, None

    return greedy_act, zero_carry(config.cell, config.rnn_size, (num_envs,))


def transition_arrays(config: QLearningConfig, transitions: Transition) -> dict[str, jax.Array]:
    """The arrays of `transitions` that replay stores, rewards multiplied by `config.reward_scale` (exact at 1)."""
    return {
        "obs": transitions.obs,
        "action": transitions.action,
        "reward": config.reward_scale * transitions.reward,
        "next_obs": transitions.next_obs,
        "terminated": transitions.terminated.astype(jnp.float32),
        "done": transitions.done.astype(jnp.float32),
    }


def n_step_transitions(window: dict[str, jax.Array], n: int, gamma: jax.Array) -> dict[str, jax.Array]:
    """n-step transitions from a [T + n - 1, num_envs] window of one-step transitions, for its first T steps.

    reward = sum_{k<m} gamma^k r_{t+k}, where m <= n stops after the first episode end; next_obs = the pre-reset
    observation after step t+m-1; discount = gamma^m (1 - terminated_{t+m-1}) multiplies the bootstrap value.
    """
    T = window["reward"].shape[0] - (n - 1)
    reward = jnp.zeros_like(window["reward"][:T])
    next_obs = window["next_obs"][:T]
    discount = jnp.zeros_like(reward)
    alive = jnp.ones_like(reward)  # no episode end yet inside the window
    scale = jnp.ones_like(reward)  # gamma^k
    for k in range(n):  # n is static and small
        reward = reward + alive * scale * window["reward"][k : k + T]
        scale = scale * gamma
        keep = (alive > 0).reshape(alive.shape + (1,) * (next_obs.ndim - alive.ndim))  # over the obs's axes
        next_obs = jnp.where(keep, window["next_obs"][k : k + T], next_obs)
        discount = jnp.where(alive > 0, scale * (1.0 - window["terminated"][k : k + T]), discount)
        alive = alive * (1.0 - window["done"][k : k + T])
    return {
        "obs": window["obs"][:T],
        "action": window["action"][:T],
        "reward": reward,
        "next_obs": next_obs,
        "discount": discount,
    }


def td_targets(
    q_next_online: jax.Array,
    q_next_target: jax.Array,
    reward: jax.Array,
    discount: jax.Array,
    double_q: bool = True,
) -> jax.Array:
    """reward + discount * Q_target(s', a*), a* = argmax_a Q_online(s', a) (double) or argmax Q_target(s', a).

    For one-step DQN, discount = gamma (1 - terminated); for n-step, see `n_step_transitions`."""
    chooser = q_next_online if double_q else q_next_target
    best = jnp.argmax(chooser, axis=-1)
    bootstrap = jnp.take_along_axis(q_next_target, best[..., None], -1)[..., 0]
    return reward + discount * bootstrap


def q_lambda_targets(
    reward: jax.Array,
    terminated: jax.Array,
    done: jax.Array,
    next_q: jax.Array,
    gamma: jax.Array,
    q_lambda: jax.Array,
) -> jax.Array:
    """Q(lambda) targets of a time-major rollout [T, ...]: with c_t = 0 where the episode ends at step t (`done`) or
    t is the rollout's last step, else `q_lambda`,

        G_t = r_t + gamma (1 - terminated_t) ((1 - c_t) next_q_t + c_t G_{t+1}),

    where `next_q` is max_a Q(s'_t, a) of the pre-reset next observation. That is the lambda-weighted mix of the
    n-step returns that stay inside the episode and the rollout (Watkins / Peng-style, without trace cutting)."""
    last = jnp.zeros_like(done, dtype=bool).at[-1].set(True)
    carries = jnp.where(jnp.logical_or(done, last), 0.0, q_lambda)

    def backward(later_return, step):
        r, term, q, c = step
        target = r + gamma * (1.0 - term) * ((1.0 - c) * q + c * later_return)
        return target, target

    _, targets = jax.lax.scan(
        backward, jnp.zeros_like(reward[0]), (reward, terminated.astype(reward.dtype), next_q, carries), reverse=True
    )
    return targets


def bootstrap_values(
    value_fn: Callable[[Any, jax.Array], jax.Array], params: Any, acted_values: jax.Array, transitions: Transition
) -> jax.Array:
    """`value_fn(params, obs)` of each step's pre-reset next observation, [T, num_envs], from a rollout whose act
    function kept `acted_values`, the values of the observations it acted on (`epsilon_greedy_act` with
    `greedy_values=True`).

    Where an episode goes on, step t's next observation is the one acted on at t + 1, so its value is already there;
    where it terminated, the value is not used (no bootstrap). Two passes of `num_envs` rows remain: the last step's
    next observations, and the truncations' pre-reset observations, gathered (a time limit of at least T steps
    allows one per env). A rollout with more truncations than envs (short time limits) takes one pass over every
    next observation instead (a branch, `uniform_cond`). Under the "gpu" strategy, where a branch reads its
    predicate back to the host, it is that one pass, as before. Each value is `value_fn`'s of that observation
    whichever way it comes (to float rounding)."""

    def every(params: Any, truncated: jax.Array, acted_values: jax.Array, next_obs: jax.Array) -> jax.Array:
        return value_fn(params, next_obs)

    def gathered(params: Any, truncated: jax.Array, acted_values: jax.Array, next_obs: jax.Array) -> jax.Array:
        later = jnp.concatenate([acted_values[1:], value_fn(params, next_obs[-1])[None]])
        flat = truncated.reshape(-1)
        rows = jnp.nonzero(flat, size=truncated.shape[-1], fill_value=flat.size)[0]  # padding: past the end
        obs = next_obs.reshape(-1, *next_obs.shape[2:]).at[rows].get(mode="fill", fill_value=0)
        fresh = value_fn(params, obs)
        return later.reshape(-1).at[rows].set(fresh, mode="drop").reshape(later.shape)  # the padding dropped

    truncated = jnp.logical_and(transitions.done, jnp.logical_not(transitions.terminated))
    operands = (params, truncated, acted_values, transitions.next_obs)
    if strategy.is_gpu():
        return every(*operands)
    return uniform_cond(truncated.sum() > truncated.shape[-1], every, gathered, *operands)


def learn_or_wait(
    learning: jax.Array, learn: Any, params: Any, opt_state: Any, *args: Any
) -> tuple[Any, Any, jax.Array]:
    """`learn(params, opt_state, *args) -> (params, opt_state, loss)` once learning has started; before, `params`
    and `opt_state` unchanged and a zero loss. A real branch in a vmapped sweep, also on a GPU (`update_where`:
    every configuration of a batch starts learning at the same step), that updates them in place: a select would
    run the gradient steps before learning starts too (40% of the updates of a 2,500-step run; docs/gpu.md)."""

    def learn_state(state: tuple[Any, Any, jax.Array], *args: Any) -> tuple[Any, Any, jax.Array]:
        params, opt_state, _ = state
        return learn(params, opt_state, *args)

    return update_where(learning, learn_state, (params, opt_state, jnp.float32(0.0)), *args)


def target_sync(
    config: QLearningConfig, learning: jax.Array, env_steps: jax.Array, new_env_steps: jax.Array
) -> jax.Array:
    """Whether the target network changes in the update from `env_steps` to `new_env_steps`: each time
    `target_update_interval` env steps have passed, once learning has started (`update_target`'s predicate)."""
    interval = config.target_update_interval
    return learning & (new_env_steps // interval != env_steps // interval)


def update_target(config: QLearningConfig, sync: jax.Array, params: Any, target_params: Any) -> Any:
    """The target network, blended with rate tau where `sync` (`target_sync`); a branch in a vmapped sweep too,
    updated in place (`update_where`), as a plain implementation with one step counter does."""
    return update_where(
        sync,
        lambda target, tau, params: optax.incremental_update(params, target, tau),
        target_params,
        config.tau,
        params,
    )
