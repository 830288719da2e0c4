"""brax environments through amjax: env-steps/s and compile time at a batch of vmapped envs, per env and backend.

    python benchmarks/brax_speed.py                                   # 3 envs x 4 backends, 256 envs
    python benchmarks/brax_speed.py --envs reacher --backends spring --batch 1024
    python benchmarks/brax_speed.py --ppo 15 --backends generalized spring     # PPO training, 15 configurations

Each case is `amjax.make_env("brax:<env>:<backend>")` (the plain adapter: random actions in [-1, 1], gymnax's
auto-reset, which computes a fresh reset every step and keeps it where an episode ended) stepped in a jitted
`lax.scan` of `env.step` vmapped over `--batch` envs on one JAX device, beside brax's own `env.step` (no reset, no
time limit) in the same kind of program: the gap is what the adapter's auto-reset costs. The timed run is the
fastest of `--repeats` after one untimed run. Compile: seconds to lower and compile that program. Prints a markdown
table with the machine and writes it to benchmarks/results/brax_speed_<date>.md.

With `--ppo N` it times PPO training instead: N configurations (costs 0.1 / 0.2 / 0.3 in turn, PPO's defaults:
8 envs each) of `--ppo-steps` env steps on the active-measure env, as the sweep runner compiles and runs them (the
programs of `benchmarks/throughput`, one greedy test episode at the end), per env and backend.
"""

from __future__ import annotations

import argparse
import datetime
import os
import sys
import time
from importlib.metadata import version
from pathlib import Path

import jax

import amjax

if "--ppo" in sys.argv:  # PPO as the sweep runner trains it: one CPU device per core, set before JAX starts
    amjax.use_all_cores()

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the benchmarks are not installed

from amjax.envs.brax_env import BACKENDS, make_brax  # noqa: E402
from benchmarks.throughput.report import machine_info, save_table  # noqa: E402
from benchmarks.throughput.runners import build_amjax  # noqa: E402
from benchmarks.throughput.timing import timed  # noqa: E402

ENVS = ("inverted_pendulum", "inverted_double_pendulum", "reacher")


def adapter_rollout(env, n_steps: int):
    """(states, key) -> states: `n_steps` random-action steps of amjax's adapter, vmapped over the batch."""
    params = env.default_params
    step = jax.vmap(env.step, (0, 0, 0, None))

    def rollout(states, key):
        def body(states, key):
            key_step, key_action = jax.random.split(key)
            batch = jax.tree.leaves(states)[0].shape[0]
            actions = jax.random.uniform(key_action, (batch, env.action_size), minval=-1.0, maxval=1.0)
            states = step(jax.random.split(key_step, batch), states, actions, params)[1]
            return states, None

        return jax.lax.scan(body, states, jax.random.split(key, n_steps))[0]

    return rollout


def brax_rollout(env, n_steps: int):
    """The same with brax's own step (no auto-reset, no time limit) on the brax states."""
    step = jax.vmap(env.brax_env.step)

    def rollout(states, key):
        def body(states, key):
            batch = states.obs.shape[0]
            actions = jax.random.uniform(key, (batch, env.action_size), minval=-1.0, maxval=1.0)
            return step(states, actions), None

        return jax.lax.scan(body, states, jax.random.split(key, n_steps))[0]

    return rollout


def time_rollout(rollout, states, n_steps: int, batch: int, repeats: int) -> tuple[float, float]:
    """(env-steps/s of the fastest timed run, compile seconds)."""
    key = jax.random.key(1)
    start = time.perf_counter()
    compiled = jax.jit(rollout).lower(states, key).compile()
    compile_s = time.perf_counter() - start
    states = jax.block_until_ready(compiled(states, key))  # untimed
    best = float("inf")
    for i in range(repeats):
        start = time.perf_counter()
        states = jax.block_until_ready(compiled(states, jax.random.key(2 + i)))
        best = min(best, time.perf_counter() - start)
    return batch * n_steps / best, compile_s


def measure(env_name: str, backend: str, batch: int, n_steps: int, repeats: int) -> dict[str, float]:
    env, params = make_brax(f"brax:{env_name}:{backend}")
    keys = jax.random.split(jax.random.key(0), batch)
    _, states = jax.jit(jax.vmap(env.reset, (0, None)))(keys, params)
    adapter, adapter_compile = time_rollout(adapter_rollout(env, n_steps), states, n_steps, batch, repeats)
    brax, brax_compile = time_rollout(brax_rollout(env, n_steps), states.brax_state, n_steps, batch, repeats)
    return {"adapter": adapter, "adapter_compile": adapter_compile, "brax": brax, "brax_compile": brax_compile}


def measure_ppo(env_name: str, backend: str, configs: int, steps: int, repeats: int) -> dict[str, float]:
    """PPO training env-steps/s (all configurations together, the fastest of `repeats` runs) and compile seconds."""
    case = {
        "agent": "ppo",
        "env_id": f"brax:{env_name}:{backend}",
        "configs": configs,
        "steps": steps,
        "evals": 1,
        "eval_episodes": 1,
        "vanilla": False,
        "target_chunks": 1,
    }
    built = build_amjax(case)
    run_s = timed(built["run"], repeats)["run_s"]
    return {"ppo": configs * steps / run_s, "ppo_compile": built["compile_s"]}


def ppo_table(args: argparse.Namespace, info: dict[str, str], load_start: float) -> str:
    rows = []
    for env_name in args.envs:
        for backend in args.backends:
            row = measure_ppo(env_name, backend, args.ppo, args.ppo_steps, args.repeats)
            rows.append((env_name, backend, row))
            print(
                f"{env_name} / {backend}: PPO {row['ppo']:,.0f} env-steps/s, compile {row['ppo_compile']:.1f} s",
                flush=True,
            )
    lines = [
        f"# brax through amjax: PPO training speed, {args.ppo} configurations x {args.ppo_steps:,} env steps, "
        f"{datetime.date.today()}",
        "",
        f"Machine: {info['cpu']}. {info['software']}, brax {version('brax')}. {len(jax.devices())} CPU devices "
        f"(one per core, `amjax.use_all_cores`, as in a sweep). Load average (1 min) at the start {load_start:.2f}, "
        f"at the end {os.getloadavg()[0]:.2f}.",
        "",
        "| env | backend | PPO training env-steps/s (all configurations) | compile (s) |",
        "|---|---|---|---|",
    ]
    lines += [f"| {e} | {b} | {r['ppo']:,.0f} | {r['ppo_compile']:.1f} |" for e, b, r in rows]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--envs", nargs="+", default=list(ENVS))
    parser.add_argument("--backends", nargs="+", choices=BACKENDS, default=list(BACKENDS))
    parser.add_argument("--batch", type=int, default=256, help="vmapped envs")
    parser.add_argument("--steps", type=int, default=200, help="steps of every env per timed run")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--ppo", type=int, default=0, metavar="N", help="time PPO training of N configurations")
    parser.add_argument("--ppo-steps", type=int, default=102_400, help="env steps per PPO configuration")
    args = parser.parse_args()

    info, load_start = machine_info(), os.getloadavg()[0]
    if args.ppo:
        save_table(ppo_table(args, info, load_start), args.out, "brax_ppo_speed")
        return
    rows = []
    for env_name in args.envs:
        for backend in args.backends:
            try:
                row = measure(env_name, backend, args.batch, args.steps, args.repeats)
            except Exception as error:  # a backend an env does not support: reported, not fatal
                print(f"{env_name} / {backend}: failed: {type(error).__name__}: {error}", flush=True)
                row = None
            rows.append((env_name, backend, row))
            if row:
                print(
                    f"{env_name} / {backend}: {row['adapter']:,.0f} env-steps/s (brax's step alone "
                    f"{row['brax']:,.0f}), compile {row['adapter_compile']:.1f} s",
                    flush=True,
                )

    lines = [
        f"# brax through amjax: speed at {args.batch} vmapped envs, {datetime.date.today()}",
        "",
        f"Machine: {info['cpu']}. {info['software']}, brax {version('brax')}, mujoco {version('mujoco')}, "
        f"mujoco-mjx {version('mujoco-mjx')}. One JAX device. Load average (1 min) at the start "
        f"{load_start:.2f}, at the end {os.getloadavg()[0]:.2f}.",
        "",
        "| env | backend | amjax adapter env-steps/s | compile (s) | brax's step alone env-steps/s | compile (s) "
        "| adapter / brax |",
        "|---|---|---|---|---|---|---|",
    ]
    for env_name, backend, row in rows:
        if row is None:
            lines.append(f"| {env_name} | {backend} | failed | - | - | - | - |")
            continue
        lines.append(
            f"| {env_name} | {backend} | {row['adapter']:,.0f} | {row['adapter_compile']:.1f} "
            f"| {row['brax']:,.0f} | {row['brax_compile']:.1f} | {row['adapter'] / row['brax']:.2f} |"
        )
    table = "\n".join(lines) + "\n"
    save_table(table, args.out, "brax_speed")


if __name__ == "__main__":
    main()
