"""The cost front of cost-conditioned agents: each saved policy of a `cost_conditioned` sweep scored at a grid of
costs, beside per-cost specialists from an ordinary sweep.

```python
points = cost_front("runs/pareto/conditioned", costs=(0.0, 0.1, 0.2))   # one row per policy and cost
table = front_table(points, load_results("runs/pareto/specialists").summary)
plot_front(points, specialists=load_results("runs/pareto/specialists").summary, path="front.png")
```
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import jax
import pandas as pd
from matplotlib.figure import Figure

from amjax.analysis.results import load_results
from amjax.sweep.runner import load_sweep_policy

FRONT_KEY = 20_261_126  # the front's test episodes: apart from the sweeps' training and evaluation keys
METRICS = ["return", "raw_return", "measured"]


def cost_front(folder: str | Path, costs: Sequence[float], episodes: int = 100, key: int = FRONT_KEY) -> pd.DataFrame:
    """Every saved best policy of the cost-conditioned sweep in `folder`, evaluated at each cost on `episodes`
    fresh greedy test episodes (`SavedPolicy.evaluate(..., cost=c)`): columns agent, seed,
    config_id, cost, return (costed), raw_return, measured (fraction of steps)."""
    summary = load_results(folder).summary
    rows = []
    for run in summary.itertuples():
        policy = load_sweep_policy(folder, run.config_id)
        if not policy.config.cost_conditioned:
            raise ValueError(
                f"folder: {run.config_id} in {folder} is not cost-conditioned; a front needs a sweep "
                "with cost_conditioned=True"
            )
        for cost in costs:
            means = policy.evaluate(jax.random.key(key), episodes, cost=float(cost))
            rows.append(
                {
                    "agent": run.agent,
                    "seed": run.seed,
                    "config_id": run.config_id,
                    "cost": float(cost),
                    "return": means["costed_return"],
                    "raw_return": means["raw_return"],
                    "measured": means["measurements"] / means["length"],
                }
            )
    return pd.DataFrame(rows)


def front_medians(points: pd.DataFrame) -> pd.DataFrame:
    """Medians over seeds per agent and cost."""
    return points.assign(cost=points.cost.round(6)).groupby(["agent", "cost"], as_index=False)[METRICS].median()


def specialist_medians(summary: pd.DataFrame) -> pd.DataFrame:
    """An ordinary sweep's medians over seeds per agent and cost of its best policies re-scored on fresh episodes,
    and of the paper's best-of-evaluations metric (biased upward; a conditioned run has none per cost: its
    evaluations mix costs)."""
    costed = summary[~summary.vanilla] if "vanilla" in summary else summary
    return (
        costed.assign(cost=costed.cost.round(6))
        .groupby(["agent", "cost"], as_index=False)
        .agg(
            **{
                "return": ("best_policy_return", "median"),
                "raw_return": ("best_policy_raw_return", "median"),
                "measured": ("best_policy_measured_fraction", "median"),
                "best": ("best_return", "median"),
            }
        )
    )


def front_table(points: pd.DataFrame, specialists: pd.DataFrame) -> pd.DataFrame:
    """At the specialists' costs: the conditioned medians, the specialists' and the gap, (conditioned -
    specialists) / |specialists| in costed reward: positive when the conditioned agent scores more, whatever the
    sign of the rewards (Acrobot's are negative)."""
    special = specialist_medians(specialists)
    table = front_medians(points).merge(special, on=["agent", "cost"], suffixes=(" conditioned", " specialists"))
    table = table.rename(columns={"best": "best specialists (paper's metric)"})
    table["gap"] = (table["return conditioned"] - table["return specialists"]) / table["return specialists"].abs()
    return table


def plot_front(
    points: pd.DataFrame,
    specialists: pd.DataFrame | None = None,
    path: str | Path | None = None,
    title: str | None = None,
) -> Figure:
    """Costed reward and measured fraction against the cost: a line per conditioned agent (medians over seeds),
    stars for the specialists (an ordinary sweep's summary)."""
    medians = front_medians(points)
    special = None if specialists is None else specialist_medians(specialists)
    fig = Figure(figsize=(10, 4), layout="constrained")
    left, right = fig.subplots(1, 2)
    for agent, group in medians.groupby("agent"):
        line = left.plot(group.cost, group["return"], marker="o", label=f"{agent}, one conditioned agent")[0]
        right.plot(group.cost, group.measured, marker="o", color=line.get_color(), label=agent)
        if special is not None:
            spec = special[special.agent == agent]
            style = {"marker": "*", "s": 150, "color": line.get_color(), "edgecolor": "black", "zorder": 3}
            left.scatter(spec.cost, spec["return"], label=f"{agent}, one specialist per cost", **style)
            right.scatter(spec.cost, spec.measured, **style)
    left.set(xlabel="cost per measurement", ylabel="costed reward (median over seeds)")
    right.set(xlabel="cost per measurement", ylabel="measured fraction of steps")
    left.legend(fontsize="small")
    if title:
        fig.suptitle(title)
    if path is not None:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path, dpi=120)
    return fig
