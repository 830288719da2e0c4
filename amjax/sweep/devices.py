"""Spreading a sweep's configurations over the CPU cores: one JAX CPU device per core, configurations sharded.

One XLA CPU program keeps about 1.4 of 2 cores busy on a vmapped sweep (many of its ops are too small to split),
so the runner splits a batch's configurations over the CPU devices with `jax.shard_map`: each device runs the same
vmapped program on its share, on its own core, with no communication between them. JAX has one CPU device per
core after `amjax.use_all_cores()` (`amjax.cores`; the `amjax` command calls it), otherwise one.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from typing import Any

import jax
import jaxlib
import numpy as np
from jax.extend.mlir.dialects import stablehlo
from jax.interpreters import mlir
from jax.interpreters.mlir import ir
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
    sharding = config_sharding(devices)
    # check_vma=False: the configurations never talk to each other, so nothing varies across devices that the
    # program would need to know about (the check rejects while-loop carries that are created inside the body).
    return jax.shard_map(function, mesh=sharding.mesh, in_specs=sharding.spec, out_specs=sharding.spec, check_vma=False)


def _mulhi(x: jax.Array, y: jax.Array) -> jax.Array:
    """`lax.mulhi` (high half of the double-width product) in same-width integer arithmetic: half-width limbs.
    Only for 64-bit integers (`_mulhi_lowering` widens narrower ones): about 20 ops where a widening multiply is 4."""
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


_mulhi_limbs_lowering = mlir.lower_fun(_mulhi, multiple_results=False)


def _mulhi_lowering(ctx: Any, x: Any, y: Any) -> Any:
    """`lax.mulhi` of integers up to 32 bits as stablehlo ops: both sides widened to twice the width, multiplied,
    shifted down and narrowed (the same bits as `chlo.mulhi`: see tests/sweep/test_devices.py); 64-bit ones through
    `_mulhi`'s limbs (no 128-bit integers in XLA).

    Not `_mulhi` for every width: its ~20 ops per call, times Philox's 10 rounds per draw, made a Dueling DQN chunk
    with instruments (many draws per step) too large for LLVM once XLA compiled its env loop as one kernel (the
    small-loop option, `amjax.cores`): the sharded compile ran past 10 min where this one takes 13 s."""
    out = ctx.avals_out[0]
    bits = np.dtype(out.dtype).itemsize * 8
    if bits > 32:
        return _mulhi_limbs_lowering(ctx, x, y)
    out_type = mlir.aval_to_ir_type(ctx.module_context, out)
    signed = np.issubdtype(out.dtype, np.signedinteger)
    wide_element = ir.IntegerType.get_signless(2 * bits) if signed else ir.IntegerType.get_unsigned(2 * bits)
    wide = ir.RankedTensorType.get(list(out.shape), wide_element)

    def widened(operand: Any, aval: Any) -> Any:
        if tuple(aval.shape) != tuple(out.shape):  # a scalar (or size-1 axes) broadcast as lax.mulhi allows
            dims = list(range(len(out.shape) - len(aval.shape), len(out.shape)))
            operand = stablehlo.broadcast_in_dim(out_type, operand, dims)
        return stablehlo.convert(wide, operand)

    product = stablehlo.multiply(*(widened(v, a) for v, a in zip((x, y), ctx.avals_in, strict=True)))
    shift = stablehlo.constant(ir.DenseElementsAttr.get_splat(wide, ir.IntegerAttr.get(wide_element, bits)))
    high = (stablehlo.shift_right_arithmetic if signed else stablehlo.shift_right_logical)(product, shift)
    return [stablehlo.convert(out_type, high)]


# jaxlib 0.10.2 cannot compile a sharded CPU program that holds `chlo.mulhi` ("Unable to convert MHLO to
# StableHLO"), and the trainers' Philox keys (`amjax.agents.rollout`) use it. Versions before 0.10 lowered mulhi
# through plain ops; the later versions amjax allows (< 0.12) are assumed to need the same until checked.
_MULHI_NEEDS_PLAIN_LOWERING = tuple(int(p) for p in jaxlib.__version__.split(".")[:2]) >= (0, 10)


@contextlib.contextmanager
def _mulhi_lowered_without_chlo() -> Iterator[None]:
    """While open, `lax.mulhi` lowers on CPU through plain stablehlo ops (`_mulhi_lowering`, the same bits)
    instead of `chlo.mulhi`; the previous lowering is restored on exit, so programs outside amjax's sharded sweeps
    are lowered as JAX would lower them."""
    if not _MULHI_NEEDS_PLAIN_LOWERING:
        yield
        return
    rules = mlir._platform_specific_lowerings["cpu"]
    previous = rules.get(jax.lax.mulhi_p)
    mlir.register_lowering(jax.lax.mulhi_p, _mulhi_lowering, platform="cpu")
    try:
        yield
    finally:
        if previous is None:
            rules.pop(jax.lax.mulhi_p, None)
        else:
            rules[jax.lax.mulhi_p] = previous


class sharded_jit:  # noqa: N801 (used like jax.jit)
    """`jax.jit(shard_configs(function, devices), **jit_kwargs)`, traced and lowered with the mulhi workaround
    (`_mulhi_lowered_without_chlo`) applied to this program only."""

    def __init__(self, function: Callable, devices: list[jax.Device], **jit_kwargs: Any):
        self._jitted = jax.jit(shard_configs(function, devices), **jit_kwargs)
        self._sharded = len(devices) > 1

    def _scope(self) -> contextlib.AbstractContextManager:
        return _mulhi_lowered_without_chlo() if self._sharded else contextlib.nullcontext()

    def __call__(self, *args: Any) -> Any:
        with self._scope():
            return self._jitted(*args)

    def lower(self, *args: Any) -> Any:
        with self._scope():
            return self._jitted.lower(*args)
