"""Recurrent agents' training speed at sweep scale, old settings beside new ones, in one invocation (issue 13).

Each case trains `--configs` configurations of one agent (costs 0 / 0.1 / 0.2 / 0.3 / 0.4 x seeds, CartPole-v0,
mode "last") as one vmapped, jitted program, in its own child process (so peak memory is the case's own), and
reports the compile time, the env steps per second of the compiled run (all configurations together, evaluations
included) and the child's peak resident memory. Cases:

- `drqn-old`: DRQN with the settings it had before issue 13 (4 envs, 8 steps per env between gradient phases,
  4 gradient steps of 32 sequences, 8 + 16 steps per sequence, a 64-unit MLP under a 64-unit GRU).
- `drqn`: DRQN with today's defaults.
- `ppo-rnn`: recurrent PPO with its defaults.

    taskset -c 1 python benchmarks/recurrent_speed.py  # benchmarks/results/recurrent_speed_<date>_<machine>.jsonl / .md
    python benchmarks/recurrent_speed.py --configs 4 --steps 4096 --cases drqn  # a smoke run
    python benchmarks/recurrent_speed.py --devices 2  # every case split over 2 CPU devices, as a sweep runs

`--devices 1` (the default) runs each case as one XLA CPU program; `--devices N` splits its configurations over N
JAX CPU devices (one per core, `jax.shard_map`), as the sweep runner does (`amjax.sweep.devices`).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

if not __package__:  # run as a file: the repository importable, for `benchmarks.harness`
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks import harness  # noqa: E402

# The settings DRQN had before issue 13 (its defaults then); every other field is today's default.
OLD_DRQN = {
    "num_envs": 4,
    "train_freq": 8,
    "gradient_steps": 4,
    "batch_size": 32,
    "seq_len": 16,
    "burn_in": 8,
    "buffer_size": 2_000,
    "learning_rate": 2e-3,
    "rnn_size": 64,
    "hidden": (64,),
    "train_group": 0,
}
CASES: dict[str, tuple[str, dict[str, Any]]] = {
    "drqn-old": ("drqn", OLD_DRQN),
    "drqn": ("drqn", {}),
    "ppo-rnn": ("ppo-rnn", {}),
}
COSTS = (0.0, 0.1, 0.2, 0.3, 0.4)


def run_case(name: str, configs: int, steps: int, eval_every: int, devices: int = 1) -> dict[str, Any]:
    """Compile and time one case in this process, its configurations split over `devices` CPU devices."""
    import jax

    jax.config.update("jax_num_cpu_devices", devices)  # before JAX starts (this child's first JAX call)
    import jax.numpy as jnp

    from amjax.agents import ALGORITHMS

    agent, overrides = CASES[name]
    algo = ALGORITHMS[agent]
    items = [algo.config_type(cost=COSTS[i % len(COSTS)], **overrides) for i in range(configs)]
    unit = items[0].steps_per_update()
    every = max(unit, eval_every // unit * unit)
    total = max(every, steps // every * every)
    items = [c.replace(eval_every=every, total_timesteps=total).validate() for c in items]
    keys = jnp.stack([jax.random.PRNGKey(i // len(COSTS)) for i in range(configs)])
    timing = harness.time_training_batch(algo, items, keys)  # on the `devices` CPU devices set above
    return {"case": name, "agent": agent, "overrides": overrides, "configs": configs, "devices": devices, **timing}


def render(runs: list[dict[str, Any]]) -> str:
    """The markdown of a results file: one table per run, env steps/s against drqn-old's of the same run."""
    parts = []
    for run in runs:
        settings, results = run["settings"], [r for r in run["cases"] if r["status"] == "ok"]
        base = next((r for r in results if r["case"] == "drqn-old"), None)

        def ratio(r: dict[str, Any], base: dict[str, Any] | None = base) -> str:
            return f"{r['env_steps_per_s'] / base['env_steps_per_s']:.1f}x" if base else ""

        parts.append(
            f"# Recurrent agents at sweep scale ({run['date'][:10]})\n\n"
            f"{settings['configs']} configurations (costs {', '.join(map(str, COSTS))} x seeds) of CartPole-v0 "
            f'(mode "last") in one vmapped program per case, split over {settings["devices"]} CPU device(s), each '
            "case in its own process, one after the other. Env steps/s: all configurations together, evaluations "
            f"included, compile excluded. {harness.describe(run)}\n\n"
            + harness.markdown_table(
                results,
                [
                    ("case", lambda r: r["case"]),
                    ("settings", lambda r: ", ".join(f"{k}={v}" for k, v in r["overrides"].items()) or "defaults"),
                    ("steps / config", lambda r: r["steps_per_config"]),
                    ("compile (s)", lambda r: r["compile_s"]),
                    ("run (s)", lambda r: r["run_s"]),
                    ("env steps/s", lambda r: r["env_steps_per_s"]),
                    ("vs drqn-old", ratio),
                    ("peak RSS (MiB)", lambda r: r["peak_rss_mib"]),
                ],
            )
            + "".join(f"\n{r['case']}: {r['status']}\n" for r in run["cases"] if r["status"] != "ok")
        )
    return "\n".join(parts)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    parser.add_argument("--configs", type=int, default=50)
    parser.add_argument("--steps", type=int, default=20_480, help="env steps per configuration (rounded)")
    parser.add_argument("--eval-every", type=int, default=10_240)
    parser.add_argument(
        "--devices",
        type=int,
        default=1,
        help="split each case's configurations over this many CPU devices, one per core, as a sweep "
        "does (default 1: one program on one device)",
    )
    parser.add_argument(
        "--out",
        help="results file to append to (default: benchmarks/results/recurrent_speed_<date>_<machine>.jsonl; the "
        "markdown table is written beside it)",
    )
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    from amjax.cores import usable_cores

    if not 1 <= args.devices <= usable_cores():
        parser.error(f"--devices: {args.devices}; allowed values: 1 to {usable_cores()} (usable cores)")
    if args.configs % args.devices:
        parser.error(f"--configs: {args.configs} must be a multiple of --devices ({args.devices})")
    if args.child:
        case = json.loads(args.child)
        harness.child_result(
            run_case(case["case"], case["configs"], case["steps"], case["eval_every"], case["devices"])
        )
        return 0

    cases = [
        {
            "case": name,
            "configs": args.configs,
            "steps": args.steps,
            "eval_every": args.eval_every,
            "devices": args.devices,
        }
        for name in args.cases
    ]
    harness.run_cases("recurrent_speed", harness.settings_of(args), args.out, __file__, cases, render)
    return 0


if __name__ == "__main__":
    sys.exit(main())
