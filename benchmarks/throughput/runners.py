"""The child process: compile and time one case of one implementation (amjax's sweep programs, the interleaved
wrapper overhead, the plain reference, or Stable-Baselines3), then print its measurements, with its peak RSS, as the
`RESULT` line `benchmarks.harness.run_child` reads (`harness.child_result`)."""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from benchmarks import harness

from .cases import agent_config, costs
from .timing import current_rss_mib, interleaved, overhead_figures, timed

BENCHMARKS = Path(__file__).resolve().parents[1]  # where reference_ppo.py and reference_dqn.py live
ENV_ONLY_ENVS, ENV_ONLY_STEPS = 2048, 256  # the env-only overhead rollout: envs x steps, random actions


@dataclass
class SweepPrograms:
    """The sweep runner's two programs compiled for one case, and what they run on."""

    init: Any  # init_run under lax.map: (stacked configs, keys) -> states
    chunk: Any  # jit(vmap(run_evals)) of a chunk of evaluations: (sharded configs, states) -> (states, rows)
    stacked: Any
    keys: Any
    sharding: Any
    sharded_configs: Any
    chunks: int  # chunks per run
    devices: int
    compile_s: float


def case_batch(case: dict[str, Any]) -> tuple[list[Any], Any, Any]:
    """The case's agent configs (one per cost), stacked, and one key per configuration (seeds 0, 1, ...)."""
    import jax
    import jax.numpy as jnp

    from amjax.agents import stack_configs

    configs = [agent_config(case, cost).validate() for cost in costs(case)]
    keys = jnp.stack([jax.random.PRNGKey(seed) for seed in range(case["configs"])])
    return configs, stack_configs(configs), keys


def reference_program(case: dict[str, Any]) -> tuple[Any, Any, Any]:
    """benchmarks/reference_{ppo,dqn}.py's `jax.jit(jax.vmap(train))` for the case, and its arguments (keys,
    costs)."""
    import jax
    import jax.numpy as jnp

    sys.path.insert(0, str(BENCHMARKS))
    if case["agent"] == "ppo":
        from reference_ppo import make_train
    else:
        from reference_dqn import make_train

    config = agent_config(case, 0.0).validate()
    train = jax.jit(jax.vmap(make_train(config, vanilla=case["vanilla"], evaluate=case["reference_eval"])))
    keys = jnp.stack([jax.random.PRNGKey(seed) for seed in range(case["configs"])])
    return train, keys, jnp.asarray(costs(case), jnp.float32)


def _compile_amjax(case: dict[str, Any], compiler_options: dict[str, Any] | None = None) -> SweepPrograms:
    """Stack the case's configs and lower and compile the sweep runner's two programs for them (with XLA's
    `compiler_options`, if any: `Lowered.compile`'s), with arrays placed
    as the runner places them."""
    import jax

    from amjax.agents import ALGORITHMS
    from amjax.sweep.batches import chunk_evals, compiled_programs
    from amjax.sweep.devices import config_sharding, sweep_devices

    configs, stacked, keys = case_batch(case)
    evals_per_chunk = chunk_evals(configs[0].num_evals, case["target_chunks"])
    devices = sweep_devices()
    if case["configs"] % len(devices):
        devices = devices[:1]  # the runner would pad the batch; the benchmark keeps the sizes it names
    init, chunk = compiled_programs(ALGORITHMS[case["agent"]], evals_per_chunk, tuple(devices))
    sharding = config_sharding(devices)

    start = time.perf_counter()
    init_compiled = init.lower(stacked, keys).compile(compiler_options)
    compile_s = time.perf_counter() - start
    # The chunk is lowered with arrays placed as the runner places them (a first init run, not timed).
    first_states = jax.device_put(init_compiled(stacked, keys), sharding)
    sharded_configs = jax.device_put(stacked, sharding)
    start = time.perf_counter()
    chunk_compiled = chunk.lower(sharded_configs, first_states).compile(compiler_options)
    compile_s += time.perf_counter() - start
    chunks = configs[0].num_evals // evals_per_chunk
    return SweepPrograms(
        init_compiled, chunk_compiled, stacked, keys, sharding, sharded_configs, chunks, len(devices), compile_s
    )


def sweep_run(p: SweepPrograms) -> Callable[[], float]:
    """One run as the sweep runner trains a fresh batch: init, then the chunks, each queued before the previous
    one's rows are fetched (here only the costed test return); returns the median last test return."""
    import jax
    import numpy as np

    def run():
        states = jax.device_put(p.init(p.stacked, p.keys), p.sharding)  # the states stay on the device
        queued = p.chunk(p.sharded_configs, states)  # states are donated, as in the runner
        for index in range(p.chunks):
            states, rows = queued
            if index + 1 < p.chunks:
                queued = p.chunk(p.sharded_configs, states)
            last = jax.device_get(rows.test.costed_return)[:, -1]
        jax.block_until_ready(states)
        return float(np.median(last))

    return run


def build_amjax(case: dict[str, Any]) -> dict[str, Any]:
    """Compile what the sweep runner compiles for the case; returns the compile time and a `run` that trains."""
    p = _compile_amjax(case)
    return {"devices": p.devices, "compile_s": p.compile_s, "run": sweep_run(p), "chunks": p.chunks}


def run_amjax(case: dict[str, Any]) -> dict[str, Any]:
    baseline = current_rss_mib()
    built = build_amjax(case)
    result = timed(built.pop("run"), case["repeats"])
    eval_return = result.pop("out")
    return {**built, **result, "eval_return": eval_return, "baseline_rss_mib": baseline}


def build_env_only(case: dict[str, Any]) -> Callable[[], Any]:
    """A compiled rollout of ENV_ONLY_ENVS training envs (the agent config's own env stack, episode statistics
    included) under uniformly random actions, through the trainers' own `rollout`, its transitions reduced into a
    checksum: the env alone."""
    import jax

    from amjax.agents.rollout import PRNG_IMPL, reset_envs, rollout
    from amjax.agents.setup import training_env

    env, params, _ = training_env(agent_config(case, costs(case)[0]).validate())
    num_actions = env.action_space(params).n

    def random_action(batch, carry, key):
        return jax.random.randint(key, batch.first.shape, 0, num_actions), carry, None

    @jax.jit
    def random_rollout(key):
        batch = reset_envs(env, params, key, ENV_ONLY_ENVS)
        _, _, t, _, episodes = rollout(env, params, batch, None, random_action, key, ENV_ONLY_STEPS)
        return t.reward.sum() + t.next_obs.sum() + t.obs.sum() + episodes.sums.length.sum()

    key = jax.random.key(0, impl=PRNG_IMPL)
    compiled = random_rollout.lower(key).compile()
    return lambda: compiled(key).block_until_ready()


def run_overhead(case: dict[str, Any]) -> dict[str, Any]:
    """The wrapper's overhead with the machine's drift taken out: the active-measure and the vanilla-env
    programs compiled in one process and timed in alternation, for training (the sweep runner's programs) and for
    the env alone (a random-action rollout)."""
    train = interleaved({v: build_amjax({**case, "vanilla": v})["run"] for v in (False, True)}, case["repeats"])
    env = interleaved({v: build_env_only({**case, "vanilla": v}) for v in (False, True)}, case["repeats"])
    return {
        "run_s": float(min(train[False])),
        "run_cpu_s": None,  # paired wall times only: no CPU time or compile time of its own
        "compile_s": None,
        "eval_return": None,
        "train": overhead_figures(train[False], train[True]),
        "env_only": {
            **overhead_figures(env[False], env[True]),
            "envs": ENV_ONLY_ENVS,
            "steps": ENV_ONLY_STEPS,
            "active_steps_per_s": ENV_ONLY_ENVS * ENV_ONLY_STEPS / min(env[False]),
            "vanilla_steps_per_s": ENV_ONLY_ENVS * ENV_ONLY_STEPS / min(env[True]),
        },
    }


def compile_reference(
    case: dict[str, Any], compiler_options: dict[str, Any] | None = None
) -> tuple[Any, Callable[[], float | None], float]:
    """benchmarks/reference_{ppo,dqn}.py compiled as `jax.jit(jax.vmap(train))(keys, costs)` (with XLA's
    `compiler_options`, if any): the compiled program, a `run` that trains once (the median last test return, or None
    without evaluation) and the compile time."""
    import jax
    import numpy as np

    train, keys, case_costs = reference_program(case)
    start = time.perf_counter()
    compiled = train.lower(keys, case_costs).compile(compiler_options)
    compile_s = time.perf_counter() - start

    def run():
        out = np.asarray(jax.device_get(compiled(keys, case_costs)))
        return float(np.median(out[:, -1])) if case["reference_eval"] else None

    return compiled, run, compile_s


def run_reference(case: dict[str, Any]) -> dict[str, Any]:
    """benchmarks/reference_{ppo,dqn}.py as `jax.jit(jax.vmap(train))(keys, costs)`."""
    baseline = current_rss_mib()
    _, run, compile_s = compile_reference(case)
    result = timed(run, case["repeats"])
    eval_return = result.pop("out")
    return {"compile_s": compile_s, **result, "eval_return": eval_return, "baseline_rss_mib": baseline}


def run_sb3(case: dict[str, Any]) -> dict[str, Any]:
    """Stable-Baselines3's DQN or PPO with its defaults on Gymnasium CartPole-v1, each run on a fresh model."""
    import gymnasium as gym
    import torch
    from stable_baselines3 import DQN, PPO

    torch.set_num_threads(case["sb3_threads"])
    baseline = current_rss_mib()
    algo = DQN if case["agent"] == "dqn" else PPO

    def setup():
        return algo("MlpPolicy", gym.make("CartPole-v1"), seed=0, device="cpu", verbose=0)

    start = time.perf_counter()
    setup()
    setup_s = time.perf_counter() - start

    def run(model):
        model.learn(total_timesteps=case["steps"])
        return int(model.num_timesteps)  # PPO rounds up to whole rollouts of n_steps

    result = timed(run, case["repeats"], prepare=setup)  # each run on a fresh model, built before its clock
    steps = result.pop("out")
    return {"compile_s": setup_s, **result, "steps": steps, "eval_return": None, "baseline_rss_mib": baseline}


def run_child(case: dict[str, Any]) -> None:
    """Run the case in this process and print its measurements (`harness.child_result` adds the peak RSS)."""
    if case["impl"] != "sb3":
        import amjax

        amjax.use_all_cores()  # before JAX starts: one CPU device per core, as a sweep, or the count _child_env set
        import jax

        jax.config.update("jax_enable_compilation_cache", False)  # compile times must be real ones
    if case["impl"] == "sb3":
        runner = run_sb3
    elif case["impl"].startswith("reference"):
        runner = run_reference
    elif case["impl"] == "overhead":
        runner = run_overhead
    else:
        runner = run_amjax
    harness.child_result(runner(case))
