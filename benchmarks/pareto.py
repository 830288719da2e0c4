"""One cost-conditioned agent for the whole cost range (issue 16), against per-cost specialists.

A sweep trains one agent per seed on an env whose episodes draw their cost uniformly from [0, COST_HIGH] and show
it (`cost_conditioned=True`), for 1.47x the env steps of one specialist. Each seed's saved best policy is then
evaluated at a grid of costs (`SavedPolicy.evaluate(..., cost_low=c, cost_high=c)`, 100 fresh episodes each, keys
apart from training's): costed reward, raw reward and measured fraction per cost, the front. The specialists are an
ordinary sweep of the same agents at costs 0.1 / 0.2 / 0.3 (the paper's budget), same seeds; their saved best
policies were re-scored by their sweep on 100 fresh episodes (`best_policy_return`). Writes OUT/front.csv,
OUT/table.md (conditioned vs specialists at 0.1-0.3) and OUT/front.png.

    python benchmarks/pareto.py --out runs/pareto          # CartPole-v0, Dueling DQN and PPO, 5 seeds
    python benchmarks/pareto.py --smoke --out /tmp/pareto  # a tiny smoke run
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import jax
import numpy as np
import pandas as pd
from matplotlib.figure import Figure

import amjax

amjax.use_all_cores()  # one CPU device per core, before the imports below start JAX

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the benchmarks are not installed

from amjax.analysis import load_results, to_markdown  # noqa: E402
from amjax.sweep import load_sweep_policy, run_sweep  # noqa: E402
from amjax.sweep.grid import SweepSpec  # noqa: E402
from train.presets import REPLICATE_BUDGETS, env_hyperparams  # noqa: E402

AGENTS = ("dqn", "ppo")
COST_HIGH = 0.5
GRID = tuple(round(0.05 * i, 2) for i in range(11))  # 0 to 0.5
SPECIALIST_COSTS = (0.1, 0.2, 0.3)
FRONT_EPISODES = 100
FRONT_KEY = 20_261_126  # apart from the sweeps' training and evaluation keys


def front(out: Path, summary: pd.DataFrame) -> pd.DataFrame:
    """Each conditioned policy evaluated at every cost of the grid."""
    rows = []
    for run in summary.itertuples():
        policy = load_sweep_policy(out, run.config_id)
        for cost in GRID:
            means = policy.evaluate(jax.random.key(FRONT_KEY), FRONT_EPISODES, cost_low=cost, cost_high=cost)
            rows.append({"agent": run.agent, "seed": run.seed, "cost": cost, "return": means["costed_return"],
                         "raw_return": means["raw_return"],
                         "measured": means["measurements"] / means["length"]})
    return pd.DataFrame(rows)


def plot(medians: pd.DataFrame, specialists: pd.DataFrame, path: Path) -> None:
    fig = Figure(figsize=(10, 4), layout="constrained")
    left, right = fig.subplots(1, 2)
    for agent, group in medians.groupby("agent"):
        line = left.plot(group.cost, group["return"], marker="o", label=f"{agent}, one conditioned agent")[0]
        right.plot(group.cost, group.measured, marker="o", color=line.get_color(), label=agent)
        spec = specialists[specialists.agent == agent]
        left.scatter(spec.cost, spec["return"], marker="*", s=150, color=line.get_color(), edgecolor="black",
                     zorder=3, label=f"{agent}, specialists (one per cost)")
        right.scatter(spec.cost, spec.measured, marker="*", s=150, color=line.get_color(), edgecolor="black", zorder=3)
    left.set(xlabel="cost per measurement", ylabel="costed reward (median over seeds)")
    right.set(xlabel="cost per measurement", ylabel="measured fraction of steps")
    left.legend(fontsize="small")
    fig.savefig(path, dpi=120)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="CartPole-v0")
    parser.add_argument("--out", required=True, help="output folder (rerun to resume)")
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--smoke", action="store_true", help="2 seeds, a few thousand steps (checks the pipeline)")
    args = parser.parse_args()
    steps, every = REPLICATE_BUDGETS[args.env]
    seeds = 2 if args.smoke else args.seeds
    if args.smoke:
        steps, every = 4096, 2048
    conditioned_steps = round(1.5 * steps / every - 0.5) * every  # at most 1.5x a specialist's, whole periods
    out = Path(args.out)
    common = {"envs": (args.env,), "agents": AGENTS, "seeds": tuple(range(seeds)), "eval_every": every,
              "env_defaults": {args.env: env_hyperparams(args.env, AGENTS)}}
    run_sweep(SweepSpec(**common, costs=(0.0,), total_timesteps=conditioned_steps,
                        hyperparams={"cost_conditioned": True, "cost_high": COST_HIGH}), out / "conditioned")
    run_sweep(SweepSpec(**common, costs=SPECIALIST_COSTS, total_timesteps=steps), out / "specialists")

    points = front(out / "conditioned", load_results(out / "conditioned").summary)
    points.to_csv(out / "front.csv", index=False)
    medians = points.groupby(["agent", "cost"], as_index=False)[["return", "raw_return", "measured"]].median()
    special = load_results(out / "specialists").summary
    specialists = special.groupby(["agent", "cost"], as_index=False).agg(
        **{"return": ("best_policy_return", "median"), "measured": ("best_policy_measured_fraction", "median")})
    table = medians[medians.cost.isin(SPECIALIST_COSTS)].merge(specialists, on=["agent", "cost"],
                                                                 suffixes=(" conditioned", " specialists"))
    table["ratio"] = table["return conditioned"] / table["return specialists"]
    text = to_markdown(table)
    (out / "table.md").write_text(text + f"\n\nenv steps: conditioned {conditioned_steps:,} "
                                  f"({conditioned_steps / steps:.2f}x a specialist's {steps:,})\n")
    print(text)
    print(to_markdown(medians))
    plot(medians, specialists, out / "front.png")
    print(f"conditioned agents trained for {conditioned_steps:,} env steps ({conditioned_steps / steps:.2f}x); "
          f"front, table and plot in {out}; median ratio {np.median(table.ratio):.3f}")


if __name__ == "__main__":
    main()
