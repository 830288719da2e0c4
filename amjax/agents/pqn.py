"""PQN, parallelised Q-learning (Gallici et al. 2025, "Simplifying Deep Temporal Difference Learning"), as one pure,
scanned update: no replay buffer and no target network. LayerNorm in the network and Q(lambda) targets over many
parallel envs keep the bootstrapped targets stable.

One `update`: roll out `num_steps` epsilon-greedy steps of `num_envs` envs -> Q(lambda) targets from the network's
own greedy values of the pre-reset next observations (kept from acting, where the next observation is the one acted
on next; `q_learning.bootstrap_values`) -> `update_epochs` epochs of `num_minibatches` squared-error minibatch steps
on Q(s, a). A terminated episode does not bootstrap; a truncated one bootstraps from its pre-reset observation; no
target runs across an episode's end.

Differences from the reference (github.com/mttga/purejaxql, `pqn_gymnax.py`): Adam (the agents' shared optimiser)
where the reference uses RAdam; truncation bootstraps where the reference treats it as termination; the defaults are
sized for amjax's budgets (CartPole-v0: 102,400-153,600 env steps, not 500,000; docs/pqn.md has the tuning runs).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import jax
import jax.numpy as jnp
import optax
from flax import struct

from amjax.agents.config import AgentConfig, static
from amjax.agents.networks import VECTOR_TORSO, DuelingQNetwork, Torso, check_activation
from amjax.agents.optim import (
    check_epoch_fields,
    check_row_minibatches,
    epoch_optimizer,
    minibatch_epochs,
    minibatch_step,
)
from amjax.agents.q_learning import bootstrap_values, epsilon, epsilon_greedy_act, greedy, q_lambda_targets
from amjax.agents.rollout import EnvBatch, fast_key, key_bits, reset_envs, rollout
from amjax.agents.setup import Setup
from amjax.agents.training import Algorithm, UpdateStats, make_train
from amjax.batching import shared_field
from amjax.validation import check_bool


@struct.dataclass
class PQNBaseConfig(AgentConfig):
    """The fields of PQN and recurrent PQN (pqn_rnn.py), with PQN's defaults. Static: the rollout and minibatch
    shapes and the network; traced: the rest."""

    num_envs: int = static(16)
    num_steps: int = static(32)  # rollout length per env per update
    update_epochs: int = static(4)
    num_minibatches: int = static(4)
    hidden: Sequence[int] = static((128, 128))
    activation: str = static("relu")
    layer_norm: bool = static(True)  # LayerNorm after each hidden Dense layer: what makes PQN stable
    dueling: bool = static(False)  # the reference's plain Q head; True for a dueling value/advantage split
    anneal_lr: bool = static(True)  # linear decay of the learning rate to 0 over training
    learning_rate: float = 1e-3  # docs/pqn.md: 1e-3 against 3e-4 on CartPole-v0
    gamma: float = 0.99
    q_lambda: float = 0.95  # the lambda of the Q(lambda) targets (0: one-step Q-learning targets)
    epsilon_start: float = 1.0
    epsilon_end: float = 0.05
    exploration_fraction: float = 0.2  # fraction of training over which epsilon decays linearly
    max_grad_norm: float = 10.0
    reward_scale: float = 0.1  # rewards (measurement costs included) are multiplied by this in the targets

    WIDTH_FIELDS: ClassVar[tuple[str, ...]] = ("hidden",)
    TRACED_BOUNDS: ClassVar[dict[str, str]] = {
        "learning_rate": "positive",
        "gamma": "unit",
        "q_lambda": "unit",
        "epsilon_start": "unit",
        "epsilon_end": "unit",
        "exploration_fraction": "unit",
        "max_grad_norm": "positive",
        "reward_scale": "positive",
    }

    def steps_per_update(self) -> int:
        return self.num_envs * self.num_steps

    def check_fields(self) -> None:
        check_epoch_fields(self.num_envs, self.num_steps, self.update_epochs, self.num_minibatches)
        check_activation(self.activation)
        check_bool("layer_norm", self.layer_norm)
        check_bool("dueling", self.dueling)
        check_row_minibatches(self.num_envs, self.num_steps, self.num_minibatches)
        super().check_fields()


@struct.dataclass
class PQNConfig(PQNBaseConfig):
    """PQN's fields (`PQNBaseConfig`'s, with its defaults)."""


@struct.dataclass
class PQNState:
    params: Any
    opt_state: Any
    envs: EnvBatch
    key: jax.Array
    env_steps: jax.Array = shared_field()  # equal in every member of a sweep batch


def network(config: PQNConfig, action_space: Any, torso: Torso = VECTOR_TORSO) -> DuelingQNetwork:
    return DuelingQNetwork(
        action_space.n,
        tuple(config.hidden),
        config.activation,
        config.dueling,
        config.factored_masks,
        torso,
        layer_norm=config.layer_norm,
    )


def make_optimizer(config: PQNBaseConfig) -> optax.GradientTransformation:
    return epoch_optimizer(config)


def init(config: PQNConfig, setup: Setup, key: jax.Array) -> PQNState:
    net_key, env_key, key = jax.random.split(key, 3)
    envs = reset_envs(setup.env, setup.env_params, env_key, config.num_envs)
    params = setup.network.init(net_key, envs.obs[:1])
    return PQNState(params, make_optimizer(config).init(params), envs, key_bits(key), jnp.int32(0))


def update(config: PQNConfig, setup: Setup, state: PQNState) -> tuple[PQNState, UpdateStats]:
    network = setup.network
    rollout_key, epoch_key, key = jax.random.split(fast_key(state.key), 3)

    # 1. Act epsilon-greedily for num_steps steps of every env.
    act = epsilon_greedy_act(setup, state.params, epsilon(config, state.env_steps), greedy_values=True)
    envs, _, transitions, acted_q, episodes = rollout(
        setup.env, setup.env_params, state.envs, None, act, rollout_key, config.num_steps
    )

    # 2. Q(lambda) targets from the same parameters' greedy values of the pre-reset next observations (mostly the
    #    values computed while acting).
    def greedy_value(params, obs):
        return network.apply(params, obs).max(-1)

    next_q = bootstrap_values(greedy_value, state.params, acted_q, transitions)
    reward = config.reward_scale * transitions.reward
    targets = q_lambda_targets(reward, transitions.terminated, transitions.done, next_q, config.gamma, config.q_lambda)

    # 3. Epochs of minibatch steps on 0.5 (Q(s, a) - G)^2.
    def loss_fn(params, minibatch):
        obs, action, target = minibatch
        q_taken = jnp.take_along_axis(network.apply(params, obs), action[:, None], -1)[:, 0]
        return 0.5 * jnp.square(q_taken - target).mean()

    batch = jax.tree.map(lambda x: x.reshape(-1, *x.shape[2:]), (transitions.obs, transitions.action, targets))
    step = minibatch_step(make_optimizer(config), loss_fn)
    (params, opt_state), loss = minibatch_epochs(
        step, (state.params, state.opt_state), batch, epoch_key, config.update_epochs, config.num_minibatches
    )
    env_steps = state.env_steps + config.steps_per_update()
    return PQNState(params, opt_state, envs, key_bits(key), env_steps), UpdateStats(loss, episodes)


PQN = Algorithm("pqn", PQNConfig, network, init, update, greedy, params=lambda state: state.params)
train = make_train(PQN)

__all__ = [
    "PQN",
    "PQNBaseConfig",
    "PQNConfig",
    "PQNState",
    "greedy",
    "init",
    "network",
    "q_lambda_targets",
    "train",
    "update",
]
