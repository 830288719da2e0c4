"""amjax: active-measure reinforcement learning in JAX.

Layers, bottom to top: `amjax.envs` (pure-JAX environments, gymnax API) -> `amjax.wrappers` (the active-measure
MDP, episode statistics, Gymnasium bridges) -> `amjax.agents` (networks and one file per algorithm) ->
`amjax.sweep` (grids of configurations trained in one compiled program, results, resume).

Importing amjax does not start JAX (its names below load on first use); it adds one option to `XLA_FLAGS`, read
at JAX's first compile, that compiles small loops as one kernel each (`amjax.cores.xla_cpu_options`;
`AMJAX_XLA_OPTIONS=0` turns it off). `amjax.use_all_cores()`, called before JAX
starts, gives JAX one CPU device per core so that sweeps can use every core.
"""

from importlib import import_module as _import_module
from importlib import metadata as _metadata

from amjax.cores import use_all_cores
from amjax.cores import xla_cpu_options as _xla_cpu_options

_xla_cpu_options()

try:
    __version__ = _metadata.version("amjax-rl")  # the distribution's name; the import package is `amjax`
except _metadata.PackageNotFoundError:  # a source tree on sys.path without an install
    __version__ = "0+unknown"

# Public names and the modules they live in, imported on first access (PEP 562): importing gymnax starts JAX's
# backend, which must not happen before a program had the chance to call `use_all_cores()`.
_LAZY = {
    "make_env": "amjax.envs.registry",
    "register": "amjax.envs.registry",
    "registered_envs": "amjax.envs.registry",
    "make": "amjax.factory",
    "wrap": "amjax.factory",
    "ActiveMeasure": "amjax.wrappers.active_measure",
    "AlwaysMeasured": "amjax.wrappers.active_measure",
    "MeasureParams": "amjax.wrappers.active_measure",
    "MeasureState": "amjax.wrappers.active_measure",
    "MeasureSpec": "amjax.wrappers.spec",
    "EpisodeStats": "amjax.wrappers.episode_stats",
}


def __getattr__(name: str):
    if name in _LAZY:
        value = getattr(_import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'amjax' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *_LAZY])


__all__ = [*sorted(_LAZY), "use_all_cores"]
