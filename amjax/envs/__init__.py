"""Pure-JAX environments (gymnax API) and the registry behind `amjax.make`; `brax_env` adapts brax's physics
environments (ids "brax:<env_name>[:<backend>]", the optional `brax` extra)."""

from amjax.envs.registry import make_env, register, registered_envs
from amjax.files import write_compile_cache_whole

# Every program amjax builds starts here (envs under wrappers under agents): from now on this process writes JAX's
# persistent compilation cache entries whole, so a kill or a concurrent reader never meets half of one.
write_compile_cache_whole()

__all__ = ["make_env", "register", "registered_envs"]
