"""Recurrent PPO: PPO (ppo.py's sibling) with a GRU or LSTM core shared by the policy and value heads.

The hidden state is the agent carry of the shared rollout, carried from one update's rollout into the next and
reset to zeros at every episode's first step (`EnvBatch.first`, also stored with the rollout).

One `update`: roll out `num_steps` steps of `num_envs` envs, keeping the hidden state each env started the rollout
with -> GAE advantages (`ppo_core.gae`; the bootstrap value of each step's pre-reset next observation is one more
recurrent step from the carry after that step, so truncated episodes bootstrap correctly) -> `update_epochs`
epochs of `num_minibatches` minibatches of *whole env sequences*: each minibatch re-unrolls its envs' stored
[num_steps] sequences from their initial hidden states with the current parameters (resetting at the stored
episode starts) and takes a step on the clipped objective (`ppo_core.clipped_loss`).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from amjax.agents.config import AgentConfig, static
from amjax.agents.networks import VECTOR_TORSO, RecurrentActorCritic, Torso, check_core_fields, zero_carry
from amjax.agents.optim import check_sequence_minibatches, minibatch_step, sequence_minibatch_epochs
from amjax.agents.ppo_core import (
    PPOBaseConfig,
    clipped_loss,
    eval_action,
    make_optimizer,
    policy_distribution,
    rollout_advantages,
)
from amjax.agents.rollout import EnvBatch, FinishedEpisodes, fast_key, key_bits, reset_envs, rollout
from amjax.agents.setup import Setup
from amjax.agents.training import Algorithm, UpdateStats, make_train
from amjax.batching import shared_field


@struct.dataclass
class PPORNNConfig(PPOBaseConfig):
    """`PPOBaseConfig`'s fields plus the recurrent core's; `hidden` is the MLP under the cell. The core is shared by
    the policy and value heads."""

    hidden: tuple[int, ...] = static((64,))
    rnn_size: int = static(64)
    cell: str = static("gru")  # "gru" or "lstm"

    @classmethod
    def from_dict(cls, fields: dict[str, Any]) -> AgentConfig:
        """As `AgentConfig.from_dict`; files written before the two PPO configs became siblings also name
        `shared_network` (always True then), which is dropped."""
        if fields.get("shared_network", True) is True:
            fields = {k: v for k, v in fields.items() if k != "shared_network"}
        return super().from_dict(fields)

    def check_fields(self) -> None:
        check_core_fields(self.rnn_size, self.cell)
        super().check_fields()
        check_sequence_minibatches(self.num_envs, self.num_minibatches)


@struct.dataclass
class PPORNNState:
    params: Any
    opt_state: Any
    envs: EnvBatch
    carry: Any  # the hidden state of every training env
    key: jax.Array
    updates: jax.Array = shared_field()  # equal in every member of a sweep batch


def network(config: PPORNNConfig, action_space: Any, torso: Torso = VECTOR_TORSO) -> RecurrentActorCritic:
    return RecurrentActorCritic(
        policy_distribution(config, action_space),
        tuple(config.hidden),
        config.rnn_size,
        config.cell,
        config.activation,
        config.measure_prior,
        torso,
    )


def init(config: PPORNNConfig, setup: Setup, key: jax.Array) -> PPORNNState:
    net_key, env_key, key = jax.random.split(key, 3)
    envs = reset_envs(setup.env, setup.env_params, env_key, config.num_envs)
    carry = zero_carry(config.cell, config.rnn_size, (config.num_envs,))
    params = setup.network.init(net_key, carry, envs.obs, envs.first)
    return PPORNNState(params, make_optimizer(config).init(params), envs, carry, key_bits(key), jnp.int32(0))


def collect(
    config: PPORNNConfig, setup: Setup, params: Any, envs: EnvBatch, carry: Any, key: jax.Array
) -> tuple[EnvBatch, Any, Any, tuple[jax.Array, ...], FinishedEpisodes]:
    """Roll out `num_steps` steps with the stochastic policy. Returns the final envs and carry, the transitions
    [T, E], per step (log-probability, value, `first` flag, carry after the step) and the finished episodes."""

    distribution = setup.network.distribution

    def act(batch: EnvBatch, carry: Any, key: jax.Array):
        carry, (policy, value) = setup.network.apply(params, carry, batch.obs, batch.first)
        action = distribution.sample(key, policy)
        return action, carry, (distribution.log_prob(policy, action), value, batch.first, carry)

    return rollout(setup.env, setup.env_params, envs, carry, act, key, config.num_steps)


def unroll_sequences(
    net: RecurrentActorCritic, params: Any, start: Any, obs: jax.Array, first: jax.Array
) -> tuple[jax.Array, jax.Array]:
    """Policy parameters and values [T, E, ...] of time-major sequences re-unrolled from their initial carries."""
    _, (policy, value) = net.apply(params, start, obs, first, method="unroll")
    return policy, value


def update(config: PPORNNConfig, setup: Setup, state: PPORNNState) -> tuple[PPORNNState, UpdateStats]:
    net = setup.network
    optimizer = make_optimizer(config)
    rollout_key, epoch_key, key = jax.random.split(fast_key(state.key), 3)

    # 1. Collect a rollout with the current stochastic policy, keeping each step's carry and `first` flag.
    envs, carry, transitions, (log_probs, values, first, carries), episodes = collect(
        config, setup, state.params, state.envs, state.carry, rollout_key
    )

    # 2. Advantages: the value of every pre-reset next observation, one recurrent step on from its carry.
    _, (_, next_values) = net.apply(state.params, carries, transitions.next_obs, jnp.zeros_like(first))
    advantages, targets = rollout_advantages(config, transitions, values, next_values)

    # 3. Epochs of minibatches of whole env sequences, re-unrolled from the rollout's initial carries.
    sequences = (transitions.obs, first, transitions.action, log_probs, values, advantages, targets)  # [T, E, ...]

    def loss_fn(params, minibatch):
        start, (obs, first, *rest) = minibatch
        return clipped_loss(config, net.distribution, *unroll_sequences(net, params, start, obs, first), *rest)

    step = minibatch_step(optimizer, loss_fn)
    (params, opt_state), loss = sequence_minibatch_epochs(
        step,
        (state.params, state.opt_state),
        state.carry,
        sequences,
        epoch_key,
        config.update_epochs,
        config.num_minibatches,
    )
    new_state = PPORNNState(params, opt_state, envs, carry, key_bits(key), state.updates + 1)
    return new_state, UpdateStats(loss, episodes)


def greedy(config: PPORNNConfig, setup: Setup, params: Any, num_envs: int):
    """The test policy (`ppo_core.eval_action`), carrying the hidden state; a zero hidden state for `num_envs`
    test envs."""

    def act(batch: EnvBatch, carry: Any, key: jax.Array):
        carry, (policy, _) = setup.network.apply(params, carry, batch.obs, batch.first)
        return eval_action(config, setup.network.distribution, policy, key), carry, None

    return act, zero_carry(config.cell, config.rnn_size, (num_envs,))


PPO_RNN = Algorithm("ppo-rnn", PPORNNConfig, network, init, update, greedy, params=lambda state: state.params)
train = make_train(PPO_RNN)

__all__ = [
    "PPO_RNN",
    "PPORNNConfig",
    "PPORNNState",
    "collect",
    "greedy",
    "init",
    "network",
    "train",
    "unroll_sequences",
    "update",
]
