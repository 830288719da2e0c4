"""The shape shared by the cost experiments (brax_active_measure.py, minatar.py): per env one sweep of the agents,
vanilla and at the env's costs (`amjax.sweep.run_sweep`: a compiled, vmapped program per static key; results,
resume and saved best policies as in any sweep; rerunning the command resumes it), then its report
(`amjax.analysis.write_report`: figures and the measurement maps of the saved best policies) and one joint
paper-style table: median best test costed reward over seeds (the paper's metric, biased upward), the same best
policies re-scored on fresh episodes, the raw returns and measured fractions of both, and the always-measure bound
(the best evaluation episodes of the env's sweep, every step charged the cost)."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import pandas as pd

from amjax.analysis import paper_table, to_markdown, write_report
from amjax.analysis.report import format_paper_table
from amjax.presets import env_hyperparams
from amjax.sweep import run_sweep
from amjax.sweep.grid import SweepSpec

# env id -> (costs, env steps per configuration, env steps between evaluations)
Experiments = dict[str, tuple[tuple[float, ...], int, int]]
SETTING = ["env", "agent", "vanilla", "cost"]
TABLE_COLUMNS = [
    *SETTING,
    "seeds",
    "best_return",
    "best_raw_return",
    "measured_fraction",
    "rescored_return",
    "rescored_raw_return",
    "rescored_measured_fraction",
    "always_measure",
    "gain_vs_always_measure",
]
SMOKE = (20_480, 10_240)  # env steps and evaluation interval of a smoke run
UNIT = 10_240  # `--steps` evaluates on multiples of this (of every agent's env steps per update, by default)


def add_arguments(parser: argparse.ArgumentParser, experiments: Experiments, seeds: int = 5) -> None:
    """The command-line flags every cost experiment takes."""
    parser.add_argument("--out", required=True, help="output folder (resumes the sweeps already there)")
    parser.add_argument("--envs", nargs="+", default=list(experiments), choices=list(experiments))
    parser.add_argument("--seeds", type=int, default=seeds)
    parser.add_argument("--eval-episodes", type=int, default=10)
    parser.add_argument("--no-maps", action="store_true", help="skip the measurement maps in the reports")
    parser.add_argument("--smoke", action="store_true", help="2 seeds, 20,480 steps, 2 test episodes")
    parser.add_argument(
        "--steps",
        type=int,
        help="env steps per configuration instead of each env's budget (say which in the report), about 20 "
        "evaluations (both rounded to multiples of 10,240)",
    )


def results_table(summary: pd.DataFrame, results: pd.DataFrame) -> pd.DataFrame:
    """`amjax.analysis.paper_table` with the median raw returns (before measurement costs) of the best evaluations
    and of the re-scored best policies beside the costed ones."""
    raw = summary.groupby(SETTING, as_index=False)[["best_raw_return", "best_policy_raw_return"]].median()
    raw = raw.rename(columns={"best_policy_raw_return": "rescored_raw_return"})
    return paper_table(summary, results).merge(raw, on=SETTING)[TABLE_COLUMNS]


def run(
    experiments: Experiments,
    agents: tuple[str, ...],
    args: argparse.Namespace,
    hyperparams: dict[str, list] | None = None,
) -> str:
    """Run (or resume) the sweeps of `args.envs`, write each report and OUT/table.md; returns the table."""
    seeds, eval_episodes = (2, 2) if args.smoke else (args.seeds, args.eval_episodes)
    tables = []
    for env_id in args.envs:
        costs, steps, eval_every = (experiments[env_id][0], *SMOKE) if args.smoke else experiments[env_id]
        if args.steps and not args.smoke:  # about 20 evaluations, on a multiple of every agent's update size
            eval_every = max(UNIT, round(args.steps / 20 / UNIT) * UNIT)
            steps = max(1, round(args.steps / eval_every)) * eval_every
        spec = SweepSpec(
            envs=(env_id,),
            agents=agents,
            costs=costs,
            seeds=tuple(range(seeds)),
            total_timesteps=steps,
            eval_every=eval_every,
            eval_episodes=eval_episodes,
            vanilla=True,
            hyperparams=hyperparams or {},
            env_defaults={env_id: env_hyperparams(env_id, agents)},
        )
        out = Path(args.out) / env_id.replace(":", "_")
        start = time.monotonic()
        result = run_sweep(spec, out)
        print(f"{env_id}: sweep done in {time.monotonic() - start:.0f} s (this invocation)", flush=True)
        report = write_report(out, maps=not args.no_maps)
        print(f"{env_id}: report {report}", flush=True)
        tables.append(results_table(result.summary, result.results))

    joint = pd.concat(tables, ignore_index=True)
    if joint["agent"].nunique() == 1:
        joint = joint.drop(columns="agent")
    shown = format_paper_table(joint)
    table = to_markdown(
        shown.rename(columns={"best_raw_return": "best raw return", "rescored_raw_return": "re-scored raw return"})
    )
    (Path(args.out) / "table.md").write_text(table + "\n")
    return table


def main(doc: str, experiments: Experiments, agents: tuple[str, ...], argv: list[str] | None = None) -> int:
    """The command line of a cost experiment (`doc`: its help text): parse, run, print the table."""
    parser = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_arguments(parser, experiments)
    print(run(experiments, agents, parser.parse_args(argv)))
    return 0
