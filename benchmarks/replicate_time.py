"""How long `python -m train replicate` takes on this machine, projected from short runs of its own batches.

For each environment x agent of the replication grid it builds the replicate command's batch (the same 50
configurations: 4 costs + vanilla x 10 seeds, the same hyperparameters, split over the same CPU devices), but with
a short budget: two evaluation periods of `--probe-steps` env steps each. It times compilation and the second period
(the first holds the replay warm-up), and projects the full batch as

    compile + configurations x budget / (env-steps/s of the second period).

Evaluation is inside the timed period, so it is counted at the probe's (higher) evaluations-per-step ratio, but with
untrained policies, whose episodes are short on CartPole and LunarLander (cheaper evaluations than trained ones).
Check the method against a measured run: `python -m train replicate --env CartPole-v0` writes its wall time to
`OUT/wall_times.json`.

    python benchmarks/replicate_time.py                                   # every env x agent (~10 min on 2 cores)
    python benchmarks/replicate_time.py --env CartPole-v0 --agent drqn
"""

from __future__ import annotations

import argparse
import math
import time

import jax
import numpy as np

from amjax.agents import stack_configs
from amjax.sweep.devices import config_sharding, sweep_devices
from amjax.sweep.grid import expand
from amjax.sweep.runner import _batches, _compiled
from train.presets import REPLICATE_AGENTS, REPLICATE_BUDGETS, replicate_specs


def probe(env: str, agent: str, seeds: int, probe_steps: int) -> dict[str, float]:
    """Compile time and steady env-steps/s of the replicate batch of (env, agent), and its projected time."""
    spec = replicate_specs((env,), (agent,), seeds)[env]
    devices = sweep_devices()
    (batch,) = _batches(expand(spec), 1024, len(devices))
    unit = batch.runs[0].config.steps_per_update()
    period = math.ceil(probe_steps / unit) * unit
    configs = [r.config.replace(total_timesteps=2 * period, eval_every=period).validate() for r in batch.runs]
    stacked = stack_configs(configs + [configs[-1]] * (batch.size - len(configs)))
    _, keys = batch.stacked()
    init, chunk = _compiled(batch.algo, 1, tuple(devices))
    states = jax.device_get(init(stacked, keys))
    stacked, states = jax.device_put((stacked, states), config_sharding(devices))
    start = time.perf_counter()
    chunk = chunk.lower(stacked, states).compile()
    compile_s = time.perf_counter() - start
    states, rows = chunk(stacked, states)  # the first period (replay warm-up included)
    jax.block_until_ready(rows)
    start = time.perf_counter()
    states, rows = chunk(stacked, states)
    jax.block_until_ready(rows)
    rate = len(batch.runs) * period / (time.perf_counter() - start)  # padding configurations count as overhead
    total_steps = len(batch.runs) * spec.total_timesteps
    return {
        "configs": len(batch.runs), "devices": len(devices), "probe_steps": period, "compile_s": compile_s,
        "steps_per_s": rate, "total_steps": total_steps, "projected_s": compile_s + total_steps / rate,
        "eval_return": float(np.median(np.asarray(rows.eval_return)[: len(batch.runs), -1])),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", nargs="+", default=list(REPLICATE_BUDGETS), metavar="ENV")
    parser.add_argument("--agent", nargs="+", default=list(REPLICATE_AGENTS), metavar="AGENT")
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--probe-steps", type=int, default=8192, help="env steps per probe period (per config)")
    args = parser.parse_args()
    unknown = [env for env in args.env if env not in REPLICATE_BUDGETS]
    if unknown:
        parser.error(f"--env: {', '.join(unknown)}; allowed values: {', '.join(REPLICATE_BUDGETS)}")
    print(f"{len(sweep_devices())} CPU devices; probe: 2 periods of about {args.probe_steps:,} steps per config")
    print(f"{'env':<16}{'agent':<7}{'configs':>8}{'compile s':>11}{'env-steps/s':>13}{'env steps':>14}"
          f"{'projected':>11}")
    total = 0.0
    for env in args.env:
        for agent in args.agent:
            r = probe(env, agent, args.seeds, args.probe_steps)
            total += r["projected_s"]
            print(f"{env:<16}{agent:<7}{r['configs']:>8}{r['compile_s']:>11.1f}{r['steps_per_s'] / 1e3:>12.1f}k"
                  f"{r['total_steps']:>14,}{r['projected_s'] / 60:>9.1f} m", flush=True)
    print(f"projected total: {total / 3600:.2f} h (training and compilation; reports add about a minute per env)")


if __name__ == "__main__":
    main()
