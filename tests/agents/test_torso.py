"""The networks' body: an MLP for vectors, the MinAtar CNN for images, picked from the observation (`torso` "auto")
or forced; the shapes it builds, its errors before compiling, and the CNN agents in a vmapped batch equal alone."""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from amjax.agents import ALGORITHMS, DQNConfig, PPOConfig
from amjax.agents.networks import (
    CONV_FEATURES,
    CONV_KERNEL,
    ActorCritic,
    DuelingQNetwork,
    PatchConv,
    RecurrentActorCritic,
    RecurrentQNetwork,
    Torso,
    pick_torso,
    zero_carry,
)
from amjax.agents.policies import Categorical


@pytest.mark.parametrize(
    ("torso", "shape", "kind"),
    [
        ("auto", (4,), "mlp"),
        ("auto", (10, 10, 5), "cnn"),
        ("auto", (10, 5, 2), "cnn"),
        ("auto", (1, 1, 15), "mlp"),  # SimpleBandit's one pixel: too small for a 3 x 3 filter
        ("mlp", (10, 10, 5), "mlp"),
        ("cnn", (8, 8, 2), "cnn"),
    ],
)
def test_auto_picks_a_cnn_for_images(torso, shape, kind):
    assert pick_torso(torso, shape) == Torso(kind, len(shape))


def test_bad_torsos_name_the_field():
    with pytest.raises(ValueError, match="torso: 'cnn' needs an image"):
        pick_torso("cnn", (4,))
    with pytest.raises(ValueError, match="torso: got 'resnet'; allowed values: 'auto', 'mlp', 'cnn'"):
        pick_torso("resnet", (4,))
    # In a config: refused by validate, before anything compiles.
    with pytest.raises(ValueError, match="torso: 'cnn' needs an image"):
        PPOConfig(env_id="CartPole-v0", torso="cnn").validate()
    with pytest.raises(ValueError, match="torso"):
        DQNConfig(env_id="Breakout-MinAtar", torso="conv").validate()
    DQNConfig(env_id="Breakout-MinAtar", torso="cnn").validate()
    DQNConfig(env_id="Breakout-MinAtar", torso="mlp").validate()


IMAGE = jnp.zeros((10, 10, 5))  # Breakout's 4 channels and the flag
CNN, MLP_ON_IMAGE = Torso("cnn", 3), Torso("mlp", 3)


def _kernels(params):
    return {
        "/".join(str(k.key) for k in path): leaf.shape for path, leaf in jax.tree_util.tree_leaves_with_path(params)
    }


def test_the_cnn_is_minatars_and_the_mlp_flattens():
    """16 filters of 3 x 3 over the channels, then the Dense layers on the 8 x 8 x 16 features; the MLP body reads
    the 500 pixels flattened. Batch axes of any number pass through."""
    q_net = DuelingQNetwork(6, (32,), torso=CNN)
    params = q_net.init(jax.random.key(0), IMAGE)
    shapes = _kernels(params)
    assert shapes["params/ConvTorso_0/Conv_0/kernel"] == (3, 3, 5, 16)
    assert shapes["params/ConvTorso_0/MLP_0/Dense_0/kernel"] == (8 * 8 * 16, 32)
    assert q_net.apply(params, jnp.zeros((7, 3, 10, 10, 5))).shape == (7, 3, 6)
    flat = DuelingQNetwork(6, (32,), torso=MLP_ON_IMAGE)
    flat_params = flat.init(jax.random.key(0), IMAGE)
    assert _kernels(flat_params)["params/MLP_0/Dense_0/kernel"] == (500, 32)
    assert flat.apply(flat_params, jnp.zeros((7, 3, 10, 10, 5))).shape == (7, 3, 6)
    actor_critic = ActorCritic(Categorical(6, True), (32,), torso=CNN)
    ac_params = actor_critic.init(jax.random.key(0), IMAGE)
    assert {"actor_torso", "critic_torso"} <= set(ac_params["params"])
    logits, value = actor_critic.apply(ac_params, jnp.zeros((4, 10, 10, 5)))
    assert logits.shape == (4, 6) and value.shape == (4,)


@settings(max_examples=6, deadline=None)  # each example compiles its shapes
@given(
    height=st.integers(3, 9),
    width=st.integers(3, 9),
    channels=st.integers(1, 6),
    batch=st.lists(st.integers(1, 3), max_size=2),
    seed=st.integers(0, 2**16),
)
@pytest.mark.slow
def test_patch_conv_is_flaxs_convolution(height, width, channels, batch, seed):
    """The convolution as one product of patches: flax's `nn.Conv` (3 x 3, no padding) with the same parameters,
    its gradients too, for any image size and batch axes."""
    x = jax.random.normal(jax.random.key(seed), (*batch, height, width, channels))
    patch = PatchConv(CONV_FEATURES, CONV_KERNEL)
    params = patch.init(jax.random.key(seed + 1), x)
    conv = nn.Conv(CONV_FEATURES, (CONV_KERNEL, CONV_KERNEL), padding="VALID")
    np.testing.assert_allclose(patch.apply(params, x), conv.apply(params, x), rtol=1e-5, atol=1e-5)
    grads = [jax.grad(lambda p, f=f: (f(p, x) ** 2).sum())(params) for f in (patch.apply, conv.apply)]
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-4), *grads)


@pytest.mark.parametrize("network", ["drqn", "ppo-rnn"])
def test_recurrent_networks_take_the_cnn(network):
    if network == "drqn":
        net = RecurrentQNetwork(6, (32,), rnn_size=16, torso=CNN)
    else:
        net = RecurrentActorCritic(Categorical(6, True), (32,), rnn_size=16, torso=CNN)
    carry = zero_carry("gru", 16, (3,))
    params = net.init(jax.random.key(0), carry, jnp.zeros((3, 10, 10, 5)), jnp.zeros(3, bool))
    assert _kernels(params)["params/core/torso/Conv_0/kernel"] == (3, 3, 5, 16)  # the body keeps its name
    carries, _ = net.apply(params, carry, jnp.zeros((8, 3, 10, 10, 5)), jnp.zeros((8, 3), bool), method="unroll")
    assert carries.shape == (8, 3, 16)


def test_vector_networks_keep_their_parameter_names():
    """The default body on a vector is the MLP it always was: saved policies keep loading."""
    params = ActorCritic(Categorical(4, True), (8,)).init(jax.random.key(0), jnp.zeros(5))
    assert set(params["params"]) == {"actor_torso", "critic_torso", "logits", "value"}
    q_params = DuelingQNetwork(4, (8,)).init(jax.random.key(0), jnp.zeros(5))
    assert set(q_params["params"]) == {"MLP_0", "state_value", "advantage"}


@pytest.mark.parametrize("name", ["ppo", "dqn", "drqn", "ppo-rnn"])
def test_configs_pick_the_body_from_the_env(name):
    algo = ALGORITHMS[name]
    assert algo.setup(algo.config_type(env_id="Catch-bsuite")).network.torso == Torso("cnn", 3)
    assert algo.setup(algo.config_type(env_id="CartPole-v0")).network.torso == Torso("mlp", 1)
    assert algo.setup(algo.config_type(env_id="Breakout-MinAtar", torso="mlp")).network.torso == Torso("mlp", 3)


CATCH = {
    "ppo": PPOConfig(
        env_id="Catch-bsuite",
        total_timesteps=1024,
        eval_every=512,
        num_envs=4,
        num_steps=32,
        eval_episodes=2,
        hidden=(16,),
    ),
    "dqn": DQNConfig(
        env_id="Catch-bsuite",
        total_timesteps=600,
        eval_every=300,
        buffer_size=300,
        learning_starts=100,
        batch_size=8,
        eval_episodes=2,
        hidden=(16,),
    ),
}


@pytest.mark.parametrize("name", ["ppo", "dqn"])
@pytest.mark.slow
def test_cnn_agents_in_a_vmapped_batch_equal_alone(name, assert_batch_equals_alone):
    """Catch's [10, 5] board as an image: each configuration of a vmapped batch (its convolutions batched over
    configurations) equals the same configuration trained alone, and different seeds differ."""
    configs = [CATCH[name].replace(cost=c, learning_rate=lr) for c, lr in [(0.0, 1e-3), (0.1, 3e-4)]]
    keys = jnp.stack([jax.random.PRNGKey(s) for s in (0, 1)])
    rows, _ = assert_batch_equals_alone(ALGORITHMS[name], configs, keys)
    losses = rows.columns()["loss"]
    assert np.isfinite(losses).all() and not np.array_equal(losses[0], losses[1])
