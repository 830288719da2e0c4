"""Joint vs factored measurement head (issue 16): the paper's one output per (control, measure) pair against a
control head plus a measure head, for Dueling DQN and PPO at costs 0.1 / 0.2 / 0.3.

One sweep per env (`amjax.sweep.run_sweep`, resumable; the paper's budget and the env's presets from
amjax/presets.py), `measure_head` swept as a static field (two compiled programs per agent). Per env, agent, cost
and head, medians over seeds of: the best test costed reward (the paper's metric, biased upward), the same best
policies re-scored on 100 fresh episodes, the measured fraction of those episodes, and for sample efficiency the mean
evaluation costed reward over training (the area under the learning curve, divided by the number of evaluations)
and the env steps at which the evaluation first reached 90% of that run's best.

    python experiments/measure_head.py --env CartPole-v0 Acrobot-v1 --out runs/measure_head
    python experiments/measure_head.py --env CartPole-v0 --smoke --out /tmp/measure_head
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import pandas as pd

import amjax

amjax.use_all_cores()  # one CPU device per core, before the imports below start JAX

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the experiments are not installed

from amjax.analysis import load_results, to_markdown  # noqa: E402
from amjax.presets import env_hyperparams  # noqa: E402
from amjax.sweep import run_sweep  # noqa: E402
from amjax.sweep.grid import SweepSpec  # noqa: E402
from train.presets import REPLICATE_BUDGETS  # noqa: E402

AGENTS = ("dqn", "ppo")
COSTS = (0.1, 0.2, 0.3)
SETTING = ["env", "agent", "cost", "measure_head"]


def sample_efficiency(results: pd.DataFrame) -> pd.DataFrame:
    """Per configuration: the mean evaluation costed reward over training and the env steps at which it first
    reached 90% of the run's best (from its lowest evaluation)."""

    def one(run: pd.DataFrame) -> pd.Series:
        run = run.sort_values("env_steps")
        returns = run["eval_return"].to_numpy()
        low, best = returns.min(), returns.max()
        reached = run["env_steps"].to_numpy()[returns >= low + 0.9 * (best - low)][0]
        return pd.Series({"mean_eval_return": returns.mean(), "steps_to_90": reached})

    return results.groupby("config_id").apply(one, include_groups=False).reset_index()


def head_table(summary: pd.DataFrame, results: pd.DataFrame) -> pd.DataFrame:
    rows = summary.merge(sample_efficiency(results), on="config_id")
    columns = {
        "best_return": "best costed reward",
        "best_policy_return": "re-scored",
        "best_policy_measured_fraction": "measured",
        "mean_eval_return": "mean eval reward",
        "steps_to_90": "steps to 90% of best",
    }
    grouped = rows.groupby(SETTING, as_index=False)
    table = grouped[list(columns)].median().rename(columns=columns)
    table.insert(4, "seeds", grouped.size()["size"])
    table["steps to 90% of best"] = table["steps to 90% of best"].round().astype(int)
    return table


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", nargs="+", default=["CartPole-v0", "Acrobot-v1"])
    parser.add_argument("--out", required=True, help="output folder, one sweep per env inside (rerun to resume)")
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--smoke", action="store_true", help="2 seeds, a few thousand steps (checks the pipeline)")
    args = parser.parse_args()
    tables, times = [], {}
    for env in args.env:
        steps, every = REPLICATE_BUDGETS[env]
        seeds = args.seeds
        if args.smoke:
            seeds, steps, every = 2, 4096, 2048
        spec = SweepSpec(
            envs=(env,),
            agents=AGENTS,
            costs=COSTS,
            seeds=tuple(range(seeds)),
            total_timesteps=steps,
            eval_every=every,
            hyperparams={"measure_head": ["joint", "factored"]},
            env_defaults={env: env_hyperparams(env, AGENTS)},
        )
        out = Path(args.out) / env
        start = time.perf_counter()
        run_sweep(spec, out, progress=True)
        times[env] = time.perf_counter() - start
        data = load_results(out)
        tables.append(head_table(data.summary, data.results))
    table = pd.concat(tables, ignore_index=True)
    text = to_markdown(table)
    Path(args.out, "table.md").write_text(text + "\n")
    table.to_csv(Path(args.out, "table.csv"), index=False)
    print(text)
    print("wall time: " + ", ".join(f"{env} {seconds:.0f} s" for env, seconds in times.items()))


if __name__ == "__main__":
    main()
