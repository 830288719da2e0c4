"""The environment registry: ids -> pure-JAX (gymnax API) environments and their default params."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import gymnax
import jax.numpy as jnp
from gymnax.environments import spaces
from gymnax.environments.environment import Environment
from gymnax.wrappers.purerl import GymnaxWrapper

from amjax.envs import brax_env, suites

EnvFactory = Callable[[], tuple[Environment, Any]]


def _cartpole_v0() -> tuple[Environment, Any]:
    # Gymnasium's CartPole-v0 is CartPole-v1 with a 200-step limit (the paper's setting).
    env, params = gymnax.make("CartPole-v1")
    return env, params.replace(max_steps_in_episode=200)


def _lunar_lander() -> tuple[Environment, Any]:
    from amjax.envs.lunar_lander import LunarLander

    env = LunarLander()
    return env, env.default_params


def _memory_probe() -> tuple[Environment, Any]:
    from amjax.envs.memory_probe import MemoryProbe

    env = MemoryProbe()
    return env, env.default_params


def _cstr() -> tuple[Environment, Any]:
    from amjax.envs.reactor import StirredTankReactor

    env = StirredTankReactor()
    return env, env.default_params


class CorrectedBounds(GymnaxWrapper):
    """`env` with the observation bounds `bounds(space) -> (low, high)` in place of those it declares; the rest is
    `env`'s own."""

    def __init__(self, env: Environment, bounds: Callable[[spaces.Box], tuple[Any, Any]]):
        super().__init__(env)
        self._bounds = bounds

    def observation_space(self, params: Any = None) -> spaces.Box:
        space = self._env.observation_space(params)
        low, high = (jnp.broadcast_to(jnp.asarray(b, jnp.float32), space.shape) for b in self._bounds(space))
        return spaces.Box(low, high, space.shape, jnp.float32)


UNBOUNDED = float(jnp.finfo(jnp.float32).max)  # gymnax's "unbounded"
# gymnax 1.0.1 declares observation bounds that two of its envs' own observations leave, which the wrapper's mode
# "random" samples within and mode "noisy" clips to, and Gymnasium's `check_env` rejects; corrected from each
# env's `get_obs`:
# - MemoryChain-bsuite (bsuite/memory_chain.py): the context bits are shown as 2c - 1 in {-1, 1} (declared low 0);
# - GaussianBandit-misc (misc/gaussian_bandit.py): [last reward (Gaussian: unbounded), one-hot action (2), time
#   normalised from [0, 100] to [-1, 1] (declared low 0)].
_GYMNAX_BOUNDS: dict[str, Callable[[spaces.Box], tuple[Any, Any]]] = {
    "MemoryChain-bsuite": lambda space: (-1.0, space.high),
    "GaussianBandit-misc": lambda space: (
        jnp.array([-UNBOUNDED, 0.0, 0.0, -1.0]),
        jnp.array([UNBOUNDED, 1.0, 1.0, UNBOUNDED]),
    ),
}


def _gymnax(env_id: str) -> tuple[Environment, Any]:
    env, params = gymnax.make(env_id)
    if env_id in _GYMNAX_BOUNDS:
        env = CorrectedBounds(env, _GYMNAX_BOUNDS[env_id])
    return env, params


_AMJAX_ENVS: dict[str, EnvFactory] = {
    "CartPole-v0": _cartpole_v0,
    "LunarLander-v3": _lunar_lander,
    "MemoryProbe-v0": _memory_probe,
    "CSTR-v0": _cstr,
}
_CUSTOM_ENVS: dict[str, EnvFactory] = {}


def register(env_id: str, factory: EnvFactory) -> None:
    """Register `factory() -> (env, default_params)` under `env_id` (a gymnax-API environment)."""
    if not isinstance(env_id, str) or not env_id:
        raise ValueError(f"env_id must be a non-empty string, got {env_id!r}")
    _CUSTOM_ENVS[env_id] = factory


def registered_envs() -> list[str]:
    """The ids `make_env` accepts: amjax's own, user-registered ones, gymnax's, and (with brax installed) three of
    brax's; any "brax:<env_name>[:<backend>]" works too (`amjax.envs.brax_env`)."""
    brax_ids = brax_env.LISTED if brax_env.brax_installed() else ()
    others = set(brax_ids) | set(suites.listed_ids())
    return sorted(set(_AMJAX_ENVS) | set(_CUSTOM_ENVS) | set(gymnax.registered_envs) | others)


def make_env(env_id: str) -> tuple[Environment, Any]:
    """Build the plain (unwrapped) environment `env_id` and its default params."""
    for table in (_CUSTOM_ENVS, _AMJAX_ENVS):
        if env_id in table:
            return table[env_id]()
    if env_id in gymnax.registered_envs:
        return _gymnax(env_id)
    if isinstance(env_id, str) and env_id.startswith(brax_env.PREFIX):
        return brax_env.make_brax(env_id)
    if suites.suite_of(env_id):
        return suites.make_suite_env(env_id)
    raise ValueError(
        f"env_id: unknown environment {env_id!r}; allowed values: {', '.join(registered_envs())}, or "
        f"'{brax_env.PREFIX}<env_name>[:<backend>]' for any brax environment ({brax_env.INSTALL_HINT}), "
        f"'craftax:<name>' or 'xminigrid:<name>' ({', '.join(suites.SUITES.values())})"
    )
