"""Where a replicate batch's compile time goes, and what XLA compiler options change (issue 13's grid time).

Builds one batch of `amjax replicate`'s grid (the same configurations and CPU devices as the command), traces and
lowers its three programs (initialisation, training chunk, re-scoring) once, then for each named set of compiler
options compiles all three and runs them: the seconds each compile takes (and the process CPU seconds of all three),
the seconds of one training period (about `--probe-steps` env steps per configuration, after one untimed period)
and of the re-scoring, and whether the initial train states are bit-identical to XLA's default options (anything
else changes every trained number downstream).

    python benchmarks/batch_compile.py --env LunarLander-v3 --agent dqn
    python benchmarks/batch_compile.py --env CartPole-v0 --agent drqn --options default O0
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import jax
import numpy as np

import amjax

amjax.use_all_cores()  # one CPU device per core, as the replicate command
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the benchmarks are not installed

from amjax.sweep.batches import compiled_programs, plan_batches, rescore_program  # noqa: E402
from amjax.sweep.devices import config_sharding, sweep_devices  # noqa: E402
from amjax.sweep.grid import expand  # noqa: E402
from benchmarks.replicate_time import probe_inputs  # noqa: E402
from train.presets import REPLICATE_BUDGETS, replicate_specs  # noqa: E402

OPTIONS: dict[str, dict[str, object] | None] = {
    "default": None,
    "O1": {"xla_backend_optimization_level": 1},
    "O0": {"xla_backend_optimization_level": 0},
    "no-expensive-passes": {"xla_llvm_disable_expensive_passes": True},
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="LunarLander-v3", choices=list(REPLICATE_BUDGETS))
    parser.add_argument("--agent", default="dqn", choices=["dqn", "ppo", "drqn", "ppo-rnn"])
    parser.add_argument(
        "--batch",
        default="costed",
        choices=["costed", "vanilla"],
        help="the batch of costs 0-0.3 x seeds, or the vanilla one",
    )
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--probe-steps", type=int, default=8192, help="env steps per configuration per period")
    parser.add_argument("--options", nargs="+", default=list(OPTIONS), choices=list(OPTIONS))
    args = parser.parse_args()

    devices = tuple(sweep_devices())
    spec = replicate_specs((args.env,), (args.agent,), args.seeds)[args.env]
    batches = plan_batches(expand(spec), 1024, len(devices))
    batch = next(b for b in batches if b.runs[0].vanilla == (args.batch == "vanilla"))
    stacked, keys, period = probe_inputs(batch, args.probe_steps)
    init, chunk = compiled_programs(batch.algo, 1, devices)
    sharding = config_sharding(list(devices))
    print(
        f"{args.env} {args.agent}, {args.batch} batch: {len(batch.runs)} configurations on {len(devices)} CPU "
        f"devices; periods of {period:,} env steps per configuration",
        flush=True,
    )
    start = time.perf_counter()
    states = jax.device_get(init(stacked, keys))  # traced, lowered and compiled with the default options
    configs_placed, states_placed = jax.device_put((stacked, states), sharding)
    lowered = {
        "init": init.lower(stacked, keys),
        "chunk": chunk.lower(configs_placed, states_placed),
        "rescore": rescore_program(batch.algo, devices).lower(configs_placed, states_placed),
    }
    print(
        f"first initialisation (trace, lower, compile, run) and the others' tracing and lowering: "
        f"{time.perf_counter() - start:.1f} s",
        flush=True,
    )
    for name in args.options:
        options = OPTIONS[name]
        row: dict[str, object] = {"options": name}
        cpu = time.process_time()
        compiled = {}
        for program, lowering in lowered.items():
            start = time.perf_counter()
            # A fresh compile even for the default options (a lowering caches only its default executable).
            compiled[program] = lowering.compile(options or {"xla_backend_optimization_level": 2})
            row[f"compile_{program}_s"] = round(time.perf_counter() - start, 1)
        row["compile_cpu_s"] = round(time.process_time() - cpu, 1)
        start = time.perf_counter()
        fresh = jax.device_get(compiled["init"](stacked, keys))
        row["init_run_s"] = round(time.perf_counter() - start, 2)
        row["init_identical"] = all(
            np.array_equal(a, b, equal_nan=True)
            for a, b in zip(jax.tree.leaves(fresh), jax.tree.leaves(states), strict=True)
        )
        run_states = jax.device_put(jax.tree.map(np.array, states), sharding)
        run_states, rows = compiled["chunk"](configs_placed, run_states)  # the first period (replay warm-up)
        jax.block_until_ready(rows)
        start = time.perf_counter()
        run_states, rows = compiled["chunk"](configs_placed, run_states)
        jax.block_until_ready(rows)
        row["period_s"] = round(time.perf_counter() - start, 2)
        start = time.perf_counter()
        jax.block_until_ready(compiled["rescore"](configs_placed, run_states))
        row["rescore_s"] = round(time.perf_counter() - start, 2)
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
