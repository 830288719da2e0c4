"""LunarLander-v3 speed: the pure-JAX port against Gymnasium's Box2D original, timed in one invocation.

    python benchmarks/lunar_lander_speed.py                       # 1, 64, 1,024, 4,096, 16,384 envs
    python benchmarks/lunar_lander_speed.py --envs 1 1024 --steps-per-run 50000
    python benchmarks/lunar_lander_speed.py --solvers sweeps --envs 64 --heuristic-envs --steps-per-run 6400 \
        --burn-in 100 --gymnasium-steps 1000 --single-env-steps 100 --step-compiles 1 --out /tmp/ll.jsonl  # a smoke run

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
`env.step` at 1,024 envs (`--step-compiles` fresh compiles, one after the other in one process).

Each case (Gymnasium's loop; per solver, each single-env path, the step compiles, each batch) runs in a child process
of its own, one after the other (`benchmarks.harness`: the child's peak resident memory is the case's own, and one
case's compiled programs cannot slow the next); the records go to
benchmarks/results/lunar_lander_speed_<date>_<machine>.jsonl (or `--out`) and the markdown table (env-steps/s,
compile time, memory) is rendered beside it.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if not __package__:  # run as a file: the repository importable, for `benchmarks.harness`
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks import harness  # noqa: E402

if TYPE_CHECKING:
    from amjax.envs.lunar_lander import LunarLander

# JAX and the port are imported in the children only (`run_case` calls `amjax.use_all_cores()` first): the parent
# must not start JAX (nor hold an accelerator) while its children run.


def gymnasium_rate(n_steps: int, seed: int = 0) -> float:
    """Env-steps/s of Gymnasium's LunarLander-v3, random actions, reset on termination or 1000 steps."""
    from amjax.envs.lunar_lander.reference import load_gymnasium_lunar_lander

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
    import jax

    from amjax.envs.lunar_lander.env import heuristic_action

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
) -> dict[str, Any]:
    """Env-steps/s, compile seconds and program memory of `n_envs` envs split over `devices`, timed over
    `n_steps` steps after at least `burn_in` untimed ones."""
    import jax
    from jax.sharding import Mesh, PartitionSpec

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
        "devices": used,
        "rate": round(n_envs * n_steps / seconds),
        "compile_s": round(compile_s, 2),
        "program_mib": round(program_bytes / 2**20, 2),
    }


def step_compile_seconds(env: LunarLander, n_envs: int) -> float:
    """Seconds from a fresh `jax.jit(jax.vmap(env.step))` to its compiled program (trace, lowering, XLA compile):
    the first call's cost."""
    import jax

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
    import jax

    from amjax.cores import TreeLayout, jit_one_kernel
    from amjax.wrappers.gymnasium import to_gymnasium

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


def run_case(case: dict[str, Any]) -> dict[str, Any]:
    """One case in this (child) process: the measurements `render` shows."""
    import amjax

    amjax.use_all_cores()  # one CPU device per core, before JAX starts
    import jax

    from amjax.cores import REDUCTIONS_IN_XLA
    from amjax.envs.lunar_lander import LunarLander

    result = {
        "cpu_devices": len(jax.devices()),
        "xla_options": "xla_cpu_small_while_loop" in os.environ.get("XLA_FLAGS", ""),
    }
    if case["case"] == "gymnasium":
        return {**result, "rate": round(gymnasium_rate(case["steps"]))}
    solver = case["solver"]
    env = LunarLander(exact_free_flight=solver == "exact_free_flight", jump_sweeps=solver == "jump_sweeps")
    if case["case"] == "single":
        return {**result, "rate": round(single_env_rate(env, case["steps"], case["path"]))}
    if case["case"] == "step_compile":  # fresh compiles one after the other in one process, on purpose
        return {
            **result,
            "seconds": [round(step_compile_seconds(env, case["envs"]), 2) for _ in range(case["repeats"])],
        }
    options = REDUCTIONS_IN_XLA if case["reductions_in_xla"] else None
    return {
        **result,
        **port_rate(env, case["envs"], case["steps"], jax.devices(), case["burn_in"], case["policy"], options),
    }


def render(runs: list[dict[str, Any]]) -> str:
    """The markdown of a results file: one table per run, env-steps/s against Gymnasium's loop of the same run."""
    parts = []
    for run in runs:
        settings, results = run["settings"], [r for r in run["cases"] if r["status"] == "ok"]
        gym = next((r["rate"] for r in results if r["case"] == "gymnasium"), None)
        jaxed = next((r for r in results if r["case"] != "gymnasium"), results[0] if results else {})

        def ratio(rate: float, digits: int, gym: float | None = gym) -> str:
            return f"{rate / gym:.{digits}f}x" if gym else ""

        rows = []
        for r in results:
            row = {"envs": 1, "devices": 1, "rate": r.get("rate"), "compile": "-", "program": "-"}
            if r["case"] == "gymnasium":
                row.update(system="Gymnasium LunarLander-v3 (C++ Box2D), Python loop", devices="1 core", vs="1.0x")
            elif r["case"] == "single":
                row.update(
                    system=f"port ({SOLVERS[r['solver']]}), one env's step called from Python, "
                    f"{SINGLE_ENV_PATHS[r['path']]}",
                    vs=ratio(r["rate"], 2),
                )
            elif r["case"] == "port":
                actions = "" if r["policy"] == "random" else ", Gymnasium's heuristic controller"
                actions += ", compiled with `amjax.cores.REDUCTIONS_IN_XLA`" if r["reductions_in_xla"] else ""
                row.update(
                    system=f"port ({SOLVERS[r['solver']]}), vmapped `env.step` in `lax.scan`{actions}",
                    envs=r["envs"],
                    devices=r["devices"],
                    vs=ratio(r["rate"], 1),
                    compile=f"{r['compile_s']:.1f}",
                    program=f"{r['program_mib']:.1f}",
                )
            else:
                continue
            rows.append({**row, "rss": r["peak_rss_mib"]})
        options = jaxed.get("xla_options")
        compiles = [r for r in results if r["case"] == "step_compile" and r["seconds"]]
        parts.append(
            f"# LunarLander-v3 speed, {run['date'][:10]}\n\n"
            f"{jaxed.get('cpu_devices', '?')} JAX CPU devices (other jobs on the machine slow both systems). The "
            f"port's timed runs start after {settings['burn_in']} untimed steps (envs at every phase of their "
            "episodes). amjax's XLA CPU options (amjax.cores.xla_cpu_options): "
            f"{'?' if options is None else 'on' if options else 'off (XLA defaults)'}. Each case in its own process, "
            f"one after the other (peak RSS: that process's). {harness.describe(run)}\n\n"
            + harness.markdown_table(
                rows,
                [
                    ("system", lambda r: r["system"]),
                    ("envs", lambda r: r["envs"]),
                    ("devices", lambda r: r["devices"]),
                    ("env-steps/s", lambda r: r["rate"]),
                    ("vs Gymnasium", lambda r: r["vs"]),
                    ("compile (s)", lambda r: r["compile"]),
                    ("program memory (MiB)", lambda r: r["program"]),
                    ("peak RSS (MiB)", lambda r: r["rss"]),
                ],
            )
            + (
                "\nCompile of one vmapped `env.step` at 1,024 envs (`jax.jit(jax.vmap(env.step))` traced, lowered "
                "and compiled, fresh each time, one after the other in one process; the compile column above is the "
                "whole scanned rollout under `shard_map`):\n"
                + "".join(
                    f"- {SOLVERS[r['solver']]}: {', '.join(f'{t:.1f}' for t in r['seconds'])} s\n" for r in compiles
                )
                if compiles
                else ""
            )
            + "".join(
                f"\n{json.dumps({k: v for k, v in r.items() if k != 'status'})}: {r['status']}\n"
                for r in run["cases"]
                if r["status"] != "ok"
            )
        )
    return "\n".join(parts)


def main(argv: list[str] | None = None) -> int:
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
    parser.add_argument(
        "--out",
        help="results file to append to (default: benchmarks/results/lunar_lander_speed_<date>_<machine>.jsonl; "
        "the markdown table is written beside it)",
    )
    parser.add_argument(
        "--solvers",
        nargs="+",
        choices=SOLVERS,
        default=list(SOLVERS),
        help="the port's settings to time: Box2D's sweeps everywhere (the default env), "
        "jump_sweeps=True and/or exact_free_flight=True",
    )
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        harness.child_result(run_case(json.loads(args.child)))
        return 0

    cases: list[dict[str, Any]] = [{"case": "gymnasium", "steps": args.gymnasium_steps}]
    for solver in args.solvers:
        cases += [
            {"case": "single", "solver": solver, "path": p, "steps": args.single_env_steps} for p in SINGLE_ENV_PATHS
        ]
        if args.step_compiles > 0:
            cases.append({"case": "step_compile", "solver": solver, "envs": 1024, "repeats": args.step_compiles})
        runs = [(n, "random") for n in args.envs] + [(n, "heuristic") for n in args.heuristic_envs]
        for (n, policy), in_xla in itertools.product(runs, [False, True] if args.reductions_in_xla else [False]):
            cases.append(
                {
                    "case": "port",
                    "solver": solver,
                    "envs": n,
                    "policy": policy,
                    "reductions_in_xla": in_xla,
                    "steps": int(np.clip(args.steps_per_run // n, 100, 2000)),
                    "burn_in": args.burn_in,
                }
            )
    harness.run_cases("lunar_lander_speed", harness.settings_of(args), args.out, __file__, cases, render)
    return 0


if __name__ == "__main__":
    sys.exit(main())
