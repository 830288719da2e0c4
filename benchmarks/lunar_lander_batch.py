"""LunarLander-v3 port at large batch sizes, on whatever backend JAX has (the GPU table of docs/gpu.md).

    python benchmarks/lunar_lander_batch.py --envs 65536 262144 1048576  # benchmarks/results/, .jsonl and .md
    python benchmarks/lunar_lander_batch.py --envs 4096 --strategy cpu --steps 20 --burn-in 20   # the CPU layout
    python benchmarks/lunar_lander_batch.py --envs 256 --steps 5 --burn-in 5 --out /tmp/lander.jsonl  # a smoke run

Random actions, auto-reset included: one jitted program steps every env `--steps` times (`env.step` vmapped inside
a `lax.scan`, the states donated). It runs `--burn-in` steps untimed from the reset, so that the envs are spread
over their episodes (contacts and resets in their usual proportions; a window from the reset times free fall
only), then is timed over `--repeats` calls (the fastest kept). Each size runs in a child process of its own
(`benchmarks.harness`), which reports env-steps/s, the compile time, the device's peak memory where JAX reports one
(GPU), else the process's peak RSS, and the child's peak RSS; the records go to `--out` and the markdown table
beside it. `--strategy` chooses amjax's layout (`amjax.strategy`; default: the backend's).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from functools import partial
from pathlib import Path
from typing import Any

if not __package__:  # run as a file: the repository importable, for `benchmarks.harness`
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks import harness  # noqa: E402

STRATEGIES = ("cpu", "gpu")  # amjax.strategy.STRATEGIES, without importing JAX in the parent


def peak_memory_gib() -> tuple[float, str]:
    """The device's peak allocation where JAX reports one (GPU), else the process's peak RSS."""
    import jax

    stats = jax.devices()[0].memory_stats() or {}
    if "peak_bytes_in_use" in stats:
        return stats["peak_bytes_in_use"] / 2**30, "device peak"
    return harness.peak_rss_mib() / 2**10, "peak RSS"


def time_size(num_envs: int, steps: int, burn_in: int, repeats: int) -> dict[str, Any]:
    """Compile and time one batch size in this process (under the strategy in force)."""
    import jax
    import jax.numpy as jnp

    from amjax import strategy
    from amjax.envs.lunar_lander import LunarLander

    env = LunarLander()
    params = env.default_params

    @jax.jit
    def reset(key):
        return jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(key, num_envs), params)[1]

    def one_step(carry, key):
        state, total = carry
        action_key, env_key = jax.random.split(key)
        action = jax.random.randint(action_key, (num_envs,), 0, env.num_actions)
        keys = jax.random.split(env_key, num_envs)
        _, state, reward, *_ = jax.vmap(env.step, in_axes=(0, 0, 0, None))(keys, state, action, params)
        return (state, total + reward.sum()), None

    @partial(jax.jit, donate_argnums=0)
    def run(state, key):
        (state, total), _ = jax.lax.scan(one_step, (state, jnp.float32(0.0)), jax.random.split(key, steps))
        return state, total

    key = jax.random.key(0)
    state = reset(key)
    start = time.perf_counter()
    compiled = run.lower(state, key).compile()
    compile_s = time.perf_counter() - start
    for i in range(-(-burn_in // steps)):
        state, _ = compiled(state, jax.random.fold_in(key, i))
    jax.block_until_ready(state)
    times = []
    for i in range(repeats):
        start = time.perf_counter()
        state, total = compiled(state, jax.random.fold_in(key, 10_000 + i))
        jax.block_until_ready((state, total))
        times.append(time.perf_counter() - start)
    memory, memory_kind = peak_memory_gib()
    return {
        "envs": num_envs,
        "steps": steps,
        "burn_in": burn_in,
        "strategy": strategy.current(),
        "env_steps_per_s": num_envs * steps / min(times),
        "run_s": min(times),
        "compile_s": compile_s,
        "memory_gib": memory,
        "memory_kind": memory_kind,
        "device": jax.devices()[0].device_kind,
        "backend": jax.default_backend(),
    }


def render(runs: list[dict[str, Any]]) -> str:
    """The markdown of a results file: one table per run (e.g. gpu.sh's default layout, then the CPU layout)."""
    parts = []
    for run in runs:
        settings, results = run["settings"], [r for r in run["cases"] if r["status"] == "ok"]
        layout = settings["strategy"] or "the backend's"
        parts.append(
            f"# LunarLander-v3, random actions ({run['date'][:10]})\n\n"
            f"Strategy: {layout}; {settings['steps']} env steps per timed call "
            f"after {settings['burn_in']} untimed ones from the reset, the fastest of {settings['repeats']} calls; "
            "auto-reset included, compile excluded; each size in its own process. Memory: the "
            f"device's peak allocation where JAX reports one, else the process's peak RSS. {harness.describe(run)}\n\n"
            + harness.markdown_table(
                results,
                [
                    ("envs", lambda r: r["envs"]),
                    ("strategy", lambda r: r["strategy"]),
                    ("env-steps/s", lambda r: f"{r['env_steps_per_s'] / 1e3:,.0f} k"),
                    ("run (s)", lambda r: f"{r['run_s']:.2f}"),
                    ("compile (s)", lambda r: f"{r['compile_s']:.1f}"),
                    ("memory (GiB)", lambda r: f"{r['memory_gib']:.2f} ({r['memory_kind']})"),
                    ("peak RSS (MiB)", lambda r: r["peak_rss_mib"]),
                    ("device", lambda r: r["device"]),
                ],
            )
            + "".join(f"\n{r['envs']:,} envs: {r['status']}\n" for r in run["cases"] if r["status"] != "ok")
        )
    return "\n".join(parts)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", type=int, nargs="+", default=[65_536, 262_144, 1_048_576])
    parser.add_argument("--steps", type=int, default=50, help="env steps per timed call (default 50)")
    parser.add_argument("--burn-in", type=int, default=200, help="untimed steps from the reset (default 200)")
    parser.add_argument("--repeats", type=int, default=2, help="timed calls; the fastest is kept (default 2)")
    parser.add_argument("--strategy", choices=STRATEGIES, default=None, help="default: the backend's")
    parser.add_argument("--timeout", type=float, default=None, help="seconds per size before it is abandoned")
    parser.add_argument(
        "--out",
        "--json",
        dest="out",
        help="results file to append to (default: benchmarks/results/lunar_lander_batch_<date>_<machine>.jsonl; "
        "the markdown table is written beside it). --json is the former name: it appended one JSON line per size",
    )
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        from amjax import strategy

        case = json.loads(args.child)
        with strategy.use(case["strategy"]):
            harness.child_result(time_size(case["envs"], case["steps"], case["burn_in"], case["repeats"]))
        return 0

    cases = [
        {"envs": n, "steps": args.steps, "burn_in": args.burn_in, "repeats": args.repeats, "strategy": args.strategy}
        for n in args.envs
    ]
    harness.run_cases("lunar_lander_batch", harness.settings_of(args), args.out, __file__, cases, render, args.timeout)
    return 0


if __name__ == "__main__":
    sys.exit(main())
