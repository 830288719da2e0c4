"""How long `python -m train replicate` takes on this machine, projected from short runs of its own batches.

For each environment x agent of the replication grid it builds the replicate command's batches (the same
configurations: 4 costs x 10 seeds in one, vanilla x 10 seeds in another, the same hyperparameters, split over the
same CPU devices), but with a short budget: two evaluation periods of about `--probe-steps` env steps each. It
times compilation and the second period (the first holds the replay warm-up), and projects each batch as

    compile + configurations x budget / (env-steps/s of the second period), summed over the batches.

The evaluation is timed on its own and subtracted from the period, then counted once per evaluation of the real
budget: `+ evaluations x evaluation time`. It is timed with untrained policies, whose test episodes are shorter than
trained ones on CartPole (so evaluation is underestimated there) and longer on Acrobot (overestimated); the
`eval len` column gives their mean length.
Check the method against a measured run: `python -m train replicate --env CartPole-v0` writes its wall time to
`OUT/wall_times.json`.

    python benchmarks/replicate_time.py                                   # every env x agent (~15 min on 2 cores)
    python benchmarks/replicate_time.py --env Acrobot-v1 --agent drqn
    python benchmarks/replicate_time.py --env LunarLander-v3 --agent ppo --seeds 3 --devices 1   # 3 seeds, one core
"""

from __future__ import annotations

import argparse
import math
import time
from functools import partial
from typing import Any

import jax
import numpy as np

import amjax

amjax.use_all_cores()  # one CPU device per core, before the imports below start JAX

from amjax.agents import stack_configs  # noqa: E402
from amjax.agents.training import evaluate_greedy  # noqa: E402
from amjax.sweep.batches import Batch, compiled_programs, plan_batches  # noqa: E402
from amjax.sweep.devices import config_sharding, sharded_jit, sweep_devices  # noqa: E402
from amjax.sweep.grid import expand  # noqa: E402
from train.presets import REPLICATE_AGENTS, REPLICATE_BUDGETS, replicate_specs  # noqa: E402


def probe_inputs(batch: Batch, probe_steps: int) -> tuple[Any, jax.Array, int]:
    """`batch`'s configurations cut to two evaluation periods of about `probe_steps` env steps each (stacked and
    padded as the batch is), its keys, and the period's env steps."""
    unit = batch.runs[0].config.steps_per_update()
    period = math.ceil(probe_steps / unit) * unit
    configs = [r.config.replace(total_timesteps=2 * period, eval_every=period).validate() for r in batch.runs]
    _, keys = batch.stacked()
    return stack_configs(configs + [configs[-1]] * (batch.size - len(configs))), keys, period


def probe_batch(batch: Batch, budget: int, probe_steps: int, devices: list) -> dict[str, float]:
    """Compile time and steady env-steps/s of one batch, and its projected time at `budget` steps per config."""
    stacked, keys, period = probe_inputs(batch, probe_steps)
    init, chunk = compiled_programs(batch.algo, 1, tuple(devices))
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
    period_s = time.perf_counter() - start
    # The evaluation alone (the same greedy test episodes the period ended with), so that training is projected at
    # its own rate and evaluation at the replicate's count of evaluations, not at the probe's much higher ratio.
    sharding = config_sharding(devices)
    evaluation = sharded_jit(
        jax.vmap(partial(_evaluation, batch.algo)), devices, in_shardings=sharding, out_shardings=sharding
    )
    jax.block_until_ready(evaluation(stacked, states))
    start = time.perf_counter()
    lengths = jax.block_until_ready(evaluation(stacked, states))
    eval_s = time.perf_counter() - start
    rate = len(batch.runs) * period / max(period_s - eval_s, 1e-9)  # padding configurations count as overhead
    steps = len(batch.runs) * budget
    evals = budget // batch.runs[0].config.eval_every
    return {
        "configs": len(batch.runs),
        "compile_s": compile_s,
        "steps_per_s": rate,
        "steps": steps,
        "eval_s": eval_s,
        "eval_length": float(np.mean(np.asarray(lengths)[: len(batch.runs)])),
        "projected_s": compile_s + steps / rate + evals * eval_s,
    }


def _evaluation(algo, config, state):
    """Mean test-episode length of the greedy policy of `state`, as `run_evals` evaluates it."""
    key = jax.random.fold_in(state.key, state.evals_done)
    return evaluate_greedy(algo, config, algo.setup(config), algo.params(state.algo), key, config.eval_episodes).length


def probe(env: str, agent: str, seeds: int, probe_steps: int, devices: list) -> list[dict[str, float]]:
    """`probe_batch` for every batch (active-measure, vanilla) the replicate command trains for (env, agent)."""
    spec = replicate_specs((env,), (agent,), seeds)[env]
    return [
        probe_batch(batch, spec.total_timesteps, probe_steps, devices)
        for batch in plan_batches(expand(spec), 1024, len(devices))
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", nargs="+", default=list(REPLICATE_BUDGETS), metavar="ENV")
    parser.add_argument("--agent", nargs="+", default=list(REPLICATE_AGENTS), metavar="AGENT")
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--probe-steps", type=int, default=8192, help="env steps per probe period (per config)")
    parser.add_argument("--devices", type=int, help="spread each batch over this many CPU devices (default: all)")
    args = parser.parse_args()
    devices = sweep_devices()
    if args.devices is not None and not 1 <= args.devices <= len(devices):
        parser.error(f"--devices: {args.devices}; allowed values: 1 to {len(devices)}")
    devices = devices[: args.devices or len(devices)]
    unknown = [env for env in args.env if env not in REPLICATE_BUDGETS]
    if unknown:
        parser.error(f"--env: {', '.join(unknown)}; allowed values: {', '.join(REPLICATE_BUDGETS)}")
    print(f"{len(devices)} CPU devices; probe: 2 periods of about {args.probe_steps:,} steps per config")
    print(
        f"{'env':<16}{'agent':<7}{'configs':>8}{'compile s':>11}{'train steps/s':>15}{'eval s':>8}"
        f"{'eval len':>9}{'env steps':>14}{'projected':>11}"
    )
    total = 0.0
    for env in args.env:
        for agent in args.agent:
            for r in probe(env, agent, args.seeds, args.probe_steps, devices):
                total += r["projected_s"]
                print(
                    f"{env:<16}{agent:<7}{r['configs']:>8}{r['compile_s']:>11.1f}{r['steps_per_s'] / 1e3:>14.1f}k"
                    f"{r['eval_s']:>8.2f}{r['eval_length']:>9.0f}{r['steps']:>14,}{r['projected_s'] / 60:>9.1f} m",
                    flush=True,
                )
    print(f"projected total: {total / 3600:.2f} h (training and compilation; reports add about a minute per env)")


if __name__ == "__main__":
    main()
