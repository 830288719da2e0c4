"""Shared test helpers.

`rollout` runs reset + a scanned sequence of steps of any gymnax-API environment in one jitted program. The
environment is a static argument, so each (env object, sequence length) compiles once and hypothesis examples
that reuse a module-level env reuse the compiled program. `scan_steps` is the same program unjitted, for tests
that vmap it themselves.
"""

from __future__ import annotations

import functools
import gc
import os
import tempfile
from pathlib import Path
from typing import Any, NamedTuple

import jax
import numpy as np
import pytest

from amjax.cores import maps_past_half
from amjax.files import write_compile_cache_whole

# At least two CPU devices, so that the sweep runner's sharded path (`amjax.sweep.devices`) is what the tests run
# even on a one-core machine (before any test module imports gymnax, which starts JAX's backend).
jax.config.update("jax_num_cpu_devices", max(2, len(os.sched_getaffinity(0))))

# One persistent XLA compilation cache for the whole suite: both xdist workers and every process a test starts (the
# command line, the notebooks' kernels, cluster workers, killed children) reuse the programs any of them compiled,
# within a run and across runs on one machine. A cache you set yourself (JAX_COMPILATION_CACHE_DIR) is used instead.
COMPILE_CACHE = os.environ.setdefault(
    "JAX_COMPILATION_CACHE_DIR", str(Path(tempfile.gettempdir()) / "amjax-tests-compile-cache")
)
jax.config.update("jax_compilation_cache_dir", COMPILE_CACHE)
# Every program, not only those that took JAX's default 1 s to compile: the suite compiles hundreds of small
# programs (a rollout, a wrapper's step, a few updates), and loading one back is far cheaper than compiling it again.
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
jax.config.update(
    "jax_persistent_cache_min_compile_time_secs", float(os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"])
)
# JAX writes an entry in place; amjax makes every process that imports its agents write entries whole (temporary
# name, then renamed: `amjax.files.write_compile_cache_whole`), so no process reads half of one, whether its writer
# was killed or is still writing. The test processes do it from the start.
write_compile_cache_whole()


# Every loaded XLA CPU executable keeps a few memory mappings per kernel (a training program: 3,000-5,000), and JAX
# keeps every program a process compiled. An xdist worker that runs half the suite passed Linux's per-process limit
# (vm.max_map_count, 65,530 by default): LLVM's loader then failed ("Cannot allocate memory") and the worker died
# (SIGSEGV / SIGABRT) loading the next program. Past half the limit, a test's programs are dropped after it ends.
@pytest.fixture(autouse=True)
def _release_programs_near_the_map_limit():
    yield
    if maps_past_half():
        jax.clear_caches()
        gc.collect()


# Test tiers. `python -m pytest -q` (the README's command) runs the default tier: every test not marked slow. A test is
# marked slow when it takes over about 20 s on two CPU cores with an empty compile cache, as on a fresh machine
# (`python benchmarks/suite_compile.py` counts the default tier's tests over that bound): whole training programs
# (vmapped-against-alone checks, learning runs), kill-and-resume chains through subprocesses, the notebooks, the
# README demo, whole sweeps, LunarLander batches and brax steps; `--tier slow` runs those alone and `--tier all` both.
# CI runs both tiers (.ci/run). A test named on the command line (`path::name`) runs whatever its tier, and `-m EXPR`
# selects by its own expression instead.
TIERS = ("default", "slow", "all")


def pytest_addoption(parser):
    parser.addoption(
        "--tier",
        choices=TIERS,
        default="default",
        help="default: tests not marked slow (the README's command); slow: the slow ones; all: both",
    )


def pytest_collection_modifyitems(config, items):
    tier = config.getoption("--tier")
    named = any("::" in str(arg) for arg in config.args)
    if tier == "all" or config.option.markexpr or named:
        return
    chosen = {item.nodeid: (item.get_closest_marker("slow") is not None) == (tier == "slow") for item in items}
    if not all(chosen.values()):
        config.hook.pytest_deselected(items=[item for item in items if not chosen[item.nodeid]])
        items[:] = [item for item in items if chosen[item.nodeid]]


class Rollout(NamedTuple):
    """A reset followed by T steps (NumPy arrays, leading axis T for the step outputs)."""

    obs0: Any  # observation after reset
    state0: Any  # state after reset
    step_keys: Any  # the key passed to `step` at each time step
    obs: Any  # observation returned by step t (after any auto-reset)
    state: Any  # state after step t
    reward: Any
    terminated: Any
    truncated: Any
    info: dict[str, Any]


def scan_steps(env, params, reset_key, step_keys, actions):
    """Traceable (vmap/jit it): reset, then `lax.scan` the steps; returns (obs0, state0, step outputs)."""
    obs0, state0 = env.reset(reset_key, params)

    def step(state, xs):
        key, action = xs
        obs, state, reward, terminated, truncated, info = env.step(key, state, action, params)
        return state, (obs, state, reward, terminated, truncated, info)

    _, outputs = jax.lax.scan(step, state0, (step_keys, actions))
    return obs0, state0, outputs


_rollout = jax.jit(scan_steps, static_argnums=0)


def run_rollout(env, params, key, actions, step_keys=None) -> Rollout:
    """Reset with `split(key)[0]`, then step with `step_keys` (default: T keys split from `split(key)[1]`)."""
    reset_key, keys_key = jax.random.split(key)
    if step_keys is None:
        step_keys = jax.random.split(keys_key, len(actions))
    obs0, state0, outputs = _rollout(env, params, reset_key, step_keys, actions)
    obs0, state0, outputs = jax.device_get((obs0, state0, outputs))
    return Rollout(obs0, state0, step_keys, *outputs)


@pytest.fixture(scope="session")
def rollout():
    """`rollout(env, params, key, actions, step_keys=None) -> Rollout` (see `run_rollout`)."""
    return run_rollout


@pytest.fixture(scope="session")
def scan_steps_fn():
    """`scan_steps(env, params, reset_key, step_keys, actions)`: traceable, returns (obs0, state0, outputs)."""
    return scan_steps


@jax.jit
def _split_first(step_keys):
    return jax.vmap(lambda key: jax.random.split(key)[0])(step_keys)


def _inner_keys(step_keys, mode: str = "last"):
    """The keys `ActiveMeasure.step` passes to its inner env: the key itself in mode "last" (no view noise to
    draw), else `split(key)[0]`."""
    return step_keys if mode == "last" else _split_first(step_keys)


@pytest.fixture(scope="session")
def inner_keys():
    """`inner_keys(step_keys, mode="last")`: the keys `ActiveMeasure.step` passes to its inner env."""
    return _inner_keys


class SweepStopped(Exception):
    """Raised by a `stop_sweep_after` callback: a sweep stopped after a chunk, as a kill would stop it."""


@pytest.fixture
def stop_sweep_after():
    """`stop_sweep_after(n)`: an `on_chunk` callback for `run_sweep` that raises `stop_sweep_after.error`
    (SweepStopped) after the n-th chunk."""

    def make(chunks: int):
        seen = []

        def on_chunk(results):
            seen.append(len(results))
            if len(seen) == chunks:
                raise SweepStopped

        return on_chunk

    make.error = SweepStopped
    return make


def _tiny_sweep_flags(*, steps: int = 2048, seeds: int = 1, extra: tuple[str, ...] = ()) -> list[str]:
    """`amjax sweep` flags (no --out) of a one-cost PPO sweep of CartPole-v0 that trains in seconds: 4 envs x 32
    steps per update, an evaluation of 2 episodes every 1,024 steps."""
    return [
        *("--env", "CartPole-v0", "--agent", "ppo", "--cost", "0.1", "--seeds", str(seeds), "--steps", str(steps)),
        *("--eval-every", "1024", "--eval-episodes", "2", "--set", "num_envs=4", "--set", "num_steps=32"),
        "--no-progress",
        *extra,
    ]


@pytest.fixture(scope="session")
def tiny_sweep_flags():
    """`tiny_sweep_flags(steps=2048, seeds=1, extra=())`: the flags of a small command-line sweep (no --out)."""
    return _tiny_sweep_flags


class TrainingPrograms(NamedTuple):
    """One algorithm's jitted training programs, as the sweep runner builds them (each compiles once per shape)."""

    alone: Any  # (config, key) -> (final state, EvalRows): one configuration
    batched: Any  # (stacked configs, keys) -> (final states, EvalRows [configs, evals]): vmapped


@functools.cache
def _training_programs(algo) -> TrainingPrograms:
    from amjax.agents import init_run, run_evals  # after the device count is set above (amjax starts JAX's backend)

    alone = jax.jit(lambda c, k: run_evals(algo, c, init_run(algo, c, k), c.num_evals))
    init = jax.jit(jax.vmap(lambda c, k: init_run(algo, c, k)))
    batched = jax.jit(jax.vmap(lambda c, s: run_evals(algo, c, s, c.num_evals)))
    return TrainingPrograms(alone, lambda configs, keys: batched(configs, init(configs, keys)))


def _assert_batch_equals_alone(algo, configs, keys):
    """`configs` trained as one vmapped program: each equals its configuration trained alone, to float rounding.
    Returns the batch's rows and the final states of the runs alone."""
    from amjax.agents import stack_configs, unstack_config

    stacked = stack_configs([c.validate() for c in configs])
    programs = _training_programs(algo)
    _, rows = programs.batched(stacked, keys)
    states = []
    for i in range(len(configs)):
        state, alone = programs.alone(unstack_config(stacked, i), keys[i])
        states.append(state)
        for field in ("eval_return", "train_return", "loss", "eval_measurements"):
            np.testing.assert_allclose(rows.columns()[field][i], alone.columns()[field], rtol=2e-4, atol=2e-4)
    return rows, states


@pytest.fixture(scope="session")
def training_programs():
    """`training_programs(algo) -> TrainingPrograms(alone, batched)`: cached per algorithm."""
    return _training_programs


@pytest.fixture(scope="session")
def assert_batch_equals_alone():
    """`assert_batch_equals_alone(algo, configs, keys) -> (rows, states alone)`: config i inside the vmapped batch
    equals config i trained alone."""
    return _assert_batch_equals_alone


def _primitive_names(closed: Any) -> list[str]:
    """The primitives of a closed jaxpr, in order, those of its sub-jaxprs (branches, loop bodies) included."""
    from jax.extend.core import ClosedJaxpr, jaxprs_in_params

    names = []
    for eqn in closed.jaxpr.eqns:
        names.append(eqn.primitive.name)
        names += [n for sub in jaxprs_in_params(eqn.params) for n in _primitive_names(ClosedJaxpr(sub, ()))]
    return names


@pytest.fixture(scope="session")
def primitive_names():
    """`primitive_names(closed_jaxpr) -> [name, ...]`: every primitive of a `jax.make_jaxpr` result, nested ones
    included."""
    return _primitive_names
