"""Wrappers: the active-measure MDP, per-episode statistics, and (optional) Gymnasium bridges."""

from amjax.wrappers.active_measure import (
    MODES,
    ActiveMeasure,
    AlwaysMeasured,
    MeasureParams,
    MeasureState,
)
from amjax.wrappers.episode_stats import EpisodeMetrics, EpisodeStats, EpisodeStatsState

__all__ = [
    "MODES",
    "ActiveMeasure",
    "AlwaysMeasured",
    "EpisodeStats",
    "EpisodeStatsState",
    "EpisodeMetrics",
    "MeasureParams",
    "MeasureState",
]
