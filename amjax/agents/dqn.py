"""Dueling Double DQN (Wang et al. 2016; van Hasselt et al. 2016) with a uniform replay buffer in the state.

One `update`: `train_freq` epsilon-greedy steps of `num_envs` envs -> n-step transitions into the buffer ->
(once `learning_starts` steps are stored) `gradient_steps` Huber-loss steps on double-Q targets -> a (soft or
hard) target-network update whenever `target_update_interval` env steps have passed.

n-step returns carry the sparse signal of CartPole-like tasks, and the measurement cost, back n steps per update.
The default is 10 (Tianshou's and Rainbow's DQN use 3): without a measurement the agent sees a stale observation,
so the task is partially observable and one-step bootstrapping through those aliased observations misjudges what a
skipped measurement costs later. On CartPole-v0 under the active-measure wrapper (3 seeds x costs 0 and 0.2, 200k
steps) n_step=5 oscillated at cost 0 and at cost 0.2 mostly learned to measure too rarely (final median raw
returns 18-173); n_step=10 reached median 197-200 at both costs in each of the learning rates and exploration
fractions tried.
The last n-1 transitions of each env wait in the state until their n-step window is complete, so every stored
transition is exact; `init` fills that window with n-1 random steps per env (not counted as training steps).
`n_step=1` is ordinary DQN.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import jax
import jax.numpy as jnp
import optax
from flax import struct

from amjax.agents.config import AgentConfig, static
from amjax.agents.networks import DuelingQNetwork
from amjax.agents.optim import clipped_adam
from amjax.agents.replay import ReplayBuffer, replay_add, replay_init, replay_sample
from amjax.agents.rollout import EnvBatch, Transition, fast_key, key_bits, reset_envs, rollout
from amjax.agents.training import (
    Algorithm,
    EpisodeSums,
    UpdateStats,
    greedy_policy,
    make_train,
)
from amjax.batching import uniform_cond
from amjax.validation import check_choice, check_positive_int


@struct.dataclass
class DQNConfig(AgentConfig):
    num_envs: int = static(1)
    buffer_size: int = static(100_000)
    batch_size: int = static(64)
    learning_starts: int = static(1_000)  # env steps stored before the first gradient step
    train_freq: int = static(4)  # steps per env between gradient phases
    gradient_steps: int = static(1)
    target_update_interval: int = static(2_000)  # env steps between target updates
    hidden: Sequence[int] = static((64, 64))
    activation: str = static("relu")
    dueling: bool = static(True)
    double_q: bool = static(True)
    n_step: int = static(10)  # multi-step returns (1 = one-step DQN)
    anneal_lr: bool = static(True)  # linear decay of the learning rate to 0 over training
    learning_rate: float = 1e-3
    gamma: float = 0.99
    tau: float = 1.0  # target update rate (1 = hard copy)
    epsilon_start: float = 1.0
    epsilon_end: float = 0.05
    exploration_fraction: float = 0.3  # fraction of training over which epsilon decays linearly
    max_grad_norm: float = 10.0

    TRACED_BOUNDS: ClassVar[dict[str, str]] = {
        "learning_rate": "positive",
        "gamma": "unit",
        "tau": "unit",
        "epsilon_start": "unit",
        "epsilon_end": "unit",
        "exploration_fraction": "unit",
        "max_grad_norm": "positive",
    }

    def steps_per_update(self) -> int:
        return self.num_envs * self.train_freq

    def validate(self) -> DQNConfig:
        for name in (
            "num_envs", "buffer_size", "batch_size", "train_freq", "gradient_steps", "target_update_interval",
            "n_step",
        ):
            check_positive_int(name, getattr(self, name))
        check_positive_int("learning_starts", self.learning_starts, minimum=0)
        check_choice("activation", self.activation, ("tanh", "relu", "elu"))
        if self.buffer_size % self.steps_per_update():
            raise ValueError(
                f"buffer_size={self.buffer_size} must be a multiple of num_envs * train_freq "
                f"= {self.steps_per_update()}"
            )
        return super().validate()


@struct.dataclass
class DQNState:
    params: Any
    target_params: Any
    opt_state: Any
    buffer: ReplayBuffer
    envs: EnvBatch
    pending: dict[str, jax.Array]  # the last n_step - 1 transitions per env, [n_step - 1, num_envs, ...]
    key: jax.Array
    env_steps: jax.Array


def _network(config: DQNConfig, env: Any, env_params: Any) -> DuelingQNetwork:
    num_actions = env.action_space(env_params).n
    return DuelingQNetwork(num_actions, tuple(config.hidden), config.activation, config.dueling)


def make_optimizer(config: DQNConfig) -> optax.GradientTransformation:
    num_updates = config.total_timesteps // config.steps_per_update()
    return clipped_adam(
        config.learning_rate,
        config.max_grad_norm,
        total_steps=num_updates * config.gradient_steps,
        anneal=config.anneal_lr,
    )


def _example_item(envs: EnvBatch) -> dict[str, jax.Array]:
    """The structure of one stored (n-step) transition."""
    obs = envs.obs[0]
    return {"obs": obs, "action": jnp.int32(0), "reward": jnp.float32(0), "next_obs": obs, "discount": jnp.float32(0)}


def transition_arrays(transitions: Transition) -> dict[str, jax.Array]:
    return {
        "obs": transitions.obs,
        "action": transitions.action,
        "reward": transitions.reward,
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
        keep = alive[..., None] > 0
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


def init(config: DQNConfig, key: jax.Array) -> DQNState:
    env, env_params, _ = config.make_env()
    net_key, env_key, warmup_key, key = jax.random.split(key, 4)
    envs = reset_envs(env, env_params, env_key, config.num_envs)
    network = _network(config, env, env_params)
    params = network.init(net_key, envs.obs[:1])

    def random_action(batch: EnvBatch, carry: Any, key: jax.Array):
        return jax.random.randint(key, batch.first.shape, 0, network.num_actions), carry, None

    # The first n-1 transitions of each env, waiting for their n-step windows.
    envs, _, transitions, _ = rollout(env, env_params, envs, None, random_action, warmup_key, config.n_step - 1)
    pending = transition_arrays(transitions)
    return DQNState(
        params=params,
        target_params=params,
        opt_state=make_optimizer(config).init(params),
        buffer=replay_init(_example_item(envs), config.buffer_size),
        envs=envs,
        pending=pending,
        key=key_bits(key),
        env_steps=jnp.int32(0),
    )


def epsilon(config: DQNConfig, env_steps: jax.Array) -> jax.Array:
    """Linear decay from epsilon_start to epsilon_end over exploration_fraction of training."""
    decay_steps = jnp.maximum(config.exploration_fraction * config.total_timesteps, 1.0)
    progress = jnp.minimum(env_steps / decay_steps, 1.0)
    return config.epsilon_start + progress * (config.epsilon_end - config.epsilon_start)


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


def update(config: DQNConfig, state: DQNState) -> tuple[DQNState, UpdateStats]:
    env, env_params, _ = config.make_env()
    network = _network(config, env, env_params)
    rollout_key, learn_key, key = jax.random.split(fast_key(state.key), 3)

    # 1. Act epsilon-greedily for train_freq steps and store the transitions.
    eps = epsilon(config, state.env_steps)

    def act(batch: EnvBatch, carry: Any, key: jax.Array):
        explore_key, random_key = jax.random.split(key)
        greedy_action = jnp.argmax(network.apply(state.params, batch.obs), -1)
        random_action = jax.random.randint(random_key, greedy_action.shape, 0, network.num_actions)
        explore = jax.random.uniform(explore_key, greedy_action.shape) < eps
        return jnp.where(explore, random_action, greedy_action), carry, None

    envs, _, transitions, _ = rollout(env, env_params, state.envs, None, act, rollout_key, config.train_freq)
    window = jax.tree.map(lambda p, x: jnp.concatenate([p, x]), state.pending, transition_arrays(transitions))
    items = n_step_transitions(window, config.n_step, config.gamma)  # complete for the first train_freq steps
    pending = jax.tree.map(lambda x: x[config.train_freq :], window)
    buffer = replay_add(state.buffer, jax.tree.map(lambda x: x.reshape(-1, *x.shape[2:]), items))
    env_steps = state.env_steps + config.steps_per_update()

    # 2. Gradient steps on double-Q targets, once enough transitions are stored. `uniform_cond` keeps this a real
    #    branch in a vmapped sweep (every configuration of a batch starts learning at the same step).
    def learn(config, params, opt_state, target_params, samples):
        def loss_fn(params, sample):
            # Separate forward passes: one over [obs; next_obs] would double the backward pass's matmuls.
            q = network.apply(params, sample["obs"])
            q_taken = jnp.take_along_axis(q, sample["action"][:, None], -1)[:, 0]
            q_next_target = network.apply(target_params, sample["next_obs"])
            q_next_online = network.apply(params, sample["next_obs"]) if config.double_q else q_next_target
            target = td_targets(
                q_next_online, q_next_target, sample["reward"], sample["discount"], config.double_q
            )
            return optax.huber_loss(q_taken, jax.lax.stop_gradient(target)).mean()

        def gradient_step(carry, sample):
            params, opt_state = carry
            loss, grads = jax.value_and_grad(loss_fn)(params, sample)
            updates, opt_state = make_optimizer(config).update(grads, opt_state, params)
            return (optax.apply_updates(params, updates), opt_state), loss

        (params, opt_state), losses = jax.lax.scan(gradient_step, (params, opt_state), samples)
        return params, opt_state, losses.mean()

    def wait(config, params, opt_state, target_params, samples):
        return params, opt_state, jnp.float32(0.0)

    # The minibatches are drawn outside the branch: the buffer (megabytes per configuration) stays out of the
    # conditional's operands, which XLA may copy.
    samples = jax.vmap(lambda k: replay_sample(buffer, k, config.batch_size))(
        jax.random.split(learn_key, config.gradient_steps)
    )
    learning = env_steps >= config.learning_starts
    params, opt_state, loss = uniform_cond(
        learning, learn, wait, config, state.params, state.opt_state, state.target_params, samples
    )

    # 3. Target network: blend with rate tau each time target_update_interval env steps pass.
    sync = learning & (
        env_steps // config.target_update_interval
        != state.env_steps // config.target_update_interval
    )
    target_params = uniform_cond(
        sync,
        lambda tau, params, target: optax.incremental_update(params, target, tau),
        lambda tau, params, target: target,
        config.tau,
        params,
        state.target_params,
    )

    new_state = DQNState(params, target_params, opt_state, buffer, envs, pending, key_bits(key), env_steps)
    return new_state, UpdateStats(loss, EpisodeSums.of(transitions))


def greedy(config: DQNConfig, params: Any):
    env, env_params, _ = config.make_env()
    network = _network(config, env, env_params)
    return greedy_policy(lambda obs: network.apply(params, obs))


DQN = Algorithm("dqn", DQNConfig, init, update, greedy, params=lambda state: state.params)
train = make_train(DQN)

__all__ = [
    "DQN", "DQNConfig", "DQNState", "epsilon", "make_optimizer", "n_step_transitions", "td_targets",
    "transition_arrays", "train",
]
