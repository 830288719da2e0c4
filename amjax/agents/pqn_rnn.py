"""Recurrent PQN (PQN-RNN; Gallici et al. 2025, "Simplifying Deep Temporal Difference Learning"): PQN
(pqn.py) with a GRU or LSTM core, so that it can remember what it last measured. No replay buffer and no target
network: the rollout it has just collected is all it learns from, as whole env sequences.

Network: LayerNorm MLP torso -> GRU or LSTM cell -> Q head (`networks.RecurrentQNetwork`, DRQN's network with
LayerNorm). The hidden state is the agent carry of the shared rollout, carried from one update's rollout into the
next and reset to zeros at every episode's first step (`EnvBatch.first`, also stored with the rollout).

One `update`: roll out `num_steps` epsilon-greedy steps of `num_envs` envs, keeping the hidden state each env
started the rollout with -> Q(lambda) targets (`q_learning.q_lambda_targets`) from the same parameters' greedy
values of the pre-reset next observations (one more recurrent step from the carry after each step, so truncated
episodes bootstrap correctly and no value mixes episodes) -> `update_epochs` epochs of `num_minibatches`
minibatches of whole env sequences: each re-unrolls its envs' [num_steps] sequences from their initial hidden
states with the current parameters (resetting at the stored episode starts) and takes a squared-error step on
Q(s, a).

Differences from the reference (github.com/mttga/purejaxql, `pqn_rnn_gymnax.py`): Adam where it uses RAdam;
truncations bootstrap; the targets are computed once per rollout from the acting parameters (as in pqn.py), not
recomputed from each minibatch's own forward pass; the network sees the observation only (the reference also feeds
it the previous action and done flag; the env option `extra_obs=("last_action",)` adds the former), and each
sequence starts from the hidden state stored with it (the reference prepends the previous rollout's last 4 steps);
the defaults are sized for amjax's CartPole budgets (docs/pqn.md).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from amjax.agents.config import static
from amjax.agents.networks import VECTOR_TORSO, RecurrentQNetwork, Torso, check_core_fields, zero_carry
from amjax.agents.optim import check_sequence_minibatches, minibatch_step, sequence_minibatch_epochs
from amjax.agents.pqn import PQNBaseConfig, make_optimizer
from amjax.agents.q_learning import (
    epsilon,
    q_lambda_targets,
    recurrent_epsilon_greedy,
    recurrent_greedy,
    recurrent_q_network,
)
from amjax.agents.rollout import EnvBatch, fast_key, key_bits, reset_envs, rollout
from amjax.agents.setup import Setup
from amjax.agents.training import Algorithm, UpdateStats, make_train
from amjax.batching import shared_field


@struct.dataclass
class PQNRNNConfig(PQNBaseConfig):
    """`PQNBaseConfig`'s fields plus the recurrent core's; `hidden` is the LayerNorm MLP under the cell.
    Minibatches are whole env sequences, so `num_minibatches` must divide `num_envs`."""

    hidden: tuple[int, ...] = static((64,))
    rnn_size: int = static(64)
    cell: str = static("gru")  # "gru" or "lstm"
    learning_rate: float = 6e-3  # against 3e-4 / 1e-3 / 3e-3 and 1e-2 on CartPole-v0 (docs/pqn.md)

    def check_fields(self) -> None:
        check_core_fields(self.rnn_size, self.cell)
        super().check_fields()
        check_sequence_minibatches(self.num_envs, self.num_minibatches)


@struct.dataclass
class PQNRNNState:
    params: Any
    opt_state: Any
    envs: EnvBatch
    carry: Any  # the hidden state of every training env
    key: jax.Array
    env_steps: jax.Array = shared_field()  # equal in every member of a sweep batch


def network(config: PQNRNNConfig, action_space: Any, torso: Torso = VECTOR_TORSO) -> RecurrentQNetwork:
    return recurrent_q_network(config, action_space, torso, layer_norm=config.layer_norm)


def init(config: PQNRNNConfig, setup: Setup, key: jax.Array) -> PQNRNNState:
    net_key, env_key, key = jax.random.split(key, 3)
    envs = reset_envs(setup.env, setup.env_params, env_key, config.num_envs)
    carry = zero_carry(config.cell, config.rnn_size, (config.num_envs,))
    params = setup.network.init(net_key, carry, envs.obs, envs.first)
    return PQNRNNState(params, make_optimizer(config).init(params), envs, carry, key_bits(key), jnp.int32(0))


def rollout_targets(
    config: PQNRNNConfig, net: RecurrentQNetwork, params: Any, transitions: Any, carries_before: Any, last_carry: Any
) -> jax.Array:
    """Q(lambda) targets [T, E] of a rollout acted with `params`: the bootstrap value of step t's pre-reset next
    observation is one more recurrent step from the carry after step t (the carry before step t + 1; after the last
    step, `last_carry`), with no reset."""
    carries_after = jax.tree.map(
        lambda before, last: jnp.concatenate([before[1:], last[None]]), carries_before, last_carry
    )
    _, q_next = net.apply(params, carries_after, transitions.next_obs, jnp.zeros(transitions.done.shape, bool))
    reward = config.reward_scale * transitions.reward
    return q_lambda_targets(
        reward, transitions.terminated, transitions.done, q_next.max(-1), config.gamma, config.q_lambda
    )


def update(config: PQNRNNConfig, setup: Setup, state: PQNRNNState) -> tuple[PQNRNNState, UpdateStats]:
    net = setup.network
    rollout_key, epoch_key, key = jax.random.split(fast_key(state.key), 3)

    # 1. Act epsilon-greedily for num_steps steps of every env, keeping each step's carry and `first` flag.
    act = recurrent_epsilon_greedy(setup, state.params, epsilon(config, state.env_steps))
    envs, carry, transitions, (carries, first), episodes = rollout(
        setup.env, setup.env_params, state.envs, state.carry, act, rollout_key, config.num_steps
    )

    # 2. Q(lambda) targets from the same parameters.
    targets = rollout_targets(config, net, state.params, transitions, carries, carry)

    # 3. Epochs of minibatches of whole env sequences, re-unrolled from the rollout's initial carries.
    def loss_fn(params, minibatch):
        start, (obs, first, action, target) = minibatch
        _, q = net.apply(params, start, obs, first, method="unroll")
        q_taken = jnp.take_along_axis(q, action[..., None], -1)[..., 0]
        return 0.5 * jnp.square(q_taken - target).mean()

    step = minibatch_step(make_optimizer(config), loss_fn)
    (params, opt_state), loss = sequence_minibatch_epochs(
        step,
        (state.params, state.opt_state),
        state.carry,
        (transitions.obs, first, transitions.action, targets),
        epoch_key,
        config.update_epochs,
        config.num_minibatches,
    )
    env_steps = state.env_steps + config.steps_per_update()
    return PQNRNNState(params, opt_state, envs, carry, key_bits(key), env_steps), UpdateStats(loss, episodes)


greedy = recurrent_greedy  # the greedy policy and a zero hidden state for the test envs
PQN_RNN = Algorithm("pqn-rnn", PQNRNNConfig, network, init, update, greedy, params=lambda state: state.params)
train = make_train(PQN_RNN)

__all__ = [
    "PQN_RNN",
    "PQNRNNConfig",
    "PQNRNNState",
    "greedy",
    "init",
    "network",
    "rollout_targets",
    "train",
    "update",
]
