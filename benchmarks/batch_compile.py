"""Where a replicate batch's compile time goes, and what XLA compiler options change (issue 13's grid time).

Builds one batch of `amjax replicate`'s grid (the same configurations and CPU devices as the command), traces and
lowers its three programs (initialisation, training chunk, re-scoring) once, then for each named set of compiler
options compiles all three and runs them: the seconds each compile takes (and the process CPU seconds of all three),
the seconds of one training period (about `--probe-steps` env steps per configuration, after one untimed period)
and of the re-scoring, and whether the initial train states are bit-identical to XLA's default options (anything
else changes every trained number downstream).

Everything runs in this one process, on purpose: the option sets are compiles of the same lowerings, compared with
each other and with the first initialisation's states, so they are not split into child processes; the harness
(`benchmarks.harness`) records the results and renders the table. The peak resident memory shown is this process's
so far, after each option set.

    python benchmarks/batch_compile.py --env LunarLander-v3 --agent dqn
    python benchmarks/batch_compile.py --env CartPole-v0 --agent drqn --options default O0
    python benchmarks/batch_compile.py --env CartPole-v0 --agent ppo --batch vanilla --seeds 1 --probe-steps 1 \
        --options default --out /tmp/batch_compile.jsonl  # a smoke run

Results: `benchmarks/results/batch_compile_<date>_<machine>.jsonl` (`--out`), the markdown table beside it.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

if not __package__:  # run as a file: the repository importable, for `benchmarks.harness`
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks import harness  # noqa: E402

OPTIONS: dict[str, dict[str, object] | None] = {
    "default": None,
    "O1": {"xla_backend_optimization_level": 1},
    "O0": {"xla_backend_optimization_level": 0},
    "no-expensive-passes": {"xla_llvm_disable_expensive_passes": True},
}


def render(runs: list[dict[str, Any]]) -> str:
    """The markdown of a results file: one table per run, a row per set of compiler options."""
    out = []
    for run in runs:
        settings = run["settings"]
        setup = next((r for r in run["cases"] if r["case"] == "lowering"), None)
        rows = [r for r in run["cases"] if r["case"] == "options"]
        missing = [name for name in settings["options"] if name not in {r["options"] for r in rows}]
        flags = "; ".join(
            f"{name}: " + (", ".join(f"{k}={v}" for k, v in options.items()) if options else "XLA's defaults")
            for name, options in settings["xla_options"].items()
        )
        batch = (
            f"{setup['configurations']} configurations on {setup['devices']} CPU devices, periods of "
            f"{setup['period']:,} env steps per configuration; the first initialisation (trace, lower, compile, run) "
            f"and the others' tracing and lowering: {setup['first_s']} s"
            if setup
            else "no batch built"
        )
        out.append(
            f"# A replicate batch's compile time under XLA compiler options ({run['date'][:10]})\n\n"
            f"{settings['env']} {settings['agent']}, {settings['batch']} batch ({settings['seeds']} seeds): {batch}. "
            "Then, in the same process, each option set compiles the three lowerings afresh and runs them. "
            "compile: wall seconds of each XLA compile; compile CPU: process CPU seconds of the three; period: one "
            "training period (after one untimed); init identical: the initial train states bit-equal to the default "
            f"options'; peak RSS: this process's so far. Options: {flags}. {harness.describe(run)}\n\n"
            + harness.markdown_table(
                rows,
                [
                    ("options", lambda r: r["options"]),
                    ("compile init (s)", lambda r: r["compile_init_s"]),
                    ("compile chunk (s)", lambda r: r["compile_chunk_s"]),
                    ("compile rescore (s)", lambda r: r["compile_rescore_s"]),
                    ("compile CPU (s)", lambda r: r["compile_cpu_s"]),
                    ("init run (s)", lambda r: r["init_run_s"]),
                    ("init identical", lambda r: r["init_identical"]),
                    ("period (s)", lambda r: r["period_s"]),
                    ("rescore (s)", lambda r: r["rescore_s"]),
                    ("peak RSS (MiB)", lambda r: r["peak_rss_mib"]),
                ],
            )
            + (f"\nNot finished: {', '.join(missing)}.\n" if missing else "")
        )
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    import amjax

    amjax.use_all_cores()  # one CPU device per core, as the replicate command (before JAX starts)
    from train.presets import REPLICATE_BUDGETS

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
    parser.add_argument(
        "--out",
        help="results file to append to (default: benchmarks/results/batch_compile_<date>_<machine>.jsonl; the "
        "markdown table is written beside it)",
    )
    args = parser.parse_args(argv)
    settings = {**vars(args), "xla_options": {name: OPTIONS[name] for name in args.options}}
    recorder = harness.Recorder("batch_compile", settings, args.out)
    try:
        measure(args, recorder)
    finally:
        recorder.end()
        print(f"written to {recorder.path} and {harness.write_markdown(recorder.path, render)}")
    return 0


def measure(args: argparse.Namespace, recorder: harness.Recorder) -> None:
    """Build the batch, lower its programs once, then compile and run them under each option set, recording each."""
    import jax
    import numpy as np

    from amjax.sweep.batches import compiled_programs, plan_batches, rescore_program
    from amjax.sweep.devices import config_sharding, sweep_devices
    from amjax.sweep.grid import expand
    from benchmarks.replicate_time import probe_inputs
    from train.presets import replicate_specs

    devices = tuple(sweep_devices())
    spec = replicate_specs((args.env,), (args.agent,), args.seeds)[args.env]
    batches = plan_batches(expand(spec), 1024, len(devices))
    batch = next(b for b in batches if b.runs[0].vanilla == (args.batch == "vanilla"))
    stacked, keys, period = probe_inputs(batch, args.probe_steps)
    init, chunk = compiled_programs(batch.algo, 1, devices)
    sharding = config_sharding(list(devices))
    start = time.perf_counter()
    states = jax.device_get(init(stacked, keys))  # traced, lowered and compiled with the default options
    configs_placed, states_placed = jax.device_put((stacked, states), sharding)
    lowered = {
        "init": init.lower(stacked, keys),
        "chunk": chunk.lower(configs_placed, states_placed),
        "rescore": rescore_program(batch.algo, devices).lower(configs_placed, states_placed),
    }
    recorder.case(
        {
            "case": "lowering",
            "configurations": len(batch.runs),
            "devices": len(devices),
            "period": period,
            "first_s": round(time.perf_counter() - start, 1),  # the first init and the others' trace and lowering
        }
    )
    for name in args.options:
        options = OPTIONS[name]
        row: dict[str, object] = {"case": "options", "options": name}
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
        row["peak_rss_mib"] = round(harness.peak_rss_mib())  # this process's so far
        recorder.case(row)


if __name__ == "__main__":
    sys.exit(main())
