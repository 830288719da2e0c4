"""Throughput of amjax's compiled sweep trainers against plain single-file references and Stable-Baselines3.

For PPO and DQN on CartPole-v0 (the 200-step CartPole) and 1 / 16 / 256 / 1024 configurations it times:
- `amjax`: exactly what `amjax.sweep.run_sweep` compiles for one batch: the configs stacked with
  `amjax.agents.stack_configs` (costs 0.1 / 0.2 / 0.3 cycling, seeds 0..n-1) and the runner's own two programs
  (`init_run` under `lax.map`, then `jax.jit(jax.vmap(run_evals ...))` chunks, from
  `amjax.sweep.batches.compiled_programs`), with periodic greedy evaluation as in a real sweep (every
  steps / --evals env steps);
- `amjax-vanilla-env`: the same on the plain environment (`vanilla=True`: no measure action, no cost), so the
  difference is the active-measure wrapper's cost;
- `plain reference`: benchmarks/reference_{ppo,dqn}.py, PureJaxRL-style single-file trainers with the same
  hyperparameters, env and (by default) the same evaluation, as `jax.jit(jax.vmap(train))(keys, costs)`;
- `SB3` (if stable_baselines3 is importable): DQN and PPO with their default hyperparameters on Gymnasium
  CartPole-v1, 1 env, and amjax DQN with SB3's DQN hyperparameters at --sb3-configs configurations, for a speed-up.

Every case runs in a fresh subprocess, so its peak RSS (getrusage in the child) is its own. Compile time is
`.lower(...).compile()` of every program the case runs; run time is everything after (initialisation included);
env-steps/s = configs x steps per config / run time (training steps only; evaluation episodes are extra work).

    python benchmarks/throughput.py --markdown throughput.md   # the full table: ~15-20 min on 2 quiet cores
    python benchmarks/throughput.py --quick                    # smoke run, tiny sizes (~5 min)
    python benchmarks/throughput.py --agents ppo --sizes 1,16 --steps 1:102400,16:20480 --repeats 3
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import platform
import resource
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
COSTS = (0.1, 0.2, 0.3)  # cycled over the configurations of an active-measure case
ENV_ID = "CartPole-v0"
MAX_EPISODE_STEPS = 200  # CartPole-v0; an evaluation scans this many steps whatever the episodes do
TRANSITION_BYTES = 52  # obs + next_obs (5 float32 each with the flag) + action + reward + discount
IMPLS = ("amjax", "amjax-vanilla", "reference", "reference-vanilla")
IMPL_LABELS = {
    "amjax": "amjax",
    "amjax-vanilla": "amjax-vanilla-env",
    "reference": "plain reference",
    "reference-vanilla": "plain reference, vanilla env",
    "amjax-sb3": "amjax, SB3 DQN hyperparameters",
    "amjax-buffer": "amjax (buffer scan)",
    "overhead": "amjax, active vs vanilla env interleaved",
    "sb3": "SB3",
}
# Steps per configuration: min(max, max(min, budget // configs)), rounded to a multiple of evals x steps per
# update. On 2 quiet cores that is about 1-30 s (PPO) and 3-50 s (DQN) of run time per case.
STEP_RULES = {
    "ppo": {"max": 102_400, "min": 5_120, "budget": 2_621_440},
    "dqn": {"max": 50_000, "min": 2_500, "budget": 1_280_000},
}
QUICK_STEP_RULES = {
    "ppo": {"max": 10_240, "min": 5_120, "budget": 20_480},
    "dqn": {"max": 2_000, "min": 1_000, "budget": 4_000},
}
# Stable-Baselines3 2.x DQN defaults, as amjax DQNConfig fields (plain DQN: no dueling, no double-Q).
SB3_DQN = {
    "learning_rate": 1e-4,
    "buffer_size": 1_000_000,
    "learning_starts": 100,
    "batch_size": 32,
    "tau": 1.0,
    "gamma": 0.99,
    "train_freq": 4,
    "gradient_steps": 1,
    "target_update_interval": 10_000,
    "exploration_fraction": 0.1,
    "epsilon_start": 1.0,
    "epsilon_end": 0.05,
    "max_grad_norm": 10.0,
    "hidden": (64, 64),
    "activation": "relu",
    "dueling": False,
    "double_q": False,
    "n_step": 1,  # one-step targets
    "anneal_lr": False,  # constant learning rate
    "num_envs": 1,
}


# ---------------------------------------------------------------------------------------------------------------
# The child: one case, one process.
# ---------------------------------------------------------------------------------------------------------------


def _peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def _current_rss_mib() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def _timed(run: Callable[..., Any], repeats: int, prepare: Callable[[], Any] | None = None) -> dict[str, Any]:
    """Run `run` `repeats` times (on `prepare()`'s result, made before the clock starts, if given); the fastest
    run's wall and CPU seconds, every run's wall time, and the fastest run's output."""
    times = []
    for _ in range(repeats):
        args = () if prepare is None else (prepare(),)
        start, cpu = time.perf_counter(), time.process_time()
        out = run(*args)
        times.append((time.perf_counter() - start, time.process_time() - cpu, out))
    best = min(times, key=lambda t: t[0])
    return {"run_s": best[0], "run_cpu_s": best[1], "run_all_s": [t[0] for t in times], "out": best[2]}


def _agent_config(case: dict[str, Any], cost: float):
    from amjax.agents import DQNConfig, PPOConfig

    steps = case["steps"]
    kwargs: dict[str, Any] = {
        "env_id": ENV_ID,
        "total_timesteps": steps,
        "eval_every": steps // case["evals"],
        "eval_episodes": case["eval_episodes"],
        "vanilla": case["vanilla"],
        "cost": cost,
    }
    if case["agent"] == "ppo":
        return PPOConfig(**kwargs)
    if case.get("hparams") == "sb3":
        kwargs.update(SB3_DQN)
    kwargs["buffer_size"] = case["buffer"]
    return DQNConfig(**kwargs)


def _costs(case: dict[str, Any]) -> list[float]:
    return [0.0 if case["vanilla"] else COSTS[i % len(COSTS)] for i in range(case["configs"])]


def _build_amjax(case: dict[str, Any]) -> dict[str, Any]:
    """Compile what the sweep runner compiles for the case; returns the compile time and a `run` that trains."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from amjax.agents import ALGORITHMS, stack_configs
    from amjax.sweep.batches import chunk_evals, compiled_programs
    from amjax.sweep.devices import config_sharding, sweep_devices

    algo = ALGORITHMS[case["agent"]]
    configs = [_agent_config(case, cost).validate() for cost in _costs(case)]
    stacked = stack_configs(configs)
    keys = jnp.stack([jax.random.PRNGKey(seed) for seed in range(case["configs"])])
    num_evals = configs[0].num_evals
    evals_per_chunk = chunk_evals(num_evals, case["target_chunks"])
    devices = sweep_devices()
    if case["configs"] % len(devices):
        devices = devices[:1]  # the runner would pad the batch; the benchmark keeps the sizes it names
    init, chunk = compiled_programs(algo, evals_per_chunk, tuple(devices))
    sharding = config_sharding(devices)

    start = time.perf_counter()
    init_compiled = init.lower(stacked, keys).compile()
    compile_s = time.perf_counter() - start
    # The chunk is lowered with arrays placed as the runner places them (a first init run, not timed).
    first_states = jax.device_put(jax.device_get(init_compiled(stacked, keys)), sharding)
    sharded_configs = jax.device_put(stacked, sharding)
    start = time.perf_counter()
    chunk_compiled = chunk.lower(sharded_configs, first_states).compile()
    compile_s += time.perf_counter() - start
    del first_states

    def run():
        states = init_compiled(stacked, keys)
        # As the runner does (fresh or restored states alike): a host round trip, then split over the devices.
        states = jax.device_put(jax.device_get(states), sharding)
        last = None
        for _ in range(num_evals // evals_per_chunk):
            states, rows = chunk_compiled(sharded_configs, states)  # states are donated, as in the runner
            last = jax.device_get(rows.eval_return)[:, -1]  # as the runner does: rows come back after each chunk
        jax.block_until_ready(states)
        return float(np.median(last))

    return {"devices": len(devices), "compile_s": compile_s, "run": run, "chunks": num_evals // evals_per_chunk}


def _run_amjax(case: dict[str, Any]) -> dict[str, Any]:
    baseline = _current_rss_mib()
    built = _build_amjax(case)
    timed = _timed(built.pop("run"), case["repeats"])
    eval_return = timed.pop("out")
    return {**built, **timed, "eval_return": eval_return, "baseline_rss_mib": baseline}


ENV_ONLY_ENVS, ENV_ONLY_STEPS = 2048, 256  # the env-only overhead rollout: envs x steps, random actions


def _build_env_only(case: dict[str, Any]) -> Callable[[], Any]:
    """A compiled rollout of ENV_ONLY_ENVS training envs (the agent config's own env stack, episode statistics
    included) under uniformly random actions, through the trainers' own `rollout`, its transitions reduced into a
    checksum: the env alone."""
    import jax

    from amjax.agents.rollout import PRNG_IMPL, reset_envs, rollout

    env, params, _ = _agent_config(case, _costs(case)[0]).validate().make_env()
    num_actions = env.action_space(params).n

    def random_action(batch, carry, key):
        return jax.random.randint(key, batch.first.shape, 0, num_actions), carry, None

    @jax.jit
    def random_rollout(key):
        batch = reset_envs(env, params, key, ENV_ONLY_ENVS)
        _, _, t, _ = rollout(env, params, batch, None, random_action, key, ENV_ONLY_STEPS)
        return t.reward.sum() + t.next_obs.sum() + t.obs.sum() + t.episode.length.sum()

    key = jax.random.key(0, impl=PRNG_IMPL)
    compiled = random_rollout.lower(key).compile()
    return lambda: compiled(key).block_until_ready()


def _interleaved(runs: dict[bool, Callable[[], Any]], rounds: int) -> dict[bool, list[float]]:
    """Wall times of each run, in alternation (a, b, b, a, ...), after one untimed run of each."""
    times: dict[bool, list[float]] = {key: [] for key in runs}
    for run in runs.values():
        run()  # warm-up: first-run allocations stay out of the timings
    for round_ in range(rounds):
        for key in list(runs) if round_ % 2 == 0 else list(runs)[::-1]:
            start = time.perf_counter()
            runs[key]()
            times[key].append(time.perf_counter() - start)
    return times


def _overhead_figures(active: list[float], vanilla: list[float]) -> dict[str, Any]:
    import numpy as np

    active_s, vanilla_s = np.asarray(active), np.asarray(vanilla)
    return {
        "min": float(active_s.min() / vanilla_s.min() - 1),
        "median": float(np.median(active_s) / np.median(vanilla_s) - 1),
        # Paired by round: the spread of the per-round ratio says how far to trust the two figures above.
        "rounds": (active_s / vanilla_s - 1).tolist(),
        "active_s": active,
        "vanilla_s": vanilla,
    }


def _run_overhead(case: dict[str, Any]) -> dict[str, Any]:
    """The wrapper's overhead with the machine's drift taken out: the active-measure and the vanilla-env
    programs compiled in one process and timed in alternation, for training (the sweep runner's programs) and for
    the env alone (a random-action rollout)."""
    train = _interleaved({v: _build_amjax({**case, "vanilla": v})["run"] for v in (False, True)}, case["repeats"])
    env = _interleaved({v: _build_env_only({**case, "vanilla": v}) for v in (False, True)}, case["repeats"])
    return {
        "run_s": float(min(train[False])),
        "run_cpu_s": float("nan"),
        "compile_s": float("nan"),
        "eval_return": None,
        "train": _overhead_figures(train[False], train[True]),
        "env_only": {
            **_overhead_figures(env[False], env[True]),
            "envs": ENV_ONLY_ENVS,
            "steps": ENV_ONLY_STEPS,
            "active_steps_per_s": ENV_ONLY_ENVS * ENV_ONLY_STEPS / min(env[False]),
            "vanilla_steps_per_s": ENV_ONLY_ENVS * ENV_ONLY_STEPS / min(env[True]),
        },
    }


def _run_reference(case: dict[str, Any]) -> dict[str, Any]:
    import jax
    import jax.numpy as jnp
    import numpy as np

    sys.path.insert(0, str(HERE))
    if case["agent"] == "ppo":
        from reference_ppo import make_train
    else:
        from reference_dqn import make_train

    config = _agent_config(case, 0.0).validate()
    train = jax.jit(jax.vmap(make_train(config, vanilla=case["vanilla"], evaluate=case["reference_eval"])))
    keys = jnp.stack([jax.random.PRNGKey(seed) for seed in range(case["configs"])])
    costs = jnp.asarray(_costs(case), jnp.float32)
    baseline = _current_rss_mib()

    start = time.perf_counter()
    compiled = train.lower(keys, costs).compile()
    compile_s = time.perf_counter() - start

    def run():
        out = np.asarray(jax.device_get(compiled(keys, costs)))
        return float(np.median(out[:, -1])) if case["reference_eval"] else None

    timed = _timed(run, case["repeats"])
    eval_return = timed.pop("out")
    return {"compile_s": compile_s, **timed, "eval_return": eval_return, "baseline_rss_mib": baseline}


def _run_sb3(case: dict[str, Any]) -> dict[str, Any]:
    import gymnasium as gym
    import torch
    from stable_baselines3 import DQN, PPO

    torch.set_num_threads(case["sb3_threads"])
    baseline = _current_rss_mib()
    algo = DQN if case["agent"] == "dqn" else PPO

    def setup():
        return algo("MlpPolicy", gym.make("CartPole-v1"), seed=0, device="cpu", verbose=0)

    start = time.perf_counter()
    setup()
    setup_s = time.perf_counter() - start

    def run(model):
        model.learn(total_timesteps=case["steps"])
        return int(model.num_timesteps)  # PPO rounds up to whole rollouts of n_steps

    timed = _timed(run, case["repeats"], prepare=setup)  # each run on a fresh model, built before its clock
    steps = timed.pop("out")
    return {"compile_s": setup_s, **timed, "steps": steps, "eval_return": None, "baseline_rss_mib": baseline}


def run_child(case: dict[str, Any]) -> None:
    if case["impl"] != "sb3":
        import jax

        jax.config.update("jax_enable_compilation_cache", False)  # compile times must be real ones
    if case["impl"] == "sb3":
        runner = _run_sb3
    elif case["impl"].startswith("reference"):
        runner = _run_reference
    elif case["impl"] == "overhead":
        runner = _run_overhead
    else:
        runner = _run_amjax
    result = runner(case)
    result["peak_rss_mib"] = _peak_rss_mib()
    print("RESULT " + json.dumps(result), flush=True)


# ---------------------------------------------------------------------------------------------------------------
# The parent: build the cases, run each in a subprocess, print the table.
# ---------------------------------------------------------------------------------------------------------------


def _steps_per_update(agent: str, hparams: str = "default") -> int:
    from amjax.agents import DQNConfig, PPOConfig

    if agent == "ppo":
        return PPOConfig().steps_per_update()
    return (DQNConfig(**SB3_DQN) if hparams == "sb3" else DQNConfig()).steps_per_update()


def _round_steps(steps: int, unit: int) -> int:
    return max(unit, round(steps / unit) * unit)


def _parse_steps(text: str | None) -> dict[int, int] | int | None:
    if text is None:
        return None
    if ":" not in text:
        return int(text)
    return {int(k): int(v) for k, v in (item.split(":") for item in text.split(","))}


def _budget_steps(rule: dict[str, int], configs: int) -> int:
    """Steps per configuration by a STEP_RULES entry: the budget shared out, clipped to [min, max]."""
    return min(rule["max"], max(rule["min"], rule["budget"] // configs))


def _default_buffer(steps: int, unit: int) -> int:
    """min(DQNConfig's default buffer, the steps of one run), a multiple of the steps per update."""
    from amjax.agents import DQNConfig

    return min(DQNConfig().buffer_size, math.ceil(steps / unit) * unit)


def build_cases(args: argparse.Namespace) -> list[dict[str, Any]]:
    rules = QUICK_STEP_RULES if args.quick else STEP_RULES
    steps_arg = _parse_steps(args.steps)
    common = {
        "evals": args.evals,
        "eval_episodes": args.eval_episodes,
        "reference_eval": not args.no_reference_eval,
        "target_chunks": args.target_chunks,
        "sb3_threads": args.sb3_threads,
        "repeats": args.repeats,
        "cores": args.cores,
    }
    cases = []
    for agent in args.agents:
        unit = args.evals * _steps_per_update(agent)
        for size in args.sizes:
            if isinstance(steps_arg, int):
                steps = steps_arg
            elif isinstance(steps_arg, dict) and size in steps_arg:
                steps = steps_arg[size]
            else:
                steps = _budget_steps(rules[agent], size)
            steps = _round_steps(steps, unit)
            for impl in args.impls:
                case = {
                    "impl": impl,
                    "agent": agent,
                    "configs": size,
                    "steps": steps,
                    "vanilla": impl.endswith("vanilla"),
                    **common,
                }
                if agent == "dqn":
                    case["buffer"] = args.buffer or _default_buffer(steps, _steps_per_update(agent))
                cases.append(case)
    if args.sb3:
        sb3_steps = _round_steps(args.sb3_steps, args.evals * _steps_per_update("dqn", "sb3"))
        if "dqn" in args.agents:
            cases.append(
                {
                    "impl": "sb3",
                    "agent": "dqn",
                    "configs": 1,
                    "steps": sb3_steps,
                    "vanilla": True,
                    "buffer": SB3_DQN["buffer_size"],
                    **common,
                }
            )
            cases.append(
                {
                    "impl": "amjax-sb3",
                    "agent": "dqn",
                    "configs": args.sb3_configs,
                    "steps": sb3_steps,
                    "vanilla": False,
                    "hparams": "sb3",
                    "buffer": args.sb3_buffer,
                    **common,
                }
            )
        if "ppo" in args.agents:
            cases.append(
                {"impl": "sb3", "agent": "ppo", "configs": 1, "steps": args.sb3_steps, "vanilla": True, **common}
            )
    for agent in args.agents:
        for size in args.overhead:
            steps = _round_steps(_budget_steps(rules[agent], size), _steps_per_update(agent))
            case = {"impl": "overhead", "agent": agent, "configs": size, "steps": steps, "vanilla": False, **common}
            # Training only: one evaluation of one episode at the end, so the env and the learner are what is timed.
            case.update(evals=1, eval_episodes=1, repeats=args.overhead_rounds)
            if agent == "dqn":
                case["buffer"] = args.buffer or _default_buffer(steps, _steps_per_update(agent))
            cases.append(case)
    for buffer in args.buffer_scan:
        steps = _round_steps(args.buffer_scan_steps, args.evals * _steps_per_update("dqn"))
        cases.append(
            {
                "impl": "amjax-buffer",
                "agent": "dqn",
                "configs": args.buffer_scan_configs,
                "steps": steps,
                "vanilla": False,
                "buffer": _round_steps(buffer, _steps_per_update("dqn")),
                **common,
            }
        )
    return cases


def run_case(case: dict[str, Any], timeout: float) -> dict[str, Any]:
    pythonpath = os.pathsep.join(filter(None, [str(HERE.parent), os.environ.get("PYTHONPATH")]))
    # CPU devices: amjax takes one per core on import unless told (--cores); the plain reference runs on one.
    devices = {"JAX_NUM_CPU_DEVICES": "1"} if not case["impl"].startswith("amjax") else (
        {"JAX_NUM_CPU_DEVICES": str(case["cores"])} if case["cores"] else {}
    )
    start = time.perf_counter()
    try:
        proc = subprocess.run(
            [sys.executable, str(Path(__file__).resolve()), "--child", json.dumps(case)],
            capture_output=True,
            text=True,
            timeout=timeout,
            env=dict(os.environ, PYTHONPATH=pythonpath, **devices),
            cwd=str(HERE.parent),
        )
    except subprocess.TimeoutExpired:
        return {**case, "status": f"timeout after {timeout:.0f} s"}
    wall = time.perf_counter() - start
    for line in proc.stdout.splitlines():
        if line.startswith("RESULT "):
            result = {**case, **json.loads(line[len("RESULT ") :]), "status": "ok", "wall_s": wall}
            result["steps_per_s"] = result["configs"] * result["steps"] / result["run_s"]
            return result
    tail = (proc.stderr or proc.stdout).strip().splitlines()[-1:] or [f"exit {proc.returncode}"]
    return {**case, "status": f"failed: {tail[0][:200]}"}


def machine_info() -> dict[str, str]:
    from importlib.metadata import version

    import jax

    cpu = platform.processor() or "unknown"
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    try:
        mem = f"{os.sysconf('SC_PAGE_SIZE') * os.sysconf('SC_PHYS_PAGES') / 2**30:.0f} GiB RAM"
    except (ValueError, OSError):
        mem = "RAM unknown"
    software = (
        f"Python {platform.python_version()}, jax {jax.__version__}, jaxlib {version('jaxlib')}, "
        f"flax {version('flax')}, optax {version('optax')}, gymnax {version('gymnax')}, backend {jax.default_backend()}"
    )
    with contextlib.suppress(Exception):  # optional
        software += f", stable-baselines3 {version('stable_baselines3')}, torch {version('torch')}"
    return {
        "cpu": f"{cpu}, {len(os.sched_getaffinity(0))} cores usable ({os.cpu_count()} online), {mem}",
        "software": software,
    }


def _fmt(value: Any, spec: str = ".1f") -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    return format(value, spec)


def _rate(value: float | None) -> str:
    if value is None:
        return "-"
    if value >= 1e6:
        return f"{value / 1e6:.2f} M"
    if value >= 1e3:
        return f"{value / 1e3:.1f} k"
    return f"{value:.0f}"


def _env_label(r: dict[str, Any]) -> str:
    if r["impl"] == "sb3":
        return "Gymnasium CartPole-v1"
    return f"{ENV_ID} vanilla" if r["vanilla"] else f"{ENV_ID} active-measure"


def _eval_ratio(r: dict[str, Any]) -> float | None:
    """Evaluation env steps (each evaluation scans MAX_EPISODE_STEPS) per training env step."""
    if r["impl"] == "sb3" or (r["impl"].startswith("reference") and not r["reference_eval"]):
        return None
    return r["evals"] * r["eval_episodes"] * MAX_EPISODE_STEPS / r["steps"]


HEADER = [
    "implementation",
    "agent",
    "env",
    "configs",
    "steps/config",
    "buffer/config",
    "eval/train steps",
    "compile (s)",
    "run (s)",
    "run CPU (s)",
    "env-steps/s",
    "peak RSS (MiB)",
    "eval return",
]


def table_rows(results: list[dict[str, Any]]) -> list[list[str]]:
    rows = []
    for r in results:
        if r["impl"] == "overhead":
            continue  # reported as ratios: its run times are paired, not a throughput
        ok = r.get("status") == "ok"
        label = f"SB3 {r['agent'].upper()} (defaults)" if r["impl"] == "sb3" else IMPL_LABELS[r["impl"]]
        rows.append(
            [
                label,
                r["agent"].upper(),
                _env_label(r),
                str(r["configs"]),
                f"{r['steps']:,}",
                f"{r['buffer']:,}" if r.get("buffer") else "-",
                _fmt(_eval_ratio(r), ".2f"),
                _fmt(r.get("compile_s")) if ok else "-",
                _fmt(r.get("run_s")) if ok else "-",
                _fmt(r.get("run_cpu_s")) if ok else "-",
                _rate(r.get("steps_per_s")) if ok else r.get("status", "?"),
                _fmt(r.get("peak_rss_mib"), ".0f") if ok else "-",
                _fmt(r.get("eval_return")) if ok else "-",
            ]
        )
    return rows


def format_text(rows: list[list[str]]) -> str:
    widths = [max([len(h), *(len(row[i]) for row in rows)]) for i, h in enumerate(HEADER)]

    def line(cells: list[str]) -> str:
        return "  ".join(
            c.rjust(w) if i >= 3 else c.ljust(w) for i, (c, w) in enumerate(zip(cells, widths, strict=True))
        )

    return "\n".join([line(HEADER), line(["-" * w for w in widths]), *map(line, rows)])


def format_markdown(rows: list[list[str]]) -> str:
    align = "|" + "|".join("---" if i < 3 else "---:" for i in range(len(HEADER))) + "|"
    return "\n".join(["| " + " | ".join(HEADER) + " |", align, *("| " + " | ".join(row) + " |" for row in rows)])


def _find(results: list[dict[str, Any]], impl: str, agent: str, configs: int | None = None) -> dict | None:
    for r in results:
        ok = r.get("status") == "ok"
        if ok and r["impl"] == impl and r["agent"] == agent and configs in (None, r["configs"]):
            return r
    return None


def ratio_lines(results: list[dict[str, Any]]) -> list[str]:
    lines = []
    sizes = sorted({r["configs"] for r in results if r["impl"] in IMPLS})
    for agent in ("ppo", "dqn"):
        for size in sizes:
            am, van = _find(results, "amjax", agent, size), _find(results, "amjax-vanilla", agent, size)
            ref, ref_van = _find(results, "reference", agent, size), _find(results, "reference-vanilla", agent, size)
            parts = []
            if am and ref:
                parts.append(
                    f"amjax / plain reference = {am['steps_per_s'] / ref['steps_per_s']:.2f}x "
                    f"(by CPU seconds: {ref['run_cpu_s'] / am['run_cpu_s']:.2f}x)"
                )
            if am and van:
                parts.append(
                    f"active-measure wrapper overhead (amjax) = "
                    f"{(van['steps_per_s'] / am['steps_per_s'] - 1) * 100:+.0f}%"
                )
            if ref and ref_van:
                parts.append(
                    f"wrapper overhead (reference) = {(ref_van['steps_per_s'] / ref['steps_per_s'] - 1) * 100:+.0f}%"
                )
            if am and ref:
                parts.append(f"compile amjax / reference = {am['compile_s'] / ref['compile_s']:.2f}x")
            if parts:
                lines.append(f"{agent.upper()} x {size}: " + "; ".join(parts))
    for r in results:
        if r["impl"] == "overhead" and r.get("status") == "ok":
            train, env = r["train"], r["env_only"]
            lines.append(
                f"{r['agent'].upper()} x {r['configs']}: active-measure overhead, interleaved in one process "
                f"({len(train['rounds'])} runs each): training {train['min'] * 100:+.1f}% (fastest vs fastest), "
                f"{train['median'] * 100:+.1f}% (median vs median), per round {min(train['rounds']) * 100:+.1f}% to "
                f"{max(train['rounds']) * 100:+.1f}%; the env alone ({env['envs']:,} envs x {env['steps']} random "
                f"steps: {_rate(env['active_steps_per_s'])} vs {_rate(env['vanilla_steps_per_s'])} steps/s) "
                f"{env['min'] * 100:+.1f}% / {env['median'] * 100:+.1f}%"
            )
    sb3_dqn, amjax_sb3 = _find(results, "sb3", "dqn"), _find(results, "amjax-sb3", "dqn")
    if sb3_dqn and amjax_sb3:
        n = amjax_sb3["configs"]
        sequential = n * sb3_dqn["run_s"] * amjax_sb3["steps"] / sb3_dqn["steps"]
        lines.append(
            f"DQN with SB3's default hyperparameters: amjax x {n} configs {_rate(amjax_sb3['steps_per_s'])} "
            f"env-steps/s vs SB3 DQN {_rate(sb3_dqn['steps_per_s'])}/s: speed-up "
            f"{amjax_sb3['steps_per_s'] / sb3_dqn['steps_per_s']:.1f}x ({n} runs: amjax "
            f"{amjax_sb3['compile_s'] + amjax_sb3['run_s']:.0f} s including compile, SB3 {sequential:.0f} s one "
            "after another)"
        )
    sb3_ppo = _find(results, "sb3", "ppo")
    if sb3_ppo:
        for size in sizes:
            am = _find(results, "amjax", "ppo", size)
            if am:
                lines.append(
                    f"PPO: amjax x {size} configs / SB3 PPO (1 env) = "
                    f"{am['steps_per_s'] / sb3_ppo['steps_per_s']:.1f}x aggregate env-steps/s"
                )
    scan = sorted(
        (r for r in results if r["impl"] == "amjax-buffer" and r.get("status") == "ok"), key=lambda r: r["buffer"]
    )
    if len(scan) > 1:
        lines.append(
            f"DQN step cost vs replay capacity (amjax, {scan[0]['configs']} configs, {scan[0]['steps']:,} steps "
            "each): "
            + ", ".join(
                f"{r['buffer']:,} slots {_rate(r['steps_per_s'])}/s "
                f"({r['steps_per_s'] / scan[0]['steps_per_s']:.2f}x, CPU {r['run_cpu_s']:.1f} s, "
                f"RSS {r['peak_rss_mib']:.0f} MiB)"
                for r in scan
            )
        )
    return lines


def note_lines(args: argparse.Namespace, results: list[dict[str, Any]]) -> list[str]:
    from amjax.agents import DQNConfig

    chunks = sorted({r["chunks"] for r in results if r.get("chunks")})
    baselines = [r["baseline_rss_mib"] for r in results if r.get("baseline_rss_mib") and r["impl"] != "sb3"]
    starts = DQNConfig().learning_starts
    dqn_steps = sorted({r["steps"] for r in results if r["agent"] == "dqn" and r["impl"] in IMPLS})
    notes = [
        "env-steps/s = configs x steps/config / run time: training env steps only, all configs together"
        + (f"; run time is the fastest of {args.repeats} runs" if args.repeats > 1 else "")
        + ". run CPU = the child's user + system CPU seconds over that run (all threads): CPU / wall near the core "
        "count means the cores were the program's; other load on the machine inflates wall time first.",
        f"Evaluation: amjax runs {args.evals} greedy evaluations of {args.eval_episodes} episodes per config "
        f"(every steps/config / {args.evals} env steps), as a sweep does; "
        + (
            "the plain reference runs the same evaluation (same count, episodes and greedy policy). "
            if not args.no_reference_eval
            else "the plain reference has NO evaluation (--no-reference-eval). "
        )
        + f"Each evaluation scans {MAX_EPISODE_STEPS} steps of its episodes: 'eval/train steps' is that work per "
        "training step (forward passes only; a real sweep, e.g. 491,520 steps with 24 evaluations, has 0.2).",
        "eval return = median over configs of the last evaluation's mean costed test return: a check that the "
        "implementations learn alike (at these budgets they are far from converged; vanilla has no cost and 2 "
        "actions, so it learns faster).",
        f"amjax compile = .lower().compile() of the sweep runner's two programs (init_run under lax.map; "
        f"jit(vmap(run_evals)) of a chunk of evaluations); run = init + all {chunks or '?'} chunks, the eval rows "
        "fetched after each (no disk writes or checkpoints). Reference: one jit(vmap(train)) program.",
        f"Active-measure configs use costs {', '.join(map(str, COSTS))} in turn (traced: one compiled program) and "
        "seeds 0..n-1; vanilla-env configs cost 0.",
        f"DQN buffer/config: min(DQNConfig's default {DQNConfig().buffer_size:,}, steps/config): a buffer at least "
        "as large as the run "
        "never wraps, so the run is the same as with a larger one. Replay memory = configs x buffer x "
        f"{TRANSITION_BYTES} B (obs and next_obs of 5 float32 + action + reward + discount): "
        + ", ".join(
            f"{r['configs']} x {r['buffer']:,} = {r['configs'] * r['buffer'] * TRANSITION_BYTES / 2**20:,.1f} MiB"
            for r in results
            if r["impl"] in ("amjax", "amjax-sb3") and r["agent"] == "dqn"
        )
        + f". SB3's 1e6 buffer x 1024 configs would need 50 GiB; {DQNConfig().buffer_size:,} x 1024 would need "
        f"{DQNConfig().buffer_size * 1024 * TRANSITION_BYTES / 2**30:.1f} GiB.",
        "Peak RSS is the child process's maximum resident set (jax, compiled programs and buffers included)"
        + (f"; a child's RSS before compiling is {min(baselines):.0f}-{max(baselines):.0f} MiB." if baselines else "."),
    ]
    if dqn_steps and "reference" in args.impls:
        notes.append(
            f"DQN warm-up: the first learning_starts = {starts:,} env steps have no gradient step "
            + ", ".join(f"({min(starts / s, 1):.0%} of the run at {s:,} steps)" for s in dqn_steps)
            + ". Both skip that work: the reference's lax.cond on its unbatched step counter, amjax's "
            "batching.uniform_cond on its per-config counters (a real branch under vmap)."
        )
    if any(r["impl"] == "overhead" for r in results):
        notes.append(
            "Wrapper overhead (interleaved): separate processes drift by a few percent between runs, as much as the "
            "overhead itself, so it is also timed with both programs compiled in one process and run in alternation "
            "(active, vanilla, vanilla, active, ...), after one untimed run of each: training only (one evaluation "
            "of one episode at the end), and the env alone (the training env stack stepped under random actions, "
            "every transition summed into a checksum). The vanilla env has 2 actions and 4 observations, the "
            "active-measure one 4 and 5: the training figure includes the larger network and action distribution, "
            "not only the wrapper's code; the env-alone figure is the wrapper's own cost."
        )
    if any(r["impl"] == "sb3" for r in results):
        notes.append(
            "SB3 rows: Stable-Baselines3 defaults on Gymnasium CartPole-v1 (500-step episodes, no measure action), "
            f"1 env, CPU torch with {args.sb3_threads} thread(s) (--sb3-threads), no evaluation; their 'compile' "
            "column is model construction. The amjax row with SB3's DQN hyperparameters (lr 1e-4, buffer as listed, "
            "learning_starts 100, batch 32, tau 1, gamma 0.99, train_freq 4, 1 gradient step, target every 10,000 "
            "steps, exploration 0.1 -> 0.05, max_grad_norm 10, [64, 64] relu, no dueling, no double-Q) runs the "
            "active-measure CartPole-v0 with its periodic evaluation: more work per step than SB3's, so its speed-up "
            "is conservative."
        )
    return notes


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--child", help=argparse.SUPPRESS)
    parser.add_argument("--agents", default="ppo,dqn", help="comma-separated: ppo, dqn (default: both)")
    parser.add_argument("--sizes", default=None, help="configurations per case (default 1,16,256,1024; quick 1,4)")
    parser.add_argument(
        "--impls",
        default="amjax,amjax-vanilla,reference",
        help=f"comma-separated, from {', '.join(IMPLS)} (default: the first three)",
    )
    parser.add_argument(
        "--steps",
        default=None,
        help="env steps per config: one number for every size, or size:steps pairs "
        "(1:204800,16:51200); rounded to a multiple of evals x steps per update "
        "(default: min(max, max(min, budget / configs)), see STEP_RULES)",
    )
    parser.add_argument("--cores", type=int, default=None,
                        help="CPU devices amjax spreads its configurations over (default: one per usable core, "
                        "as amjax does; the plain reference always runs as written, on one device)")
    parser.add_argument("--evals", type=int, default=5, help="evaluations per run (default 5)")
    parser.add_argument("--eval-episodes", type=int, default=10, help="test episodes per evaluation (default 10)")
    parser.add_argument("--target-chunks", type=int, default=10, help="the sweep runner's target_chunks (default 10)")
    parser.add_argument("--no-reference-eval", action="store_true", help="the plain reference skips evaluation")
    parser.add_argument(
        "--repeats",
        type=int,
        default=1,
        help="run each compiled case this many times and keep the fastest (default 1; use 3 on a busy machine)",
    )
    parser.add_argument(
        "--buffer",
        type=int,
        default=None,
        help="DQN buffer per config for every size (default: min(DQNConfig's buffer_size, steps per config))",
    )
    parser.add_argument(
        "--sb3",
        dest="sb3",
        action="store_true",
        default=None,
        help="SB3 rows (default: if stable_baselines3 is importable)",
    )
    parser.add_argument("--no-sb3", dest="sb3", action="store_false")
    parser.add_argument("--sb3-steps", type=int, default=None, help="env steps for the SB3 rows (default 20,000)")
    parser.add_argument(
        "--sb3-configs", type=int, default=None, help="amjax configs with SB3's DQN hyperparameters (default 64)"
    )
    parser.add_argument(
        "--sb3-threads",
        type=int,
        default=1,
        help="torch threads for SB3 (default 1: faster for "
        "these small networks; 2 threads on a busy 2-core machine ran 20x slower)",
    )
    parser.add_argument(
        "--sb3-buffer",
        type=int,
        default=SB3_DQN["buffer_size"],
        help="buffer per config for that case (default SB3's 1,000,000)",
    )
    parser.add_argument(
        "--buffer-scan",
        default="",
        help="also time amjax DQN at these buffer sizes "
        "(e.g. 1000,10000,100000) to see whether the step cost grows with capacity",
    )
    parser.add_argument("--buffer-scan-configs", type=int, default=16)
    parser.add_argument(
        "--overhead",
        default=None,
        help="configuration counts at which to time the wrapper's overhead with the active-measure and vanilla "
        "programs interleaved in one process, training only (default 256; quick 4; '' skips)",
    )
    parser.add_argument("--overhead-rounds", type=int, default=6, help="timed runs of each program (default 6)")
    parser.add_argument("--buffer-scan-steps", type=int, default=20_000)
    parser.add_argument("--timeout", type=float, default=900, help="seconds per case before it is abandoned")
    parser.add_argument("--markdown", default=None, help="also write the table and notes as markdown to this path")
    parser.add_argument("--json", default=None, help="also write the raw results as JSON to this path")
    parser.add_argument("--quick", action="store_true", help="smoke run: tiny sizes and budgets")
    args = parser.parse_args()

    if args.child:
        run_child(json.loads(args.child))
        return

    args.agents = [a for a in args.agents.split(",") if a]
    args.impls = [i for i in args.impls.split(",") if i]
    for impl in args.impls:
        if impl not in IMPLS:
            parser.error(f"--impls: unknown {impl!r}; allowed: {', '.join(IMPLS)}")
    for agent in args.agents:
        if agent not in ("ppo", "dqn"):
            parser.error(f"--agents: unknown {agent!r}; allowed: ppo, dqn")
    args.sizes = [int(s) for s in (args.sizes or ("1,4" if args.quick else "1,16,256,1024")).split(",")]
    args.buffer_scan = [int(b) for b in args.buffer_scan.split(",") if b]
    overhead = ("4" if args.quick else "256") if args.overhead is None else args.overhead
    args.overhead = [int(s) for s in overhead.split(",") if s]
    if args.sb3 is None:
        try:
            import stable_baselines3  # noqa: F401

            args.sb3 = True
        except ImportError:
            args.sb3 = False
    args.sb3_steps = args.sb3_steps or (2_000 if args.quick else 20_000)
    args.sb3_configs = args.sb3_configs or (4 if args.quick else 64)

    sys.path.insert(0, str(HERE.parent))
    info = machine_info()
    load_start = os.getloadavg()
    header = [
        f"Machine: {info['cpu']}",
        f"Software: {info['software']}",
        f"Load average at start: {load_start[0]:.2f} (1 min); above ~0.5 the timings are noisy",
    ]
    print("\n".join(header), flush=True)

    cases = build_cases(args)
    print(f"{len(cases)} cases, each in a fresh process:", flush=True)
    results = []
    for i, case in enumerate(cases, 1):
        extra = f", buffer {case['buffer']:,}" if case.get("buffer") else ""
        print(
            f"[{i}/{len(cases)}] {IMPL_LABELS[case['impl']]} {case['agent']} x {case['configs']} "
            f"({case['steps']:,} steps/config{extra}) ... ",
            end="",
            flush=True,
        )
        result = run_case(case, args.timeout)
        results.append(result)
        if result["status"] == "ok" and case["impl"] == "overhead":
            train, env = result["train"], result["env_only"]
            print(
                f"training {train['min'] * 100:+.1f}% (fastest) {train['median'] * 100:+.1f}% (median); env alone "
                f"{env['min'] * 100:+.1f}% {env['median'] * 100:+.1f}%",
                flush=True,
            )
        elif result["status"] == "ok":
            print(
                f"compile {result['compile_s']:.1f} s, run {result['run_s']:.1f} s "
                f"(CPU {result['run_cpu_s']:.1f} s), {_rate(result['steps_per_s'])} steps/s, "
                f"peak {result['peak_rss_mib']:.0f} MiB",
                flush=True,
            )
        else:
            print(result["status"], flush=True)

    header.append(f"Load average at end: {os.getloadavg()[0]:.2f} (1 min)")
    rows = table_rows(results)
    ratios, notes = ratio_lines(results), note_lines(args, results)
    print("\n" + "\n".join(header) + "\n")
    print(format_text(rows))
    print("\nRatios (env-steps/s):")
    print("\n".join(f"  {line}" for line in ratios) or "  (none: a pair of cases is missing)")
    print("Notes:")
    print("\n".join(f"  - {line}" for line in notes))
    if args.markdown:
        md = ["\n".join(f"- {line}" for line in header), "", format_markdown(rows), "", "Ratios (env-steps/s):", ""]
        md += [f"- {line}" for line in ratios] + ["", "Notes:", ""] + [f"- {line}" for line in notes]
        Path(args.markdown).write_text("\n".join(md) + "\n")
        print(f"markdown written to {args.markdown}")
    if args.json:
        payload = {"machine": info, "load_start": load_start, "args": vars(args), "results": results}
        Path(args.json).write_text(json.dumps(payload, indent=1, default=str))
        print(f"raw results written to {args.json}")


if __name__ == "__main__":
    main()
