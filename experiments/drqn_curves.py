"""DRQN's learning curves and best-policy figures from sweep folders, side by side (issue 55).

Reads one or more sweep output folders (`amjax sweep ... --out DIR`, this code's or an older commit's: only
`results.parquet` is needed, `rescored.parquet` where there is one) and prints, per cost:

- the learning curves: at every evaluation point, the median over seeds of the test costed return and of the
  measured fraction of test steps (`return / percent`), one row per run (folder x agent x swept hyperparameters);
- the best-policy figures: median (IQR) over seeds of the best test costed reward, the median measured fraction
  at that evaluation, the median re-scored reward of that best policy (100 fresh episodes) and its measured
  fraction, and the first evaluation at which the median test costed return beats CartPole-v0's "measure every
  other step" policy (200 steps at half the cost, 200 - 100 x cost) by more than a point: where the median seed
  has learned to skip; and how many seeds' best evaluation measured on fewer than 45% of steps (found a skipping
  policy).

`--upto N` keeps only the evaluations up to N env steps, so folders that stopped at different points (or runs of
different budgets) compare at one budget; the re-scored columns are then left empty for the runs it cuts short
(they score the best policy of the whole run).

    python experiments/drqn_curves.py old=/work/runs_drqn/old_102k head=/work/runs_drqn/head_102k
    python experiments/drqn_curves.py head=runs/x --agents drqn --costs 0.2 0.3 --every 4  # every 4th point
    python experiments/drqn_curves.py old=... head=... --upto 51200 --no-curves  # best figures at 51,200 steps

A folder given as LABEL=PATH is labelled LABEL (else by its name). Runs are split by every hyperparameter column
that varies in a folder (e.g. `--set drqn.hidden=(64,),(32,)`), so one sweep over a static field prints one row
per value.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from amjax.analysis.results import hyper_columns
from amjax.sweep import storage

# A seed "skips" when its best evaluation measured on fewer than this fraction of steps (the memoryless policy
# measures on every other step, about 50%).
SKIPPING = 0.45


# CartPole-v0's memoryless optimum under a cost: 200 steps, measured on every other one (the paper's DQN policy).
def every_other_step(cost: float) -> float:
    return 200.0 - 100.0 * cost


def load(label: str, path: str | Path) -> tuple[pd.DataFrame, pd.DataFrame | None]:
    """A sweep folder's per-evaluation rows (with a `run` label column) and its re-scored rows (or None)."""
    path = Path(path)
    results = storage.read_table(path / "results")
    if results is None or results.empty:
        raise SystemExit(f"{path}: no results yet")
    rescored = storage.read_table(path / "rescored")
    if "eval_measured_fraction" not in results:
        results["eval_measured_fraction"] = results.eval_measurements / results.eval_length
    if "diverged" not in results:
        results["diverged"] = False
    varying = [c for c in hyper_columns(results) if results[c].astype(str).nunique() > 1]
    # A field another agent of the sweep lacks (a DQN row of `--set drqn.learning_rate=...`) is left out of its name.
    names = results[varying].apply(lambda row: ",".join(f"{c}={v}" for c, v in row.items() if not pd.isna(v)), axis=1)
    results["run"] = label + np.where(names != "", " " + names, "") if varying else label
    results["run"] = results["run"] + " " + results["agent"]
    return results, rescored


def best_rows(results: pd.DataFrame, rescored: pd.DataFrame | None) -> pd.DataFrame:
    """Per configuration: its best evaluation (highest costed return, diverged points excluded; the first of
    ties, as the sweep keeps it) and the re-scored figures of that policy where the folder has them."""
    healthy = results[~results.diverged.astype(bool)].sort_values(["config_id", "env_steps"], kind="stable")
    index = healthy.groupby("config_id").eval_return.idxmax()
    best = healthy.loc[
        index, ["config_id", "run", "cost", "seed", "eval_return", "eval_measured_fraction", "env_steps"]
    ]
    if rescored is not None and not rescored.empty:
        columns = ["config_id", "best_policy_return", "best_policy_measured_fraction"]
        best = best.merge(
            rescored.reset_index()[columns] if "config_id" not in rescored else rescored[columns],
            on="config_id",
            how="left",
        )
    else:
        best["best_policy_return"] = np.nan
        best["best_policy_measured_fraction"] = np.nan
    return best


def curve_table(results: pd.DataFrame, cost: float, every: int) -> pd.DataFrame:
    """Rows: runs; columns: evaluation points (every `every`-th, the last always); cells "return / percent"."""
    rows = results[np.isclose(results.cost, cost) & ~results.diverged.astype(bool)]
    grouped = rows.groupby(["run", "env_steps"])
    medians = grouped.agg(
        ret=("eval_return", "median"), frac=("eval_measured_fraction", "median"), seeds=("seed", "nunique")
    ).reset_index()
    steps = sorted(medians.env_steps.unique())
    keep = set(steps[every - 1 :: every]) | {steps[-1]}
    medians = medians[medians.env_steps.isin(keep)]
    medians["cell"] = [f"{r:.1f}/{100 * f:.0f}" for r, f in zip(medians.ret, medians.frac, strict=True)]
    table = medians.pivot(index="run", columns="env_steps", values="cell")
    table.columns = [f"{s / 1000:g}k" for s in table.columns]
    return table.fillna("")


def summary_table(best: pd.DataFrame, results: pd.DataFrame, cost: float) -> pd.DataFrame:
    """Per run at `cost`: seeds, median best (IQR), measured there, re-scored, and when the median curve first
    beats "measure every other step" by a point (`every_other_step`)."""
    rows = best[np.isclose(best.cost, cost)]
    curve = results[np.isclose(results.cost, cost)].groupby(["run", "env_steps"]).eval_return.median()
    out = []
    for run, group in rows.groupby("run"):
        q1, med, q3 = np.nanpercentile(group.eval_return, [25, 50, 75])
        under = curve.loc[run][curve.loc[run] > every_other_step(cost) + 1.0]
        out.append(
            {
                "run": run,
                "seeds": group.seed.nunique(),
                "best": f"{med:.1f} ({q1:.1f}-{q3:.1f})",
                "measured": f"{100 * group.eval_measured_fraction.median():.0f}%",
                "re-scored": f"{group.best_policy_return.median():.1f}",  # NaN where the folder has none
                "re-scored measured": f"{100 * group.best_policy_measured_fraction.median():.0f}%",
                "skips from": f"{under.index[0] / 1000:g}k" if len(under) else "-",
                "skipping seeds": f"{(group.eval_measured_fraction < SKIPPING).sum()}/{group.seed.nunique()}",
            }
        )
    return pd.DataFrame(out).set_index("run")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folders", nargs="+", help="sweep folders, each PATH or LABEL=PATH")
    parser.add_argument("--agents", nargs="+", default=None, help="only these agents (default: all)")
    parser.add_argument("--costs", type=float, nargs="+", default=None, help="only these costs (default: all)")
    parser.add_argument("--seeds", type=int, nargs="+", default=None, help="only these seeds (default: all)")
    parser.add_argument("--every", type=int, default=1, help="print every N-th evaluation point of the curves")
    parser.add_argument("--no-curves", action="store_true", help="only the best-policy figures")
    parser.add_argument("--upto", type=int, default=None, help="only the evaluations up to N env steps")
    args = parser.parse_args(argv)

    frames, bests = [], []
    for item in args.folders:
        label, _, path = item.rpartition("=")
        label = label or Path(path).name
        results, rescored = load(label, path)
        if args.agents:
            results = results[results.agent.isin(args.agents)]
        if args.seeds:
            results = results[results.seed.isin(args.seeds)]
        cut = set()
        if args.upto is not None:
            cut = set(results.config_id[results.env_steps > args.upto])
            results = results[results.env_steps <= args.upto]
        frames.append(results)
        best = best_rows(results, rescored)
        best.loc[best.config_id.isin(cut), ["best_policy_return", "best_policy_measured_fraction"]] = np.nan
        bests.append(best)
    results, best = pd.concat(frames, ignore_index=True), pd.concat(bests, ignore_index=True)
    costs = args.costs or sorted(results.cost.unique())
    pd.set_option("display.width", 250, "display.max_columns", 100, "display.max_colwidth", 60)
    for cost in costs:
        if not args.no_curves:
            print(f"\n== cost {cost:g}: median over seeds of the test costed return / measured % at each evaluation")
            print(curve_table(results, cost, args.every).to_string())
        print(f"\n== cost {cost:g}: best test costed reward, measured there, re-scored (100 episodes)")
        print(summary_table(best, results, cost).to_string())
    return 0


if __name__ == "__main__":
    sys.exit(main())
