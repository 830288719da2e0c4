"""Wrappers: the active-measure MDP and its setting (`MeasureSpec`), per-episode statistics, and Gymnasium bridges."""

from amjax.wrappers.active_measure import (
    MODES,
    ActiveMeasure,
    AlwaysMeasured,
    MeasureParams,
    MeasureState,
)
from amjax.wrappers.episode_stats import EpisodeMetrics, EpisodeStats, EpisodeStatsState
from amjax.wrappers.spec import MeasureSpec

__all__ = [
    "MODES",
    "ActiveMeasure",
    "AlwaysMeasured",
    "EpisodeStats",
    "EpisodeStatsState",
    "EpisodeMetrics",
    "MeasureParams",
    "MeasureSpec",
    "MeasureState",
]
