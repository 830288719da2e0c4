"""Spreading a sweep's configurations over the CPU cores: one JAX CPU device per core, configurations sharded.

One XLA CPU program keeps about 1.4 of 2 cores busy on a vmapped sweep (many of its ops are too small to split),
so the runner splits a batch's configurations over the CPU devices with `jax.shard_map`: each device runs the same
vmapped program on its share, on its own core, with no communication between them. amjax asks JAX for one CPU
device per core when it is imported (`amjax.cores`); `JAX_NUM_CPU_DEVICES=1` keeps everything on one.
"""

from __future__ import annotations

import functools

import jax
import numpy as np
from jax.interpreters import mlir
from jax.sharding import Mesh, NamedSharding, PartitionSpec

CONFIG_AXIS = "configs"


def sweep_devices() -> list[jax.Device]:
    """The devices a sweep's configurations are spread over: every local device of the default backend."""
    return jax.local_devices()


def config_sharding(devices: list[jax.Device]) -> NamedSharding:
    """Arrays with a leading configuration axis, split evenly over `devices`."""
    return NamedSharding(Mesh(np.array(devices), (CONFIG_AXIS,)), PartitionSpec(CONFIG_AXIS))


def shard_configs(function, devices: list[jax.Device]):
    """`function` (vmapped over a leading configuration axis of every argument and output) run on each device's
    share of the configurations; the plain function when there is one device."""
    if len(devices) == 1:
        return function
    _lower_mulhi_without_chlo()
    sharding = config_sharding(devices)
    # check_vma=False: the configurations never talk to each other, so nothing varies across devices that the
    # program would need to know about (the check rejects while-loop carries that are created inside the body).
    return jax.shard_map(
        function, mesh=sharding.mesh, in_specs=sharding.spec, out_specs=sharding.spec, check_vma=False
    )


def _mulhi(x: jax.Array, y: jax.Array) -> jax.Array:
    """`lax.mulhi` (high half of the double-width product) in same-width integer arithmetic: half-width limbs."""
    bits = np.iinfo(x.dtype).bits
    unsigned = np.dtype(f"uint{bits}")
    half = np.array(bits // 2, unsigned)
    mask = np.array((1 << (bits // 2)) - 1, unsigned)
    xu, yu = jax.lax.convert_element_type(x, unsigned), jax.lax.convert_element_type(y, unsigned)
    x_lo, x_hi = xu & mask, xu >> half
    y_lo, y_hi = yu & mask, yu >> half
    lo_lo, lo_hi, hi_lo = x_lo * y_lo, x_lo * y_hi, x_hi * y_lo
    cross = (lo_lo >> half) + (lo_hi & mask) + (hi_lo & mask)  # < 3 * 2**(bits/2): no overflow
    high = x_hi * y_hi + (lo_hi >> half) + (hi_lo >> half) + (cross >> half)
    if np.issubdtype(x.dtype, np.signedinteger):  # signed product's high half: subtract y if x < 0, x if y < 0
        high = high - jax.numpy.where(x < 0, yu, 0).astype(unsigned) - jax.numpy.where(y < 0, xu, 0).astype(unsigned)
    return jax.lax.convert_element_type(high, x.dtype)


@functools.cache
def _lower_mulhi_without_chlo() -> None:
    """Lower `lax.mulhi` on CPU through plain integer ops instead of `chlo.mulhi`.

    jaxlib 0.10.2 cannot compile a sharded CPU program that holds `chlo.mulhi` ("Unable to convert MHLO to
    StableHLO"), and the trainers' Philox keys (`amjax.agents.rollout`) use it. The replacement computes the same
    bits (tests/sweep/test_devices.py); older jaxlibs lowered mulhi through plain ops too.
    """
    mlir.register_lowering(jax.lax.mulhi_p, mlir.lower_fun(_mulhi, multiple_results=False), platform="cpu")
