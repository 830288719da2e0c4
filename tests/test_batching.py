"""`amjax.batching`: branches and compacted selects give what `lax.cond` / `jnp.where` give, at every vmap level;
`update_where` updates a loop's state in place; `in_groups` gives what `vmap` gives."""

from __future__ import annotations

import re
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import struct
from hypothesis import given, settings
from hypothesis import strategies as st
from jax.sharding import Mesh, PartitionSpec

from amjax import strategy
from amjax.batching import (
    in_groups,
    member_axes,
    select_compacted,
    shared_disagreements,
    shared_field,
    take_shared,
    uniform_cond,
    update_where,
)


def expensive(x, y):
    return {"a": jnp.sin(x) * y, "b": jnp.stack([x, y]).sum()}


def cheap(x, y):
    return {"a": x + y, "b": x - y}


def reference(pred, x, y):
    return jax.tree.map(lambda a, b: jnp.where(pred, a, b), expensive(x, y), cheap(x, y))


@jax.jit
def compacted(pred, x, y):
    # Chunks of 2 rows out of 32: up to 16 iterations.
    return jax.vmap(lambda p, a, b: select_compacted(p, expensive, cheap, a, b, min_chunk=1))(pred, x, y)


@jax.jit
def compacted_small_batch(pred, x, y):
    # 8 members, chunks of min_chunk=16 rows: `expensive` runs on every member (when any needs it), then a select.
    return jax.vmap(lambda p, a, b: select_compacted(p, expensive, cheap, a, b))(pred, x, y)


@jax.jit
def compacted_nested(pred, x, y):
    inner = jax.vmap(lambda p, a, b: select_compacted(p, expensive, cheap, a, b, capacity=0.25))
    return jax.vmap(inner, in_axes=(0, 0, None))(pred, x, y)


@jax.jit
def branched(pred, x, y):
    return jax.vmap(jax.vmap(lambda p, a, b: uniform_cond(p, expensive, cheap, a, b)))(pred, x, y)


@pytest.mark.parametrize(
    ("program", "size"),
    [(compacted, 32), (compacted_small_batch, 8)],
    ids=["32 members in chunks of 2", "8 members within one chunk"],
)
@settings(max_examples=30, deadline=None)
@given(data=st.data(), seed=st.integers(0, 2**31 - 1))
def test_select_compacted_equals_a_select(program, size, data, seed):
    """Whatever the number of members that take `expensive` (none, within one chunk, many chunks, all)."""
    pred = jnp.array(data.draw(st.lists(st.booleans(), min_size=size, max_size=size)))
    x, y = jax.random.normal(jax.random.PRNGKey(seed), (2, size))
    got = program(pred, x, y)
    want = jax.vmap(reference)(pred, x, y)
    jax.tree.map(lambda g, w: np.testing.assert_allclose(g, w, rtol=1e-6), got, want)


@settings(max_examples=20, deadline=None)
@given(count=st.integers(0, 24), seed=st.integers(0, 2**31 - 1))
def test_select_compacted_nested_vmap_and_unbatched_operand(count, seed):
    """Two vmap levels flattened into one batch (24 members, chunks of 16); an operand unbatched at the outer
    level is broadcast."""
    key = jax.random.PRNGKey(seed)
    pred = (jnp.arange(24) < count)[jax.random.permutation(key, 24)].reshape(4, 6)
    x = jax.random.normal(key, (4, 6))
    y = jax.random.normal(jax.random.fold_in(key, 1), (6,))
    got = compacted_nested(pred, x, y)
    want = jax.vmap(jax.vmap(reference), in_axes=(0, 0, None))(pred, x, y)
    jax.tree.map(lambda g, w: np.testing.assert_allclose(g, w, rtol=1e-6), got, want)


def test_select_compacted_unbatched_is_a_cond():
    x, y = jnp.float32(0.3), jnp.float32(-2.0)
    for pred in (True, False):
        got = jax.jit(lambda p: select_compacted(p, expensive, cheap, x, y))(jnp.bool_(pred))
        jax.tree.map(lambda g, w: np.testing.assert_allclose(g, w, rtol=1e-6), got, reference(pred, x, y))


def test_select_compacted_runs_expensive_once_on_a_smaller_batch():
    """The compiled program holds `expensive` once, at the chunk size (2 of 32: capacity 1/16), not at 32."""
    text = compacted.lower(jnp.zeros(32, bool), jnp.zeros(32), jnp.zeros(32)).as_text()
    sines = [line for line in text.splitlines() if "stablehlo.sine" in line]
    assert len(sines) == 1 and "tensor<2xf32>" in sines[0], sines


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"capacity": 0.0}, "capacity must be in"),
        ({"capacity": 1.5}, "capacity must be in"),
        ({"min_chunk": 0}, "min_chunk must be an int"),
        ({"min_chunk": 2.0}, "min_chunk must be an int"),
    ],
)
def test_select_compacted_rejects_bad_chunk_settings(kwargs, message):
    with pytest.raises(ValueError, match=message):
        select_compacted(jnp.bool_(True), expensive, cheap, jnp.float32(1), jnp.float32(2), **kwargs)


@settings(max_examples=30, deadline=None)
@given(mask=st.lists(st.booleans(), min_size=12, max_size=12), seed=st.integers(0, 2**31 - 1))
@pytest.mark.slow
def test_uniform_cond_equals_cond_per_member(mask, seed):
    pred = jnp.array(mask).reshape(3, 4)
    x, y = jax.random.normal(jax.random.PRNGKey(seed), (2, 3, 4))
    got = branched(pred, x, y)
    want = jax.vmap(jax.vmap(reference))(pred, x, y)
    jax.tree.map(lambda g, w: np.testing.assert_allclose(g, w, rtol=1e-6), got, want)


def update(state, scale):
    return {"w": jnp.tanh(state["w"]) * scale, "n": state["n"] + 1}


def updated_where(pred, state, scale):
    return jax.tree.map(lambda a, b: jnp.where(pred, a, b), update(state, scale), state)


@settings(max_examples=30, deadline=None)
@given(mask=st.lists(st.booleans(), min_size=12, max_size=12), seed=st.integers(0, 2**31 - 1))
def test_update_where_equals_cond_per_member(mask, seed):
    """Two vmap levels (3 x 4 members, an argument unbatched at the inner one): all, some or none of a row take the
    update."""
    pred = jnp.array(mask).reshape(3, 4)
    state = {"w": jax.random.normal(jax.random.PRNGKey(seed), (3, 4, 2)), "n": jnp.zeros((3, 4), jnp.int32)}
    scale = jnp.array([0.5, -1.0, 2.0])

    def member(p, s, c):
        return update_where(p, update, s, c)

    got = jax.jit(jax.vmap(jax.vmap(member, (0, 0, None))))(pred, state, scale)
    want = jax.vmap(jax.vmap(updated_where, (0, 0, None)))(pred, state, scale)
    jax.tree.map(np.testing.assert_array_equal, got, want)
    unbatched = jax.jit(member)(pred[0, 0], jax.tree.map(lambda x: x[0, 0], state), scale[0])
    jax.tree.map(np.testing.assert_array_equal, unbatched, jax.tree.map(lambda x: x[0, 0], want))


@pytest.mark.parametrize("helper", ["update_where", "uniform_cond", "select_compacted"])
@pytest.mark.parametrize("pred", [True, False])
def test_an_unbatched_predicate_stays_one_conditional(helper, pred, primitive_names):
    """A predicate every member shares (a step counter's: `shared_field`) under vmap: one conditional over the
    batch, no loop for disagreeing members and no reduction (a GPU reads it back to the host once), with each
    member's own result; under a further vmap whose members differ, still a branch."""
    state = {"w": jax.random.normal(jax.random.PRNGKey(0), (4, 2)), "n": jnp.zeros(4, jnp.int32)}
    scale = jnp.array([0.5, -1.0, 2.0, 3.0])
    member = {
        "update_where": lambda p, s, c: update_where(p, update, s, c),
        "uniform_cond": lambda p, s, c: uniform_cond(p, update, lambda s, c: s, s, c),
        "select_compacted": lambda p, s, c: select_compacted(p, update, lambda s, c: s, s, c, min_chunk=1),
    }[helper]
    batched = jax.vmap(member, (None, 0, 0))
    names = primitive_names(jax.make_jaxpr(batched)(jnp.bool_(pred), state, scale))
    assert names.count("cond") == 1 and "while" not in names and "reduce_and" not in names, names
    got = jax.jit(batched)(jnp.bool_(pred), state, scale)
    want = jax.vmap(updated_where, (None, 0, 0))(jnp.bool_(pred), state, scale)
    jax.tree.map(np.testing.assert_array_equal, got, want)
    # Shared within each row but not across rows: the outer vmap keeps the helper's own rule (a branch, or
    # select_compacted's loop over the members that need `expensive`), not a select that computes both for all.
    preds, rows = jnp.array([pred, not pred]), jax.tree.map(lambda x: jnp.stack([x, -x]), (state, scale))
    nested = jax.vmap(batched)
    names = primitive_names(jax.make_jaxpr(nested)(preds, *rows))
    assert "cond" in names or "while" in names, names
    want = jax.vmap(jax.vmap(updated_where, (None, 0, 0)))(preds, *rows)
    jax.tree.map(np.testing.assert_array_equal, jax.jit(nested)(preds, *rows), want)


@pytest.mark.parametrize("pred", [True, False])
def test_update_where_under_the_gpu_strategy_is_a_loop_of_at_most_one_iteration(pred, primitive_names):
    """Under the "gpu" strategy an unbatched predicate gives a loop of at most one iteration, not a conditional
    (XLA's GPU compiler copies a loop-carried state into a conditional's operands and through a branch that keeps
    it; a loop it updates in place: `benchmarks/gpu_thunks.py`), with the "cpu" strategy's results: alone, under a
    vmap and under a vmap whose members disagree."""
    state = {"w": jax.random.normal(jax.random.PRNGKey(1), (4, 2)), "n": jnp.zeros(4, jnp.int32)}
    scale = jnp.array([0.5, -1.0, 2.0, 3.0])
    preds, rows = jnp.array([pred, not pred]), jax.tree.map(lambda x: jnp.stack([x, -x]), (state, scale))
    results = {}
    for name in ("cpu", "gpu"):

        def member(p, s, c):  # defined per strategy: JAX reuses a function's trace, and the strategy is read there
            return update_where(p, update, s, c)

        batched = jax.vmap(member, (None, 0, 0))
        with strategy.use(name):
            names = primitive_names(jax.make_jaxpr(batched)(jnp.bool_(pred), state, scale))
            results[name] = (
                jax.jit(member)(jnp.bool_(pred), jax.tree.map(lambda x: x[0], state), scale[0]),
                jax.jit(batched)(jnp.bool_(pred), state, scale),
                jax.jit(jax.vmap(batched))(preds, *rows),
            )
        assert (names.count("while"), names.count("cond")) == ((1, 0) if name == "gpu" else (0, 1)), names
    want = jax.vmap(updated_where, (None, 0, 0))(jnp.bool_(pred), state, scale)
    jax.tree.map(np.testing.assert_array_equal, results["gpu"][1], want)
    jax.tree.map(np.testing.assert_array_equal, results["gpu"][0], jax.tree.map(lambda x: x[0], want))
    jax.tree.map(np.testing.assert_array_equal, results["gpu"], results["cpu"])


@struct.dataclass
class Counted:
    params: jax.Array
    steps: jax.Array = shared_field()
    unused: Any = None


def test_shared_fields_go_unbatched():
    """`member_axes` maps `shared_field`s to None wherever their dataclass sits; `take_shared` takes them from the
    first member; `shared_disagreements` names those whose members differ."""
    batch = {
        "a": Counted(jnp.ones((3, 2)), jnp.full(3, 7)),
        "b": [jnp.zeros(3), Counted(jnp.ones(3), jnp.array([1, 2, 1]))],
    }
    axes = member_axes(batch)
    assert axes == {"a": Counted(0, None, None), "b": [0, Counted(0, None, None)]}
    taken = take_shared(batch)
    assert taken["a"].steps.shape == () and int(taken["b"][1].steps) == 1
    np.testing.assert_array_equal(taken["a"].params, batch["a"].params)
    assert shared_disagreements(jax.device_get(batch)) == ["['b'][1].steps"]
    out = jax.vmap(lambda c: c.replace(params=c.params * c.steps, steps=c.steps + 1), (axes["a"],))(taken["a"])
    np.testing.assert_array_equal(out.params, 7 * batch["a"].params)
    np.testing.assert_array_equal(out.steps, jnp.full(3, 8))  # vmap's out_axes 0 spreads it over the batch again


def _loop_body_copies(compiled_text: str, shape: str, marker: str) -> int:
    """Copies of an array of `shape` (e.g. "f32[8,32,32]") in the body of the loop whose state holds `marker` (an
    array type only that loop carries)."""
    loop = next(line for line in compiled_text.splitlines() if " while(" in line and marker in line.split(" while(")[0])
    body = re.search(r"body=%?([\w.\-]+)", loop).group(1)
    text = compiled_text[compiled_text.index(f"\n%{body} ") :].split("\n}\n", 1)[0]
    return len(re.findall(rf"= {re.escape(shape)}{{[\d,]*}} copy\(", text))


def test_update_where_keeps_a_loop_state_in_place():
    """A vmapped loop whose state (a learning step's parameters, a replay buffer) goes through `update_where` at
    every iteration compiles without copying it back into the loop's state; a `uniform_cond` whose other branch
    passes the state through copies it each iteration (what the Q-learners' updates did: issue 58)."""

    def program(branch):
        def member(state, starts):
            def step(state, i):
                return branch(i >= starts, state), None

            return jax.lax.scan(step, state, jnp.arange(16))[0]

        return jax.jit(jax.vmap(member))

    def halve_tanh(state):
        return jax.tree.map(lambda x: jnp.tanh(x) * 0.5, state)

    def in_place(pred, state):
        return update_where(pred, halve_tanh, state)

    def passed_through(pred, state):
        return uniform_cond(pred, halve_tanh, lambda s: s, state)

    state, starts = {"w": jnp.ones((8, 32, 32)), "b": jnp.ones((8, 32))}, jnp.full((8,), 4)
    texts = {f.__name__: program(f).lower(state, starts).compile().as_text() for f in (in_place, passed_through)}
    # The scan's loop alone carries its steps' indices, s32[16].
    assert _loop_body_copies(texts["in_place"], "f32[8,32,32]", "s32[16]") == 0
    assert _loop_body_copies(texts["passed_through"], "f32[8,32,32]", "s32[16]") > 0
    want = jax.tree.map(lambda x: jax.lax.fori_loop(0, 12, lambda _, x: jnp.tanh(x) * 0.5, x), state)
    jax.tree.map(lambda g, w: np.testing.assert_allclose(g, w, rtol=1e-6), program(in_place)(state, starts), want)


@pytest.mark.parametrize("keep_unbatched", [False, True])
@pytest.mark.parametrize("batch", [3, 4, 10])
def test_in_groups_equals_vmap(batch, keep_unbatched):
    def fun(x, scale):
        return {"y": jnp.sin(x) * scale, "total": x.sum() * scale}

    x = jnp.arange(batch * 2, dtype=jnp.float32).reshape(batch, 2)
    grouped = jax.vmap(in_groups(fun, 4, keep_unbatched=keep_unbatched), (0, None))(x, jnp.float32(1.5))
    plain = jax.vmap(fun, (0, None))(x, jnp.float32(1.5))
    jax.tree.map(np.testing.assert_array_equal, grouped, plain)


def test_in_groups_keep_unbatched_compiles_small_batches_as_plain_vmap():
    def fun(x, scale):
        return jnp.sin(x) * scale

    x, scale = jnp.ones((4, 3)), jnp.float32(2.0)
    plain = str(jax.make_jaxpr(jax.vmap(fun, (0, None)))(x, scale))
    kept = str(jax.make_jaxpr(jax.vmap(in_groups(fun, 4, keep_unbatched=True), (0, None)))(x, scale))
    broadcast = str(jax.make_jaxpr(jax.vmap(in_groups(fun, 4), (0, None)))(x, scale))
    assert kept == plain
    assert broadcast != plain  # the default broadcasts unbatched arguments to the batch
    grouped = str(jax.make_jaxpr(jax.vmap(in_groups(fun, 2, keep_unbatched=True), (0, None)))(x, scale))
    assert "scan" in grouped and "scan" not in plain  # past group_size the groups are a loop


def test_functions_are_traced_once_under_nested_vmap():
    """Each helper's functions run their Python once per trace: the batching rules replay the recorded jaxpr
    (LunarLander's step nests them, and a second trace of each level was a third of its compile's tracing)."""
    calls = {"expensive": 0, "cheap": 0, "true": 0, "false": 0, "update": 0, "grouped": 0}

    def counted(name, fun):
        def wrapped(*args):
            calls[name] += 1
            return fun(*args)

        return wrapped

    def member(pred, x, y):
        a = select_compacted(pred, counted("expensive", expensive), counted("cheap", cheap), x, y)
        b = uniform_cond(pred, counted("true", expensive), counted("false", cheap), x, y)
        c = update_where(pred, counted("update", update), {"w": x, "n": jnp.int32(0)}, y)
        return a, b, c

    pred = jnp.arange(12).reshape(3, 4) % 3 == 0
    x, y = jax.random.normal(jax.random.PRNGKey(0), (2, 3, 4))
    step = in_groups(counted("grouped", member), 2)
    got = jax.jit(jax.vmap(jax.vmap(step)))(pred, x, y)
    assert calls == dict.fromkeys(calls, 1)
    want = jax.vmap(jax.vmap(reference))(pred, x, y)
    for value in got[:2]:
        jax.tree.map(lambda g, w: np.testing.assert_allclose(g, w, rtol=1e-6), value, want)
    state = {"w": x, "n": jnp.zeros((3, 4), jnp.int32)}
    jax.tree.map(np.testing.assert_array_equal, got[2], jax.vmap(jax.vmap(updated_where))(pred, state, y))


def test_helpers_hold_shard_maps_varying_axes_check():
    """Inside `jax.shard_map` (default `check_vma=True`) with an operand that does not vary over the mesh: rows
    gathered by a varying index vary where that operand did not when `expensive` was traced, so the recorded
    program no longer fits them and `expensive` runs again at their types (the LunarLander step's auto-reset)."""
    calls = {"expensive": 0}

    def mixed(x, scale):  # a constant meets the unvarying `scale`: no cast recorded while `scale` is unvarying
        calls["expensive"] += 1
        return {"a": jnp.sin(x) * (scale * jnp.float32(2.0)), "b": x * scale}

    def member(pred, x, scale):
        a = select_compacted(pred, mixed, cheap, x, scale, min_chunk=1)
        b = uniform_cond(pred, mixed, cheap, x, scale)
        c = update_where(pred, lambda state, scale: {"w": mixed(state["w"], scale)["b"]}, {"w": x}, scale)
        return (a, b, c), in_groups(lambda x: x * scale, 4)(x)

    def per_device(pred, x):
        return jax.vmap(member, (0, 0, None))(pred, x, jnp.float32(0.5))

    devices = jax.devices()
    mesh, spec = Mesh(np.array(devices), ("rows",)), PartitionSpec("rows")
    size = 32 * len(devices)
    pred = jnp.arange(size) % 3 == 0
    x = jax.random.normal(jax.random.PRNGKey(0), (size,))
    (a, b, c), grouped = jax.jit(jax.shard_map(per_device, mesh=mesh, in_specs=spec, out_specs=spec))(pred, x)
    assert calls["expensive"] >= 2  # traced once, then again for the gathered rows
    want = {"a": jnp.where(pred, jnp.sin(x), x + 0.5), "b": jnp.where(pred, x * 0.5, x - 0.5)}
    for got in (a, b):
        jax.tree.map(lambda g, w: np.testing.assert_allclose(g, w, rtol=1e-6), got, want)
    np.testing.assert_allclose(c["w"], jnp.where(pred, x * 0.5, x), rtol=1e-6)
    np.testing.assert_allclose(grouped, x * 0.5, rtol=1e-6)
