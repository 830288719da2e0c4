"""A self-contained report of a sweep folder: report.md, its figures (PNG, optionally SVG) and its tables.

Works on finished and partly finished sweeps; figures that the data cannot support (no vanilla runs, no cost-0
runs) are skipped with a note in the report instead of failing.
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable, Sequence
from pathlib import Path

import pandas as pd
from matplotlib.figure import Figure

from amjax.analysis import plots
from amjax.analysis.maps import plot_measurement_map, record_agent
from amjax.analysis.results import SweepData, hyper_columns, load_results, sweep_progress
from amjax.analysis.tables import paper_table, seed_spread, to_markdown

_MAX_ROWS = 80  # longer per-configuration tables go to per_config.csv only
_TABLE_LABELS = {
    "best_return": "best costed return",
    "best_return_q25": "q25",
    "best_return_q75": "q75",
    "measured_fraction": "measured fraction",
    "rescored_return": "re-scored return",
    "rescored_return_q25": "re-scored q25",
    "rescored_return_q75": "re-scored q75",
    "rescored_measured_fraction": "re-scored measured fraction",
    "measurement_reduction": "measurements saved",
    "always_measure": "always measure",
    "gain_vs_always_measure": "gain vs always",
    "paper_best_return": "paper",
    "paper_always_measure": "paper always measure",
}

_SPREAD_LABELS = {
    f"{column}_{stat}": f"{label} {stat}"
    for column, label in (("best_return", "best"), ("rescored_return", "re-scored"))
    for stat in ("mean", "sd", "min", "max")
}

_FIGURES: list[tuple[str, str, str]] = [
    (
        "learning_curves",
        "Learning curves",
        "Median over seeds (band: 25th-75th percentile) of the greedy test costed return, one line per cost; "
        "cost 0 (black) is the reference. Dotted horizontal lines: the always-measure bound of each cost (the "
        "best observed test episodes of this env, any run, scored as if every step were measured: raw return - "
        "cost x length).",
    ),
    (
        "learning_curves_raw",
        "Learning curves, raw return",
        "As above without the bounds, and with the raw return (before measurement costs) of each cost dashed: "
        "the gap between a dashed line and its solid line is what the measurements cost.",
    ),
    (
        "vanilla_vs_cost0",
        "Vanilla vs cost 0",
        "Test return on the plain environment (vanilla) and on the active-measure environment with free "
        "measurements (the paper's first figure): what the doubled action space costs in learning speed.",
    ),
    (
        "cost_analysis",
        "Best costed return vs cost",
        "Median over seeds (error bars: 25th-75th percentile) of the best test costed return reached during "
        "training. Dotted: always-measure bound from this sweep's data; x: the paper's bound; *: the paper's "
        "median, where it gives one.",
    ),
    (
        "agent_comparison",
        "Agents compared",
        "Median best test costed return per cost and agent (error bars: 25th-75th percentile); dotted segments: "
        "always-measure bound.",
    ),
]


def _figure_makers(data: SweepData) -> dict[str, Callable[[], Figure]]:
    results, summary = data.results, data.summary
    return {
        "learning_curves": lambda: plots.learning_curves(results),
        "learning_curves_raw": lambda: plots.learning_curves(results, raw=True, bound="none"),
        "vanilla_vs_cost0": lambda: plots.vanilla_vs_cost0(results),
        "cost_analysis": lambda: plots.cost_analysis(summary, results),
        "agent_comparison": lambda: plots.agent_comparison(summary, results),
    }


def _spec_lines(data: SweepData) -> list[str]:
    spec = data.metadata.get("spec", {})
    progress = sweep_progress(data)
    planned = progress["configs_planned"]
    points = progress["points_planned"]
    status = "finished" if progress["finished"] else "partial (still running or interrupted)"
    lines = [
        f"- Status: {status}: {progress['configs_started']} of {planned if planned is not None else '?'} "
        f"configurations started, {progress['points_done']} of {points if points is not None else '?'} "
        "evaluation points done.",
        f"- Environments: {', '.join(map(str, spec.get('envs', [])))}; agents: "
        f"{', '.join(map(str, spec.get('agents', [])))}; costs: {', '.join(f'{c:g}' for c in spec.get('costs', []))}"
        f"{' + vanilla' if spec.get('vanilla') else ''}; seeds: {len(spec.get('seeds', []))}; mode: "
        f"{spec.get('mode', 'last')}.",
        f"- Budget: {int(spec.get('total_timesteps', 0)):,} env steps per configuration, a greedy evaluation "
        f"({spec.get('eval_episodes')} episodes) every {int(spec.get('eval_every', 0)):,} steps.",
    ]
    if spec.get("hyperparams"):
        lines.append(f"- Hyperparameters: `{json.dumps(spec['hyperparams'])}`.")
    swept = [c for c in hyper_columns(data.results) if data.results[c].nunique(dropna=False) > 1]
    if swept:
        lines.append(
            f"- Swept hyperparameters ({', '.join(swept)}): each figure shows, per env x agent x cost, "
            "the combination with the highest median best costed return; the table lists them all."
        )
    versions = data.metadata.get("versions", {})
    if versions:
        lines.append(
            "- Versions: "
            + ", ".join(f"{k} {v}" for k, v in versions.items() if v)
            + f"; git {str(data.metadata.get('git_revision'))[:10]}; {data.metadata.get('machine', '?')}."
        )
    return lines


def format_paper_table(table: pd.DataFrame) -> pd.DataFrame:
    """The paper table (`tables.paper_table`) with readable column names and a setting column."""
    return _readable(table, _TABLE_LABELS)


def _readable(table: pd.DataFrame, labels: dict[str, str]) -> pd.DataFrame:
    """`table` with a setting column ("vanilla" / "cost c") for its vanilla and cost columns, `labels` applied, and
    columns without any value dropped."""
    shown = table.copy()
    shown.insert(
        2, "setting", ["vanilla" if v else f"cost {c:g}" for v, c in zip(shown.vanilla, shown.cost, strict=True)]
    )
    shown = shown.drop(columns=["vanilla", "cost"]).rename(columns=labels)
    return shown.dropna(axis=1, how="all")


def _map_lines(data: SweepData, path: Path, figure_dir: Path, formats: Sequence[str], episodes: int) -> list[str]:
    """Measurement maps of the best saved policy per env x agent x cost (one figure per env x agent)."""
    import jax

    from amjax.sweep import load_sweep_policy, policy_path

    costed = data.summary[~data.summary.vanilla.astype(bool) & data.summary.best_return.notna()]
    costed = costed[[policy_path(path, c).exists() for c in costed.config_id]]
    if costed.empty:
        return [
            "_No saved policies in this sweep folder (sweeps write `policies/` since amjax 0.1; "
            "`run_sweep(..., save_policies=False)` turns it off)._",
            "",
        ]
    lines = [
        f"The best saved policy (highest best test costed return over seeds) of each env x agent x cost, "
        f"run greedily for {episodes} test episodes: a dark cell is a paid measurement, a light one a step "
        "without one, grey is after the episode ended. Files: `policies/<config_id>.msgpack` "
        "(`amjax.sweep.load_sweep_policy`).",
        "",
    ]
    for (env, agent), group in costed.groupby(["env", "agent"], sort=True):
        panels, chosen = {}, []
        for cost, runs in group.groupby("cost", sort=True):
            best = runs.sort_values(["best_return", "seed"], ascending=[False, True]).iloc[0]
            saved = load_sweep_policy(path, best.config_id)
            chosen.append(f"cost {cost:g}: seed {best.seed}, `{best.config_id}`")
            panels[f"cost {cost:g}, seed {best.seed}"] = record_agent(
                saved.config, saved.params, jax.random.key(0), num_episodes=episodes
            )
        name = re.sub(r"[^A-Za-z0-9._-]", "_", f"maps_{env}_{agent}")  # "brax:reacher" -> "brax_reacher"
        plots.save_figure(
            plot_measurement_map(panels, title=f"{env}, {agent}"), figure_dir / f"{name}.{formats[0]}", formats[1:]
        )
        lines += [
            f"### {env}, {agent}",
            "",
            f"![{env} {agent} measurement maps](figures/{name}.{formats[0]})",
            "",
            "Policies: " + "; ".join(chosen) + ".",
            "",
        ]
    return lines


def write_report(
    path: str | Path,
    out: str | Path | None = None,
    *,
    formats: Sequence[str] = ("png",),
    maps: bool = True,
    map_episodes: int = 10,
) -> Path:
    """Write the report of the sweep folder `path` into `out` (default `path/report`); returns report.md's path.

    `formats`: image formats of each figure ("png", "svg", ...); the report embeds the first. `maps`: draw the
    measurement maps of the sweep's saved best policies (`map_episodes` test episodes each; runs them, so it
    compiles one program per agent). Raises `NotASweepError` when `path` is not a sweep folder with results.
    """
    data = load_results(path)
    out = Path(path) / "report" if out is None else Path(out)
    figure_dir = out / "figures"
    figure_dir.mkdir(parents=True, exist_ok=True)
    formats = [f.lstrip(".") for f in formats] or ["png"]
    makers = _figure_makers(data)

    lines = [f"# Sweep report: {Path(path).resolve().name}", "", *_spec_lines(data), ""]
    lines += [
        "## Results table",
        "",
        "Per env x agent x cost, medians over seeds: best test costed return (q25-q75; the paper's metric, "
        "the best of many noisy evaluations, so biased upward), fraction of test steps measured at that "
        "evaluation, the same best policy re-scored on fresh test episodes never used to pick it (q25-q75, "
        "and its measured fraction: the unbiased figure), measurements saved vs always measuring "
        "(1 - fraction), the always-measure bound from this sweep's data and the gain over it, and the "
        "paper's numbers (Bellinger et al., Canadian AI 2022) where it gives them.",
        "",
    ]
    table = paper_table(data.summary, data.results)
    lines += [to_markdown(format_paper_table(table)), ""]
    table.to_csv(out / "paper_table.csv", index=False)
    lines += [
        "## Spread over seeds",
        "",
        "The same settings: mean, standard deviation, minimum and maximum over seeds of the best test costed return "
        "and of the re-scored return (the medians and quartiles are in the table above).",
        "",
        to_markdown(_readable(seed_spread(data.summary), _SPREAD_LABELS)),
        "",
    ]

    for name, heading, caption in _FIGURES:
        lines += [f"## {heading}", ""]
        try:
            fig = makers[name]()
        except ValueError as error:
            lines += [f"_Not drawn: {error}._", ""]
            continue
        plots.save_figure(fig, figure_dir / f"{name}.{formats[0]}", formats[1:])
        lines += [f"![{heading}](figures/{name}.{formats[0]})", "", caption, ""]

    lines += ["## Measurement maps", ""]
    if maps:
        lines += _map_lines(data, Path(path), figure_dir, formats, int(map_episodes))
    else:
        lines += ["_Not drawn (maps=False / --no-maps)._", ""]
    configs = data.summary.sort_values(["env", "agent", "vanilla", "cost", "seed"])[
        [
            "env",
            "agent",
            "vanilla",
            "cost",
            "seed",
            *hyper_columns(data.summary),
            "best_return",
            "best_measured_fraction",
            "best_env_steps",
            "best_policy_return",
            "best_policy_measured_fraction",
            "final_return",
            "diverged",
        ]
    ].rename(
        columns={
            "best_env_steps": "at env steps",
            "best_policy_return": "re-scored",
            "best_policy_measured_fraction": "re-scored measured fraction",
        }
    )
    configs.to_csv(out / "per_config.csv", index=False)
    lines += [
        "## Per configuration",
        "",
        "Best, re-scored and final test costed return of every configuration (also in per_config.csv).",
        "",
    ]
    lines += [to_markdown(configs) if len(configs) <= _MAX_ROWS else f"_{len(configs)} rows: see per_config.csv._", ""]
    report = out / "report.md"
    report.write_text("\n".join(lines))
    return report
