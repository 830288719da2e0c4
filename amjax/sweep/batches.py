"""A sweep's compiled batches: how its configurations are grouped into padded batches, and the jitted programs
that initialise, train and re-score one batch (the pieces the runner drives and the benchmarks time)."""

from __future__ import annotations

import functools
import gc
import math
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from amjax import strategy
from amjax.agents import ALGORITHMS, Algorithm, init_run, rescore, run_evals, stack_configs
from amjax.batching import member_axes, take_shared
from amjax.cores import maps_past_half
from amjax.sweep.devices import config_sharding, sharded_jit, sweep_devices
from amjax.sweep.grid import RunConfig, group_runs


def chunk_evals(num_evals: int, target_chunks: int) -> int:
    """The largest divisor of num_evals giving at least `target_chunks` chunks (or 1)."""
    want = max(1, num_evals // max(target_chunks, 1))
    return max(d for d in range(1, want + 1) if num_evals % d == 0)


@dataclass
class Batch:
    """Up to `max_batch` configurations of one group, padded to a fixed size so every batch of a group shares
    one compiled program."""

    name: str
    algo: Algorithm
    runs: list[RunConfig]
    size: int

    def stacked(self) -> tuple[Any, jax.Array]:
        padded = self.runs + [self.runs[-1]] * (self.size - len(self.runs))
        configs = stack_configs([r.config for r in padded])
        keys = jnp.stack([jax.random.PRNGKey(r.seed) for r in padded])
        return configs, keys

    def pad(self, tree: Any) -> Any:
        """Rows of the real configurations, padded to the batch size with copies of the last one."""
        extra = self.size - len(self.runs)
        return jax.tree.map(lambda x: np.concatenate([x, np.repeat(x[-1:], extra, axis=0)]), tree)


def plan_batches(runs: Sequence[RunConfig], max_batch: int, num_devices: int = 1) -> list[Batch]:
    """Each compiled group split into batches of at most `max_batch` configurations (then padded to a multiple
    of `num_devices`, so every device gets an equal share)."""
    batches = []
    for group in group_runs(runs):
        algo = ALGORITHMS[group[0].agent]
        count = math.ceil(len(group) / max_batch)
        per_batch = math.ceil(len(group) / count)
        size = math.ceil(per_batch / num_devices) * num_devices
        for i in range(count):
            part = group[i * per_batch : (i + 1) * per_batch]
            batches.append(Batch(f"{group[0].agent}-{part[0].config_id}", algo, part, size))
    return batches


def compiled_programs(
    algo: Algorithm,
    chunk_evals: int,
    devices: tuple[jax.Device, ...] | None = None,
    strategy_name: str | None = None,
) -> tuple[Callable, Callable]:
    """Jitted init and chunk functions of an algorithm; cached so reruns in one process reuse the compiled
    programs (jax caches one per shape and static config). The chunk spreads the configurations over `devices`
    (default: `sweep_devices()`); give it arguments placed with `config_sharding(devices)`. Both trace with
    `strategy_name` (default: `amjax.strategy.current()`), whenever they are traced."""
    devices = tuple(devices or sweep_devices())
    return _compiled_programs(algo, chunk_evals, devices, strategy_name or strategy.current())


@functools.cache
def _compiled_programs(
    algo: Algorithm, chunk_evals: int, devices: tuple[jax.Device, ...], strategy_name: str
) -> tuple[Callable, Callable]:
    def init_one(config, key):
        with strategy.use(strategy_name):
            state = init_run(algo, config, key)
        # Plain (strongly typed) leaves, as the chunk program takes them: fresh states go to it without a host trip.
        return jax.tree.map(lambda x: jax.lax.convert_element_type(x, x.dtype), state)

    def chunk_one(config, state):
        with strategy.use(strategy_name):
            return run_evals(algo, config, state, chunk_evals)

    # Initialisation is vmapped like the chunk (the networks' initialisers are QR-free: no batched linear algebra,
    # so no jaxlib CPU deadlock, research notes). A loop over configurations (lax.map) would be compiled as one
    # kernel under amjax's small-loop option, body and all: 47 s instead of 17.5 for LunarLander-v3's Dueling DQN,
    # whose initialisation steps the envs (docs/lunar_lander.md, "Initialisation vmapped").
    init = jax.jit(jax.vmap(init_one))

    def chunk_batch(configs, states):
        # The step counters every configuration shares go in once, unbatched (`batching.shared_field`): branches
        # on them (learning has started, the target update) stay single conditionals, as in a plain implementation.
        return jax.vmap(chunk_one, in_axes=(0, member_axes(states)))(configs, take_shared(states))

    # Shardings pinned on both sides, so the states a chunk returns (zero-size arrays included, which XLA would
    # otherwise return replicated) are placed as the next chunk expects them.
    sharding = config_sharding(list(devices))
    chunk = sharded_jit(chunk_batch, list(devices), donate_argnums=1, in_shardings=sharding, out_shardings=sharding)
    return init, chunk


def rescore_program(algo: Algorithm, devices: tuple[jax.Device, ...], strategy_name: str | None = None) -> Callable:
    """Jitted re-scoring of every configuration's best policy (`training.rescore`), split over `devices`, traced
    with `strategy_name` (default: `amjax.strategy.current()`)."""
    return _rescore_program(algo, tuple(devices), strategy_name or strategy.current())


@functools.cache
def _rescore_program(algo: Algorithm, devices: tuple[jax.Device, ...], strategy_name: str) -> Callable:
    def rescore_one(config, state):
        with strategy.use(strategy_name):
            return rescore(algo, config, state)

    sharding = config_sharding(list(devices))
    return sharded_jit(jax.vmap(rescore_one), list(devices), in_shardings=sharding, out_shardings=sharding)


def release_programs() -> bool:
    """Drop every program compiled through `compiled_programs` and `rescore_program` if this process holds over half
    of the kernel's limit on memory mappings (`amjax.cores.maps_past_half`); returns whether it did.

    Their jitted functions are cached (so a batch of the same shapes and static config reuses its programs), and JAX
    keeps each executable they compiled loaded for as long as the function lives. So every finished batch's programs
    stay loaded (a LunarLander-v3 batch's take about 10,000 mappings), and a long sweep would pass the limit and
    die. Called after each batch; programs compiled ahead for later batches are kept (their queue holds them)."""
    if not maps_past_half():
        return False
    _compiled_programs.cache_clear()
    _rescore_program.cache_clear()
    gc.collect()  # the executables are freed with the functions' caches, some through reference cycles
    return True


@dataclass(frozen=True)
class BatchPrograms:
    """One batch's stacked configurations and keys (`Batch.stacked`) and its programs compiled for them:
    `init(configs, keys)`, `chunk(configs, states)` (train `evals_per_chunk` evaluation periods) and
    `rescore(configs, states)`. `chunk` and `rescore` take configs and plain (strongly typed) state arrays placed
    with `config_sharding(devices)`, as the runner passes them."""

    configs: Any
    keys: jax.Array
    init: Callable
    chunk: Callable
    rescore: Callable
    evals_per_chunk: int


# jaxlib 0.10.2 is not safe compiling two programs at once: the first compile of an operation in a process can fail
# ("Unable to convert MHLO to StableHLO", an "mhlo.unknown" op) while another thread compiles. Seen 2026-11-26: 4 tiny
# PPO batches compiled on 4 threads, 8 rounds after `jax.clear_caches()`: the first round failed in 2-3 threads
# (also after a DQN batch had compiled alone), every later round passed.
COMPILE_LOCK = threading.Lock()


def compile_batch(
    batch: Batch, target_chunks: int, devices: tuple[jax.Device, ...], strategy_name: str | None = None
) -> BatchPrograms:
    """Compile a batch's programs ahead of time (nothing is allocated or run: the train states are sized with
    `jax.eval_shape`), so that the sweep runner can compile the next batch on another thread while the current
    one trains (pass `strategy_name`, `amjax.strategy.current()` of the thread that asks, since a `strategy.use`
    block does not reach other threads). One compile at a time in the process (`COMPILE_LOCK`)."""
    evals_per_chunk = chunk_evals(batch.runs[0].config.num_evals, target_chunks)
    sharding = config_sharding(list(devices))

    def placed(tree: Any, weak: bool) -> Any:
        return jax.tree.map(
            lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sharding, weak_type=weak and x.weak_type), tree
        )

    with COMPILE_LOCK:
        init, chunk = compiled_programs(batch.algo, evals_per_chunk, devices, strategy_name)
        configs, keys = batch.stacked()
        states = placed(jax.eval_shape(init, configs, keys), weak=False)  # fresh or restored: plain arrays
        configs_placed = placed(configs, weak=True)
        return BatchPrograms(
            configs=configs,
            keys=keys,
            init=init.lower(configs, keys).compile(),
            chunk=chunk.lower(configs_placed, states).compile(),
            rescore=rescore_program(batch.algo, devices, strategy_name).lower(configs_placed, states).compile(),
            evals_per_chunk=evals_per_chunk,
        )


__all__ = [
    "COMPILE_LOCK",
    "Batch",
    "BatchPrograms",
    "chunk_evals",
    "compile_batch",
    "compiled_programs",
    "plan_batches",
    "release_programs",
    "rescore_program",
]
