"""Proximal Policy Optimization (Schulman et al. 2017) with GAE, as one pure, scanned update.

One `update`: roll out `num_steps` steps of `num_envs` envs -> GAE advantages -> `update_epochs` epochs of
`num_minibatches` clipped-objective minibatch steps. Truncated episodes bootstrap from the value of the
pre-reset observation; terminated ones do not.
The config, optimiser, GAE and loss it shares with recurrent PPO are in ppo_core.py; the minibatch epochs in optim.py.
"""

from __future__ import annotations

from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from amjax import strategy
from amjax.agents.config import static
from amjax.agents.networks import VECTOR_TORSO, ActorCritic, Torso
from amjax.agents.optim import check_row_minibatches, minibatch_epochs, minibatch_step, shuffle
from amjax.agents.ppo_core import (
    PPOBaseConfig,
    clipped_loss,
    eval_action,
    gae,
    make_optimizer,
    policy_distribution,
    rollout_advantages,
)
from amjax.agents.rollout import EnvBatch, fast_key, key_bits, reset_envs, rollout
from amjax.agents.setup import Setup
from amjax.agents.training import Algorithm, UpdateStats, greedy_policy, make_train
from amjax.batching import in_groups, shared_field


@struct.dataclass
class PPOConfig(PPOBaseConfig):
    """`PPOBaseConfig`'s fields and the choice of separate or shared torsos."""

    shared_network: bool = static(False)  # one torso for actor and critic

    def check_fields(self) -> None:
        super().check_fields()
        check_row_minibatches(self.num_envs, self.num_steps, self.num_minibatches)


@struct.dataclass
class PPOState:
    params: Any
    opt_state: Any
    envs: EnvBatch
    key: jax.Array
    updates: jax.Array = shared_field()  # equal in every member of a sweep batch


def network(config: PPOConfig, action_space: Any, torso: Torso = VECTOR_TORSO) -> ActorCritic:
    return ActorCritic(
        policy_distribution(config, action_space),
        tuple(config.hidden),
        config.activation,
        config.shared_network,
        config.measure_prior,
        torso,
    )


def init(config: PPOConfig, setup: Setup, key: jax.Array) -> PPOState:
    net_key, env_key, key = jax.random.split(key, 3)
    envs = reset_envs(setup.env, setup.env_params, env_key, config.num_envs)
    params = setup.network.init(net_key, envs.obs[:1])
    return PPOState(params, make_optimizer(config).init(params), envs, key_bits(key), jnp.int32(0))


# Under a vmapped sweep the heavy passes run in groups of configurations whose activations fit in a core's cache
# (`batching.in_groups`): about this many bytes of one [rows, width] float32 activation per group.
_GROUP_BYTES = 1 << 20


def _group_size(rows: int, width: int) -> int:
    return max(1, 1 << max(0, (_GROUP_BYTES // (4 * rows * width)).bit_length() - 1))


def update(config: PPOConfig, setup: Setup, state: PPOState) -> tuple[PPOState, UpdateStats]:
    network = setup.network
    distribution = network.distribution
    rollout_key, epoch_key, key = jax.random.split(fast_key(state.key), 3)
    width = max(config.hidden, default=1)

    # 1. Collect a rollout with the current stochastic policy. Only the policy runs step by step (XLA drops the
    #    unused critic); log-probabilities and values come after the rollout from the same parameters, batched.
    def act(batch: EnvBatch, carry: Any, key: jax.Array):
        policy, _ = network.apply(state.params, batch.obs)
        return distribution.sample(key, policy), carry, policy

    envs, _, transitions, policies, episodes = rollout(
        setup.env, setup.env_params, state.envs, None, act, rollout_key, config.num_steps
    )
    log_probs = distribution.log_prob(policies, transitions.action)

    # 2. Advantages: V(obs) and V(pre-reset next obs) (the latter handles truncation) in one pass; on CPU in chunks
    #    of about 256 rows (one [T, E] pass would stream megabytes per op), on a GPU at once (`amjax.strategy`).
    def values_of(params, obs):
        if strategy.is_gpu():
            return network.apply(params, obs)[1]
        steps = obs.shape[0]
        chunk = max((d for d in range(1, steps + 1) if steps % d == 0 and d * config.num_envs <= 256), default=1)
        return jax.lax.map(lambda o: network.apply(params, o)[1], obs, batch_size=chunk)

    both_obs = jnp.concatenate([transitions.obs, transitions.next_obs])
    both_values = in_groups(values_of, _group_size(256, width))(state.params, both_obs)
    values, next_values = jnp.split(both_values, 2)
    advantages, targets = rollout_advantages(config, transitions, values, next_values)

    # 3. Epochs of minibatch steps on the clipped objective.
    batch = (transitions.obs, transitions.action, log_probs, values, advantages, targets)
    batch = jax.tree.map(lambda x: x.reshape(-1, *x.shape[2:]), batch)

    def learn(config: PPOConfig, params: Any, opt_state: Any, batch: Any, key_data: jax.Array):
        optimizer = make_optimizer(config)

        def loss_fn(params, minibatch):
            obs, *rest = minibatch
            return clipped_loss(config, distribution, *network.apply(params, obs), *rest)

        step = minibatch_step(optimizer, loss_fn)
        (params, opt_state), loss = minibatch_epochs(
            step, (params, opt_state), batch, fast_key(key_data), config.update_epochs, config.num_minibatches
        )
        return params, opt_state, loss

    rows = config.steps_per_update() // config.num_minibatches
    params, opt_state, loss = in_groups(learn, _group_size(rows, width))(
        config, state.params, state.opt_state, batch, key_bits(epoch_key)
    )
    new_state = PPOState(params, opt_state, envs, key_bits(key), state.updates + 1)
    return new_state, UpdateStats(loss, episodes)


def greedy(config: PPOConfig, setup: Setup, params: Any, num_envs: int):
    mode = partial(eval_action, config, setup.network.distribution)
    return greedy_policy(lambda obs: setup.network.apply(params, obs)[0], mode)


PPO = Algorithm("ppo", PPOConfig, network, init, update, greedy, params=lambda state: state.params)
train = make_train(PPO)

__all__ = [
    "PPO",
    "PPOConfig",
    "PPOState",
    "clipped_loss",
    "gae",
    "greedy",
    "init",
    "network",
    "shuffle",
    "train",
    "update",
]
