"""Other JAX environment suites behind the gymnax API: ids "craftax:<name>" and "xminigrid:<name>".

`make_suite_env("craftax:Craftax-Classic-Symbolic-v1")` builds the suite's env and wraps it as a gymnax 1.0
`Environment` (`SuiteEnv`), so `amjax.make` puts the active-measure wrapper on top as on any other env and the
agents, sweeps and the Gymnasium bridge take it by id. Each suite is an optional dependency imported on first use
(`pip install "amjax-rl[craftax]"`, `"amjax-rl[xminigrid]"`); this module imports without them.

What the adapters do:
- Auto-reset and `info["final_observation"]` come from gymnax's `Environment.step`, which splits the step's key
  and resets from one half where an episode ended (the suites' own auto-reset wrappers are not used).
- Time limits end an episode as *truncated* (`SuiteParams.max_steps_in_episode`, the suite's own limit); the
  suite's other episode ends (Craftax: death or lava; xland-minigrid: the goal reached) are *terminated*.
- Craftax (Matthews et al. 2024): the symbolic variants observe a vector (Classic: 1,345 floats in [0, 1]), the
  pixel ones an image; the env's `step_env` without auto-reset is stepped. Episodes last up to 10,000 steps.
- xland-minigrid (Nikulin et al. 2024): the agent's 7 x 7 view has two integer channels, a tile id and a colour id,
  which the adapter shows one-hot (`NUM_TILES` + `NUM_COLORS` = 25 channels of 0 / 1), so a CNN reads categories,
  not magnitudes. xland-minigrid draws its randomness from a key in its own state, seeded by the reset key (a
  threefry key as it is; any other key through its bits, `_threefry`).

Suites that do not install with amjax's pins (docs/guide/envs.md says why): navix, popgym-arcade, kinetix.
"""

from __future__ import annotations

import functools
import importlib.util
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct
from gymnax.environments import environment, spaces

SUITES = {"craftax": 'pip install "amjax-rl[craftax]"', "xminigrid": 'pip install "amjax-rl[xminigrid]"'}
# The ids `registered_envs()` lists when the suite is installed (the ones amjax's tests step); the suite's other
# names work too.
LISTED = {
    "craftax": ("craftax:Craftax-Classic-Symbolic-v1",),
    "xminigrid": ("xminigrid:MiniGrid-Empty-8x8", "xminigrid:MiniGrid-DoorKey-5x5"),
}


@struct.dataclass
class SuiteParams(environment.EnvParams):
    inner: Any = None  # the suite's own env params


@struct.dataclass
class SuiteState(environment.EnvState):
    inner: Any  # the suite's own env state (xland-minigrid: its TimeStep)


def suite_of(env_id: Any) -> str | None:
    """The suite an id names ("craftax" for "craftax:..."), or None."""
    if not isinstance(env_id, str) or ":" not in env_id:
        return None
    suite = env_id.split(":", 1)[0]
    return suite if suite in SUITES else None


def installed(suite: str) -> bool:
    return importlib.util.find_spec(suite) is not None


def listed_ids() -> tuple[str, ...]:
    """The listed ids of the suites that are installed."""
    return tuple(env_id for suite, ids in LISTED.items() if installed(suite) for env_id in ids)


class SuiteEnv(environment.Environment[SuiteState, SuiteParams]):
    """A suite's env as a gymnax `Environment`: `reset(key, inner_params) -> (obs, inner_state)` and
    `step(key, inner_state, action, inner_params) -> (obs, inner_state, reward, terminated)` of the suite's own
    env, with its spaces (see the module docstring)."""

    def __init__(
        self,
        env_id: str,
        reset: Callable[..., tuple[Any, Any]],
        step: Callable[..., tuple[Any, Any, Any, Any]],
        params: SuiteParams,
        observation_space: spaces.Box,
        num_actions: int,
    ):
        super().__init__()
        self.env_id = env_id
        self._reset, self._step = reset, step
        self._params, self._observation_space, self._num_actions = params, observation_space, num_actions

    @property
    def default_params(self) -> SuiteParams:
        return self._params

    def reset_env(self, key: jax.Array, params: SuiteParams) -> tuple[jax.Array, SuiteState]:
        obs, inner = self._reset(key, params.inner)
        return obs, SuiteState(time=0, inner=inner)

    def step_env(
        self, key: jax.Array, state: SuiteState, action: Any, params: SuiteParams
    ) -> tuple[jax.Array, SuiteState, jax.Array, jax.Array, dict[str, Any]]:
        obs, inner, reward, terminated = self._step(key, state.inner, action, params.inner)
        terminated = jnp.asarray(terminated, bool)
        info = {"discount": 1.0 - terminated.astype(jnp.float32)}
        return obs, SuiteState(time=state.time + 1, inner=inner), jnp.asarray(reward, jnp.float32), terminated, info

    @property
    def name(self) -> str:
        return self.env_id

    @property
    def num_actions(self) -> int:
        return self._num_actions

    def action_space(self, params: SuiteParams | None = None) -> spaces.Discrete:
        return spaces.Discrete(self._num_actions)

    def observation_space(self, params: SuiteParams | None = None) -> spaces.Box:
        return self._observation_space


def make_suite_env(env_id: str) -> tuple[SuiteEnv, SuiteParams]:
    """The env `env_id` ("craftax:<name>" or "xminigrid:<name>") and its default params; ValueError for an unknown
    name (listing the suite's), ImportError naming the extra to install if the suite is missing."""
    suite = suite_of(env_id)
    if suite is None:
        raise ValueError(f"env_id: {env_id!r} names no suite; allowed prefixes: {', '.join(s + ':' for s in SUITES)}")
    if not installed(suite):
        raise ImportError(f"env_id {env_id!r} needs {suite}, an optional dependency: {SUITES[suite]}")
    return _cached(env_id)


@functools.cache
def _cached(env_id: str) -> tuple[SuiteEnv, SuiteParams]:
    """One env object per id, so that every `make` of it shares the jitted functions."""
    suite, name = env_id.split(":", 1)
    return (_craftax if suite == "craftax" else _xminigrid)(env_id, name)


def _craftax(env_id: str, name: str) -> tuple[SuiteEnv, SuiteParams]:
    from craftax.craftax_env import make_craftax_env_from_name

    try:
        env = make_craftax_env_from_name(name, auto_reset=False)
    except Exception as error:  # craftax raises a bare ValueError("Unknown Craftax environment")
        raise ValueError(f"env_id: {env_id!r}: {error}; e.g. {', '.join(LISTED['craftax'])}") from error
    inner_params = env.default_params

    def step(key, state, action, params):
        obs, state, reward, done, _ = env.step_env(key, state, action, params)
        return obs, state, reward, done & (state.timestep < params.max_timesteps)  # the time limit: truncated

    inner_space = env.observation_space(inner_params)
    low = jnp.broadcast_to(jnp.asarray(inner_space.low, jnp.float32), inner_space.shape)
    high = jnp.broadcast_to(jnp.asarray(inner_space.high, jnp.float32), inner_space.shape)
    params = SuiteParams(max_steps_in_episode=int(inner_params.max_timesteps), inner=inner_params)
    space = spaces.Box(low, high, inner_space.shape, jnp.float32)
    return SuiteEnv(env_id, env.reset_env, step, params, space, int(env.action_space(inner_params).n)), params


def _threefry(key: jax.Array) -> jax.Array:
    """`key` as a raw threefry key (uint32[2]), for a suite that stores a key in its state: a threefry key's own
    data, else a key drawn from its bits. amjax's loops pass typed, raw and Philox keys, and the stored key must
    have one type (for the auto-reset's select) and be plain data (sweep checkpoints hold env states)."""
    if not jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
        key = jax.random.wrap_key_data(key) if key.shape == (2,) else jax.random.key(jax.random.bits(key))
    if str(jax.random.key_impl(key)) != "threefry2x32":
        key = jax.random.key(jax.random.bits(key, dtype=jnp.uint32))
    return jax.random.key_data(key)


def _xminigrid(env_id: str, name: str) -> tuple[SuiteEnv, SuiteParams]:
    import xminigrid
    from xminigrid.core.constants import NUM_COLORS, NUM_TILES

    if name not in xminigrid.registered_environments():
        raise ValueError(
            f"env_id: {env_id!r}: xland-minigrid has no {name!r}; allowed: "
            + ", ".join(f"xminigrid:{n}" for n in xminigrid.registered_environments())
        )
    env, inner_params = xminigrid.make(name)

    def one_hot(view: jax.Array) -> jax.Array:
        tiles = jax.nn.one_hot(view[..., 0], NUM_TILES, dtype=jnp.float32)
        colours = jax.nn.one_hot(view[..., 1], NUM_COLORS, dtype=jnp.float32)
        return jnp.concatenate([tiles, colours], -1)

    def reset(key, params):
        timestep = env.reset(params, _threefry(key))
        return one_hot(timestep.observation), timestep

    def step(key, timestep, action, params):
        timestep = env.step(params, timestep, action)  # its randomness: the key in its state
        return one_hot(timestep.observation), timestep, timestep.reward, timestep.discount == 0

    height, width, _ = env.observation_shape(inner_params)
    shape = (height, width, NUM_TILES + NUM_COLORS)
    params = SuiteParams(max_steps_in_episode=int(inner_params.max_steps), inner=inner_params)
    space = spaces.Box(0.0, 1.0, shape, jnp.float32)
    return SuiteEnv(env_id, reset, step, params, space, int(env.num_actions(inner_params))), params


__all__ = ["LISTED", "SUITES", "SuiteEnv", "SuiteParams", "SuiteState", "make_suite_env", "suite_of"]
