"""Batched environment interaction shared by every agent: reset, step, and `lax.scan` rollouts."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from amjax.wrappers.episode_stats import EpisodeMetrics

# The trainers draw their randomness with Philox 4x32 (Random123): on CPU, jaxlib lowers the default Threefry as a
# rolled loop (a while loop of 5 rounds per split/draw), which dominated the cost of stepping small batches of
# envs; Philox is unrolled and about 4x cheaper per draw here. Keys stay plain uint32[2] arrays in train states
# (checkpoints unchanged); `fast_key` reinterprets their bits.
PRNG_IMPL = "philox4x32"


def fast_key(key: jax.Array) -> jax.Array:
    """A typed Philox key with the bits of `key` (a raw uint32[2] key or a typed key of 2 words)."""
    if jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
        if jax.random.key_impl(key) == jax.random.key_impl(jax.random.key(0, impl=PRNG_IMPL)):
            return key
        key = jax.random.key_data(key)
    return jax.random.wrap_key_data(key, impl=PRNG_IMPL)


def key_bits(key: jax.Array) -> jax.Array:
    """The raw uint32 bits of a key, typed or raw (what train states store)."""
    return jax.random.key_data(key) if jnp.issubdtype(key.dtype, jax.dtypes.prng_key) else key


@struct.dataclass
class EnvBatch:
    """Observations and states of `num_envs` parallel environments; `first` marks an episode's first step."""

    obs: jax.Array
    state: Any
    first: jax.Array


@struct.dataclass
class FinishedEpisodes:
    """How many episodes finished and the sums of their metrics (`means()` divides). The trainers keep them per env
    (arrays [num_envs]) while they step, adding elementwise (`add`), and sum them once per evaluation period
    (`total`): no reduction and no per-step history inside the loops."""

    count: jax.Array
    sums: EpisodeMetrics

    @classmethod
    def zeros(cls, shape: tuple[int, ...] = ()) -> FinishedEpisodes:
        zero = jnp.zeros(shape, jnp.float32)
        return cls(zero, EpisodeMetrics(zero, zero, zero, zero))

    def add(self, done: jax.Array, episode: EpisodeMetrics) -> FinishedEpisodes:
        """These plus the episodes that end where `done`, with metrics `episode` (elementwise, broadcasting)."""
        done = done.astype(jnp.float32)
        return FinishedEpisodes(self.count + done, jax.tree.map(lambda s, x: s + done * x, self.sums, episode))

    def total(self) -> FinishedEpisodes:
        """Summed over every axis (per configuration under `vmap`)."""
        return jax.tree.map(lambda x: x.sum(), self)

    def means(self) -> EpisodeMetrics:
        """Metrics per finished episode (NaN if none finished)."""
        count = jnp.where(self.count > 0, self.count, jnp.nan)
        return jax.tree.map(lambda x: x / count, self.sums)


@struct.dataclass
class Transition:
    """One step of every parallel env. `next_obs` is the observation before any auto-reset, so value targets
    bootstrap correctly on truncation; `done` = terminated or truncated cuts multi-step returns. `reward` is what
    the targets use: the env's reward less `info["paid_at_truncation"]` where the env reports it (reward_timing
    "on_measure": owed rewards paid only because a time limit cut the episode, which the bootstrap from `next_obs`
    already counts); the episode's scores (`episode`) keep every payment."""

    obs: jax.Array
    action: jax.Array
    reward: jax.Array
    next_obs: jax.Array
    terminated: jax.Array
    done: jax.Array
    measured: jax.Array
    episode: EpisodeMetrics | None  # totals of the episode that ended here (valid where episode_done)
    episode_done: jax.Array | None  # (a `rollout`'s stacked transitions leave both out: it sums them instead)


def reset_envs(env: Any, env_params: Any, key: jax.Array, num_envs: int) -> EnvBatch:
    obs, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(key, num_envs), env_params)
    return EnvBatch(obs, state, jnp.ones(num_envs, bool))


def step_envs(
    env: Any, env_params: Any, batch: EnvBatch, action: jax.Array, key: jax.Array
) -> tuple[EnvBatch, Transition]:
    keys = jax.random.split(key, batch.obs.shape[0])
    obs, state, reward, terminated, truncated, info = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
        keys, batch.state, action, env_params
    )
    if "paid_at_truncation" in info:  # counted once, by the bootstrap value (see `Transition`)
        reward = reward - info["paid_at_truncation"]
    transition = Transition(
        obs=batch.obs,
        action=action,
        reward=reward,
        next_obs=info["final_observation"],
        terminated=terminated,
        done=jnp.logical_or(terminated, truncated),
        measured=info["measured"],
        episode=info["episode"],
        episode_done=info["episode_done"],
    )
    return EnvBatch(obs, state, transition.done), transition


# act(batch, agent_carry, key) -> (action, agent_carry, extras). `agent_carry` is a recurrent agent's hidden
# state (reset where `batch.first`), or None.
ActFn = Callable[[EnvBatch, Any, jax.Array], tuple[jax.Array, Any, Any]]


def rollout(
    env: Any,
    env_params: Any,
    batch: EnvBatch,
    agent_carry: Any,
    act: ActFn,
    key: jax.Array,
    num_steps: int,
) -> tuple[EnvBatch, Any, Transition, Any, FinishedEpisodes]:
    """Step every env `num_steps` times with `act`.

    Returns the final batch and agent carry, the stacked transitions [num_steps, num_envs, ...] (without their
    `episode` metrics), the stacked extras (for example the policy outputs PPO keeps) and the episodes that
    finished, per env ([num_envs]). The episode sums ride in the loop's carry: stacking their per-step totals cost
    one more write per metric and step (a kernel each on a GPU).
    """

    def one_step(carry: tuple[EnvBatch, Any, FinishedEpisodes], step_key: jax.Array):
        batch, agent_carry, episodes = carry
        act_key, env_key = jax.random.split(step_key)
        action, agent_carry, extras = act(batch, agent_carry, act_key)
        batch, transition = step_envs(env, env_params, batch, action, env_key)
        episodes = episodes.add(transition.episode_done, transition.episode)
        return (batch, agent_carry, episodes), (transition.replace(episode=None, episode_done=None), extras)

    initial = (batch, agent_carry, FinishedEpisodes.zeros(batch.first.shape))
    (batch, agent_carry, episodes), (transitions, extras) = jax.lax.scan(
        one_step, initial, jax.random.split(key, num_steps)
    )
    return batch, agent_carry, transitions, extras, episodes
