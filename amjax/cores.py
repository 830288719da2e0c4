"""One JAX CPU device per core, chosen when amjax is imported (before gymnax starts JAX's backend).

A vmapped sweep in one XLA CPU program keeps only about 1.4 of 2 cores busy (many of its ops are too small to
split), so the sweep runner spreads a batch's configurations over the CPU devices (`amjax.sweep.devices`), one
per core. JAX makes one CPU device unless told otherwise before it starts, and importing gymnax starts it, so
amjax asks for one device per usable core on import, unless the user has chosen a count already
(`JAX_NUM_CPU_DEVICES=1 python ...` keeps one device; so does `jax.config.update("jax_num_cpu_devices", 1)`
before importing amjax) or JAX has already started. Programs that do not shard run on the first device, as usual.
"""

from __future__ import annotations

import contextlib
import os

import jax


def usable_cores() -> int:
    """CPU cores this process may run on (its affinity mask where the OS has one)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def default_cpu_devices() -> None:
    """Ask JAX for one CPU device per usable core unless a count was chosen or JAX has already started."""
    if jax.config.jax_num_cpu_devices != -1 or "xla_force_host_platform_device_count" in os.environ.get(
        "XLA_FLAGS", ""
    ):
        return
    with contextlib.suppress(RuntimeError):  # JAX's backend has already started: its devices stay as they are
        jax.config.update("jax_num_cpu_devices", usable_cores())
