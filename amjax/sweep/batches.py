"""A sweep's compiled batches: how its configurations are grouped into padded batches, and the jitted programs
that initialise and train one batch (the pieces the runner drives and the benchmarks time)."""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from amjax.agents import ALGORITHMS, Algorithm, init_run, run_evals, stack_configs
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


@functools.cache
def compiled_programs(
    algo: Algorithm, chunk_evals: int, devices: tuple[jax.Device, ...] | None = None
) -> tuple[Callable, Callable]:
    """Jitted init and chunk functions of an algorithm; cached so reruns in one process reuse the compiled
    programs (jax caches one per shape and static config). The chunk spreads the configurations over `devices`
    (default: `sweep_devices()`); give it arguments placed with `config_sharding(devices)`."""
    devices = list(devices or sweep_devices())
    # Initialisation runs configuration by configuration (lax.map), not vmapped: cheap, and it keeps batched
    # linear algebra out of network initialisation (the jaxlib CPU deadlock in the research notes).
    init = jax.jit(lambda configs, keys: jax.lax.map(lambda ck: init_run(algo, *ck), (configs, keys)))
    batched_chunk = jax.vmap(lambda config, state: run_evals(algo, config, state, chunk_evals))
    # Shardings pinned on both sides, so the states a chunk returns (zero-size arrays included, which XLA would
    # otherwise return replicated) are placed as the next chunk expects them.
    sharding = config_sharding(devices)
    chunk = sharded_jit(batched_chunk, devices, donate_argnums=1, in_shardings=sharding, out_shardings=sharding)
    return init, chunk


__all__ = ["Batch", "chunk_evals", "compiled_programs", "plan_batches"]
