"""Reading a sweep's output folder and the aggregations every figure and table shares.

Terms used throughout `amjax.analysis`:
- a *setting* is one (env, agent, vanilla, cost) cell of the grid, pooled over seeds;
- the *costed return* is the test (greedy) return net of measurement costs; the *raw return* is before costs;
- the *always-measure bound* of an env at cost c is the best costed return an agent that measures on every step
  would score: max over the env's evaluation points (any agent, cost or vanilla run) of
  `eval_raw_return - c * eval_length`, i.e. what the best observed test episodes would score if every step were
  measured and paid for. For CartPole-v0, once some run reaches 200 steps, it is 200 x (1 - c), the paper's line.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import pandas as pd

from amjax.agents.registry import ALGORITHMS, algorithm
from amjax.sweep import storage
from amjax.sweep.grid import MEASURE_FIELDS, is_swept

SETTING = ["env", "agent", "vanilla", "cost"]
# Columns the runner writes itself; any other column of results.parquet is a swept hyperparameter.
_RESULT_COLUMNS = {*storage.ID_COLUMNS, "env_steps", "diverged", "measured_fraction", *storage.METRIC_COLUMNS}


class NotASweepError(ValueError):
    """The folder is missing, is not a sweep output folder, or holds no results yet."""


class SweepData(NamedTuple):
    """A sweep folder's tables: unpack as `results, summary, metadata = load_results(path)`."""

    results: pd.DataFrame  # one row per configuration x evaluation point
    summary: pd.DataFrame  # one row per configuration (recomputed from `results`, so partial sweeps work)
    metadata: dict[str, Any]  # metadata.json: the spec, package versions, machine


def hyper_columns(frame: pd.DataFrame) -> list[str]:
    """The swept hyperparameter columns of a results or summary table."""
    known = _RESULT_COLUMNS | {
        "best_return",
        "best_raw_return",
        "best_measured_fraction",
        "best_env_steps",
        "final_return",
        "final_raw_return",
        "final_measured_fraction",
        "measurement_reduction",
    }
    metrics = ("eval_", "train_", "best_", "final_")
    return sorted(c for c in frame.columns if c not in known and not c.startswith(metrics))


def load_results(path: str | Path) -> SweepData:
    """Read `path` (a folder written by `amjax.sweep.run_sweep` or `python -m train sweep`), finished or not.

    The per-configuration summary is recomputed from the results (the runner writes summary.parquet only at the
    end), so a sweep still running or killed half-way loads too. Raises `NotASweepError` with a clear message
    when the folder is missing, holds no metadata.json, or no evaluation has finished yet.
    """
    path = Path(path)
    if not path.is_dir():
        raise NotASweepError(f"{path}: no such folder")
    meta_path = path / "metadata.json"
    if not meta_path.is_file():
        raise NotASweepError(f"{path}: not a sweep folder (no metadata.json); give the --out folder of a sweep")
    try:
        metadata = json.loads(meta_path.read_text())
    except (OSError, ValueError) as error:
        raise NotASweepError(f"{meta_path}: unreadable ({error})") from None
    if not isinstance(metadata, dict) or "spec" not in metadata:
        raise NotASweepError(f"{meta_path}: not a sweep's metadata (no 'spec')")
    try:
        results = storage.read_table(path / "results")
        rescored = storage.read_table(path / "rescored")
    except storage.UnreadableFileError as error:
        raise NotASweepError(str(error)) from None
    if results is None or results.empty:
        raise NotASweepError(f"{path}: the sweep has no results yet (no evaluation has finished)")
    if "eval_measured_fraction" not in results:
        results["eval_measured_fraction"] = results.eval_measurements / results.eval_length
    summary = storage.summarize(results, hyper_columns(results), rescored)
    return SweepData(results, summary, metadata)


def quantiles(values: pd.Series) -> tuple[float, float, float]:
    """(median, 25th, 75th percentile) of the finite values; NaNs if there are none."""
    values = values[np.isfinite(values.astype(float))]
    if values.empty:
        return np.nan, np.nan, np.nan
    return float(values.median()), float(values.quantile(0.25)), float(values.quantile(0.75))


def best_hyperparams(results: pd.DataFrame, summary: pd.DataFrame | None = None) -> pd.DataFrame:
    """Keep, for each setting, the hyperparameter combination with the highest median best costed return.

    A sweep over hyperparameters has several combinations per (env, agent, vanilla, cost); the figures show one
    line each, so they show the tuned one. Filter the table yourself first to show another. Works on results
    and on summary tables; without hyperparameter columns the table is returned unchanged.
    """
    columns = [c for c in hyper_columns(results) if results[c].nunique(dropna=False) > 1]
    if not columns:
        return results
    if summary is None:
        summary = storage.summarize(results, hyper_columns(results)) if "eval_return" in results else results
    medians = summary.groupby(SETTING + columns, dropna=False).best_return.median().reset_index()
    medians = medians.sort_values("best_return", ascending=False, na_position="last")
    chosen = medians.drop_duplicates(SETTING, keep="first")[SETTING + columns]
    return results.merge(chosen, on=SETTING + columns, how="inner")


def learning_curve_table(results: pd.DataFrame, column: str = "eval_return") -> pd.DataFrame:
    """Median, 25th and 75th percentile over seeds of `column` per setting and evaluation point.

    Evaluation points of a configuration after it diverged are left out.
    """
    healthy = results[~results.diverged.astype(bool)]
    grouped = healthy.groupby(SETTING + ["env_steps"], sort=True)[column]
    table = grouped.agg(
        median="median",
        q25=lambda s: s.quantile(0.25),
        q75=lambda s: s.quantile(0.75),
        seeds="count",
    )
    return table.reset_index()


def always_measure_bound(results: pd.DataFrame, env: str, costs: Iterable[float]) -> np.ndarray:
    """The always-measure bound of `env` at each of `costs` (see the module docstring); NaN without data."""
    rows = results[(results.env == env) & ~results.diverged.astype(bool)]
    raw = rows.eval_raw_return.to_numpy(float)
    length = rows.eval_length.to_numpy(float)
    keep = np.isfinite(raw) & np.isfinite(length)
    raw, length = raw[keep], length[keep]
    costs = np.asarray(list(costs), float)
    if raw.size == 0:
        return np.full(costs.shape, np.nan)
    return (raw[None, :] - costs[:, None] * length[None, :]).max(axis=1)


def always_measure_return(results: pd.DataFrame) -> pd.Series:
    """Per evaluation point: what the same test episodes would score if every step were measured."""
    return results.eval_raw_return - results.cost * results.eval_length


def agent_config(metadata: dict[str, Any], agent: str, env: str | None = None, **changes: Any) -> Any:
    """The config of `agent` as the sweep in `metadata` trained it, with `changes` applied (e.g. `cost=0.2`).

    Static fields and budgets come from the sweep (metadata["agent_configs"], else the spec's single-valued
    hyperparameters); a swept traced field takes its first value. `env` picks among the sweep's envs (default:
    the first). Use it to retrain one configuration, e.g. to draw its measurement map.
    """
    config_type = algorithm(agent).config_type
    spec = metadata["spec"]
    env = spec["envs"][0] if env is None else env
    stored = [
        c
        for c in metadata.get("agent_configs", [])
        if c.get("agent") == agent and c.get("env_id") == env and not c.get("vanilla")
    ]
    if stored:
        fields = {k: tuple(v) if isinstance(v, list) else v for k, v in stored[0].items() if k != "agent"}
    else:
        owned = set(config_type.__dataclass_fields__)
        fields = {
            "env_id": env,
            "mode": spec.get("mode", "last"),
            "total_timesteps": spec["total_timesteps"],
            "eval_every": spec["eval_every"],
            "eval_episodes": spec["eval_episodes"],
            **{k: v for k, v in spec.get("hyperparams", {}).items() if k in owned and not isinstance(v, list)},
        }
    fields = {k: v for k, v in fields.items() if k in config_type.__dataclass_fields__}
    return config_type(**{**fields, "env_id": env, **changes}).validate()


def _planned_configs(spec: dict[str, Any]) -> int | None:
    """Configurations in a sweep spec (as stored in metadata.json, where tuples became lists); vanilla runs are not
    multiplied by the active-measure fields (`amjax.sweep.grid.MEASURE_FIELDS`), as the grid does."""
    try:
        total = 0
        for agent in spec["agents"]:
            fields = ALGORITHMS[agent].config_type.__dataclass_fields__ if agent in ALGORITHMS else None
            costed = plain = 1
            for key, value in spec.get("hyperparams", {}).items():
                scope, _, name = key.rpartition(".")
                if (fields is not None and name not in fields) or scope not in ("", agent):
                    continue
                if not scope and f"{agent}.{name}" in spec["hyperparams"]:
                    continue  # the agent's own value replaces the shared one
                count = len(value) if is_swept(name, value, None if fields is None else fields[name]) else 1
                costed *= count
                plain *= 1 if name in MEASURE_FIELDS else count
            total += len(spec["costs"]) * costed + bool(spec.get("vanilla")) * plain
        return len(spec["envs"]) * len(spec["seeds"]) * total
    except (KeyError, TypeError):
        return None


def sweep_progress(data: SweepData) -> dict[str, Any]:
    """How far a (possibly partial) sweep got: configurations and evaluation points done vs planned."""
    spec = data.metadata.get("spec", {})
    planned_configs = _planned_configs(spec)
    evals_per_config = None
    if spec.get("eval_every"):
        evals_per_config = int(spec["total_timesteps"]) // int(spec["eval_every"])
    done_points = len(data.results)
    planned_points = None
    if planned_configs is not None and evals_per_config is not None:
        planned_points = planned_configs * evals_per_config
    return {
        "configs_started": int(data.results.config_id.nunique()),
        "configs_planned": planned_configs,
        "points_done": done_points,
        "points_planned": planned_points,
        "finished": planned_points is not None and done_points >= planned_points,
    }
