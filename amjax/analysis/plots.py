"""Figures of a sweep, as in Bellinger et al. (2022): learning curves per cost, vanilla vs cost 0, best costed
reward vs cost, and agent comparison bars.

Every function takes the tables of `load_results` (or of `run_sweep`), returns a `matplotlib.figure.Figure`
(built without pyplot, so it works headless and leaves no global state) and, given `path`, also saves it (the
suffix picks the format: .png, .svg, .pdf). Lines and bars are medians over seeds; bands and error bars span the
25th to 75th percentile. Evaluation points after a configuration diverged are left out. When the sweep varies
hyperparameters, each setting shows its best combination (`amjax.analysis.best_hyperparams`).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib import colormaps
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from amjax.analysis.paper import PAPER_ALWAYS_MEASURE, PAPER_BEST_RETURN
from amjax.analysis.results import (
    always_measure_bound,
    always_measure_return,
    best_hyperparams,
    learning_curve_table,
    quantiles,
)

BOUND_STYLE = {"color": "0.35", "linestyle": ":", "linewidth": 1.5}
REFERENCE_COLOR = "black"  # the cost-0 curve


def save_figure(fig: Figure, path: str | Path, formats: Sequence[str] = ()) -> list[Path]:
    """Save `fig` to `path` (format from its suffix) and to the same stem with each extra suffix in `formats`."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    paths = [path] + [path.with_suffix("." + f.lstrip(".")) for f in formats if "." + f.lstrip(".") != path.suffix]
    for p in paths:
        fig.savefig(p, dpi=120, bbox_inches="tight")
    return paths


def _finish(fig: Figure, path: str | Path | None) -> Figure:
    if path is not None:
        save_figure(fig, path)
    return fig


def _grid(count: int, ncols: int, size: tuple[float, float] = (4.8, 3.4)) -> tuple[Figure, list[Axes]]:
    ncols = max(1, min(ncols, count))
    nrows = max(1, -(-count // ncols))
    fig = Figure(figsize=(size[0] * ncols, size[1] * nrows), layout="constrained")
    axes = fig.subplots(nrows, ncols, squeeze=False).ravel().tolist()
    for ax in axes[count:]:
        ax.set_visible(False)
    return fig, axes[:count]


def _select(frame: pd.DataFrame, envs: Sequence[str] | None, agents: Sequence[str] | None) -> pd.DataFrame:
    if envs is not None:
        frame = frame[frame.env.isin(envs)]
    if agents is not None:
        frame = frame[frame.agent.isin(agents)]
    if frame.empty:
        raise ValueError("no results for the requested envs / agents")
    return frame


def _panels(frame: pd.DataFrame) -> list[tuple[str, str]]:
    return sorted(set(zip(frame.env, frame.agent, strict=True)))


def cost_colors(costs: Sequence[float]) -> dict[float, object]:
    """Cost 0 in black (the reference); other costs along viridis, cheapest first."""
    positive = sorted(c for c in set(costs) if c > 0)
    cmap = colormaps["viridis"]
    colors: dict[float, object] = {0.0: REFERENCE_COLOR}
    for i, cost in enumerate(positive):
        colors[cost] = cmap(0.2 + 0.6 * i / max(len(positive) - 1, 1))
    return colors


def _band(ax: Axes, curve: pd.DataFrame, color: object, label: str, linestyle: str = "-", band: bool = True) -> None:
    ax.plot(curve.env_steps, curve["median"], color=color, label=label, linestyle=linestyle, linewidth=1.8)
    if band:
        ax.fill_between(curve.env_steps, curve.q25, curve.q75, color=color, alpha=0.18, linewidth=0)


def learning_curves(
    results: pd.DataFrame,
    *,
    raw: bool = False,
    bound: str = "best",
    envs: Sequence[str] | None = None,
    agents: Sequence[str] | None = None,
    path: str | Path | None = None,
) -> Figure:
    """Test costed return vs env steps, one panel per env x agent and one line per cost (cost 0 in black, the
    reference), median over seeds with an interquartile band.

    Args:
      raw: also draw the raw return (before measurement costs) of each cost as a dashed line.
      bound: "best" draws each cost's always-measure bound as a dotted horizontal line (the best observed test
        episodes of the env, measured on every step); "episodes" instead draws, per cost, what the curve's own
        test episodes would score if every step were measured (raw return - cost x length), dotted; "none".
    """
    if bound not in ("best", "episodes", "none"):
        raise ValueError(f"bound: got {bound!r}; allowed values: 'best', 'episodes', 'none'")
    selected = _select(best_hyperparams(results), envs, agents)
    costed = selected[~selected.vanilla.astype(bool)]
    if costed.empty:
        raise ValueError("learning_curves: no costed (non-vanilla) runs")
    colors = cost_colors(costed.cost.unique())
    costed = costed.assign(always=always_measure_return(costed))
    tables = {"eval_return": learning_curve_table(costed)}
    if raw:
        tables["eval_raw_return"] = learning_curve_table(costed, "eval_raw_return")
    if bound == "episodes":
        tables["always"] = learning_curve_table(costed, "always")
    panels = _panels(costed)
    fig, axes = _grid(len(panels), ncols=min(3, len(panels)))
    for ax, (env, agent) in zip(axes, panels, strict=True):
        for cost in sorted(costed[(costed.env == env) & (costed.agent == agent)].cost.unique()):
            curve = {name: t[(t.env == env) & (t.agent == agent) & (t.cost == cost)] for name, t in tables.items()}
            _band(ax, curve["eval_return"], colors[cost], f"cost {cost:g}")
            if raw:
                _band(ax, curve["eval_raw_return"], colors[cost], "_raw", linestyle="--", band=False)
            if bound == "episodes" and cost > 0:
                _band(ax, curve["always"], colors[cost], "_always", linestyle=":", band=False)
            if bound == "best" and cost > 0:
                level = always_measure_bound(results, env, [cost])[0]  # from every run of the env
                if np.isfinite(level):
                    ax.axhline(level, color=colors[cost], linestyle=":", linewidth=1.2)
        ax.set_title(f"{env} · {agent}")
        ax.set_xlabel("env steps")
        ax.set_ylabel("test costed return")
        ax.grid(alpha=0.3)
    legend = {label: handle for ax in axes for handle, label in zip(*ax.get_legend_handles_labels(), strict=True)}
    ordered = sorted(legend, key=lambda label: float(label.split()[-1]))
    notes = {"best": "dotted: always-measure bound", "episodes": "dotted: same episodes, always measured", "none": ""}
    title = "\n".join(n for n in [notes[bound], "dashed: raw return" if raw else ""] if n) or None
    fig.legend(
        [legend[k] for k in ordered],
        ordered,
        loc="outside lower center",
        ncols=min(len(ordered), 6),
        title=title,
        fontsize="small",
        title_fontsize="small",
    )
    return _finish(fig, path)


def vanilla_vs_cost0(
    results: pd.DataFrame,
    *,
    envs: Sequence[str] | None = None,
    agents: Sequence[str] | None = None,
    path: str | Path | None = None,
) -> Figure:
    """The paper's first figure: test return vs env steps on the plain env (vanilla) and on the active-measure
    env at cost 0 (where measuring is free, so costed = raw return), per env x agent.

    Raises ValueError when the results hold no vanilla run or no cost-0 run to compare.
    """
    results = _select(best_hyperparams(results), envs, agents)
    vanilla = results.vanilla.astype(bool)
    cost0 = ~vanilla & (results.cost == 0)
    panels = sorted(set(_panels(results[vanilla])) & set(_panels(results[cost0])))
    if not panels:
        raise ValueError("vanilla_vs_cost0: needs vanilla runs and cost-0 runs of the same env and agent")
    curves = learning_curve_table(results[vanilla | cost0])
    fig, axes = _grid(len(panels), ncols=min(3, len(panels)))
    for ax, (env, agent) in zip(axes, panels, strict=True):
        for is_vanilla, color, label in ((True, "tab:orange", "vanilla"), (False, REFERENCE_COLOR, "cost 0")):
            pick = (curves.env == env) & (curves.agent == agent) & (curves.vanilla == is_vanilla)
            _band(ax, curves[pick], color, label)
        ax.set_title(f"{env} · {agent}")
        ax.set_xlabel("env steps")
        ax.set_ylabel("test return")
        ax.grid(alpha=0.3)
        ax.legend(fontsize="small")
    return _finish(fig, path)


def _best_by_cost(summary: pd.DataFrame) -> pd.DataFrame:
    rows = []
    costed = summary[~summary.vanilla.astype(bool)]
    for (env, agent, cost), group in costed.groupby(["env", "agent", "cost"], sort=True):
        median, q25, q75 = quantiles(group.best_return)
        rows.append({"env": env, "agent": agent, "cost": cost, "median": median, "q25": q25, "q75": q75})
    return pd.DataFrame(rows, columns=["env", "agent", "cost", "median", "q25", "q75"])


def _agent_colors(agents: Sequence[str]) -> dict[str, object]:
    cmap = colormaps["tab10"]
    return {agent: cmap(i % 10) for i, agent in enumerate(sorted(agents))}


def cost_analysis(
    summary: pd.DataFrame,
    results: pd.DataFrame | None = None,
    *,
    envs: Sequence[str] | None = None,
    agents: Sequence[str] | None = None,
    paper: bool = True,
    path: str | Path | None = None,
) -> Figure:
    """Median best test costed reward vs cost, one panel per env and one line per agent (IQR error bars).

    The dotted line is the always-measure bound computed from `results` (when given); with `paper`, the paper's
    bound (x) and its reported medians (*, labelled with the agent) are marked where it gives them.
    """
    summary = _select(best_hyperparams(summary), envs, agents)
    table = _best_by_cost(summary)
    if table.empty:
        raise ValueError("cost_analysis: no costed (non-vanilla) runs")
    colors = _agent_colors(table.agent.unique())
    env_names = sorted(table.env.unique())
    fig, axes = _grid(len(env_names), ncols=min(3, len(env_names)))
    for ax, env in zip(axes, env_names, strict=True):
        rows = table[table.env == env]
        for agent, line in rows.groupby("agent", sort=True):
            err = np.vstack([line["median"] - line.q25, line.q75 - line["median"]])
            ax.errorbar(line.cost, line["median"], yerr=err, color=colors[agent], marker="o", capsize=4, label=agent)
        costs = np.array(sorted(rows.cost.unique()))
        ticks = set(costs)
        if results is not None:
            level = always_measure_bound(results, env, costs)
            ax.plot(costs, level, label="always measure", **BOUND_STYLE)
        if paper:
            known = PAPER_ALWAYS_MEASURE.get(env, {})
            if known:
                ax.plot(list(known), list(known.values()), "x", color="0.35", label="always measure (paper)")
                ticks |= set(known)
            for (paper_env, agent), values in PAPER_BEST_RETURN.items():
                if paper_env == env and agent in colors:
                    ax.plot(
                        list(values),
                        list(values.values()),
                        "*",
                        color=colors[agent],
                        markersize=10,
                        markeredgecolor="black",
                        label=f"{agent} (paper)",
                    )
        ax.set_title(env)
        ax.set_xlabel("measurement cost")
        ax.set_ylabel("best test costed return")
        ax.set_xticks(sorted(ticks))
        ax.grid(alpha=0.3)
        ax.legend(fontsize="small")
    return _finish(fig, path)


def agent_comparison(
    summary: pd.DataFrame,
    results: pd.DataFrame | None = None,
    *,
    envs: Sequence[str] | None = None,
    agents: Sequence[str] | None = None,
    path: str | Path | None = None,
) -> Figure:
    """Bars of the median best test costed reward per cost (and vanilla), one bar per agent, IQR error bars; one
    panel per env. With `results`, each cost's always-measure bound is drawn as a dotted segment over its group.
    """
    summary = _select(best_hyperparams(summary), envs, agents)
    agent_names = sorted(summary.agent.unique())
    colors = _agent_colors(agent_names)
    env_names = sorted(summary.env.unique())
    fig, axes = _grid(len(env_names), ncols=min(2, len(env_names)), size=(6.0, 3.6))
    width = 0.8 / len(agent_names)
    for ax, env in zip(axes, env_names, strict=True):
        rows = summary[summary.env == env]
        groups = [(True, 0.0)] if rows.vanilla.astype(bool).any() else []
        groups += [(False, c) for c in sorted(rows[~rows.vanilla.astype(bool)].cost.unique())]
        for i, agent in enumerate(agent_names):
            stats = [
                quantiles(rows[(rows.agent == agent) & (rows.vanilla.astype(bool) == v) & (rows.cost == c)].best_return)
                for v, c in groups
            ]
            median, q25, q75 = (np.array(s, float) for s in zip(*stats, strict=True))
            x = np.arange(len(groups)) - 0.4 + width * (i + 0.5)
            ax.bar(
                x,
                median,
                width,
                color=colors[agent],
                label=agent,
                yerr=np.vstack([median - q25, q75 - median]),
                capsize=3,
                error_kw={"linewidth": 1},
            )
        if results is not None:
            for g, (is_vanilla, cost) in enumerate(groups):
                if not is_vanilla:
                    level = always_measure_bound(results, env, [cost])[0]
                    ax.hlines(
                        level,
                        g - 0.45,
                        g + 0.45,
                        label="always measure" if g == len(groups) - 1 else None,
                        **BOUND_STYLE,
                    )
        ax.set_xticks(np.arange(len(groups)), ["vanilla" if v else f"cost {c:g}" for v, c in groups])
        ax.set_title(env)
        ax.set_ylabel("best test costed return")
        ax.grid(axis="y", alpha=0.3)
        ax.legend(fontsize="small")
    return _finish(fig, path)
