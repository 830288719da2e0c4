"""Wrappers: the active-measure MDP, per-episode statistics, and (optional) Gymnasium bridges."""

from amjax.wrappers.active_measure import (
    MODES,
    ActiveMeasure,
    AlwaysMeasured,
    MeasureParams,
    MeasureState,
)
from amjax.wrappers.episode_stats import EpisodeStats, EpisodeStatsState, EpisodeTotals

__all__ = [
    "MODES",
    "ActiveMeasure",
    "AlwaysMeasured",
    "EpisodeStats",
    "EpisodeStatsState",
    "EpisodeTotals",
    "MeasureParams",
    "MeasureState",
]
