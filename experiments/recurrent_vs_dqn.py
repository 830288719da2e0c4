"""DRQN vs Dueling Double DQN on the active-measure CartPole-v0 (issue 4; the paper's DQN-vs-DRQN comparison).

Trains both agents at costs 0.1 / 0.2 / 0.3 with 10 seeds through `amjax.sweep.run_sweep` (one compiled, vmapped
program per agent; results, resume and checkpoints as in any sweep), then prints per agent and cost the median and
IQR over seeds of the best test costed reward and the measured fraction of steps at that point, and checks the
issue's claims: DRQN measures on fewer than 50% of steps and reaches a higher median costed reward than DQN.
Last, it draws the measurement maps (10 greedy test episodes) of each agent's best configuration at the highest cost
(`--maps-cost`) from the sweep's saved best policies, and prints each agent's longest run of unmeasured steps.

    python experiments/recurrent_vs_dqn.py --out runs/recurrent_vs_dqn \
        --maps docs/figures/recurrent_maps_cost0.3.png                                  # the full experiment
    python experiments/recurrent_vs_dqn.py --smoke --out /tmp/recurrent_smoke           # a tiny smoke run

The full run is 2 agents x 3 costs x 10 seeds x 153,600 env steps: 44 min on one CPU core, almost all of
it DRQN (docs/recurrent.md has the results); rerunning the same command resumes it.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import jax
import numpy as np

import amjax

amjax.use_all_cores()  # one CPU device per core, before the imports below start JAX

from amjax.analysis import MeasurementMap, plot_measurement_map, record_agent  # noqa: E402
from amjax.sweep import load_sweep_policy, run_sweep  # noqa: E402
from amjax.sweep.grid import SweepSpec  # noqa: E402

AGENTS = ("dqn", "drqn")


def longest_unmeasured_run(mmap: MeasurementMap) -> np.ndarray:
    """Per episode, the most consecutive steps of the episode on which the agent did not pay to measure."""
    longest = np.zeros(mmap.measured.shape[0], int)
    for i, (measured, active) in enumerate(zip(mmap.measured, mmap.active, strict=True)):
        run = 0
        for skipped in ~measured[active]:
            run = run + 1 if skipped else 0
            longest[i] = max(longest[i], run)
    return longest


def draw_maps(out: str, summary, cost: float, path: str, episodes: int = 10) -> dict[str, dict[str, float]]:
    """Measurement maps of each agent's best configuration (highest best_return) at `cost`, from the policies the
    sweep saved; returns per agent its config id, measured fraction and longest unmeasured runs."""
    maps, stats = {}, {}
    for agent in AGENTS:
        rows = summary[(summary["agent"] == agent) & np.isclose(summary["cost"], cost)]
        if rows.empty:
            continue
        best = rows.loc[rows["best_return"].idxmax()]
        saved = load_sweep_policy(out, best["config_id"])
        mmap = record_agent(saved.config, saved.params, jax.random.PRNGKey(0), num_episodes=episodes)
        longest = longest_unmeasured_run(mmap)
        maps[f"{agent.upper()} (seed {best['seed']}), cost {cost}"] = mmap
        stats[agent] = {
            "config_id": best["config_id"],
            "sweep_best_return": round(float(best["best_return"]), 2),
            "map_mean_costed_return": round(float(np.mean(mmap.costed_return)), 2),
            "map_mean_raw_return": round(float(np.mean(mmap.raw_return)), 2),
            "map_measured_fraction": round(mmap.measured_fraction, 3),
            "longest_unmeasured_run": int(longest.max()),
            "median_longest_unmeasured_run_per_episode": float(np.median(longest)),
        }
    plot_measurement_map(maps, path=path)
    return stats


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", required=True, help="output folder (resumes a sweep already there)")
    parser.add_argument("--costs", type=float, nargs="+", default=[0.1, 0.2, 0.3])
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--first-seed", type=int, default=0, help="seeds first-seed, first-seed + 1, ...")
    parser.add_argument("--agents", nargs="+", default=list(AGENTS), choices=AGENTS)
    parser.add_argument("--steps", type=int, default=153_600, help="env steps per configuration")
    parser.add_argument("--eval-every", type=int, default=10_240)
    parser.add_argument("--eval-episodes", type=int, default=10)
    parser.add_argument("--maps", default=None, help="measurement-map PNG (default: OUT/measurement_maps.png)")
    parser.add_argument("--maps-cost", type=float, default=None, help="cost of the maps (default: the highest)")
    parser.add_argument("--smoke", action="store_true", help="2 seeds, costs 0.1 / 0.3, 10240 steps: a smoke test")
    args = parser.parse_args(argv)
    if args.smoke:
        args.costs, args.seeds, args.steps, args.eval_every, args.eval_episodes = [0.1, 0.3], 2, 10_240, 5_120, 5

    spec = SweepSpec(
        envs=("CartPole-v0",),
        agents=tuple(args.agents),
        costs=tuple(args.costs),
        seeds=tuple(range(args.first_seed, args.first_seed + args.seeds)),
        total_timesteps=args.steps,
        eval_every=args.eval_every,
        eval_episodes=args.eval_episodes,
    )
    start = time.monotonic()
    result = run_sweep(spec, args.out)
    elapsed = time.monotonic() - start

    summary = result.summary
    best, frac = "best_return", "best_measured_fraction"
    rows = {}
    print(f"\n{'agent':6} {'cost':>5} {'median best costed reward (IQR)':>34} {'median measured fraction':>26}")
    for (agent, cost), group in summary.groupby(["agent", "cost"]):
        values, fractions = group[best].to_numpy(float), group[frac].to_numpy(float)
        q1, med, q3 = np.nanpercentile(values, [25, 50, 75])
        rows[(agent, cost)] = (med, float(np.nanmedian(fractions)))
        print(f"{agent:6} {cost:5.2f} {med:16.1f} ({q1:.1f} - {q3:.1f}){'':5} {np.nanmedian(fractions):20.3f}")
    checks = {}
    for cost in args.costs:
        if ("drqn", cost) in rows and ("dqn", cost) in rows:
            checks[f"cost {cost}: DRQN measures < 50%"] = bool(rows[("drqn", cost)][1] < 0.5)
            checks[f"cost {cost}: DRQN beats DQN"] = bool(rows[("drqn", cost)][0] > rows[("dqn", cost)][0])
    print(json.dumps({"seconds": round(elapsed, 1), "checks": checks}, indent=2))

    maps_cost = max(args.costs) if args.maps_cost is None else args.maps_cost
    maps_path = args.maps or f"{args.out}/measurement_maps.png"
    stats = draw_maps(args.out, summary, maps_cost, maps_path)
    print(json.dumps({"maps": maps_path, "best configurations": stats}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
