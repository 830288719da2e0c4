"""LunarLander-v3 speed: the pure-JAX port against Gymnasium's Box2D original, timed in one invocation.

    python benchmarks/lunar_lander_speed.py                       # 1, 64, 1,024, 4,096, 16,384 envs
    python benchmarks/lunar_lander_speed.py --envs 1 1024 --steps-per-run 50000

Random actions, auto-reset included in both. Gymnasium: one env in a Python loop (its C++ Box2D on one core,
episodes cut at 1000 steps as LunarLander-v3's TimeLimit does). The port: `env.step` vmapped over the envs inside
a jitted `lax.scan`, the envs split over the CPU devices with `jax.shard_map` (one device per core, as
`amjax.use_all_cores()` sets up and the sweep runner uses; default `check_vma`). Also one env's jitted step called
from Python, one call per step that splits the carried key (the path of notebooks and the Gymnasium bridge), with
`jax.jit`, compiled as one kernel (`amjax.cores.jit_one_kernel`), and as one kernel with the key and state carried
as one packed vector (`amjax.cores.TreeLayout`), as the bridge does; and the bridge itself (`to_gymnasium`). The
programs are compiled with the XLA CPU options `import amjax` sets (`amjax.cores.xla_cpu_options`: small loops as
single kernels, reductions in XLA; run with `AMJAX_XLA_OPTIONS=0` to time XLA's defaults). The port's timed run
starts after a burn-in of `--burn-in` steps (500 by default) from the reset, so its envs are spread over their
episodes (landings, contacts and auto-resets in the usual proportions); a window that starts at the reset times
only free fall, which ran 7x faster at 4,096 envs. Three solver settings are timed by default:
Box2D's velocity sweeps in every env (the default env), ``jump_sweeps=True`` and ``exact_free_flight=True``.
Also timed: 1,024 envs driven by Gymnasium's heuristic controller (`--heuristic-envs`: landers that touch down and
rest, legs on the ground on about 29% of env-steps, the costly contact path), and the compile of one vmapped
`env.step` at 1,024 envs. Prints a markdown table (env-steps/s, compile time, memory) and writes it to
benchmarks/results/lunar_lander_speed_<date>.md.
"""

from __future__ import annotations

import argparse
import datetime
import itertools
import os
import platform
import resource
import sys
import time
from pathlib import Path

import jax
import numpy as np
from jax.sharding import Mesh, PartitionSpec

import amjax

amjax.use_all_cores()  # one CPU device per core, before the imports below start JAX

from amjax.cores import REDUCTIONS_IN_XLA, TreeLayout, jit_one_kernel  # noqa: E402
from amjax.envs.lunar_lander import LunarLander  # noqa: E402
from amjax.envs.lunar_lander.env import heuristic_action  # noqa: E402
from amjax.envs.lunar_lander.reference import load_gymnasium_lunar_lander  # noqa: E402
from amjax.wrappers.gymnasium import to_gymnasium  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the benchmarks are not installed
from benchmarks.throughput.report import save_table  # noqa: E402


def gymnasium_rate(n_steps: int, seed: int = 0) -> float:
    """Env-steps/s of Gymnasium's LunarLander-v3, random actions, reset on termination or 1000 steps."""
    env = load_gymnasium_lunar_lander().LunarLander()
    env.action_space.seed(seed)
    env.reset(seed=seed)
    t, start = 0, time.perf_counter()
    for _ in range(n_steps):
        _, _, terminated, _, _ = env.step(env.action_space.sample())
        t += 1
        if terminated or t == 1000:
            env.reset()
            t = 0
    return n_steps / (time.perf_counter() - start)


def port_rollout(env: LunarLander, n_steps: int, policy: str = "random"):
    """(state, keys) -> state: `n_steps` vmapped steps of every env in `state`, with random actions or Gymnasium's
    heuristic controller (`policy="heuristic"`: landings, legs on the ground on about 29% of env-steps)."""
    params = env.default_params

    def rollout(state, key):
        def body(state, key):
            if policy == "heuristic":
                actions = jax.vmap(lambda s: heuristic_action(env.get_obs(s)))(state)
            else:
                actions = jax.vmap(lambda k: env.action_space(params).sample(k))(
                    jax.vmap(jax.random.fold_in, (0, None))(key, 1)
                )
            _, state, _, _, _, _ = jax.vmap(env.step, (0, 0, 0, None))(key, state, actions, params)
            return state, None

        keys = jax.vmap(lambda k: jax.random.split(k, n_steps), out_axes=1)(key)
        return jax.lax.scan(body, state, keys)[0]

    return rollout


def port_rate(
    env: LunarLander,
    n_envs: int,
    n_steps: int,
    devices: list,
    burn_in: int,
    policy: str = "random",
    compiler_options: dict[str, str] | None = None,
) -> dict[str, float]:
    """Env-steps/s, compile seconds and program memory of `n_envs` envs split over `devices`, timed over
    `n_steps` steps after at least `burn_in` untimed ones."""
    params = env.default_params
    keys = jax.random.split(jax.random.key(0), n_envs)
    _, state = jax.jit(jax.vmap(env.reset, (0, None)))(keys, params)
    rollout = port_rollout(env, n_steps, policy)
    if len(devices) > 1 and n_envs % len(devices) == 0:
        mesh = Mesh(np.array(devices), ("envs",))
        spec = PartitionSpec("envs")
        rollout = jax.shard_map(rollout, mesh=mesh, in_specs=spec, out_specs=spec)
        used = len(devices)
    else:
        used = 1
    step_keys = jax.random.split(jax.random.key(1), n_envs)
    start = time.perf_counter()
    compiled = jax.jit(rollout, compiler_options=compiler_options).lower(state, step_keys).compile()
    compile_s = time.perf_counter() - start
    memory = compiled.memory_analysis()
    program_bytes = sum(
        getattr(memory, name, 0) or 0
        for name in ("temp_size_in_bytes", "argument_size_in_bytes", "output_size_in_bytes")
    )
    for i in range(max(1, -(-burn_in // n_steps))):  # warm-up and burn-in: episodes at every phase
        state = jax.block_until_ready(compiled(state, jax.random.split(jax.random.key(2 + i), n_envs)))
    start = time.perf_counter()
    jax.block_until_ready(compiled(state, step_keys))
    seconds = time.perf_counter() - start
    return {
        "envs": n_envs,
        "policy": policy,
        "options": bool(compiler_options),
        "devices": used,
        "rate": n_envs * n_steps / seconds,
        "compile_s": compile_s,
        "program_mib": program_bytes / 2**20,
        "rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }


def step_compile_seconds(env: LunarLander, n_envs: int) -> float:
    """Seconds from a fresh `jax.jit(jax.vmap(env.step))` to its compiled program (trace, lowering, XLA compile):
    the first call's cost."""
    params = env.default_params
    keys = jax.random.split(jax.random.key(0), n_envs)
    _, state = jax.jit(jax.vmap(env.reset, (0, None)))(keys, params)
    actions = np.zeros(n_envs, np.int32)
    start = time.perf_counter()
    jax.jit(jax.vmap(env.step, (0, 0, 0, None))).lower(keys, state, actions, params).compile()
    return time.perf_counter() - start


SINGLE_ENV_PATHS = {
    "jit": "`jax.jit`",
    "one_kernel": "compiled as one kernel (`jit_one_kernel`)",
    "packed": "one kernel, key and state carried packed (`TreeLayout`, as the Gymnasium bridge)",
    "bridge": "the Gymnasium bridge (`to_gymnasium`: checks, results copied to NumPy every step)",
}


def single_env_rate(env: LunarLander, n_steps: int, path: str) -> float:
    """Steps/s of one env stepped from Python, random actions, one call per step (see `SINGLE_ENV_PATHS`).

    "jit", "one_kernel" and "packed": a jitted step that splits the carried key and steps (auto-reset inside), the
    results left on the device; "bridge": `GymnasiumEnv.step`, reset after each episode."""
    params = env.default_params
    actions = np.random.default_rng(0).integers(0, 4, n_steps).astype(np.int32)
    if path == "bridge":
        gym_env = to_gymnasium(env, params, seed=0)
        gym_env.reset()

        def run(steps: int) -> float:
            start = time.perf_counter()
            for i in range(steps):
                _, _, terminated, truncated, _ = gym_env.step(int(actions[i]))
                if terminated or truncated:
                    gym_env.reset()
            return steps / (time.perf_counter() - start)

        run(min(n_steps, 100))  # compiles the step
        return run(n_steps)

    def raw_step(key, state, action):
        key, key_step = jax.random.split(key)
        obs, state, reward, terminated, truncated, _ = env.step(key_step, state, action, params)
        return key, state, obs, reward, terminated | truncated

    key = jax.random.key(0)
    _, state = jax.jit(env.reset)(key, params)
    if path == "packed":
        layout = TreeLayout.of((key, state))

        def packed_step(carry, action):
            key, state, obs, reward, done = raw_step(*layout.unpack(carry), action)
            return layout.pack((key, state)), obs, reward, done

        step, carry = jit_one_kernel(packed_step), jax.jit(layout.pack)((key, state))
    else:
        one_call = jit_one_kernel(raw_step) if path == "one_kernel" else jax.jit(raw_step)

        def step(carry, action):
            key, state, *out = one_call(*carry, action)
            return (key, state), *out

        carry = (key, state)
    jax.block_until_ready(step(carry, np.int32(0)))
    start = time.perf_counter()
    for i in range(n_steps):
        carry, *_ = step(carry, actions[i])
    jax.block_until_ready(carry)
    return n_steps / (time.perf_counter() - start)


SOLVERS = {"sweeps": "Box2D's sweeps", "jump_sweeps": "jump_sweeps", "exact_free_flight": "exact_free_flight"}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--envs", type=int, nargs="+", default=[1, 64, 1024, 4096, 16384])
    parser.add_argument("--steps-per-run", type=int, default=200_000, help="env-steps per timed port run")
    parser.add_argument("--gymnasium-steps", type=int, default=20_000)
    parser.add_argument("--single-env-steps", type=int, default=2_000)
    parser.add_argument("--burn-in", type=int, default=500, help="untimed steps before a timed port run")
    parser.add_argument(
        "--heuristic-envs",
        type=int,
        nargs="*",
        default=[1024],
        help="env counts also timed under Gymnasium's heuristic controller (long contact phases)",
    )
    parser.add_argument(
        "--step-compiles",
        type=int,
        default=3,
        help="fresh compiles of one vmapped step at 1,024 envs to time (the issue's compile figure)",
    )
    parser.add_argument(
        "--reductions-in-xla",
        action="store_true",
        help="also time every batch compiled with amjax.cores.REDUCTIONS_IN_XLA (opt-in option)",
    )
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument(
        "--solvers",
        nargs="+",
        choices=SOLVERS,
        default=list(SOLVERS),
        help="the port's settings to time: Box2D's sweeps everywhere (the default env), "
        "jump_sweeps=True and/or exact_free_flight=True",
    )
    args = parser.parse_args()

    devices = jax.devices()
    gym = gymnasium_rate(args.gymnasium_steps)
    singles, step_compiles, rows = {}, {}, []
    for solver in args.solvers:
        env = LunarLander(exact_free_flight=solver == "exact_free_flight", jump_sweeps=solver == "jump_sweeps")
        for path in SINGLE_ENV_PATHS:
            singles[solver, path] = single_env_rate(env, args.single_env_steps, path)
            print(f"{solver}: one env, {path}: {singles[solver, path]:,.0f} steps/s", flush=True)
        step_compiles[solver] = [step_compile_seconds(env, 1024) for _ in range(args.step_compiles)]
        print(
            f"{solver}: one vmapped step at 1,024 envs compiles in "
            f"{', '.join(f'{t:.1f}' for t in step_compiles[solver])} s",
            flush=True,
        )
        runs = [(n, "random") for n in args.envs] + [(n, "heuristic") for n in args.heuristic_envs]
        options = [None, REDUCTIONS_IN_XLA] if args.reductions_in_xla else [None]
        for (n, policy), compiler_options in itertools.product(runs, options):
            n_steps = int(np.clip(args.steps_per_run // n, 100, 2000))
            row = {**port_rate(env, n, n_steps, devices, args.burn_in, policy, compiler_options), "solver": solver}
            rows.append(row)
            print(
                f"{solver}, {policy}, {n} envs{', REDUCTIONS_IN_XLA' if compiler_options else ''}: "
                f"{row['rate']:,.0f} env-steps/s, compile {row['compile_s']:.1f} s",
                flush=True,
            )

    load = os.getloadavg()
    lines = [
        f"# LunarLander-v3 speed, {datetime.date.today()}",
        "",
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, {len(devices)} JAX CPU devices, "
        f"jax {jax.__version__}; load average at the end {load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f} "
        f"(other jobs on the machine slow both systems). The port's timed runs start after {args.burn_in} "
        "untimed steps (envs at every phase of their episodes). amjax's XLA CPU options (amjax.cores.xla_cpu_options): "
        f"{'on' if 'xla_cpu_small_while_loop' in os.environ.get('XLA_FLAGS', '') else 'off (XLA defaults)'}.",
        "",
        "| system | envs | devices | env-steps/s | vs Gymnasium | compile (s) | program memory (MiB) "
        "| peak RSS (MiB) |",
        "|---|---|---|---|---|---|---|---|",
        f"| Gymnasium LunarLander-v3 (C++ Box2D), Python loop | 1 | 1 core | {gym:,.0f} | 1.0x | - | - | - |",
    ]
    for (solver, path), single in singles.items():
        lines.append(
            f"| port ({SOLVERS[solver]}), one env's step called from Python, {SINGLE_ENV_PATHS[path]} "
            f"| 1 | 1 | {single:,.0f} | {single / gym:.2f}x | - | - | - |"
        )
    for r in rows:
        actions = "" if r["policy"] == "random" else ", Gymnasium's heuristic controller"
        actions += ", compiled with `amjax.cores.REDUCTIONS_IN_XLA`" if r["options"] else ""
        lines.append(
            f"| port ({SOLVERS[r['solver']]}), vmapped `env.step` in `lax.scan`{actions} | {r['envs']:,} "
            f"| {r['devices']} "
            f"| {r['rate']:,.0f} | "
            f"{r['rate'] / gym:.1f}x | {r['compile_s']:.1f} | {r['program_mib']:.1f} | {r['rss_mib']:,.0f} |"
        )
    lines += [
        "",
        "Compile of one vmapped `env.step` at 1,024 envs (`jax.jit(jax.vmap(env.step))` traced, lowered and "
        "compiled, fresh each time; the compile column above is the whole scanned rollout under `shard_map`):",
    ]
    for solver, times in step_compiles.items():
        if times:
            lines.append(f"- {SOLVERS[solver]}: {', '.join(f'{t:.1f}' for t in times)} s")
    table = "\n".join(lines) + "\n"
    save_table(table, args.out, "lunar_lander_speed")


if __name__ == "__main__":
    main()
