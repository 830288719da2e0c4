"""`amjax.cores.TreeLayout`: a pytree packed into one uint32 vector and back, bit for bit, inside and outside jit."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from amjax.cores import TreeLayout

DTYPES = [
    jnp.float32,
    jnp.int32,
    jnp.uint32,
    jnp.bool_,
    jnp.int8,
    jnp.uint8,
    jnp.int16,
    jnp.uint16,
    jnp.float16,
    jnp.bfloat16,
]


def bits(x: jax.Array) -> np.ndarray:
    """`x`'s bits (a key's data), so that NaN payloads and signed zeros count."""
    if jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key):
        x = jax.random.key_data(x)
    x = np.asarray(x)
    return x.view(np.dtype(f"u{x.dtype.itemsize}")) if x.dtype != np.bool_ else x


@st.composite
def leaves(draw: st.DrawFn) -> jax.Array:
    dtype = draw(st.sampled_from(DTYPES))
    shape = tuple(draw(st.lists(st.integers(0, 3), max_size=3)))
    size = int(np.prod(shape))
    raw = np.frombuffer(draw(st.binary(min_size=4 * size, max_size=4 * size)), np.uint32)  # every bit pattern
    if dtype == jnp.bool_:
        return jnp.asarray((raw & 1).astype(bool).reshape(shape))
    width = jnp.dtype(dtype).itemsize
    return jnp.asarray(raw.astype(f"u{width}").view(jnp.dtype(dtype)).reshape(shape))


@st.composite
def trees(draw: st.DrawFn) -> dict:
    tree = {f"leaf{i}": leaf for i, leaf in enumerate(draw(st.lists(leaves(), max_size=5)))}
    if draw(st.booleans()):
        tree["key"] = jax.random.key(
            draw(st.integers(0, 2**32 - 1)), impl=draw(st.sampled_from(["threefry2x32", "rbg"]))
        )
    return tree


@settings(max_examples=40, deadline=None)
@given(trees())
@pytest.mark.slow
def test_pack_then_unpack_gives_the_tree_back_bit_for_bit(tree: dict) -> None:
    layout = TreeLayout.of(tree)
    words = layout.pack(tree)
    assert words.dtype == jnp.uint32 and words.shape == (layout.size,)
    back = layout.unpack(words)
    assert jax.tree.structure(back) == jax.tree.structure(tree)
    for name, leaf in tree.items():
        assert back[name].dtype == leaf.dtype and back[name].shape == leaf.shape
        np.testing.assert_array_equal(bits(back[name]), bits(leaf))
    jitted = jax.jit(layout.unpack)(jax.jit(layout.pack)(tree))  # the same inside a program
    for name, leaf in tree.items():
        np.testing.assert_array_equal(bits(jitted[name]), bits(leaf))


def test_layout_from_shapes_equals_the_layout_from_arrays_and_is_hashable() -> None:
    tree = (jax.random.key(0), {"x": jnp.zeros((2, 3)), "done": jnp.array(True), "t": jnp.int32(4)})
    layout = TreeLayout.of(tree)
    assert TreeLayout.of(jax.eval_shape(lambda: tree)) == layout
    assert hash(TreeLayout.of(jax.eval_shape(lambda: tree))) == hash(layout)  # usable as a static argument
    assert layout.size == 2 + 6 + 1 + 1
    assert TreeLayout.of({"x": jnp.zeros(3)}) != TreeLayout.of({"x": jnp.zeros(4)})


def test_different_values_pack_differently() -> None:
    layout = TreeLayout.of({"x": jnp.zeros(3), "key": jax.random.key(0)})
    one = layout.pack({"x": jnp.zeros(3), "key": jax.random.key(0)})
    two = layout.pack({"x": jnp.zeros(3), "key": jax.random.key(1)})
    assert not np.array_equal(one, two)


def test_unsupported_leaves_are_refused_with_the_allowed_kinds() -> None:
    with pytest.raises(TypeError, match="allowed: bool, integer and floating"):
        TreeLayout.of({"z": jnp.zeros(2, jnp.complex64)})
    with pytest.raises(TypeError, match="floats of 16 bits or more"):
        TreeLayout.of({"z": jnp.zeros(2, jnp.float8_e4m3fn)})


def test_pack_refuses_trees_unlike_the_example_and_unpack_words_of_another_size() -> None:
    layout = TreeLayout.of({"x": jnp.zeros(3), "key": jax.random.key(0), "c": 0.5})
    good = {"x": jnp.ones(3), "key": jax.random.key(1), "c": 1}  # a Python scalar is cast to the example's dtype
    assert layout.unpack(layout.pack(good))["c"] == 1.0
    cast = layout.unpack(layout.pack({**good, "x": jnp.arange(3, dtype=jnp.int32)}))["x"]  # same kind: cast
    assert cast.dtype == jnp.float32 and cast.tolist() == [0.0, 1.0, 2.0]
    narrowing = TreeLayout.of({"i": jnp.zeros(2, jnp.int32)})
    with pytest.raises(ValueError, match=r"leaf \['i'\]"):
        narrowing.pack({"i": jnp.ones(2, jnp.float32)})  # float to int would lose the fraction
    bad = [
        ({**good, "x": jnp.ones(5)}, r"leaf \['x'\]"),
        ({**good, "x": jnp.ones(3, jnp.complex64)}, r"leaf \['x'\]"),
        ({**good, "key": jax.random.key(1, impl="rbg")}, r"leaf \['key'\]"),
        ({**good, "key": jax.random.key_data(jax.random.key(1))}, r"leaf \['key'\]"),
        ({"x": jnp.ones(3)}, "structure differs"),
    ]
    for tree, named in bad:
        with pytest.raises(ValueError, match=named):
            layout.pack(tree)
    with pytest.raises(ValueError, match=r"packs to uint32\[6\]"):
        layout.unpack(jnp.zeros(7, jnp.uint32))
