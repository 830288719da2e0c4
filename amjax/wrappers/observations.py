"""Observations as the active-measure wrapper takes them: vectors [d] or images [height, width, channels].

- A Discrete(n) observation (gymnax's FrozenLake-misc, for one) becomes its one-hot vector of n floats, so the stale
  flag, staleness features, budgets and instruments append to it as to any Box observation, and the agents' MLPs
  read it.
- A 2-D observation [height, width] (bsuite's Catch and DeepSea) gains a channel axis, [height, width, 1], so the
  flag and the other features append to it as constant channels, as to any image (MinAtar's [10, 10, C]).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from gymnax.environments import spaces
from gymnax.wrappers.purerl import GymnaxWrapper


def env_name(env: Any) -> str:
    """`env.name` (gymnax's environments have one), else its class name (an env of the user's own may not)."""
    return getattr(env, "name", type(env).__name__)


class MappedObservation(GymnaxWrapper):
    """`env` with every observation (and `info["final_observation"]`) passed through `convert`; subclasses set it and
    `observation_space`. Everything else is `env`'s."""

    def convert(self, obs: jax.Array) -> jax.Array:
        raise NotImplementedError

    def reset(self, key: jax.Array, params: Any = None) -> tuple[jax.Array, Any]:
        obs, state = self._env.reset(key, params)
        return self.convert(obs), state

    def step(self, key: jax.Array, state: Any, action: Any, params: Any = None) -> tuple[Any, ...]:
        obs, state, reward, terminated, truncated, info = self._env.step(key, state, action, params)
        info = {**info, "final_observation": self.convert(info["final_observation"])}
        return self.convert(obs), state, reward, terminated, truncated, info

    @property
    def name(self) -> str:
        return f"{type(self).__name__}({env_name(self._env)})"


class OneHotObservation(MappedObservation):
    """`env` with its Discrete(n) observations as float32 one-hot vectors; `observation_space` is Box(0, 1, (n,))."""

    def __init__(self, env: Any, env_params: Any = None):
        super().__init__(env)
        space = env.observation_space(env.default_params if env_params is None else env_params)
        if not isinstance(space, spaces.Discrete):
            raise TypeError(f"env: OneHotObservation needs a Discrete observation space, got {type(space).__name__}")
        self.num_values = int(space.n)

    def convert(self, obs: jax.Array) -> jax.Array:
        return jax.nn.one_hot(obs, self.num_values, dtype=jnp.float32)

    def observation_space(self, params: Any = None) -> spaces.Box:
        return spaces.Box(0.0, 1.0, (self.num_values,), jnp.float32)


class ChannelObservation(MappedObservation):
    """`env` with its 2-D observations [height, width] as float32 images [height, width, 1]; `observation_space` is
    the Box with that shape and the same bounds."""

    def __init__(self, env: Any, env_params: Any = None):
        super().__init__(env)
        space = env.observation_space(env.default_params if env_params is None else env_params)
        if not isinstance(space, spaces.Box) or len(space.shape) != 2:
            raise TypeError(f"env: ChannelObservation needs a 2-D Box observation space, got {space}")

    def convert(self, obs: jax.Array) -> jax.Array:
        return jnp.asarray(obs, jnp.float32)[..., None]

    def observation_space(self, params: Any = None) -> spaces.Box:
        space = self._env.observation_space(params)
        low = jnp.broadcast_to(jnp.asarray(space.low, jnp.float32), space.shape)[..., None]
        high = jnp.broadcast_to(jnp.asarray(space.high, jnp.float32), space.shape)[..., None]
        return spaces.Box(low, high, low.shape, jnp.float32)


def standard_observations(env: Any, env_params: Any) -> Any:
    """`env` with observations the wrapper and the agents take: a Discrete one as its one-hot vector
    (`OneHotObservation`), a 2-D one as an image with one channel (`ChannelObservation`), others as they are
    (vectors, and images [height, width, channels])."""
    space = env.observation_space(env_params)
    if isinstance(space, spaces.Discrete):
        return OneHotObservation(env, env_params)
    if isinstance(space, spaces.Box) and len(space.shape) == 2:
        return ChannelObservation(env, env_params)
    return env
