"""Dueling Double DQN (Wang et al. 2016; van Hasselt et al. 2016) with a uniform replay buffer in the state.

One `update`: `train_freq` epsilon-greedy steps of `num_envs` envs into the buffer -> (once `learning_starts`
steps are stored) `gradient_steps` Huber-loss steps on double-Q targets -> a (soft or hard) target-network update
whenever `target_update_interval` env steps have passed. The defaults are Stable-Baselines3's DQN defaults except
for the buffer size, warm-up and target interval, which are scaled to CartPole-sized budgets.
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
from amjax.agents.replay import ReplayBuffer, replay_add, replay_init, replay_sample
from amjax.agents.rollout import EnvBatch, reset_envs, rollout
from amjax.agents.training import Algorithm, EpisodeSums, UpdateStats, greedy_policy, make_train
from amjax.validation import check_choice, check_positive_int


@struct.dataclass
class DQNConfig(AgentConfig):
    num_envs: int = static(1)
    buffer_size: int = static(50_000)
    batch_size: int = static(64)
    learning_starts: int = static(1_000)  # env steps stored before the first gradient step
    train_freq: int = static(4)  # steps per env between gradient phases
    gradient_steps: int = static(1)
    target_update_interval: int = static(500)  # env steps between target updates
    hidden: Sequence[int] = static((64, 64))
    activation: str = static("relu")
    dueling: bool = static(True)
    double_q: bool = static(True)
    learning_rate: float = 5e-4
    gamma: float = 0.99
    tau: float = 1.0  # target update rate (1 = hard copy)
    epsilon_start: float = 1.0
    epsilon_end: float = 0.05
    exploration_fraction: float = 0.2  # fraction of training over which epsilon decays linearly
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
    key: jax.Array
    env_steps: jax.Array


def _network(config: DQNConfig, env: Any, env_params: Any) -> DuelingQNetwork:
    num_actions = env.action_space(env_params).n
    return DuelingQNetwork(num_actions, tuple(config.hidden), config.activation, config.dueling)


def _optimizer(config: DQNConfig) -> optax.GradientTransformation:
    return optax.chain(
        optax.clip_by_global_norm(config.max_grad_norm), optax.adam(config.learning_rate)
    )


def _example_item(envs: EnvBatch) -> dict[str, jax.Array]:
    obs = envs.obs[0]
    return {
        "obs": obs,
        "action": jnp.int32(0),
        "reward": jnp.float32(0.0),
        "next_obs": obs,
        "terminated": jnp.float32(0.0),
    }


def init(config: DQNConfig, key: jax.Array) -> DQNState:
    env, env_params, _ = config.make_env()
    net_key, env_key, key = jax.random.split(key, 3)
    envs = reset_envs(env, env_params, env_key, config.num_envs)
    params = _network(config, env, env_params).init(net_key, envs.obs[:1])
    return DQNState(
        params=params,
        target_params=params,
        opt_state=_optimizer(config).init(params),
        buffer=replay_init(_example_item(envs), config.buffer_size),
        envs=envs,
        key=key,
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
    terminated: jax.Array,
    gamma: jax.Array,
    double_q: bool = True,
) -> jax.Array:
    """r + gamma (1 - terminated) Q_target(s', a*), a* = argmax Q_online(s') (double) or argmax Q_target."""
    chooser = q_next_online if double_q else q_next_target
    best = jnp.argmax(chooser, axis=-1)
    bootstrap = jnp.take_along_axis(q_next_target, best[..., None], -1)[..., 0]
    return reward + gamma * (1.0 - terminated) * bootstrap


def update(config: DQNConfig, state: DQNState) -> tuple[DQNState, UpdateStats]:
    env, env_params, _ = config.make_env()
    network = _network(config, env, env_params)
    optimizer = _optimizer(config)
    rollout_key, learn_key, key = jax.random.split(state.key, 3)

    # 1. Act epsilon-greedily for train_freq steps and store the transitions.
    eps = epsilon(config, state.env_steps)

    def act(batch: EnvBatch, carry: Any, key: jax.Array):
        explore_key, random_key = jax.random.split(key)
        greedy_action = jnp.argmax(network.apply(state.params, batch.obs), -1)
        random_action = jax.random.randint(random_key, greedy_action.shape, 0, network.num_actions)
        explore = jax.random.uniform(explore_key, greedy_action.shape) < eps
        return jnp.where(explore, random_action, greedy_action), carry, None

    envs, _, transitions, _ = rollout(
        env, env_params, state.envs, None, act, rollout_key, config.train_freq
    )
    items = {
        "obs": transitions.obs,
        "action": transitions.action,
        "reward": transitions.reward,
        "next_obs": transitions.next_obs,
        "terminated": transitions.terminated.astype(jnp.float32),
    }
    buffer = replay_add(state.buffer, jax.tree.map(lambda x: x.reshape(-1, *x.shape[2:]), items))
    env_steps = state.env_steps + config.steps_per_update()

    # 2. Gradient steps on double-Q targets, once enough transitions are stored.
    def loss_fn(params, target_params, sample):
        q = network.apply(params, sample["obs"])
        q_taken = jnp.take_along_axis(q, sample["action"][:, None], -1)[:, 0]
        target = td_targets(
            network.apply(params, sample["next_obs"]),
            network.apply(target_params, sample["next_obs"]),
            sample["reward"],
            sample["terminated"],
            config.gamma,
            config.double_q,
        )
        return optax.huber_loss(q_taken, jax.lax.stop_gradient(target)).mean()

    def gradient_step(carry, key):
        params, opt_state = carry
        sample = replay_sample(buffer, key, config.batch_size)
        loss, grads = jax.value_and_grad(loss_fn)(params, state.target_params, sample)
        updates, opt_state = optimizer.update(grads, opt_state, params)
        return (optax.apply_updates(params, updates), opt_state), loss

    (params, opt_state), losses = jax.lax.scan(
        gradient_step,
        (state.params, state.opt_state),
        jax.random.split(learn_key, config.gradient_steps),
    )
    learning = env_steps >= config.learning_starts
    params, opt_state = jax.tree.map(
        lambda new, old: jnp.where(learning, new, old),
        (params, opt_state),
        (state.params, state.opt_state),
    )

    # 3. Target network: blend with rate tau each time target_update_interval env steps pass.
    sync = learning & (
        env_steps // config.target_update_interval
        != state.env_steps // config.target_update_interval
    )
    tau = jnp.where(sync, config.tau, 0.0)
    target_params = optax.incremental_update(params, state.target_params, tau)

    new_state = DQNState(params, target_params, opt_state, buffer, envs, key, env_steps)
    loss = jnp.where(learning, losses.mean(), 0.0)
    return new_state, UpdateStats(loss, EpisodeSums.of(transitions))


def greedy(config: DQNConfig, state: DQNState):
    env, env_params, _ = config.make_env()
    network = _network(config, env, env_params)
    return greedy_policy(lambda obs: network.apply(state.params, obs))


DQN = Algorithm("dqn", DQNConfig, init, update, greedy, params=lambda state: state.params)
train = make_train(DQN)

__all__ = ["DQN", "DQNConfig", "DQNState", "epsilon", "td_targets", "train"]
