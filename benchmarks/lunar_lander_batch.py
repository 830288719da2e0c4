"""LunarLander-v3 port at large batch sizes, on whatever backend JAX has (the GPU table of docs/gpu.md).

    python benchmarks/lunar_lander_batch.py --envs 65536 262144 1048576
    python benchmarks/lunar_lander_batch.py --envs 4096 --strategy cpu --steps 20 --burn-in 20   # the CPU layout

Random actions, auto-reset included: one jitted program steps every env `--steps` times (`env.step` vmapped inside
a `lax.scan`, the states donated). It runs `--burn-in` steps untimed from the reset, so that the envs are spread
over their episodes (contacts and resets in their usual proportions; a window from the reset times free fall
only), then is timed over `--repeats` calls (the fastest kept). Prints one markdown row per size (env-steps/s,
compile time, the device's peak memory or the process's peak RSS) and appends them as JSON lines to `--json`.
`--strategy` chooses amjax's layout (`amjax.strategy`; default: the backend's).
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from functools import partial

import jax
import jax.numpy as jnp

from amjax import strategy
from amjax.envs.lunar_lander import LunarLander


def peak_memory_gib() -> tuple[float, str]:
    """The device's peak allocation where JAX reports one (GPU), else the process's peak RSS."""
    stats = jax.devices()[0].memory_stats() or {}
    if "peak_bytes_in_use" in stats:
        return stats["peak_bytes_in_use"] / 2**30, "device peak"
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20, "peak RSS"


def time_size(num_envs: int, steps: int, burn_in: int, repeats: int) -> dict:
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


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", type=int, nargs="+", default=[65_536, 262_144, 1_048_576])
    parser.add_argument("--steps", type=int, default=50, help="env steps per timed call (default 50)")
    parser.add_argument("--burn-in", type=int, default=200, help="untimed steps from the reset (default 200)")
    parser.add_argument("--repeats", type=int, default=2, help="timed calls; the fastest is kept (default 2)")
    parser.add_argument("--strategy", choices=strategy.STRATEGIES, default=None, help="default: the backend's")
    parser.add_argument("--json", default=None, help="append one JSON line per size to this file")
    args = parser.parse_args(argv)
    print("| envs | strategy | env-steps/s | run (s) | compile (s) | memory (GiB) | device |", flush=True)
    print("|---|---|---|---|---|---|---|", flush=True)
    with strategy.use(args.strategy):
        for num_envs in args.envs:
            row = time_size(num_envs, args.steps, args.burn_in, args.repeats)
            print(
                f"| {num_envs:,} | {row['strategy']} | {row['env_steps_per_s'] / 1e3:,.0f} k | {row['run_s']:.2f} "
                f"| {row['compile_s']:.1f} | {row['memory_gib']:.2f} ({row['memory_kind']}) | {row['device']} |",
                flush=True,
            )
            if args.json:
                with open(args.json, "a") as file:
                    file.write(json.dumps(row) + "\n")
    sys.stdout.flush()


if __name__ == "__main__":
    main()
