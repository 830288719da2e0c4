"""One JAX CPU device per core, on request: ``amjax.use_all_cores()``; small loops as one kernel, on import.

A vmapped sweep in one XLA CPU program keeps only about 1.4 of 2 cores busy (many of its ops are too small to
split), so the sweep runner spreads a batch's configurations over the CPU devices (``amjax.sweep.devices``), one
per core. JAX makes one CPU device unless told otherwise before its backend starts (the first JAX computation,
or importing gymnax, starts it). Importing amjax does not choose devices; the ``amjax`` command, the notebooks and
programs that want every core call ``use_all_cores()`` first. Programs that do not shard run on the first device.

XLA's CPU runtime runs a program kernel by kernel, a few hundred ns each, so a loop of small elementwise steps (the
LunarLander port's 180 constraint sweeps: ~100 kernels each) costs its kernel count, not its arithmetic. XLA compiles
a while loop into one kernel when the bytes it accesses are below ``xla_cpu_small_while_loop_byte_threshold``
(1 KiB by default; loops with dots, convolutions, scatters or custom calls never). ``import amjax`` raises the
threshold (``xla_cpu_options``) in ``XLA_FLAGS``, which XLA reads once, at the first compile.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
import platform
import re
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np


def usable_cores() -> int:
    """CPU cores this process may run on (its affinity mask where the OS has one)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def _cpuinfo(field: str) -> str | None:
    """The value of /proc/cpuinfo's first `field` line (its first CPU's), or None where there is none."""
    try:
        with open("/proc/cpuinfo") as cpuinfo:
            return next((line.split(":", 1)[1].strip() for line in cpuinfo if line.startswith(field)), None)
    except OSError:
        return None


def cpu_model() -> str:
    """The CPU's model name (/proc/cpuinfo's, else the platform's), e.g. "AMD EPYC". With `cpu_vector_isa` and the
    device count, what sets XLA's float rounding, so runs are bit-identical only where all three are the same."""
    return _cpuinfo("model name") or platform.processor() or platform.machine() or "unknown CPU"


# The widest x86 vector extension the CPU reports, as /proc/cpuinfo names it, and how we write it.
_VECTOR_ISAS = (("avx512f", "AVX-512"), ("avx2", "AVX2"), ("avx", "AVX"))


def cpu_vector_isa() -> str:
    """The widest x86 vector extension the CPU has ("AVX-512", "AVX2", "AVX"; "" where /proc/cpuinfo does not say).
    One model name can round differently: two 2-core "AMD EPYC" machines, one with AVX-512, trained the README's demo
    to different tables (2026-11-29). Not through XLA's own code (capped at AVX2 the AVX-512 machine prints the same
    table); the kernel libraries XLA calls pick their code on the running CPU (docs/results/benchmarks.md)."""
    flags = (_cpuinfo("flags") or "").split()
    return next((name for flag, name in _VECTOR_ISAS if flag in flags), "")


def cpu_description() -> str:
    """The CPU's model and widest vector extension, e.g. "AMD EPYC, AVX-512": the machine a result is bit for bit
    reproducible on (with the same device count)."""
    return ", ".join(filter(None, (cpu_model(), cpu_vector_isa())))


def memory_maps() -> tuple[int, int] | None:
    """This process's memory mappings and the kernel's limit on them (``vm.max_map_count``, 65,530 by default), or
    None where the OS does not say (not Linux).

    Every loaded XLA CPU executable keeps a few mappings per kernel (a tiny PPO training program about 900, the
    programs of a LunarLander-v3 sweep batch about 10,000), and past the limit LLVM cannot load the next program
    ("LLVM compilation error: Cannot allocate memory") and the process dies."""
    try:
        limit = int(Path("/proc/sys/vm/max_map_count").read_text())
        with open("/proc/self/maps", "rb") as maps:
            return sum(1 for _ in maps), limit
    except (OSError, ValueError):
        return None


def maps_past_half() -> bool:
    """Whether this process holds over half the kernel's limit on memory mappings (`memory_maps`; False where the
    OS does not say): past it, the sweep runner stops compiling ahead and drops the programs of finished batches."""
    maps = memory_maps()
    return maps is not None and maps[0] > maps[1] // 2


# Loops that access less than this many bytes per iteration (HloCostAnalysis) become one kernel each.
SMALL_LOOP_BYTES = 100_000_000
_SMALL_LOOP_OPTION = "xla_cpu_small_while_loop_byte_threshold"
XLA_CPU_FLAGS = f"--xla_backend_extra_options={_SMALL_LOOP_OPTION}={SMALL_LOOP_BYTES}"
# Opt-in, for programs that step the LunarLander port in large batches: reductions as XLA's own fused loops instead
# of calls into the YNNPACK library (XLA's CPU default). From a few hundred envs per core XLA sends the port's tiny
# reductions (collision: sums, minima, maxima over a few points) to YNNPACK, and each call costs more than the sum:
# 512 envs on one core ran 134 k -> 200 k env-steps/s with it (2026-11-25, a 2-core Intel Xeon); at 80 envs XLA
# makes no such calls and nothing changes. Not a default: the agents' own reductions gain from YNNPACK (PPO's
# minibatch steps ran 12% slower without it), so a trainer's program, which holds both, does not take it.
# Per program: `jax.jit(f, compiler_options=REDUCTIONS_IN_XLA)` (the list of YNNPACK fusion kinds reduced to the
# individual dots, which is XLA's default minus reductions); process-wide: `XLA_FLAGS=REDUCE_IN_XLA_FLAG`.
REDUCTIONS_IN_XLA: dict[str, str] = {"xla_cpu_experimental_ynn_fusion_type": "LIBRARY_FUSION_TYPE_INDIVIDUAL_DOT"}
REDUCE_IN_XLA_FLAG = "--xla_cpu_experimental_ynn_fusion_type=-reduce"
# True once `xla_cpu_options` added the option to this process's XLA_FLAGS after JAX had started (XLA ignores it).
_xla_options_late = False


def xla_cpu_options(environ: dict[str, str] | None = None) -> bool:
    """Add amjax's XLA CPU option (``XLA_CPU_FLAGS``) to ``XLA_FLAGS``; returns whether it is in effect for
    programs compiled from now on.

    ``xla_cpu_small_while_loop_byte_threshold=SMALL_LOOP_BYTES`` (one of ``--xla_backend_extra_options``): XLA
    compiles a while loop into one kernel when its body accesses fewer bytes than this (1 KiB by default).

    Called by ``import amjax``. It only edits the environment: JAX reads ``XLA_FLAGS`` at its first compile, so a
    process that compiled before importing amjax keeps XLA's default. A threshold the user set is kept, and
    ``AMJAX_XLA_OPTIONS=0`` leaves ``XLA_FLAGS`` alone. Results equal XLA's default to float rounding; PPO and
    Dueling DQN on CartPole train at the same speed either way.
    """
    environ = os.environ if environ is None else environ
    if environ.get("AMJAX_XLA_OPTIONS", "1") == "0":
        return False
    given = flags = environ.get("XLA_FLAGS", "")
    if _SMALL_LOOP_OPTION not in flags:
        option = f"{_SMALL_LOOP_OPTION}={SMALL_LOOP_BYTES}"
        match = re.search(r"--xla_backend_extra_options=(\S*)", flags)
        if match:  # XLA takes one comma-separated list of extra options
            joined = f"{match.group(0)},{option}" if match.group(1) else f"{match.group(0)}{option}"
            flags = flags.replace(match.group(0), joined)
        else:
            flags = f"{flags} --xla_backend_extra_options={option}"
    if flags == given:  # set before this process started (or by an earlier call)
        return True
    environ["XLA_FLAGS"] = flags.strip()
    late = _backend_started()
    if environ is os.environ:
        global _xla_options_late
        _xla_options_late = late
    return not late


def warn_if_xla_options_late(who: str) -> None:
    """A ``RuntimeWarning`` for ``who`` (an env that needs the options) when JAX compiled before ``import amjax``."""
    if _xla_options_late:
        warnings.warn(
            f"{who} runs 1.5-10x slower in this process: JAX compiled before amjax was imported, so XLA ignores "
            "amjax's XLA CPU option (amjax.cores.xla_cpu_options). Import amjax before running JAX code, or start "
            f"Python with XLA_FLAGS='{XLA_CPU_FLAGS}'",
            RuntimeWarning,
            stacklevel=3,
        )


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


def jit_one_kernel(fn: Callable[..., Any]) -> Callable[..., Any]:
    """``jax.jit(fn)`` compiled as one XLA CPU kernel, for a small program called one call at a time from Python.

    XLA's CPU runtime launches a program's fused operations one by one, a few hundred ns each: one LunarLander-v3
    step called from Python spends most of its time on its ~900 launches, not its arithmetic. Here ``fn`` is the
    body of a one-trip ``while`` loop whose trip count XLA cannot see (it is an argument), which the small-loop
    option (``xla_cpu_options``) compiles into a single kernel. Results equal ``jax.jit(fn)``'s to float rounding
    (the code is generated apart). No gain for programs whose loop XLA will not merge: over ``SMALL_LOOP_BYTES``
    per call, or holding dots, scatters or custom calls; and none without the option (``AMJAX_XLA_OPTIONS=0``).
    """
    traced: dict[str, Any] = {}  # the output's tree and each typed-key leaf's PRNG implementation, set when traced

    def output_leaves(*args: Any) -> list[jax.Array]:
        leaves, traced["tree"] = jax.tree.flatten(fn(*args))
        leaves, traced["key_impls"] = _keys_as_data(leaves)  # a loop carries no typed keys
        return leaves

    def looped(trips: jax.Array, *args: Any) -> Any:
        def body(i: jax.Array, carry: Any) -> Any:
            # The barrier ties the inputs to the counter, so XLA cannot hoist `fn` out of the loop.
            _, inputs = jax.lax.optimization_barrier((i, carry[0]))
            return carry[0], output_leaves(*inputs)

        zeros = [jnp.zeros(s.shape, s.dtype) for s in jax.eval_shape(output_leaves, *args)]
        leaves = jax.lax.fori_loop(0, trips, body, (args, zeros))[1]
        return jax.tree.unflatten(traced["tree"], _data_as_keys(leaves, traced["key_impls"]))

    compiled = jax.jit(looped)
    one = np.int32(1)

    @functools.wraps(fn)
    def call(*args: Any) -> Any:
        return compiled(one, *args)

    call.lower = lambda *args: compiled.lower(one, *args)  # for inspection, as a jitted function's
    return call


@dataclasses.dataclass(frozen=True)
class TreeLayout:
    """Where each leaf of a pytree lies in one uint32 vector: `pack` and `unpack`, bit-exact and traceable.

    A jitted call pays for every array it takes and returns (about 2 us each on CPU): one env's state, 20-odd
    leaves in and out, costs more than a LunarLander-v3 step compiled as one kernel. A caller that steps one
    env from Python (the Gymnasium bridge) keeps the state packed between calls and unpacks it inside the
    program. Elements of 4 or 8 bytes are bit-cast (one or two words each); bools, narrower integers and 16-bit
    floats take one word per element; typed PRNG keys travel as their key data. Build it with
    `TreeLayout.of(example)`; `pack` refuses a tree whose leaves differ from the example's in shape, dtype or key
    implementation (`check`; Python scalars and same-kind dtypes are cast). Weak types are not kept: unpacked
    leaves are strongly typed.
    """

    treedef: Any
    shapes: tuple[tuple[int, ...], ...]  # of each leaf (of its key data for a key)
    dtypes: tuple[np.dtype, ...]  # of each leaf (uint32 for a key's data)
    key_impls: tuple[Any, ...]  # each leaf's PRNG implementation, None where it is not a typed key

    @classmethod
    def of(cls, example: Any) -> TreeLayout:
        """The layout of `example`, a pytree of arrays, Python scalars or `jax.ShapeDtypeStruct`s."""
        leaves, treedef = jax.tree.flatten(example)
        impls: list[Any] = []

        def key_data(*leaves: Any) -> list[Any]:
            data, found = _keys_as_data(leaves)
            impls.extend(found)
            return data

        data = jax.eval_shape(key_data, *leaves)
        for x in data:
            kinds = (jnp.bool_, jnp.integer, jnp.floating)
            if (
                not any(jnp.issubdtype(x.dtype, kind) for kind in kinds)
                or np.dtype(x.dtype).itemsize == 1
                and jnp.issubdtype(x.dtype, jnp.floating)
            ):
                raise TypeError(
                    f"TreeLayout: a leaf of dtype {x.dtype}; allowed: bool, integer and floating leaves "
                    "(floats of 16 bits or more), and typed PRNG keys"
                )
        return cls(treedef, tuple(tuple(x.shape) for x in data), tuple(np.dtype(x.dtype) for x in data), tuple(impls))

    @property
    def size(self) -> int:
        """Words (uint32) in the packed vector."""
        return sum(_words(shape, dtype) for shape, dtype in zip(self.shapes, self.dtypes, strict=True))

    def check(self, tree: Any) -> None:
        """ValueError naming the first leaf of `tree` whose structure, shape, dtype or key implementation differs
        from the example's. Python scalars may stand for any 0-d leaf that is not a key, and a leaf of a dtype that
        casts to the example's by NumPy's "same_kind" rule (int32 to float32, not float32 to int32) is cast."""
        try:
            leaves = self.treedef.flatten_up_to(tree)
        except (ValueError, TypeError) as error:
            raise ValueError(f"TreeLayout: the tree's structure differs from the example's: {error}") from None
        paths = [
            jax.tree_util.keystr(path)
            for path, _ in jax.tree_util.tree_flatten_with_path(jax.tree.unflatten(self.treedef, range(len(leaves))))[0]
        ]
        for path, x, shape, dtype, impl in zip(paths, leaves, self.shapes, self.dtypes, self.key_impls, strict=True):
            scalar = isinstance(x, bool | int | float) and impl is None and shape == ()
            if scalar:
                continue
            if impl is not None:
                got = (jax.random.key_impl(x), tuple(jax.random.key_data(x).shape)) if _is_key(x) else (None, None)
                expected = (impl, shape)
            else:
                got = ("array", tuple(jnp.shape(x)), np.dtype(x.dtype)) if not _is_key(x) else ("key",)
                expected = ("array", shape, dtype)
                if got[:2] == expected[:2] and np.can_cast(got[2], dtype, "same_kind"):
                    continue  # cast by `pack`, e.g. an int32 cost for a float32 leaf
            if got != expected:
                raise ValueError(f"TreeLayout: leaf {path or '(root)'} is {got}; the layout expects {expected}")

    def pack(self, tree: Any) -> jax.Array:
        """`tree` (laid out as the example; see `check`) as one uint32 vector of `size` words."""
        self.check(tree)
        leaves = self.treedef.flatten_up_to(tree)
        parts = [
            _to_words(jax.random.key_data(x) if impl is not None else jnp.asarray(x, dtype))
            for x, dtype, impl in zip(leaves, self.dtypes, self.key_impls, strict=True)
        ]
        return jnp.concatenate(parts) if parts else jnp.zeros(0, jnp.uint32)

    def unpack(self, words: jax.Array) -> Any:
        """The pytree that `pack` made `words` from."""
        if jnp.shape(words) != (self.size,) or jnp.result_type(words) != jnp.uint32:
            raise ValueError(
                f"TreeLayout.unpack: words of shape {jnp.shape(words)} and dtype "
                f"{jnp.result_type(words)}; the layout packs to uint32[{self.size}]"
            )
        leaves, start = [], 0
        for shape, dtype in zip(self.shapes, self.dtypes, strict=True):
            stop = start + _words(shape, dtype)
            leaves.append(_from_words(words[start:stop], shape, dtype))
            start = stop
        return jax.tree.unflatten(self.treedef, _data_as_keys(leaves, self.key_impls))


def _words(shape: tuple[int, ...], dtype: np.dtype) -> int:
    return math.prod(shape) * max(1, dtype.itemsize // 4)


def _to_words(x: jax.Array) -> jax.Array:
    if x.dtype.itemsize >= 4:  # 8-byte leaves (x64) become two words each
        return jax.lax.bitcast_convert_type(x, jnp.uint32).ravel()
    if jnp.issubdtype(x.dtype, jnp.floating):  # float16, bfloat16
        x = jax.lax.bitcast_convert_type(x, jnp.uint16)
    elif jnp.issubdtype(x.dtype, jnp.signedinteger):
        return jax.lax.bitcast_convert_type(x.astype(jnp.int32), jnp.uint32).ravel()
    return x.astype(jnp.uint32).ravel()


def _from_words(words: jax.Array, shape: tuple[int, ...], dtype: np.dtype) -> jax.Array:
    if dtype.itemsize >= 4:
        per_leaf = dtype.itemsize // 4
        return jax.lax.bitcast_convert_type(words.reshape(shape + ((per_leaf,) if per_leaf > 1 else ())), dtype)
    words = words.reshape(shape)
    if dtype == np.bool_:
        return words != 0
    if jnp.issubdtype(dtype, jnp.floating):
        return jax.lax.bitcast_convert_type(words.astype(jnp.uint16), dtype)
    if jnp.issubdtype(dtype, jnp.signedinteger):
        return jax.lax.bitcast_convert_type(words, jnp.int32).astype(dtype)
    return words.astype(dtype)


def _is_key(x: Any) -> bool:
    return jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)


def _keys_as_data(leaves: list[Any]) -> tuple[list[Any], list[Any]]:
    """`leaves` with each typed PRNG key replaced by its key data, and each leaf's PRNG implementation (None where
    it is not a key); `_data_as_keys` undoes it."""
    impls = [jax.random.key_impl(x) if _is_key(x) else None for x in leaves]
    return [x if impl is None else jax.random.key_data(x) for x, impl in zip(leaves, impls, strict=True)], impls


def _data_as_keys(leaves: list[Any], impls: Any) -> list[Any]:
    return [
        x if impl is None else jax.random.wrap_key_data(x, impl=impl) for x, impl in zip(leaves, impls, strict=True)
    ]
