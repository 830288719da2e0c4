"""Active measurement on brax continuous control (issue 17): PPO's Gaussian + Bernoulli head on inverted_pendulum
and reacher, vanilla and at three measurement costs, 5 seeds.

Each env is one sweep (`amjax.sweep.run_sweep`: a compiled, vmapped program per static key; results, resume and
saved best policies as in any sweep; rerunning the command resumes it), then its report (`amjax.analysis.
write_report`: figures and the measurement maps of the saved best policies) and the paper-style table: median best
test costed reward over seeds (the paper's metric, biased upward), the same best policies re-scored on 100 fresh
episodes, the measured fractions, and the always-measure bound (the best evaluation episodes of the env's sweep,
every step charged the cost). The joint table is written to OUT/table.md.

    python experiments/brax_active_measure.py --out runs/brax_active_measure       # the full experiment
    python experiments/brax_active_measure.py --smoke --out /tmp/brax_smoke         # a tiny smoke run

Costs are per step, scaled to each env's rewards. inverted_pendulum pays 1 per step upright (as CartPole): 0.1 /
0.2 / 0.3. reacher pays minus the fingertip's distance to the target and the squared action, about -0.2 to 0 per
step over 1,000 steps: 0.001 / 0.003 / 0.01, so an always-measuring policy pays 1 / 3 / 10 per episode against
returns of about -100 to -220 at this budget (doing nothing scores -223.5). reacher runs on brax's spring backend,
7x its default generalized one on this CPU (docs/brax.md, Speed). Hyperparameters: PPO's defaults (plus an env's
preset from amjax/presets.py where one exists; none does for these two).
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

from amjax.analysis import paper_table, to_markdown, write_report  # noqa: E402
from amjax.analysis.report import format_paper_table  # noqa: E402
from amjax.presets import env_hyperparams  # noqa: E402
from amjax.sweep import run_sweep  # noqa: E402
from amjax.sweep.grid import SweepSpec  # noqa: E402

# env id -> (costs, env steps per configuration, env steps between evaluations)
EXPERIMENTS: dict[str, tuple[tuple[float, ...], int, int]] = {
    "brax:inverted_pendulum": ((0.1, 0.2, 0.3), 1_638_400, 40_960),
    "brax:reacher:spring": ((0.001, 0.003, 0.01), 1_024_000, 102_400),
}
TABLE_COLUMNS = [
    "env",
    "vanilla",
    "cost",
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
SETTING = ["env", "vanilla", "cost"]


def results_table(summary: pd.DataFrame, results: pd.DataFrame) -> pd.DataFrame:
    """`amjax.analysis.paper_table` with the median raw returns (before measurement costs) of the best evaluations
    and of the re-scored best policies beside the costed ones."""
    raw = summary.groupby(SETTING, as_index=False)[["best_raw_return", "best_policy_raw_return"]].median()
    raw = raw.rename(columns={"best_policy_raw_return": "rescored_raw_return"})
    return paper_table(summary, results).merge(raw, on=SETTING)[TABLE_COLUMNS]


def folder_name(env_id: str) -> str:
    return env_id.replace(":", "_")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", required=True, help="output folder (resumes the sweeps already there)")
    parser.add_argument("--envs", nargs="+", default=list(EXPERIMENTS), choices=list(EXPERIMENTS))
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--eval-episodes", type=int, default=10)
    parser.add_argument("--no-maps", action="store_true", help="skip the measurement maps in the reports")
    parser.add_argument("--smoke", action="store_true", help="2 seeds, 20,480 steps, 2 test episodes")
    args = parser.parse_args(argv)

    seeds, eval_episodes = (2, 2) if args.smoke else (args.seeds, args.eval_episodes)
    tables = []
    for env_id in args.envs:
        costs, steps, eval_every = (EXPERIMENTS[env_id][0], 20_480, 10_240) if args.smoke else EXPERIMENTS[env_id]
        spec = SweepSpec(
            envs=(env_id,),
            agents=("ppo",),
            costs=costs,
            seeds=tuple(range(seeds)),
            total_timesteps=steps,
            eval_every=eval_every,
            eval_episodes=eval_episodes,
            vanilla=True,
            env_defaults={env_id: env_hyperparams(env_id, ("ppo",))},
        )
        out = Path(args.out) / folder_name(env_id)
        start = time.monotonic()
        result = run_sweep(spec, out)
        print(f"{env_id}: sweep done in {time.monotonic() - start:.0f} s (this invocation)", flush=True)
        report = write_report(out, maps=not args.no_maps)
        print(f"{env_id}: report {report}", flush=True)
        tables.append(results_table(result.summary, result.results))

    shown = format_paper_table(pd.concat(tables, ignore_index=True))
    table = to_markdown(
        shown.rename(columns={"best_raw_return": "best raw return", "rescored_raw_return": "re-scored raw return"})
    )
    (Path(args.out) / "table.md").write_text(table + "\n")
    print(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
