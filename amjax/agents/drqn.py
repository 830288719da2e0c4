"""DRQN: Dueling Double DQN with a recurrent core (Hausknecht & Stone 2015), trained R2D2-style on stored sequences
(Kapturowski et al. 2019), so that it can remember what it last measured and skip several measurements in a row.

Network: MLP torso -> GRU or LSTM cell -> dueling head (`networks.RecurrentQNetwork`). The hidden state is the
agent carry of the shared rollout: it is reset to zeros at every episode's first step (`EnvBatch.first`), when
acting, when evaluating, and when the learner unrolls a stored sequence (the stored `first` flags).

One `update`: `train_freq` epsilon-greedy steps of `num_envs` envs (hidden state carried across updates) -> one
new sequence of `burn_in + seq_len` steps per env into the replay buffer (consecutive sequences of an env overlap by
`burn_in + seq_len - train_freq` steps) -> (once `learning_starts` steps are taken) `gradient_steps` Huber-loss
steps on `batch_size` sampled sequences -> a (soft or hard) target-network update every `target_update_interval`
env steps.

Start of a replayed sequence: *stored state + burn-in* (R2D2's best variant). Each stored sequence keeps the hidden
state the actor had at its first step (`start`); the learner (online and target network alike) unrolls the first
`burn_in` steps from it without gradient, then computes the loss on the remaining `seq_len` steps. `burn_in=0` is
the plain stored-state variant.

Targets: for every step t of the trained part, the bootstrap Q-values come from one more recurrent step on the
pre-reset next observation from the carry after step t (no reset), so truncated episodes bootstrap correctly and
the values never mix episodes. n-step returns (`q_learning.n_step_transitions`) stop at an episode's end and at the
sequence's end, and use double-Q targets (`q_learning.td_targets`) from a target network.

Cached target values: the target network changes only at its updates (every `target_update_interval` env steps),
and a stored sequence never changes, so its target bootstrap Q-values are computed once (when it is stored) and
recomputed for the whole buffer at each target update, not on every sample: the same targets, with one target
unroll per stored sequence and target update instead of one per sampled sequence.

The learner is the cost (a GRU unroll of burn_in + seq_len steps per sampled sequence, with its gradient); the
runs behind the defaults and the speed measurements are in docs/recurrent.md.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import optax
from flax import struct

from amjax.agents.config import static
from amjax.agents.networks import RecurrentQNetwork, check_core_fields, zero_carry
from amjax.agents.q_learning import (
    QLearningConfig,
    epsilon,
    learn_or_wait,
    make_optimizer,
    n_step_transitions,
    recurrent_epsilon_greedy,
    recurrent_greedy,
    recurrent_q_network,
    target_sync,
    td_targets,
    transition_arrays,
    update_target,
)
from amjax.agents.replay import ReplayBuffer, sequence_add, sequence_init, sequence_sample, sequence_windows
from amjax.agents.rollout import EnvBatch, fast_key, key_bits, reset_envs, rollout
from amjax.agents.setup import Setup
from amjax.agents.training import Algorithm, UpdateStats, make_train
from amjax.batching import shared_field, update_where
from amjax.validation import check_positive_int


@struct.dataclass
class DRQNConfig(QLearningConfig):
    """`QLearningConfig`'s fields (`buffer_size` and `batch_size` count sequences, `hidden` is the MLP under the
    recurrent cell) with DRQN's defaults, plus the sequence and the recurrent core."""

    num_envs: int = static(4)
    buffer_size: int = static(2_000)  # sequences (each burn_in + seq_len steps): the last 16k env steps
    batch_size: int = static(32)
    train_freq: int = static(8)  # also the stride between an env's stored sequences
    gradient_steps: int = static(4)  # 4 x 32 sampled sequences per 32 env steps (docs/recurrent.md)
    hidden: tuple[int, ...] = static((32,))  # 32 / 32 (was 64 / 64): 2.6x faster, still ahead of DQN (docs)
    # 6e-3 (was 2e-3): skips measurements at the default budget of 102,400 steps (docs/research/drqn_default_budget.md)
    learning_rate: float = 6e-3
    exploration_fraction: float = 0.2
    seq_len: int = static(16)  # trained steps per sequence
    burn_in: int = static(8)  # steps unrolled from the stored hidden state before the trained ones
    rnn_size: int = static(32)
    cell: str = static("gru")  # "gru" or "lstm"
    # 5 configurations at a time under vmap: 1.27x the env steps/s of all at once, 40 on 2 cores (docs/recurrent.md)
    train_group: int = static(5)

    @property
    def sequence_length(self) -> int:
        """Steps per stored sequence."""
        return self.burn_in + self.seq_len

    def check_fields(self) -> None:
        check_positive_int("seq_len", self.seq_len)
        check_core_fields(self.rnn_size, self.cell)
        check_positive_int("burn_in", self.burn_in, minimum=0)
        super().check_fields()
        if self.train_freq > self.sequence_length:
            raise ValueError(
                f"train_freq={self.train_freq} must be at most burn_in + seq_len = {self.sequence_length} "
                "(every step must land in a stored sequence)"
            )
        if self.buffer_size % self.num_envs:
            raise ValueError(
                f"buffer_size={self.buffer_size} (sequences) must be a multiple of num_envs={self.num_envs}"
            )


# Stored sequences whose target values one batched unroll recomputes at a target update (bounds its memory).
REFRESH_CHUNK = 256


@struct.dataclass
class DRQNState:
    params: Any
    target_params: Any
    opt_state: Any
    buffer: ReplayBuffer  # per sequence: "steps", and "start": {"carry": the actor's hidden state, "target_q"}
    envs: EnvBatch
    carry: Any  # the hidden state of every training env
    pending: dict[str, Any]  # the last burn_in + seq_len - train_freq steps per env (with their hidden states)
    key: jax.Array
    env_steps: jax.Array = shared_field()  # equal in every member of a sweep batch


network = recurrent_q_network  # (config, action space, torso) -> DRQN's network


def _steps(config: DRQNConfig, transitions: Any, first: jax.Array) -> dict[str, jax.Array]:
    return {**transition_arrays(config, transitions), "first": first}


def init(config: DRQNConfig, setup: Setup, key: jax.Array) -> DRQNState:
    env, env_params = setup.env, setup.env_params
    net_key, env_key, warmup_key, key = jax.random.split(key, 4)
    envs = reset_envs(env, env_params, env_key, config.num_envs)
    carry = zero_carry(config.cell, config.rnn_size, (config.num_envs,))
    params = setup.network.init(net_key, carry, envs.obs, envs.first)

    # The first burn_in + seq_len - train_freq steps of each env, waiting to complete their sequence: random
    # actions, with the initial network's hidden states (not counted as training steps).
    act = recurrent_epsilon_greedy(setup, params, jnp.float32(1.0))
    warmup = config.sequence_length - config.train_freq
    envs, carry, transitions, (carries, first), _ = rollout(env, env_params, envs, carry, act, warmup_key, warmup)
    obs = envs.obs[0]
    one_step = {
        "obs": obs,
        "action": jnp.int32(0),
        "reward": jnp.float32(0),
        "next_obs": obs,
        "terminated": jnp.float32(0),
        "done": jnp.float32(0),
        "first": jnp.bool_(False),
    }
    num_actions = env.action_space(env_params).n
    one_start = {
        "carry": jax.tree.map(lambda c: c[0], carry),
        "target_q": jnp.zeros((config.seq_len, num_actions), jnp.float32),
    }
    return DRQNState(
        params=params,
        target_params=params,
        opt_state=make_optimizer(config).init(params),
        buffer=sequence_init(one_step, one_start, config.sequence_length, config.buffer_size),
        envs=envs,
        carry=carry,
        pending={"steps": _steps(config, transitions, first), "carry": carries},
        key=key_bits(key),
        env_steps=jnp.int32(0),
    )


def q_values(
    config: DRQNConfig,
    net: RecurrentQNetwork,
    params: Any,
    steps: dict[str, jax.Array],
    start: Any,
    straight: bool = False,
) -> tuple[jax.Array, jax.Array]:
    """Unroll a batch of stored sequences (time-major [burn_in + seq_len, batch]) from their stored start states.

    The first `burn_in` steps only warm the hidden state up (no gradient). For the trained steps returns the
    Q-values [seq_len, batch, A] and the bootstrap Q-values of each step's pre-reset next observation. `straight`:
    the trained steps unrolled as straight-line code, for values that are not differentiated (target values)."""
    carry = _burn_in(config, net, params, steps, start)
    return _trained_q_values(config, net, params, steps, carry, straight)


def _burn_in(config: DRQNConfig, net: RecurrentQNetwork, params: Any, steps: dict[str, jax.Array], start: Any) -> Any:
    """The hidden state after the burn-in steps (no gradient); `start` if there are none."""
    if not config.burn_in:
        return start
    carries, _ = net.apply(
        jax.lax.stop_gradient(params),
        start,
        steps["obs"][: config.burn_in],
        steps["first"][: config.burn_in],
        straight=True,
        method="unroll",
    )
    return jax.lax.stop_gradient(jax.tree.map(lambda c: c[-1], carries))


def _trained_q_values(
    config: DRQNConfig,
    net: RecurrentQNetwork,
    params: Any,
    steps: dict[str, jax.Array],
    carry: Any,
    straight: bool,
) -> tuple[jax.Array, jax.Array]:
    trained = jax.tree.map(lambda x: x[config.burn_in :], steps)
    carries, q = net.apply(params, carry, trained["obs"], trained["first"], straight, method="unroll")
    _, q_next = net.apply(params, carries, trained["next_obs"], jnp.zeros_like(trained["first"]))
    return q, q_next


def sequence_targets(
    config: DRQNConfig, steps: dict[str, jax.Array], q_next_online: jax.Array, q_next_target: jax.Array
) -> jax.Array:
    """Double-Q n-step targets for every trained step of a batch of sequences ([seq_len, batch]).

    A return stops at the first episode end (`done`; bootstrapping only if it was a truncation) and at the
    sequence's last step, so it never reaches into another episode or past the stored data."""
    trained = jax.tree.map(lambda x: x[config.burn_in :], steps)
    # Each step's bootstrap value (one number) rides through the n-step sums in place of its next observation.
    bootstrap = td_targets(q_next_online, q_next_target, 0.0, 1.0, config.double_q)
    window = {
        "obs": trained["reward"],  # unused
        "action": trained["action"],
        "reward": trained["reward"],
        "next_obs": bootstrap[..., None],
        "terminated": trained["terminated"],
        "done": trained["done"].at[-1].set(1.0),  # cut at the sequence's end
    }
    padding = jax.tree.map(lambda x: jnp.zeros((config.n_step - 1, *x.shape[1:]), x.dtype), window)
    window = jax.tree.map(lambda x, p: jnp.concatenate([x, p]), window, padding)
    items = n_step_transitions(window, config.n_step, config.gamma)
    return items["reward"] + items["discount"] * items["next_obs"][..., 0]


def target_values(
    config: DRQNConfig, net: RecurrentQNetwork, target_params: Any, steps: dict[str, jax.Array], start: Any
) -> jax.Array:
    """The target network's bootstrap Q-values [seq_len, batch, A] of a batch of stored sequences (`q_values`)."""
    return q_values(config, net, target_params, steps, start, straight=True)[1]


def loss(
    config: DRQNConfig,
    net: RecurrentQNetwork,
    params: Any,
    steps: dict[str, jax.Array],
    start: Any,
    q_next_target: jax.Array,
) -> jax.Array:
    """Mean Huber TD error over the trained steps of a batch of sequences, given the target network's bootstrap
    Q-values (`target_values`; cached in the buffer)."""
    q, q_next_online = q_values(config, net, params, steps, start)
    targets = sequence_targets(config, steps, q_next_online, q_next_target)
    action = steps["action"][config.burn_in :]
    q_taken = jnp.take_along_axis(q, action[..., None], -1)[..., 0]
    return optax.huber_loss(q_taken, jax.lax.stop_gradient(targets)).mean()


def refresh_target_values(
    config: DRQNConfig, net: RecurrentQNetwork, target_params: Any, buffer: ReplayBuffer
) -> ReplayBuffer:
    """Every stored sequence's cached target values recomputed with `target_params` (after a target update), in
    chunks of `REFRESH_CHUNK` sequences. Unfilled slots get values too; they are never sampled."""

    def one(item):  # one stored sequence (batch-major storage): a batch of 1, time-major
        steps = jax.tree.map(lambda x: x[:, None], item["steps"])
        start = jax.tree.map(lambda c: c[None], item["start"]["carry"])
        return target_values(config, net, target_params, steps, start)[:, 0]

    storage = buffer.storage
    target_q = jax.lax.map(one, storage, batch_size=min(REFRESH_CHUNK, buffer.capacity))
    return buffer.replace(storage={**storage, "start": {**storage["start"], "target_q": target_q}})


def update(config: DRQNConfig, setup: Setup, state: DRQNState) -> tuple[DRQNState, UpdateStats]:
    rollout_key, learn_key, key = jax.random.split(fast_key(state.key), 3)

    # 1. Act epsilon-greedily for train_freq steps; store one sequence per env.
    act = recurrent_epsilon_greedy(setup, state.params, epsilon(config, state.env_steps))
    envs, carry, transitions, (carries, first), episodes = rollout(
        setup.env, setup.env_params, state.envs, state.carry, act, rollout_key, config.train_freq
    )
    window, pending = sequence_windows(
        state.pending, {"steps": _steps(config, transitions, first), "carry": carries}, config.train_freq
    )
    start = jax.tree.map(lambda c: c[0], window["carry"])
    target_q = target_values(config, setup.network, state.target_params, window["steps"], start)
    buffer = sequence_add(state.buffer, window["steps"], {"carry": start, "target_q": jnp.swapaxes(target_q, 0, 1)})
    env_steps = state.env_steps + config.steps_per_update()

    # 2. Gradient steps on sampled sequences, once learning has started (traced values are operands: see
    #    `batching.update_where`).
    def learn(params, opt_state, config, buffer, key_data):
        optimizer = make_optimizer(config)

        def gradient_step(carry, key):
            params, opt_state = carry
            steps, start = sequence_sample(buffer, key, config.batch_size)
            q_next_target = jnp.swapaxes(start["target_q"], 0, 1)
            value, grads = jax.value_and_grad(loss, argnums=2)(
                config, setup.network, params, steps, start["carry"], q_next_target
            )
            updates, opt_state = optimizer.update(grads, opt_state, params)
            return (optax.apply_updates(params, updates), opt_state), value

        (params, opt_state), losses = jax.lax.scan(
            gradient_step, (params, opt_state), jax.random.split(fast_key(key_data), config.gradient_steps)
        )
        return params, opt_state, losses.mean()

    learning = env_steps >= config.learning_starts
    params, opt_state, mean_loss = learn_or_wait(
        learning, learn, state.params, state.opt_state, config, buffer, key_bits(learn_key)
    )

    # 3. Target network: blend with rate tau each time target_update_interval env steps pass; then the buffer's
    #    cached target values follow it.
    sync = target_sync(config, learning, state.env_steps, env_steps)
    target_params = update_target(config, sync, params, state.target_params)
    buffer = update_where(
        sync,
        lambda buffer, target_params: refresh_target_values(config, setup.network, target_params, buffer),
        buffer,
        target_params,
    )

    new_state = DRQNState(params, target_params, opt_state, buffer, envs, carry, pending, key_bits(key), env_steps)
    return new_state, UpdateStats(mean_loss, episodes)


greedy = recurrent_greedy  # the greedy policy and a zero hidden state for the test envs
DRQN = Algorithm("drqn", DRQNConfig, network, init, update, greedy, params=lambda state: state.params)
train = make_train(DRQN)

__all__ = [
    "DRQN",
    "DRQNConfig",
    "DRQNState",
    "greedy",
    "init",
    "loss",
    "network",
    "q_values",
    "refresh_target_values",
    "sequence_targets",
    "target_values",
    "train",
    "update",
]
