"""brax environments through amjax: env-steps/s and compile time at a batch of vmapped envs, per env and backend.

    python benchmarks/brax_speed.py                                   # 3 envs x 4 backends, 256 envs
    python benchmarks/brax_speed.py --envs reacher --backends spring --batch 1024
    python benchmarks/brax_speed.py --ppo 15 --backends generalized spring     # PPO training, 15 configurations

Each case is `amjax.make_env("brax:<env>:<backend>")` (the plain adapter: random actions in [-1, 1], gymnax's
auto-reset, which computes a fresh reset every step and keeps it where an episode ended) stepped in a jitted
`lax.scan` of `env.step` vmapped over `--batch` envs on one JAX device, beside brax's own `env.step` (no reset, no
time limit) in the same kind of program: the gap is what the adapter's auto-reset costs. The timed run is the
fastest of `--repeats` after one untimed run. Compile: seconds to lower and compile that program.

With `--ppo N` it times PPO training instead: N configurations (costs 0.1 / 0.2 / 0.3 in turn, PPO's defaults:
8 envs each) of `--ppo-steps` env steps on the active-measure env, as the sweep runner compiles and runs them (the
programs of `benchmarks/throughput`, one greedy test episode at the end), per env and backend.

Each (env, backend) case runs in a child process of its own, one after the other (`benchmarks.harness`: its peak
resident memory is its own, and a backend an env does not support fails only its case); the records go to
benchmarks/results/brax_speed_<date>_<machine>.jsonl (or `--out`; PPO runs too, each run its own table) and the
markdown table is rendered beside it.

    python benchmarks/brax_speed.py --envs inverted_pendulum --backends spring --batch 1 --steps 1 --repeats 1 \
        --out /tmp/brax.jsonl  # a smoke run
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import time
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

if not __package__:  # run as a file: the repository importable, for `benchmarks.harness`
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks import harness  # noqa: E402

ENVS = ("inverted_pendulum", "inverted_double_pendulum", "reacher")
# amjax.envs.brax_env.BACKENDS, spelled out: importing that module starts JAX, which the parent must not do (the
# children check that the two agree).
BACKENDS = ("generalized", "positional", "spring", "mjx")
SOFTWARE = ("jaxlib", "flax", "optax", "gymnax", "brax", "mujoco", "mujoco-mjx")  # besides Python and jax


def software() -> dict[str, str]:
    """The installed versions of the libraries the cases run on, from the package metadata (no jax import)."""
    versions = {}
    for name in SOFTWARE:
        with contextlib.suppress(PackageNotFoundError):
            versions[name] = version(name)
    return versions


def adapter_rollout(env, n_steps: int):
    """(states, key) -> states: `n_steps` random-action steps of amjax's adapter, vmapped over the batch."""
    import jax

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
    import jax

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
    import jax

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
    """The adapter's and brax's own env-steps/s and compile seconds, on one JAX device."""
    import jax

    from amjax.envs.brax_env import make_brax

    env, params = make_brax(f"brax:{env_name}:{backend}")
    keys = jax.random.split(jax.random.key(0), batch)
    _, states = jax.jit(jax.vmap(env.reset, (0, None)))(keys, params)
    adapter, adapter_compile = time_rollout(adapter_rollout(env, n_steps), states, n_steps, batch, repeats)
    brax, brax_compile = time_rollout(brax_rollout(env, n_steps), states.brax_state, n_steps, batch, repeats)
    return {
        "adapter": round(adapter),
        "adapter_compile": round(adapter_compile, 2),
        "brax": round(brax),
        "brax_compile": round(brax_compile, 2),
    }


def measure_ppo(env_name: str, backend: str, configs: int, steps: int, repeats: int) -> dict[str, float]:
    """PPO training env-steps/s (all configurations together, the fastest of `repeats` runs) and compile seconds."""
    from benchmarks.throughput.runners import build_amjax
    from benchmarks.throughput.timing import timed

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
    return {"ppo": round(configs * steps / run_s), "ppo_compile": round(built["compile_s"], 2)}


def run_case(case: dict[str, Any]) -> dict[str, Any]:
    """One (env, backend) case in this (child) process."""
    import amjax

    if "configs" in case:  # PPO as the sweep runner trains it: one CPU device per core, set before JAX starts
        amjax.use_all_cores()
    import jax

    from amjax.envs import brax_env

    assert brax_env.BACKENDS == BACKENDS, f"update BACKENDS to {brax_env.BACKENDS}"
    if "configs" in case:
        row = measure_ppo(case["env"], case["backend"], case["configs"], case["ppo_steps"], case["repeats"])
    else:
        row = measure(case["env"], case["backend"], case["batch"], case["steps"], case["repeats"])
    return {**row, "cpu_devices": len(jax.devices())}


def render(runs: list[dict[str, Any]]) -> str:
    """The markdown of a results file: one table per run (the env-step runs and the PPO runs (`--ppo N`) each
    their own kind of table)."""
    parts = []
    for run in runs:
        settings, cases = run["settings"], run["cases"]
        versions = ", ".join(f"{name} {v}" for name, v in settings["software"].items())
        ok = [r for r in cases if r["status"] == "ok"]
        devices = ok[0]["cpu_devices"] if ok else "?"
        if settings["ppo"]:
            parts.append(
                f"# brax through amjax: PPO training speed, {settings['ppo']} configurations x "
                f"{settings['ppo_steps']:,} env steps, {run['date'][:10]}\n\n"
                f"{versions}. {devices} CPU devices (one per core, `amjax.use_all_cores`, as in a sweep). Each case "
                f"in its own process, one after the other. {harness.describe(run)}\n\n"
                + harness.markdown_table(
                    cases,
                    [
                        ("env", lambda r: r["env"]),
                        ("backend", lambda r: r["backend"]),
                        (
                            "PPO training env-steps/s (all configurations)",
                            lambda r: r["ppo"] if r["status"] == "ok" else "failed",
                        ),
                        ("compile (s)", lambda r: f"{r['ppo_compile']:.1f}" if r["status"] == "ok" else "-"),
                        ("peak RSS (MiB)", lambda r: r["peak_rss_mib"] if r["status"] == "ok" else "-"),
                    ],
                )
            )
        else:
            parts.append(
                f"# brax through amjax: speed at {settings['batch']} vmapped envs, {run['date'][:10]}\n\n"
                f"{versions}. One JAX device. Each case in its own process, one after the other. "
                f"{harness.describe(run)}\n\n"
                + harness.markdown_table(
                    cases,
                    [
                        ("env", lambda r: r["env"]),
                        ("backend", lambda r: r["backend"]),
                        ("amjax adapter env-steps/s", lambda r: r["adapter"] if r["status"] == "ok" else "failed"),
                        ("compile (s)", lambda r: f"{r['adapter_compile']:.1f}" if r["status"] == "ok" else "-"),
                        ("brax's step alone env-steps/s", lambda r: r["brax"] if r["status"] == "ok" else "-"),
                        ("compile (s)", lambda r: f"{r['brax_compile']:.1f}" if r["status"] == "ok" else "-"),
                        (
                            "adapter / brax",
                            lambda r: f"{r['adapter'] / r['brax']:.2f}" if r["status"] == "ok" else "-",
                        ),
                        ("peak RSS (MiB)", lambda r: r["peak_rss_mib"] if r["status"] == "ok" else "-"),
                    ],
                )
            )
        parts[-1] += "".join(f"\n{r['env']} / {r['backend']}: {r['status']}\n" for r in cases if r["status"] != "ok")
    return "\n".join(parts)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--envs", nargs="+", default=list(ENVS))
    parser.add_argument("--backends", nargs="+", choices=BACKENDS, default=list(BACKENDS))
    parser.add_argument("--batch", type=int, default=256, help="vmapped envs")
    parser.add_argument("--steps", type=int, default=200, help="steps of every env per timed run")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument(
        "--out",
        help="results file to append to (default: benchmarks/results/brax_speed_<date>_<machine>.jsonl, PPO runs "
        "included; the markdown table is written beside it)",
    )
    parser.add_argument("--ppo", type=int, default=0, metavar="N", help="time PPO training of N configurations")
    parser.add_argument("--ppo-steps", type=int, default=102_400, help="env steps per PPO configuration")
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        harness.child_result(run_case(json.loads(args.child)))
        return 0

    cases = []
    for env_name in args.envs:
        for backend in args.backends:
            case = {"env": env_name, "backend": backend, "repeats": args.repeats}
            if args.ppo:
                case.update(configs=args.ppo, ppo_steps=args.ppo_steps)
            else:
                case.update(batch=args.batch, steps=args.steps)
            cases.append(case)  # a backend an env does not support fails its child: recorded and shown, not fatal
    settings = {**harness.settings_of(args), "software": software()}
    harness.run_cases("brax_speed", settings, args.out, __file__, cases, render)
    return 0


if __name__ == "__main__":
    sys.exit(main())
