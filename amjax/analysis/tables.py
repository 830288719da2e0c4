"""The paper's table (per env x agent x cost) and a dependency-free Markdown renderer for tables."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pandas as pd

from amjax.analysis.paper import paper_always_measure, paper_best_return
from amjax.analysis.results import SETTING, always_measure_bound, hyper_columns, quantiles

PAPER_TABLE_COLUMNS = [
    "seeds",
    "diverged",
    "best_return",
    "best_return_q25",
    "best_return_q75",
    "measured_fraction",
    "rescored_return",
    "rescored_return_q25",
    "rescored_return_q75",
    "rescored_measured_fraction",
    "measurement_reduction",
    "always_measure",
    "gain_vs_always_measure",
    "paper_best_return",
    "paper_always_measure",
]


def _setting_keys(summary: pd.DataFrame) -> list[str]:
    """The columns a table's rows are grouped by: env, agent, vanilla, cost and every swept hyperparameter."""
    return SETTING + [c for c in hyper_columns(summary) if summary[c].nunique(dropna=False) > 1]


def paper_table(summary: pd.DataFrame, results: pd.DataFrame | None = None) -> pd.DataFrame:
    """One row per env x agent x (vanilla, cost) (x swept hyperparameters), like the paper's results table.

    Columns (medians over seeds):
      best_return (+ _q25, _q75): best test costed reward reached during training (the paper's metric);
      measured_fraction: fraction of test steps measured at that best evaluation;
      rescored_return (+ _q25, _q75), rescored_measured_fraction: the best policy re-scored on fresh test episodes
        (`best_policy_*` of the summary; NaN where the sweep has not re-scored it): the unbiased figure;
      measurement_reduction: 1 - measured_fraction (the fraction of measurements saved vs always measuring);
      always_measure: the always-measure bound at this cost, from `results` (see `amjax.analysis.results`;
        NaN without `results`, and for vanilla rows);
      gain_vs_always_measure: best_return - always_measure;
      paper_best_return, paper_always_measure: the paper's numbers where it gives them (else NaN).
    """
    keys = _setting_keys(summary)
    rows = []
    for key, group in summary.groupby(keys, dropna=False, sort=True):
        row: dict[str, Any] = dict(zip(keys, key, strict=True))
        env, agent, vanilla, cost = row["env"], row["agent"], bool(row["vanilla"]), float(row["cost"])
        median, q25, q75 = quantiles(group.best_return)
        fraction = quantiles(group.best_measured_fraction)[0]
        nan = pd.Series([np.nan])
        rescored = quantiles(group.get("best_policy_return", nan))
        rescored_fraction = quantiles(group.get("best_policy_measured_fraction", nan))[0]
        bound = np.nan
        if results is not None and not vanilla:
            bound = float(always_measure_bound(results, env, [cost])[0])
        row.update(
            seeds=int(group.seed.nunique()),
            diverged=int(group.diverged.astype(bool).sum()),
            best_return=median,
            best_return_q25=q25,
            best_return_q75=q75,
            measured_fraction=fraction,
            rescored_return=rescored[0],
            rescored_return_q25=rescored[1],
            rescored_return_q75=rescored[2],
            rescored_measured_fraction=rescored_fraction,
            measurement_reduction=1.0 - fraction,
            always_measure=bound,
            gain_vs_always_measure=median - bound,
            paper_best_return=np.nan if vanilla else paper_best_return(env, agent, cost),
            paper_always_measure=np.nan if vanilla else paper_always_measure(env, cost),
        )
        rows.append(row)
    return pd.DataFrame(rows, columns=keys + PAPER_TABLE_COLUMNS)


def seed_spread(summary: pd.DataFrame) -> pd.DataFrame:
    """The spread over seeds beside `paper_table`'s medians: one row per env x agent x (vanilla, cost) (x swept
    hyperparameters) with the mean, sample standard deviation, minimum and maximum over seeds of the best test
    costed return and of the re-scored return (NaN where a column is missing or has under two seeds for the sd)."""
    keys = _setting_keys(summary)
    stats = {"mean": "mean", "sd": "std", "min": "min", "max": "max"}
    rows = []
    for key, group in summary.groupby(keys, dropna=False, sort=True):
        row: dict[str, Any] = dict(zip(keys, key, strict=True), seeds=int(group.seed.nunique()))
        for column, name in (("best_return", "best_return"), ("best_policy_return", "rescored_return")):
            values = group.get(column, pd.Series([np.nan])).astype(float)
            values = values[np.isfinite(values)]
            for label, method in stats.items():
                row[f"{name}_{label}"] = float(getattr(values, method)()) if len(values) else np.nan
        rows.append(row)
    return pd.DataFrame(rows)


def _cell(value: Any, digits: int) -> str:
    if isinstance(value, bool | np.bool_):
        return "yes" if value else "no"
    if isinstance(value, float | np.floating):
        if math.isnan(value):
            return "–"
        if value != 0 and abs(value) < 1:
            return f"{value:.{digits + 1}g}"  # small values (fractions, learning rates) keep significant digits
        return f"{value:.{digits}f}"
    return str(value).replace("|", "\\|")


def to_markdown(table: pd.DataFrame, digits: int = 2) -> str:
    """`table` as a GitHub Markdown table: floats to `digits` decimals (below 1 in magnitude, `digits` + 1
    significant digits), NaN as an en dash."""
    header = "| " + " | ".join(map(str, table.columns)) + " |"
    rule = "|" + "|".join("---:" if pd.api.types.is_numeric_dtype(table[c]) else "---" for c in table.columns) + "|"
    lines = [header, rule]
    for row in table.itertuples(index=False):
        lines.append("| " + " | ".join(_cell(v, digits) for v in row) + " |")
    return "\n".join(lines)
