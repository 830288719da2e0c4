"""amjax's LayerNorm (`networks.LayerNorm`, a hand-written gradient) against flax's `nn.LayerNorm`: the same
parameters, values and gradients to float rounding, for any batch axes, feature width and input scale.

The reference is flax's two-pass variance (`use_fast_variance=False`), which amjax's computes too: flax's default
one-pass E[x^2] - E[x]^2 loses every digit in float32 for features with a large mean and a small spread (hypothesis
found mean 5, spread 1e-3), where both two-pass forms agree."""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from amjax.agents.networks import MLP, LayerNorm


def _params(scale: jax.Array, bias: jax.Array) -> dict:
    return {"params": {"scale": scale, "bias": bias}}


@settings(max_examples=25, deadline=None)
@given(
    batch=st.lists(st.integers(1, 5), min_size=0, max_size=3),
    features=st.integers(2, 130),
    spread=st.sampled_from([1e-3, 1.0, 30.0]),
    offset=st.sampled_from([0.0, 5.0]),
    seed=st.integers(0, 2**16),
)
def test_values_and_gradients_equal_flax(batch, features, spread, offset, seed):
    keys = jax.random.split(jax.random.PRNGKey(seed), 4)
    x = offset + spread * jax.random.normal(keys[0], (*batch, features))
    scale, bias = 1 + jax.random.normal(keys[1], (features,)), jax.random.normal(keys[2], (features,))
    weights = jax.random.normal(keys[3], (*batch, features))  # a loss that weighs every output differently

    def loss(norm, x, scale, bias):
        return jnp.sum(weights * jnp.tanh(norm.apply(_params(scale, bias), x)))

    flax_norm = nn.LayerNorm(use_fast_variance=False)
    mine = LayerNorm().apply(_params(scale, bias), x)
    np.testing.assert_allclose(mine, flax_norm.apply(_params(scale, bias), x), rtol=1e-4, atol=1e-4)
    ours = jax.grad(loss, argnums=(1, 2, 3))(LayerNorm(), x, scale, bias)
    flax = jax.grad(loss, argnums=(1, 2, 3))(flax_norm, x, scale, bias)
    for name, a, b in zip(("x", "scale", "bias"), ours, flax, strict=True):
        tolerance = 2e-3 * max(1.0, float(jnp.abs(b).max()))  # a tiny spread makes d/dx large (1 / std)
        np.testing.assert_allclose(a, b, atol=tolerance, err_msg=f"gradient of {name}")


def test_equals_flax_default_on_well_scaled_features():
    """On features whose spread is not tiny against their mean (a network's pre-activations), flax's default
    one-pass variance agrees too."""
    x = 0.5 + 2 * jax.random.normal(jax.random.PRNGKey(4), (2, 9, 64))
    params = nn.LayerNorm().init(jax.random.PRNGKey(0), x)
    np.testing.assert_allclose(LayerNorm().apply(params, x), nn.LayerNorm().apply(params, x), atol=1e-5)


def test_parameters_named_and_initialised_as_flax():
    """Saved policies keep their layout: the MLP's LayerNorm parameters are flax's ("LayerNorm_0" with "scale" ones
    and "bias" zeros), in the same tree as an MLP built on `nn.LayerNorm`."""
    x = jnp.ones((3, 5))
    params = MLP((8, 6), "relu", layer_norm=True).init(jax.random.PRNGKey(0), x)["params"]
    assert sorted(params) == ["Dense_0", "Dense_1", "LayerNorm_0", "LayerNorm_1"]
    np.testing.assert_array_equal(params["LayerNorm_1"]["scale"], jnp.ones(6))
    np.testing.assert_array_equal(params["LayerNorm_1"]["bias"], jnp.zeros(6))
    flax_params = nn.LayerNorm().init(jax.random.PRNGKey(0), jnp.ones((3, 6)))
    assert jax.tree.structure(flax_params) == jax.tree.structure({"params": params["LayerNorm_1"]})


def test_vmapped_over_configurations_equals_each_alone():
    """Under vmap (a sweep's configurations), each lane's value and gradients are its own run's."""
    keys = jax.random.split(jax.random.PRNGKey(1), 3)
    x = jax.random.normal(keys[0], (3, 7, 16))
    scale, bias = jax.random.normal(keys[1], (3, 16)), jax.random.normal(keys[2], (3, 16))

    def grads(x, scale, bias):
        return jax.grad(lambda *a: jnp.sum(jnp.sin(LayerNorm().apply(_params(a[1], a[2]), a[0]))), (0, 1, 2))(
            x, scale, bias
        )

    batched = jax.vmap(grads)(x, scale, bias)
    for i in range(3):
        alone = grads(x[i], scale[i], bias[i])
        for a, b in zip(batched, alone, strict=True):
            np.testing.assert_allclose(a[i], b, rtol=1e-5, atol=1e-6)
