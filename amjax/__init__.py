"""amjax: active-measure reinforcement learning in JAX.

Layers, bottom to top: `amjax.envs` (pure-JAX environments, gymnax API) -> `amjax.wrappers` (the active-measure
MDP, episode statistics, Gymnasium bridges) -> `amjax.agents` (networks and one file per algorithm) ->
`amjax.sweep` (grids of configurations trained in one compiled program, results, resume).

On import, amjax gives JAX one CPU device per core (see `amjax.cores`) so that sweeps can use every core.
"""

from importlib import metadata as _metadata

from amjax.cores import default_cpu_devices

default_cpu_devices()  # before anything imports gymnax, which starts JAX's backend

from amjax.envs.registry import make_env, register, registered_envs  # noqa: E402
from amjax.make import make  # noqa: E402
from amjax.wrappers.active_measure import ActiveMeasure, AlwaysMeasured, MeasureParams, MeasureState  # noqa: E402
from amjax.wrappers.episode_stats import EpisodeStats  # noqa: E402

try:
    __version__ = _metadata.version("amjax-rl")  # the distribution's name; the import package is `amjax`
except _metadata.PackageNotFoundError:  # a source tree on sys.path without an install
    __version__ = "0+unknown"

__all__ = [
    "ActiveMeasure",
    "AlwaysMeasured",
    "EpisodeStats",
    "MeasureParams",
    "MeasureState",
    "make",
    "make_env",
    "register",
    "registered_envs",
]
