"""Per-episode statistics, correct across the auto-reset inside `step` (like gymnax's LogWrapper)."""

from __future__ import annotations

from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct
from gymnax.wrappers.purerl import GymnaxWrapper


@struct.dataclass
class EpisodeTotals:
    """Running totals of the current episode."""

    costed_return: jax.Array
    raw_return: jax.Array
    length: jax.Array
    measurements: jax.Array

    @classmethod
    def zeros(cls) -> EpisodeTotals:
        return cls(jnp.float32(0.0), jnp.float32(0.0), jnp.int32(0), jnp.int32(0))


@struct.dataclass
class EpisodeStatsState:
    env_state: Any
    totals: EpisodeTotals


class EpisodeStats(GymnaxWrapper):
    """Adds `info["episode"]`: an `EpisodeTotals` of the episode that ended on this step, and `done`.

    The totals are only meaningful where `info["episode_done"]` is true (mask with it). The wrapped env must
    report `raw_reward` and `measured` in its info (`ActiveMeasure` and `AlwaysMeasured` do).
    `measurements` counts paid measurements; the free first observation of an episode is not counted.
    """

    @partial(jax.jit, static_argnames=("self",))
    def reset(self, key: jax.Array, params: Any = None) -> tuple[jax.Array, EpisodeStatsState]:
        obs, env_state = self._env.reset(key, params)
        return obs, EpisodeStatsState(env_state, EpisodeTotals.zeros())

    @partial(jax.jit, static_argnames=("self",))
    def step(
        self, key: jax.Array, state: EpisodeStatsState, action: jax.Array, params: Any = None
    ) -> tuple[jax.Array, EpisodeStatsState, jax.Array, jax.Array, jax.Array, dict[str, Any]]:
        obs, env_state, reward, terminated, truncated, info = self._env.step(
            key, state.env_state, action, params
        )
        done = jnp.logical_or(terminated, truncated)
        totals = EpisodeTotals(
            costed_return=state.totals.costed_return + reward,
            raw_return=state.totals.raw_return + info["raw_reward"],
            length=state.totals.length + 1,
            measurements=state.totals.measurements + info["measured"].astype(jnp.int32),
        )
        carried = jax.tree.map(lambda t, z: jnp.where(done, z, t), totals, EpisodeTotals.zeros())
        info = {**info, "episode": totals, "episode_done": done}
        return obs, EpisodeStatsState(env_state, carried), reward, terminated, truncated, info
