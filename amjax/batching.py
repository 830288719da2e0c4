"""Control flow that stays cheap under ``vmap``: branches, compacted selects and grouped batches.

Under ``vmap`` a ``lax.cond`` with a batched predicate becomes a select that computes both branches for every
member. The functions here are ``custom_vmap`` rules that keep the work proportional to what the members need:

- ``uniform_cond``: a branch that computes only the branches some member takes (both, then a select, only where
  members disagree), at every level of nested ``vmap``;
- ``update_where``: a state updated where a predicate holds and kept where not, laid out so that XLA updates it in
  place (no copy of the state per call: a learning step's parameters and optimiser state, a replay buffer);
- ``select_compacted``: per member ``expensive`` where a predicate holds and ``cheap`` elsewhere, running
  ``expensive`` only on the members that need it, gathered in chunks of a smaller batch;
- ``in_groups``: a batch run in cache-sized groups instead of all at once (under the ``"cpu"`` strategy only:
  `amjax.strategy`).

A predicate that is not batched (one every member shares: a ``shared_field`` step counter's) makes each of them one
branch over the whole batch, which an outer ``vmap`` level batches by the same rule again.

The functions passed in must be pure functions of their operands (pass traced values as operands, do not close
over them), as ``custom_vmap`` requires. Each is traced once, at its operands' per-member types: ``custom_vmap``
needs the unbatched program and its rule the batched one, and the rule replays the recorded program under ``vmap``
instead of running the Python function a second time (for LunarLander's step, whose rules nest, this cuts the
trace of a vmapped step by about a third).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from jax.extend.core import jaxpr_as_fun

from amjax import strategy


def varying_axes(x: Any) -> frozenset:
    """The ``shard_map`` manual axes that ``x`` varies over (empty outside ``shard_map``)."""
    aval = jax.typeof(x)
    axis_type = getattr(aval, "manual_axis_type", None)
    return frozenset(axis_type.varying if axis_type is not None else getattr(aval, "vma", ()))


def _traced(fun: Callable, *operands: Any) -> Callable:
    """``fun`` traced once at the per-member types of ``operands`` (tracers of an enclosing ``vmap`` give their
    member's type); the result replays the recorded jaxpr, source lines included, on operands of the same
    structure, and a ``vmap`` of it batches that jaxpr without running ``fun``'s Python again.

    Under ``shard_map`` the recorded program holds the casts that its operands' varying manual axes needed then.
    Operands that vary over other axes (rows gathered by a varying index vary even where the operand did not) run
    ``fun`` itself, which casts for them, so the default ``check_vma=True`` holds."""
    closed, out_shape = jax.make_jaxpr(fun, return_shape=True)(*operands)
    replay, out_tree = jaxpr_as_fun(closed), jax.tree.structure(out_shape)
    recorded = [varying_axes(leaf) for leaf in jax.tree.leaves(operands)]

    def call(*args):
        leaves = jax.tree.leaves(args)
        if [varying_axes(leaf) for leaf in leaves] != recorded:
            return fun(*args)
        return jax.tree.unflatten(out_tree, replay(*leaves))

    return call


def _broadcast(operands: Sequence[Any], batched: Sequence[Any], axis_size: int) -> list[Any]:
    """Operands with the vmapped axis in front of every leaf (unbatched leaves broadcast)."""
    return [
        jax.tree.map(lambda x, b: x if b else jnp.broadcast_to(x, (axis_size, *jnp.shape(x))), op, flags)
        for op, flags in zip(operands, batched, strict=True)
    ]


def _cond_with_vmap_rule(
    true_fun: Callable, false_fun: Callable, batched: Callable, lifted: Callable, branch: Callable | None = None
) -> Callable:
    """``lax.cond(pred, true_fun, false_fun, *operands)`` (or ``branch(pred, *operands)``, the same function laid
    out otherwise) whose vmap rule is ``batched(pred, *operands)`` for a batched predicate and
    ``lifted(pred, *operands)`` for an unbatched one (a predicate every member shares: a `shared_field` step
    counter's), both called with the vmapped axis in front of every operand leaf (and of the predicate). ``lifted``
    is the same helper over ``vmap``'s of the functions: one branch for the whole batch, which an outer ``vmap``
    batches by the helper's own rule again, not into a select."""

    @jax.custom_batching.custom_vmap
    def cond(pred, *operands):
        if branch is not None:
            return branch(pred, *operands)
        return jax.lax.cond(pred, true_fun, false_fun, *operands)

    @cond.def_vmap
    def rule(axis_size, in_batched, pred, *operands):
        pred_batched, *operands_batched = in_batched
        operands = _broadcast(operands, operands_batched, axis_size)
        out = batched(pred, *operands) if pred_batched else lifted(pred, *operands)
        return out, _all_batched(out)

    return cond


def _all_batched(tree: Any) -> Any:
    return jax.tree.map(lambda _: True, tree)


def _select(pred: jax.Array, on_true: Any, on_false: Any) -> Any:
    """Per member of the leading axis: ``on_true`` where ``pred`` else ``on_false``."""
    return jax.tree.map(lambda a, b: jnp.where(pred.reshape(-1, *[1] * (jnp.ndim(a) - 1)), a, b), on_true, on_false)


def uniform_cond(pred: jax.Array, true_fun: Callable, false_fun: Callable, *operands: Any) -> Any:
    """``lax.cond(pred, true_fun, false_fun, *operands)`` that stays a branch under ``vmap``.

    With a batched predicate it computes ``true_fun`` for the batch when every member takes it, ``false_fun`` when
    none does, and both (then selects per member) only when members disagree; the reduced predicates are themselves
    ``uniform_cond`` predicates, so nested ``vmap`` levels (configurations x envs) stay branches too. Used for
    predicates that are usually equal across a batch (DQN's "learning has started", an auto-reset that only some
    envs need). Under the ``"gpu"`` strategy a batch takes one three-way conditional (all, some or none of its
    members take ``true_fun``) instead of nested ones.
    """

    true_fun, false_fun = _traced(true_fun, *operands), _traced(false_fun, *operands)
    true_all, false_all = jax.vmap(true_fun), jax.vmap(false_fun)

    def mixed(pred, *operands):
        return _select(pred, true_all(*operands), false_all(*operands))

    def batched(pred, *operands):
        if strategy.is_gpu():
            # One conditional (a GPU reads its index back to the host before branching): `true_fun` alone when
            # every member takes it, both and a select when members disagree, `false_fun` alone when none does.
            # (A select where all agree would copy every output: the parameters and optimiser state of a learning
            # step, a recurrent agent's whole replay buffer.)
            index = jnp.where(jnp.all(pred), 0, jnp.where(jnp.any(pred), 1, 2))
            branches = (lambda _, *operands: true_all(*operands), mixed, lambda _, *operands: false_all(*operands))
            return jax.lax.switch(index, branches, pred, *operands)
        return uniform_cond(
            jnp.all(pred),
            lambda _, *operands: true_all(*operands),
            lambda pred, *operands: uniform_cond(
                jnp.any(pred), mixed, lambda _, *operands: false_all(*operands), pred, *operands
            ),
            pred,
            *operands,
        )

    def lifted(pred, *operands):
        return uniform_cond(pred, true_all, false_all, *operands)

    return _cond_with_vmap_rule(true_fun, false_fun, batched, lifted)(pred, *operands)


def update_where(pred: jax.Array, update: Callable, state: Any, *args: Any) -> Any:
    """``update(state, *args)`` (a new state of the same structure) where ``pred`` holds, else ``state`` unchanged:
    ``lax.cond(pred, update, keep, state, *args)`` that stays a branch under ``vmap`` and updates in place.

    With an unbatched predicate (a ``shared_field`` step counter's, as in a sweep batch) it is one branch over the
    batch: a conditional, or under the ``"gpu"`` strategy a loop of at most one iteration (`_update_once`). With a
    batched one, that branch runs ``update`` for the batch when every member takes it (else keeps the state), then
    a loop of at most one iteration updates and selects per member when they disagree. A `uniform_cond` with a
    pass-through branch copies what passes through: XLA compiles a conditional whose branches disagree among
    several into fresh output buffers, which a loop-carried state (a learning step's parameters and optimiser
    state, DRQN's replay buffer) then copies back into its own at every iteration. Here the branch is
    all-or-nothing and the disagreeing case is a loop, which XLA updates in place; a batch that agrees pays neither
    the copy nor a select. Outer ``vmap`` levels reduce their predicates the same way.
    """
    update = _traced(update, state, *args)
    update_all = jax.vmap(update)

    def keep(state: Any, *_: Any) -> Any:
        return state

    def batched(pred: jax.Array, state: Any, *args: Any) -> Any:
        every = jnp.all(pred)
        state = update_where(every, update_all, state, *args)

        def disagreeing(carry: tuple[jax.Array, Any]) -> tuple[jax.Array, Any]:
            flag, state = carry  # the state unchanged by the conditional above, which kept it
            return flag & False, _select(pred, update_all(state, *args), state)  # `&`: keeps shard_map's axes

        return jax.lax.while_loop(lambda carry: carry[0], disagreeing, (jnp.any(pred) & ~every, state))[1]

    def lifted(pred: jax.Array, state: Any, *args: Any) -> Any:
        return update_where(pred, update_all, state, *args)

    def branch(pred: jax.Array, state: Any, *args: Any) -> Any:
        if strategy.is_gpu():
            return _update_once(pred, update, state, *args)
        return jax.lax.cond(pred, update, keep, state, *args)

    return _cond_with_vmap_rule(update, keep, batched, lifted, branch)(pred, state, *args)


def _update_once(pred: jax.Array, update: Callable, state: Any, *args: Any) -> Any:
    """``update(state, *args)`` where ``pred`` holds, else ``state``, as a loop of at most one iteration: the
    ``"gpu"`` strategy's branch of `update_where`. XLA's GPU compiler gives a conditional fresh output buffers, so
    a loop-carried state that goes through one is copied at every iteration, into the conditional's operands and,
    in a branch that keeps it, into its outputs (a Dueling DQN update's parameters, Adam's moments and target
    network: four copies of every parameter); a loop updates its state in place. Its predicate is read back to the
    host (twice where ``pred`` holds, once where not) unless XLA records the loop into a command buffer, which by
    default it does for a conditional and not for a loop (`benchmarks/gpu_thunks.py`): the price of the copies
    it saves."""

    def once(carry: tuple[jax.Array, Any]) -> tuple[jax.Array, Any]:
        flag, state = carry
        return flag & False, update(state, *args)  # `&`: keeps shard_map's axes

    return jax.lax.while_loop(lambda carry: carry[0], once, (jnp.asarray(pred, bool), state))[1]


_SHARED = "amjax_shared_by_batch"


def shared_field(**kwargs: Any) -> Any:
    """A field of a ``flax.struct`` dataclass that every member of a batch holds equal: a step counter, which the
    configurations of a sweep batch advance together. A ``vmap`` with ``member_axes``'s axes takes it once,
    unbatched, so a branch on it (learning has started, the target update) stays one conditional, as in a plain
    implementation with one counter."""
    return struct.field(metadata={_SHARED: True}, **kwargs)


def _is_dataclass(node: Any) -> bool:
    return dataclasses.is_dataclass(node) and not isinstance(node, type)


def member_axes(tree: Any) -> Any:
    """``vmap`` axes of a batch of ``tree``s stacked on a leading axis: ``None`` at the ``shared_field`` fields of
    its dataclasses, 0 at every other leaf."""
    if _is_dataclass(tree):
        fields = [f for f in dataclasses.fields(tree) if f.init and f.metadata.get("pytree_node", True)]
        return tree.replace(
            **{f.name: None if f.metadata.get(_SHARED) else member_axes(getattr(tree, f.name)) for f in fields}
        )
    return jax.tree.map(lambda node: member_axes(node) if _is_dataclass(node) else 0, tree, is_leaf=_is_dataclass)


def take_shared(batch: Any) -> Any:
    """A stacked ``batch`` whose ``shared_field`` leaves are its first member's, unbatched (``member_axes``)."""
    return jax.tree.map(
        lambda axis, x: x if axis == 0 or x is None else x[0], member_axes(batch), batch, is_leaf=lambda a: a is None
    )


def shared_disagreements(batch: Any) -> list[str]:
    """The ``shared_field`` leaves of a stacked ``batch`` (host arrays) whose members differ, as paths (none in a
    batch that ``take_shared`` may take from its first member)."""
    differ = []

    def check(path: Any, axis: Any, x: Any) -> None:
        if axis is None and x is not None and not np.all(np.asarray(x) == np.asarray(x)[:1]):
            differ.append(jax.tree_util.keystr(path))

    jax.tree_util.tree_map_with_path(check, member_axes(batch), batch, is_leaf=lambda a: a is None)
    return differ


def select_compacted(
    pred: jax.Array,
    expensive: Callable,
    cheap: Callable,
    *operands: Any,
    capacity: float = 1 / 16,
    min_chunk: int = 16,
) -> Any:
    """``expensive(*operands)`` where ``pred`` holds, else ``cheap(*operands)``; under ``vmap``, ``expensive`` runs
    only on the members that need it.

    Unbatched this is ``lax.cond``. Under ``vmap`` (any nesting, all levels flattened into one batch of N members)
    ``cheap`` runs on every member; the members whose ``pred`` holds are gathered in chunks of ``max(ceil(capacity
    * N), min_chunk)`` rows, ``expensive`` runs on one chunk per iteration of a loop (as many iterations as the
    members need, none when no member does) and its results are scattered back. ``expensive`` is compiled once,
    at the chunk size, whatever the number of members that take it. A chunk of N or more rows runs ``expensive``
    on every member (when any needs it) and selects.
    """
    if not 0 < capacity <= 1:
        raise ValueError(f"capacity must be in (0, 1], got {capacity!r}")
    if isinstance(min_chunk, bool) or not isinstance(min_chunk, int) or min_chunk < 1:
        raise ValueError(f"min_chunk must be an int >= 1, got {min_chunk!r}")
    expensive, cheap = _traced(expensive, *operands), _traced(cheap, *operands)
    batched = _compacted_rows(expensive, cheap, capacity, min_chunk)

    def lifted(pred, *operands):
        expensive_all, cheap_all = jax.vmap(expensive), jax.vmap(cheap)
        return select_compacted(pred, expensive_all, cheap_all, *operands, capacity=capacity, min_chunk=min_chunk)

    return _cond_with_vmap_rule(expensive, cheap, batched, lifted)(pred, *operands)


def _compacted_rows(expensive: Callable, cheap: Callable, capacity: float, min_chunk: int) -> Callable:
    """``select_compacted`` over the leading axis of its operands; further ``vmap`` levels are flattened into it."""

    @jax.custom_batching.custom_vmap
    def rows(pred, *operands):
        n = pred.shape[0]
        cheap_out = jax.vmap(cheap)(*operands)
        count = jnp.sum(pred.astype(jnp.int32))
        chunk = max(math.ceil(capacity * n), min_chunk)
        if chunk >= n:
            return jax.lax.cond(
                count > 0, lambda: _select(pred, jax.vmap(expensive)(*operands), cheap_out), lambda: cheap_out
            )
        chunks = -(-n // chunk)
        # Indices of the members that take `expensive`, in order, padded with n to whole chunks: padded rows
        # gather the last member (their results are discarded) and their scatter is dropped.
        index = jnp.nonzero(pred, size=chunks * chunk, fill_value=n)[0]

        def run_chunk(i, out):
            rows_index = jax.lax.dynamic_slice_in_dim(index, i * chunk, chunk)
            taken = jax.tree.map(lambda x: jnp.take(x, rows_index, axis=0, mode="clip"), operands)
            result = jax.vmap(expensive)(*taken)
            return jax.tree.map(lambda o, r: o.at[rows_index].set(r, mode="drop"), out, result)

        return jax.lax.fori_loop(0, (count + chunk - 1) // chunk, run_chunk, cheap_out)

    @rows.def_vmap
    def rule(axis_size, in_batched, pred, *operands):
        pred_batched, *operands_batched = in_batched
        pred = pred if pred_batched else jnp.broadcast_to(pred, (axis_size, *pred.shape))
        operands = _broadcast(operands, operands_batched, axis_size)
        flat = jax.tree.map(lambda x: x.reshape(-1, *x.shape[2:]), (pred, *operands))
        out = rows(*flat)
        out = jax.tree.map(lambda x: x.reshape(axis_size, -1, *x.shape[1:]), out)
        return out, _all_batched(out)

    return rows


def in_groups(fun: Callable, group_size: int, keep_unbatched: bool = False) -> Callable:
    """``fun`` unchanged, except that under ``vmap`` it runs the batch in consecutive groups of about
    ``group_size`` members (``lax.map`` over groups, ``vmap`` within one) instead of all members at once.
    With ``keep_unbatched``, a batch of at most ``group_size`` is the plain ``vmap`` (arguments that are not batched
    stay unbatched), so small batches compile exactly as without ``in_groups``.

    XLA executes a program op by op; vmapped over hundreds of configurations, every intermediate of a minibatch
    step (e.g. [configs, 256, 64] activations) is megabytes and streams through memory between ops. Groups whose
    intermediates fit in the core's cache run the same arithmetic faster (PPO's epochs: ~12% at 256
    configurations). On a GPU each group is a serial step that leaves most of the chip idle, so under the
    ``"gpu"`` strategy (`amjax.strategy`) ``in_groups`` returns ``fun`` itself: a vmap runs the batch at once.
    """

    def call(*args):
        if strategy.is_gpu():
            return fun(*args)
        return _grouped(_traced(fun, *args), group_size, keep_unbatched)(*args)

    return call


def _grouped(fun: Callable, group_size: int, keep_unbatched: bool) -> Callable:
    """``in_groups`` for one traced ``fun``."""

    @jax.custom_batching.custom_vmap
    def grouped(*args):
        return fun(*args)

    @grouped.def_vmap
    def rule(axis_size, in_batched, *args):
        if keep_unbatched and axis_size <= group_size:
            in_axes = jax.tree.map(lambda batched: 0 if batched else None, tuple(in_batched))
            out = jax.vmap(fun, in_axes=in_axes)(*args)
            return out, _all_batched(out)
        args = _broadcast(args, in_batched, axis_size)
        if axis_size <= group_size:
            out = jax.vmap(fun)(*args)
        else:
            # A divisor of the batch near group_size keeps one compiled group body (no remainder group).
            size = next((d for d in range(group_size, group_size // 2, -1) if axis_size % d == 0), group_size)
            out = jax.lax.map(lambda a: fun(*a), tuple(args), batch_size=size)
        return out, _all_batched(out)

    return grouped


__all__ = [
    "in_groups",
    "member_axes",
    "select_compacted",
    "shared_disagreements",
    "shared_field",
    "take_shared",
    "uniform_cond",
    "update_where",
    "varying_axes",
]
