"""Pure-JAX environments (gymnax API) and the registry behind `amjax.make`; `brax_env` adapts brax's physics
environments (ids "brax:<env_name>[:<backend>]", the optional `brax` extra)."""

from amjax.envs.registry import make_env, register, registered_envs

__all__ = ["make_env", "register", "registered_envs"]
