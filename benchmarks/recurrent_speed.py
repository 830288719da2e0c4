"""Recurrent agents' training speed at sweep scale, old settings beside new ones, in one invocation (issue 13).

Each case trains `--configs` configurations of one agent (costs 0 / 0.1 / 0.2 / 0.3 / 0.4 x seeds, CartPole-v0,
mode "last") as one vmapped, jitted program, in its own child process (so peak memory is the case's own), and
reports the compile time, the env steps per second of the compiled run (all configurations together, evaluations
included) and the child's peak resident memory. Cases:

- `drqn-old`: DRQN with the settings it had before issue 13 (4 envs, 8 steps per env between gradient phases,
  4 gradient steps of 32 sequences, 8 + 16 steps per sequence, a 64-unit MLP under a 64-unit GRU).
- `drqn`: DRQN with today's defaults.
- `ppo-rnn`: recurrent PPO with its defaults.

    taskset -c 1 python benchmarks/recurrent_speed.py  # writes benchmarks/results/recurrent_speed_<date>[_N].md
    python benchmarks/recurrent_speed.py --configs 4 --steps 4096 --cases drqn  # a smoke run
    python benchmarks/recurrent_speed.py --devices 2  # every case split over 2 CPU devices, as a sweep runs

`--devices 1` (the default) runs each case as one XLA CPU program; `--devices N` splits its configurations over N
JAX CPU devices (one per core, `jax.shard_map`), as the sweep runner does (`amjax.sweep.devices`).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import resource
import subprocess
import sys
import time
from typing import Any

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

    from amjax.agents import ALGORITHMS, stack_configs
    from amjax.agents.training import init_run, run_evals
    from amjax.sweep.devices import config_sharding, sharded_jit

    agent, overrides = CASES[name]
    algo = ALGORITHMS[agent]
    items = [algo.config_type(cost=COSTS[i % len(COSTS)], **overrides) for i in range(configs)]
    unit = items[0].steps_per_update()
    every = max(unit, eval_every // unit * unit)
    total = max(every, steps // every * every)
    items = [c.replace(eval_every=every, total_timesteps=total).validate() for c in items]
    config, num_evals = stack_configs(items), items[0].num_evals
    keys = jnp.stack([jax.random.PRNGKey(i // len(COSTS)) for i in range(configs)])

    cpus = jax.devices("cpu")  # `devices` of them (set above)

    def eval_returns(c, k):
        return run_evals(algo, c, init_run(algo, c, k), num_evals)[1].test.costed_return

    train = sharded_jit(jax.vmap(eval_returns), cpus, in_shardings=config_sharding(cpus))
    config, keys = jax.device_put((config, keys), config_sharding(cpus))
    start = time.perf_counter()
    compiled = train.lower(config, keys).compile()
    compile_s = time.perf_counter() - start
    start = time.perf_counter()
    returns = jax.block_until_ready(compiled(config, keys))
    run_s = time.perf_counter() - start
    return {
        "case": name,
        "agent": agent,
        "overrides": overrides,
        "configs": configs,
        "devices": devices,
        "steps_per_config": total,
        "compile_s": round(compile_s, 1),
        "run_s": round(run_s, 1),
        "env_steps_per_s": round(configs * total / run_s),
        "peak_rss_mib": round(_peak_rss_mib()),
        "final_eval_return_median": round(float(jnp.median(returns[:, -1])), 1),
    }


def _peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def markdown(results: list[dict[str, Any]], args: argparse.Namespace) -> str:
    base = next((r for r in results if r["case"] == "drqn-old"), None)
    lines = [
        f"# Recurrent agents at sweep scale ({datetime.date.today()})",
        "",
        f'{args.configs} configurations (costs {", ".join(map(str, COSTS))} x seeds) of CartPole-v0 (mode "last") '
        f"in one vmapped program per case, split over {args.devices} CPU device(s), each case in its own process, "
        f"one after the other; {platform.node()}, {platform.processor() or platform.machine()}, "
        f"{os.cpu_count()} CPUs, CPU affinity {sorted(os.sched_getaffinity(0))}, load average at the end "
        f"{os.getloadavg()[0]:.1f}. Env steps/s: all configurations together, evaluations included, compile "
        "excluded.",
        "",
        "| case | settings | steps / config | compile (s) | run (s) | env steps/s | vs drqn-old | peak RSS (MiB) |",
        "|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in results:
        ratio = f"{r['env_steps_per_s'] / base['env_steps_per_s']:.1f}x" if base else ""
        settings = ", ".join(f"{k}={v}" for k, v in r["overrides"].items()) or "defaults"
        lines.append(
            f"| {r['case']} | {settings} | {r['steps_per_config']:,} | {r['compile_s']} | {r['run_s']} | "
            f"{r['env_steps_per_s']:,} | {ratio} | {r['peak_rss_mib']:,} |"
        )
    return "\n".join(lines) + "\n"


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
        help="markdown file to write (default: benchmarks/results/recurrent_speed_<date>.md, "
        "with _2, _3, ... added rather than overwriting an earlier result)",
    )
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    from amjax.cores import usable_cores

    if not 1 <= args.devices <= usable_cores():
        parser.error(f"--devices: {args.devices}; allowed values: 1 to {usable_cores()} (usable cores)")
    if args.configs % args.devices:
        parser.error(f"--configs: {args.configs} must be a multiple of --devices ({args.devices})")
    if args.child:
        print(json.dumps(run_case(args.child, args.configs, args.steps, args.eval_every, args.devices)))
        return 0

    results = []
    for name in args.cases:
        command = [
            sys.executable,
            __file__,
            "--child",
            name,
            "--configs",
            str(args.configs),
            "--steps",
            str(args.steps),
            "--eval-every",
            str(args.eval_every),
            "--devices",
            str(args.devices),
        ]
        output = subprocess.run(command, check=True, capture_output=True, text=True).stdout
        results.append(json.loads(output.strip().splitlines()[-1]))
        print(json.dumps(results[-1]), flush=True)
    text = markdown(results, args)
    print(text)
    out = args.out or _unused_path(f"benchmarks/results/recurrent_speed_{datetime.date.today()}", ".md")
    os.makedirs(os.path.dirname(out) or ".", exist_ok=True)
    with open(out, "w") as f:
        f.write(text)
    print(f"written to {out}")
    return 0


def _unused_path(stem: str, suffix: str) -> str:
    """`stem + suffix`, or the first of `stem_2 + suffix`, `stem_3 + suffix`, ... that does not exist yet."""
    path, n = stem + suffix, 1
    while os.path.exists(path):
        n += 1
        path = f"{stem}_{n}{suffix}"
    return path


if __name__ == "__main__":
    sys.exit(main())
