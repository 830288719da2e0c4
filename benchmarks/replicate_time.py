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

Each env x agent runs in a child process of its own (`benchmarks.harness`: its compiles and peak memory are its
own); the records go to `--out` (default: benchmarks/results/replicate_time_<date>_<machine>.jsonl) and the markdown
table beside it.

    python benchmarks/replicate_time.py                                   # every env x agent (~15 min on 2 cores)
    python benchmarks/replicate_time.py --env Acrobot-v1 --agent drqn
    python benchmarks/replicate_time.py --env LunarLander-v3 --agent ppo --seeds 3 --devices 1   # 3 seeds, one core
    python benchmarks/replicate_time.py --env CartPole-v0 --agent ppo --seeds 2 --probe-steps 1024 --out /tmp/r.jsonl
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

if not __package__:  # run as a file: the repository importable, for `benchmarks.harness`
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks import harness  # noqa: E402

if TYPE_CHECKING:
    import jax

    from amjax.sweep.batches import Batch

# amjax, JAX and the replication presets are imported where they are used: importing the presets starts JAX (gymnax
# does), and a child must ask for one CPU device per core first (`amjax.use_all_cores()`), while the parent must not
# hold an accelerator its children need.


def probe_inputs(batch: Batch, probe_steps: int) -> tuple[Any, jax.Array, int]:
    """`batch`'s configurations cut to two evaluation periods of about `probe_steps` env steps each (stacked and
    padded as the batch is), its keys, and the period's env steps."""
    from amjax.agents import stack_configs

    unit = batch.runs[0].config.steps_per_update()
    period = math.ceil(probe_steps / unit) * unit
    configs = [r.config.replace(total_timesteps=2 * period, eval_every=period).validate() for r in batch.runs]
    _, keys = batch.stacked()
    return stack_configs(configs + [configs[-1]] * (batch.size - len(configs))), keys, period


def probe_batch(
    batch: Batch, budget: int, probe_steps: int, devices: list, report: Callable[[dict], None] = lambda _: None
) -> dict[str, float]:
    """Compile time and steady env-steps/s of one batch, and its projected time at `budget` steps per config
    (`report` gets the init's and the chunk's compile times as soon as they are known)."""
    import jax
    import numpy as np

    from amjax.sweep.batches import compiled_programs
    from amjax.sweep.devices import config_sharding, sharded_jit

    stacked, keys, period = probe_inputs(batch, probe_steps)
    init, chunk = compiled_programs(batch.algo, 1, tuple(devices))
    start = time.perf_counter()
    states = jax.device_get(init(stacked, keys))
    init_s = time.perf_counter() - start
    stacked, states = jax.device_put((stacked, states), config_sharding(devices))
    start = time.perf_counter()
    chunk = chunk.lower(stacked, states).compile()
    compile_s = time.perf_counter() - start
    report({"configs": len(batch.runs), "init_s": init_s, "compile_s": compile_s})
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
        "init_s": init_s,
        "compile_s": compile_s,
        "steps_per_s": rate,
        "steps": steps,
        "eval_s": eval_s,
        "eval_length": float(np.mean(np.asarray(lengths)[: len(batch.runs)])),
        "projected_s": compile_s + steps / rate + evals * eval_s,
    }


def _evaluation(algo, config, state):
    """Mean test-episode length of the greedy policy of `state`, as `run_evals` evaluates it."""
    import jax

    from amjax.agents.training import evaluate_greedy

    key = jax.random.fold_in(state.key, state.evals_done)
    return evaluate_greedy(algo, config, algo.setup(config), algo.params(state.algo), key, config.eval_episodes).length


def probe(env: str, agent: str, seeds: int, probe_steps: int, devices: list) -> list[dict[str, float]]:
    """`probe_batch` for every batch (active-measure, vanilla) the replicate command trains for (env, agent)."""
    from amjax.sweep.batches import plan_batches
    from amjax.sweep.grid import expand
    from train.presets import replicate_specs

    spec = replicate_specs((env,), (agent,), seeds)[env]
    done: list[dict[str, float]] = []

    def report(current: dict) -> None:  # each step, so that a case past its time limit still says what it measured
        harness.child_progress({"batches": done, "current": current})

    for batch in plan_batches(expand(spec), 1024, len(devices)):
        done.append(probe_batch(batch, spec.total_timesteps, probe_steps, devices, report))
        harness.child_progress({"batches": done})
    return done


def run_case(env: str, agent: str, seeds: int, probe_steps: int, devices: int | None) -> dict[str, Any]:
    """In a child: every batch of (env, agent) probed and projected, on `devices` of the sweep's devices."""
    import amjax

    amjax.use_all_cores()  # one CPU device per core, before the imports below start JAX
    import jax

    from amjax.sweep.devices import sweep_devices

    available = sweep_devices()
    if devices is not None and not 1 <= devices <= len(available):
        raise SystemExit(f"--devices: {devices}; allowed values: 1 to {len(available)}")
    chosen = available[: devices or len(available)]
    batches = probe(env, agent, seeds, probe_steps, chosen)
    return {
        "device_count": len(chosen),
        "backend": jax.default_backend(),
        "batches": batches,
        "projected_total_s": sum(b["projected_s"] for b in batches),
    }


def render(runs: list[dict[str, Any]]) -> str:
    """The markdown of a results file: one table per run, a row per batch, and the projected total."""
    parts = []
    for run in runs:
        settings, results = run["settings"], [r for r in run["cases"] if r["status"] == "ok"]
        rows = [{**r, **batch} for r in results for batch in r["batches"]]
        devices = ", ".join(sorted({f"{r['device_count']} {r['backend'].upper()}" for r in results})) or "?"
        total = sum(r["projected_total_s"] for r in results)
        failed = [r for r in run["cases"] if r["status"] != "ok"]
        parts.append(
            f"# amjax replicate, projected ({run['date'][:10]})\n\n"
            f"{settings['seeds']} seeds; {devices} device(s) per batch; probe: 2 periods of about "
            f"{settings['probe_steps']:,} steps per config, each env x agent in its own process. Projected per batch: "
            "compile + configurations x budget / train env-steps/s + evaluations x evaluation time; `eval len`: the "
            f"untrained policies' mean test-episode length. {harness.describe(run)}\n\n"
            + harness.markdown_table(
                rows,
                [
                    ("env", lambda r: r["env"]),
                    ("agent", lambda r: r["agent"]),
                    ("configs", lambda r: r["configs"]),
                    ("compile (s)", lambda r: f"{r['compile_s']:.1f}"),
                    ("train steps/s", lambda r: f"{r['steps_per_s'] / 1e3:.1f} k"),
                    ("eval (s)", lambda r: f"{r['eval_s']:.2f}"),
                    ("eval len", lambda r: round(r["eval_length"])),
                    ("env steps", lambda r: r["steps"]),
                    ("projected", lambda r: f"{r['projected_s'] / 60:.1f} m"),
                    ("peak RSS (MiB)", lambda r: r["peak_rss_mib"]),
                ],
            )
            + f"\nprojected total: {total / 3600:.2f} h (training and compilation; reports add about a minute per "
            f"env){' of the env x agent cases that finished' if failed else ''}; peak RSS: the env x agent's "
            "process.\n" + "".join(f"\n{r['env']} {r['agent']}: {r['status']}{_partial(r)}\n" for r in failed)
        )
    return "\n".join(parts)


def _partial(case: dict[str, Any]) -> str:
    """What a case that ran out of time finished: its probed batches, as the table would show them."""
    partial = case.get("partial", {})
    text = "".join(
        f"; its {b['configs']}-configuration batch finished (compile {b['compile_s']:.1f} s, "
        f"{b['steps_per_s'] / 1e3:.1f} k train steps/s, projected {b['projected_s'] / 60:.1f} m)"
        for b in partial.get("batches", [])
    )
    if "current" in partial:
        c = partial["current"]
        text += (
            f"; its {c['configs']}-configuration batch had compiled (init {c['init_s']:.1f} s with its compile, "
            f"training chunk {c['compile_s']:.1f} s)"
        )
    return text


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", nargs="+", metavar="ENV", help="default: every env of the replication")
    parser.add_argument("--agent", nargs="+", metavar="AGENT", help="default: every agent of the replication")
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--probe-steps", type=int, default=8192, help="env steps per probe period (per config)")
    parser.add_argument("--devices", type=int, help="spread each batch over this many CPU devices (default: all)")
    parser.add_argument("--timeout", type=float, default=None, help="seconds per env x agent before it is abandoned")
    parser.add_argument(
        "--out",
        help="results file to append to (default: benchmarks/results/replicate_time_<date>_<machine>.jsonl; the "
        "markdown table is written beside it)",
    )
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        case = json.loads(args.child)
        harness.child_result(run_case(case["env"], case["agent"], case["seeds"], case["probe_steps"], case["devices"]))
        return 0

    import jax

    jax.config.update("jax_platforms", "cpu")  # here only: the presets start JAX, and the children need the device
    from amjax.cores import usable_cores
    from train.presets import REPLICATE_AGENTS, REPLICATE_BUDGETS

    args.env, args.agent = args.env or list(REPLICATE_BUDGETS), args.agent or list(REPLICATE_AGENTS)
    if args.devices is not None and not 1 <= args.devices <= usable_cores():
        parser.error(f"--devices: {args.devices}; allowed values: 1 to {usable_cores()}")
    unknown = [env for env in args.env if env not in REPLICATE_BUDGETS]
    if unknown:
        parser.error(f"--env: {', '.join(unknown)}; allowed values: {', '.join(REPLICATE_BUDGETS)}")

    cases = [
        {"env": env, "agent": agent, "seeds": args.seeds, "probe_steps": args.probe_steps, "devices": args.devices}
        for env in args.env
        for agent in args.agent
    ]
    harness.run_cases("replicate_time", harness.settings_of(args), args.out, __file__, cases, render, args.timeout)
    return 0


if __name__ == "__main__":
    sys.exit(main())
