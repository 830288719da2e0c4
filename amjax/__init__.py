"""amjax: active-measure reinforcement learning in JAX.

Layers, bottom to top: `amjax.envs` (pure-JAX environments, gymnax API) -> `amjax.wrappers` (the active-measure
MDP, episode statistics, Gymnasium bridges) -> `amjax.agents` (networks and one file per algorithm) ->
`amjax.sweep` (grids of configurations trained in one compiled program, results, resume).
"""

from amjax.envs.registry import make_env, register, registered_envs
from amjax.make import make
from amjax.wrappers.active_measure import ActiveMeasure, AlwaysMeasured, MeasureParams, MeasureState
from amjax.wrappers.episode_stats import EpisodeStats

__version__ = "0.1.0"

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
