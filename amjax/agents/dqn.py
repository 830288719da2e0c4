"""Dueling Double DQN (Wang et al. 2016; van Hasselt et al. 2016) with a uniform replay buffer in the state.

One `update`: `train_freq` epsilon-greedy steps of `num_envs` envs -> n-step transitions into the buffer ->
(once `learning_starts` steps are stored) `gradient_steps` Huber-loss steps on double-Q targets -> a (soft or
hard) target-network update whenever `target_update_interval` env steps have passed.

n-step returns (default 10) carry the sparse signal of CartPole-like tasks, and the measurement cost, back n steps
per update: without a measurement the agent sees a stale observation, so one-step bootstrapping through those
aliased observations misjudges what a skipped measurement costs later (the runs behind the default are in
docs/tuning.md). The last n-1 transitions of each env wait in the state until their n-step window is complete, so
every stored transition is exact; `init` fills that window with n-1 random steps per env (not counted as training
steps). `n_step=1` is ordinary DQN.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import optax
from flax import struct

from amjax.agents.networks import VECTOR_TORSO, DuelingQNetwork, Torso
from amjax.agents.q_learning import (
    QLearningConfig,
    epsilon,
    epsilon_greedy_act,
    greedy,
    learn_or_wait,
    make_optimizer,
    n_step_transitions,
    target_sync,
    td_targets,
    transition_arrays,
    update_target,
)
from amjax.agents.replay import ReplayBuffer, replay_add, replay_init, replay_sample
from amjax.agents.rollout import EnvBatch, fast_key, key_bits, reset_envs, rollout
from amjax.agents.setup import Setup
from amjax.agents.training import Algorithm, UpdateStats, make_train
from amjax.batching import shared_field


@struct.dataclass
class DQNConfig(QLearningConfig):
    """`QLearningConfig`'s fields; `buffer_size` and `batch_size` count transitions."""

    def check_fields(self) -> None:
        super().check_fields()
        if self.buffer_size % self.steps_per_update():
            raise ValueError(
                f"buffer_size={self.buffer_size} must be a multiple of num_envs * train_freq "
                f"= {self.steps_per_update()}"
            )


@struct.dataclass
class DQNState:
    params: Any
    target_params: Any
    opt_state: Any
    buffer: ReplayBuffer
    envs: EnvBatch
    pending: dict[str, jax.Array]  # the last n_step - 1 transitions per env, [n_step - 1, num_envs, ...]
    key: jax.Array
    env_steps: jax.Array = shared_field()  # equal in every member of a sweep batch


def network(config: DQNConfig, action_space: Any, torso: Torso = VECTOR_TORSO) -> DuelingQNetwork:
    return DuelingQNetwork(
        action_space.n, tuple(config.hidden), config.activation, config.dueling, config.factored_masks, torso
    )


def _example_item(envs: EnvBatch) -> dict[str, jax.Array]:
    """The structure of one stored (n-step) transition."""
    obs = envs.obs[0]
    return {"obs": obs, "action": jnp.int32(0), "reward": jnp.float32(0), "next_obs": obs, "discount": jnp.float32(0)}


def init(config: DQNConfig, setup: Setup, key: jax.Array) -> DQNState:
    env, env_params = setup.env, setup.env_params
    net_key, env_key, warmup_key, key = jax.random.split(key, 4)
    envs = reset_envs(env, env_params, env_key, config.num_envs)
    params = setup.network.init(net_key, envs.obs[:1])

    def random_action(batch: EnvBatch, carry: Any, key: jax.Array):
        return jax.random.randint(key, batch.first.shape, 0, setup.num_actions), carry, None

    # The first n-1 transitions of each env, waiting for their n-step windows.
    envs, _, transitions, _, _ = rollout(env, env_params, envs, None, random_action, warmup_key, config.n_step - 1)
    pending = transition_arrays(config, transitions)
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


def update(config: DQNConfig, setup: Setup, state: DQNState) -> tuple[DQNState, UpdateStats]:
    network = setup.network
    rollout_key, learn_key, key = jax.random.split(fast_key(state.key), 3)

    # 1. Act epsilon-greedily for train_freq steps and store the transitions.
    act = epsilon_greedy_act(setup, state.params, epsilon(config, state.env_steps))
    envs, _, transitions, _, episodes = rollout(
        setup.env, setup.env_params, state.envs, None, act, rollout_key, config.train_freq
    )
    window = jax.tree.map(lambda p, x: jnp.concatenate([p, x]), state.pending, transition_arrays(config, transitions))
    items = n_step_transitions(window, config.n_step, config.gamma)  # complete for the first train_freq steps
    pending = jax.tree.map(lambda x: x[config.train_freq :], window)
    buffer = replay_add(state.buffer, jax.tree.map(lambda x: x.reshape(-1, *x.shape[2:]), items))
    env_steps = state.env_steps + config.steps_per_update()

    # 2. Gradient steps on double-Q targets, once enough transitions are stored.
    def learn(params, opt_state, config, target_params, buffer, key_data):
        def loss_fn(params, sample):
            # Separate forward passes: one over [obs; next_obs] would double the backward pass's matmuls.
            q = network.apply(params, sample["obs"])
            q_taken = jnp.take_along_axis(q, sample["action"][:, None], -1)[:, 0]
            q_next_target = network.apply(target_params, sample["next_obs"])
            q_next_online = network.apply(params, sample["next_obs"]) if config.double_q else q_next_target
            target = td_targets(q_next_online, q_next_target, sample["reward"], sample["discount"], config.double_q)
            return optax.huber_loss(q_taken, jax.lax.stop_gradient(target)).mean()

        def gradient_step(carry, sample):
            params, opt_state = carry
            loss, grads = jax.value_and_grad(loss_fn)(params, sample)
            updates, opt_state = make_optimizer(config).update(grads, opt_state, params)
            return (optax.apply_updates(params, updates), opt_state), loss

        keys = jax.random.split(fast_key(key_data), config.gradient_steps)
        samples = jax.vmap(lambda k: replay_sample(buffer, k, config.batch_size))(keys)
        (params, opt_state), losses = jax.lax.scan(gradient_step, (params, opt_state), samples)
        return params, opt_state, losses.mean()

    learning = env_steps >= config.learning_starts
    params, opt_state, loss = learn_or_wait(
        learning, learn, state.params, state.opt_state, config, state.target_params, buffer, key_bits(learn_key)
    )

    # 3. Target network: blend with rate tau each time target_update_interval env steps pass.
    sync = target_sync(config, learning, state.env_steps, env_steps)
    target_params = update_target(config, sync, params, state.target_params)

    new_state = DQNState(params, target_params, opt_state, buffer, envs, pending, key_bits(key), env_steps)
    return new_state, UpdateStats(loss, episodes)


DQN = Algorithm("dqn", DQNConfig, network, init, update, greedy, params=lambda state: state.params)
train = make_train(DQN)

__all__ = ["DQN", "DQNConfig", "DQNState", "greedy", "init", "network", "train", "update"]
