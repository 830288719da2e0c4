"""DRQN vs Dueling Double DQN on the active-measure CartPole-v0 (issue 4; the paper's DQN-vs-DRQN comparison).

Trains both agents at costs 0.1 / 0.2 / 0.3 with 10 seeds through `amjax.sweep.run_sweep` (one compiled, vmapped
program per agent; results, resume and checkpoints as in any sweep), then prints per agent and cost the median and
IQR over seeds of the best test costed reward and the measured fraction of steps at that point, and checks the
issue's claims: DRQN measures on fewer than 50% of steps and reaches a higher median costed reward than DQN.

    python benchmarks/recurrent_vs_dqn.py --out runs/recurrent_vs_dqn                  # the full experiment
    python benchmarks/recurrent_vs_dqn.py --smoke --out /tmp/recurrent_smoke           # a tiny smoke run

The full run is 2 agents x 3 costs x 10 seeds x --steps env steps: expensive on 2 CPU cores (see docs/recurrent.md
for measured throughput); rerunning the same command resumes it.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from amjax.sweep import run_sweep
from amjax.sweep.grid import SweepSpec

AGENTS = ("dqn", "drqn")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", required=True, help="output folder (resumes a sweep already there)")
    parser.add_argument("--costs", type=float, nargs="+", default=[0.1, 0.2, 0.3])
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--steps", type=int, default=491_520, help="env steps per configuration")
    parser.add_argument("--eval-every", type=int, default=20_480)
    parser.add_argument("--eval-episodes", type=int, default=10)
    parser.add_argument("--smoke", action="store_true", help="2 seeds, costs 0.1 / 0.3, 10240 steps: a smoke test")
    args = parser.parse_args(argv)
    if args.smoke:
        args.costs, args.seeds, args.steps, args.eval_every, args.eval_episodes = [0.1, 0.3], 2, 10_240, 5_120, 5

    spec = SweepSpec(
        envs=("CartPole-v0",),
        agents=AGENTS,
        costs=tuple(args.costs),
        seeds=tuple(range(args.seeds)),
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
    return 0


if __name__ == "__main__":
    sys.exit(main())
