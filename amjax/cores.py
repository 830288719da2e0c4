"""One JAX CPU device per core, on request: ``amjax.use_all_cores()``.

A vmapped sweep in one XLA CPU program keeps only about 1.4 of 2 cores busy (many of its ops are too small to
split), so the sweep runner spreads a batch's configurations over the CPU devices (``amjax.sweep.devices``), one
per core. JAX makes one CPU device unless told otherwise before its backend starts (the first JAX computation,
or importing gymnax, starts it). Importing amjax changes nothing; the ``amjax`` command, the notebooks and
programs that want every core call ``use_all_cores()`` first. Programs that do not shard run on the first device.
"""

from __future__ import annotations

import os
import re
import warnings

import jax


def usable_cores() -> int:
    """CPU cores this process may run on (its affinity mask where the OS has one)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def _backend_started() -> bool:
    from jax._src import xla_bridge  # JAX has no public "has the backend started" query

    return xla_bridge.backends_are_initialized()


def use_all_cores() -> int:
    """Ask JAX for one CPU device per usable core; returns the number of CPU devices JAX will have.

    Call it before JAX starts: before importing gymnax or ``amjax.envs`` / ``amjax.agents`` / ``amjax.sweep`` and
    before any JAX computation. A count the user chose already (``JAX_NUM_CPU_DEVICES``, the ``jax_num_cpu_devices``
    option or ``XLA_FLAGS=--xla_force_host_platform_device_count``) is kept. Once JAX has started, its devices stay
    as they are and a ``RuntimeWarning`` says how to get every core.
    """
    chosen = jax.config.jax_num_cpu_devices
    forced = "xla_force_host_platform_device_count" in os.environ.get("XLA_FLAGS", "")
    if _backend_started():
        count = len(jax.devices("cpu"))
        if count < usable_cores() and chosen == -1 and not forced:
            warnings.warn(
                f"amjax.use_all_cores(): JAX has already started with {count} CPU device(s) of {usable_cores()} "
                "cores; call it before importing gymnax or running any JAX code (or set JAX_NUM_CPU_DEVICES)",
                RuntimeWarning,
                stacklevel=2,
            )
        return count
    if chosen != -1:
        return chosen
    if forced:
        return int(re.search(r"device_count=(\d+)", os.environ["XLA_FLAGS"]).group(1))
    jax.config.update("jax_num_cpu_devices", usable_cores())
    return usable_cores()
