"""Per-episode statistics, correct across the auto-reset inside `step` (like gymnax's LogWrapper)."""

from __future__ import annotations

from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct
from gymnax.wrappers.purerl import GymnaxWrapper


@struct.dataclass
class EpisodeMetrics:
    """The statistics of an episode, one structure wherever they appear: the running totals of the current episode
    (this wrapper's state and `info["episode"]`), their sums over finished episodes (`agents.FinishedEpisodes`) and
    their means per episode (evaluation rows, re-scoring, `SavedPolicy.evaluate`)."""

    costed_return: jax.Array  # reward minus measurement costs
    raw_return: jax.Array  # the underlying env's reward
    length: jax.Array  # steps
    measurements: jax.Array  # paid measurements (the free first observation is not counted)

    @classmethod
    def zeros(cls) -> EpisodeMetrics:
        return cls(jnp.float32(0.0), jnp.float32(0.0), jnp.int32(0), jnp.int32(0))

    @property
    def measured_fraction(self) -> jax.Array:
        """Paid measurements per step."""
        return self.measurements / self.length

    def columns(self, prefix: str) -> dict[str, Any]:
        """The results-table columns of these metrics: `{prefix}return` (costed), `{prefix}raw_return`,
        `{prefix}length`, `{prefix}measurements`."""
        return {
            f"{prefix}return": self.costed_return,
            f"{prefix}raw_return": self.raw_return,
            f"{prefix}length": self.length,
            f"{prefix}measurements": self.measurements,
        }


@struct.dataclass
class EpisodeStatsState:
    env_state: Any
    totals: EpisodeMetrics


class EpisodeStats(GymnaxWrapper):
    """Adds `info["episode"]`: an `EpisodeMetrics` of the episode that ended on this step, and `done`.

    The totals are only meaningful where `info["episode_done"]` is true (mask with it). The wrapped env must
    report `raw_reward` and `measured` in its info (`ActiveMeasure` and `AlwaysMeasured` do).
    `measurements` counts paid measurements; the free first observation of an episode is not counted.
    """

    @partial(jax.jit, static_argnames=("self",))
    def reset(self, key: jax.Array, params: Any = None) -> tuple[jax.Array, EpisodeStatsState]:
        obs, env_state = self._env.reset(key, params)
        return obs, EpisodeStatsState(env_state, EpisodeMetrics.zeros())

    @partial(jax.jit, static_argnames=("self",))
    def step(
        self, key: jax.Array, state: EpisodeStatsState, action: jax.Array, params: Any = None
    ) -> tuple[jax.Array, EpisodeStatsState, jax.Array, jax.Array, jax.Array, dict[str, Any]]:
        obs, env_state, reward, terminated, truncated, info = self._env.step(key, state.env_state, action, params)
        done = jnp.logical_or(terminated, truncated)
        totals = EpisodeMetrics(
            costed_return=state.totals.costed_return + reward,
            raw_return=state.totals.raw_return + info["raw_reward"],
            length=state.totals.length + 1,
            measurements=state.totals.measurements + info["measured"].astype(jnp.int32),
        )
        carried = jax.tree.map(lambda t, z: jnp.where(done, z, t), totals, EpisodeMetrics.zeros())
        info = {**info, "episode": totals, "episode_done": done}
        return obs, EpisodeStatsState(env_state, carried), reward, terminated, truncated, info
