"""The environment registry: ids -> pure-JAX (gymnax API) environments and their default params."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import gymnax
from gymnax.environments.environment import Environment

from amjax.envs import brax_env

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
    return sorted(set(_AMJAX_ENVS) | set(_CUSTOM_ENVS) | set(gymnax.registered_envs) | set(brax_ids))


def make_env(env_id: str) -> tuple[Environment, Any]:
    """Build the plain (unwrapped) environment `env_id` and its default params."""
    for table in (_CUSTOM_ENVS, _AMJAX_ENVS):
        if env_id in table:
            return table[env_id]()
    if env_id in gymnax.registered_envs:
        return gymnax.make(env_id)
    if isinstance(env_id, str) and env_id.startswith(brax_env.PREFIX):
        return brax_env.make_brax(env_id)
    raise ValueError(
        f"env_id: unknown environment {env_id!r}; allowed values: {', '.join(registered_envs())}, or "
        f"'{brax_env.PREFIX}<env_name>[:<backend>]' for any brax environment ({brax_env.INSTALL_HINT})"
    )
