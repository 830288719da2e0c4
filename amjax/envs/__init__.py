"""Pure-JAX environments (gymnax API) and the registry behind `amjax.make`."""

from amjax.envs.registry import make_env, register, registered_envs

__all__ = ["make_env", "register", "registered_envs"]
