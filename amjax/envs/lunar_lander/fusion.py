"""How the port's step compiles: fusion boundaries, and loop carries that ``shard_map`` accepts."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

from amjax import strategy
from amjax.batching import varying_axes


def materialized(fn: Callable, *operands: Any) -> Any:
    """``fn(*operands)`` with its outputs computed once, not re-derived inside each consumer kernel.

    XLA's CPU fusion duplicates elementwise producers into their consumers. Compiled plainly, one velocity
    iteration became 46 kernels that each recomputed most of the Gauss-Seidel chain before it (5,474 fused
    operations per env), and each output of a position solve recomputed the solve's sines and cosines. A
    conditional is a fusion boundary, so ``fn`` runs behind an always-taken ``lax.cond`` on an opaque unbatched
    zero (an ``optimization_barrier``: XLA cannot fold it, and under ``vmap`` it stays a branch, not a select).
    The same arithmetic, faster to run and to compile (measurements in docs/lunar_lander.md).

    Under the ``"gpu"`` strategy (`amjax.strategy`) ``fn`` runs plainly: a GPU reads a conditional's predicate back
    to the host before it branches, one round trip per solve (over a thousand per step), and recomputing a
    producer inside its consumers costs a GPU far less than launching kernels to store it.
    """
    if strategy.is_gpu():
        return fn(*operands)
    fn = jax.jit(fn)  # traced once: the branch below reuses the trace that eval_shape made

    def never(*ops):
        # Zeros shaped like fn's outputs that, under shard_map, vary over the operands' manual axes as fn's outputs
        # do (the branches' types must agree).
        zeros = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), jax.eval_shape(fn, *ops))
        return vary_together((zeros, ops))[0]

    return jax.lax.cond(jax.lax.optimization_barrier(jnp.int32(0)) >= 0, fn, never, *operands)


def vary_together(tree: Any) -> Any:
    """``tree`` with every leaf varying over ``shard_map``'s manual axes as much as any leaf does.

    A loop carry or branch output that starts from constants (a fresh reset's zero impulses) but meets varying
    values fails ``jax.shard_map``'s default ``check_vma=True``. The leaves that vary less are cast with
    ``jax.lax.pcast`` (no computation); outside ``shard_map`` the tree is returned as arrays, unchanged.
    """
    leaves, treedef = jax.tree.flatten(tree)
    leaves = [jnp.asarray(leaf) for leaf in leaves]
    axes = frozenset().union(*(varying_axes(leaf) for leaf in leaves))

    def vary(x):
        missing = axes - varying_axes(x)
        return jax.lax.pcast(x, tuple(sorted(missing)), to="varying") if missing else x

    return jax.tree.unflatten(treedef, [vary(leaf) for leaf in leaves])
