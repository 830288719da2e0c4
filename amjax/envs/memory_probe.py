"""MemoryProbe: the smallest task that needs memory (gymnax API), for testing recurrent agents.

A cue c = +1 or -1 is drawn at reset and shown only in the first observation ([c]); every later observation is [0].
Each of the `max_steps_in_episode` = L steps pays +1/L if the action names the cue (action 1 for +1, 0 for -1)
and -1/L otherwise; the episode terminates after L steps. An agent that remembers the cue earns 1 per episode; a
memoryless one sees [0] from the second step on, guesses, and earns 1/L in expectation (the first step is free).

The registry serves it as "MemoryProbe-v0" (L = 5), so `amjax.make("MemoryProbe-v0", vanilla=True)` and
the agent configs (`env_id="MemoryProbe-v0", vanilla=True`) build it. With the active-measure wrapper in mode
"last" an agent can instead keep the cue on screen by never measuring, so the memory test uses `vanilla=True`.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from flax import struct
from gymnax.environments import environment, spaces


@struct.dataclass
class ProbeState(environment.EnvState):
    cue: jax.Array  # +1 or -1
    time: int


@struct.dataclass
class ProbeParams(environment.EnvParams):
    max_steps_in_episode: int = 5  # L: steps per episode, every one of them answered


class MemoryProbe(environment.Environment[ProbeState, ProbeParams]):
    @property
    def default_params(self) -> ProbeParams:
        return ProbeParams()

    def reset_env(self, key: jax.Array, params: ProbeParams) -> tuple[jax.Array, ProbeState]:
        cue = jnp.where(jax.random.bernoulli(key), 1.0, -1.0)
        state = ProbeState(cue=cue, time=0)
        return self.get_obs(state, params), state

    def step_env(
        self, key: jax.Array, state: ProbeState, action: Any, params: ProbeParams
    ) -> tuple[jax.Array, ProbeState, jax.Array, jax.Array, dict[str, Any]]:
        correct = (jnp.asarray(action) == 1) == (state.cue > 0)
        reward = jnp.where(correct, 1.0, -1.0) / params.max_steps_in_episode
        state = state.replace(time=state.time + 1)
        terminated = self.is_terminated(state, params)
        return self.get_obs(state, params), state, reward, terminated, {}

    def get_obs(self, state: ProbeState, params: ProbeParams | None = None, key: Any = None) -> jax.Array:
        return jnp.where(state.time == 0, state.cue, 0.0)[None].astype(jnp.float32)

    def is_terminated(self, state: ProbeState, params: ProbeParams) -> jax.Array:
        return jnp.asarray(state.time >= params.max_steps_in_episode)

    @property
    def name(self) -> str:
        return "MemoryProbe-v0"

    @property
    def num_actions(self) -> int:
        return 2

    def action_space(self, params: ProbeParams | None = None) -> spaces.Discrete:
        return spaces.Discrete(2)

    def observation_space(self, params: ProbeParams) -> spaces.Box:
        return spaces.Box(-1.0, 1.0, (1,), jnp.float32)

    def state_space(self, params: ProbeParams) -> spaces.Dict:
        return spaces.Dict(
            {
                "cue": spaces.Box(-1.0, 1.0, (), jnp.float32),
                "time": spaces.Discrete(params.max_steps_in_episode + 1),
            }
        )


__all__ = ["MemoryProbe", "ProbeParams", "ProbeState"]
