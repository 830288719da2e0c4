"""Image observations (MinAtar, bsuite's Catch and DeepSea): the wrapper keeps their shape and adds its flag and
features as constant channels. Step by step against gymnax's own envs, stale frames, instruments over channels,
spaces and errors."""

from __future__ import annotations

import gymnax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import amjax
from amjax.wrappers.active_measure import ActiveMeasure
from amjax.wrappers.observations import ChannelObservation, standard_observations

BREAKOUT, BREAKOUT_PARAMS = gymnax.make("Breakout-MinAtar")  # [10, 10, 4], 3 controls
MEASURED_BREAKOUT, MEASURED_PARAMS = amjax.make("Breakout-MinAtar", cost=0.1)


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**16), controls=st.lists(st.integers(0, 2), min_size=80, max_size=80))
def test_always_measuring_steps_like_gymnax_breakout(rollout, seed, controls):
    """Same keys, every action measuring: the frames are gymnax's with one constant flag channel of 1; rewards are
    gymnax's less the cost; ends agree."""
    want = rollout(BREAKOUT, BREAKOUT_PARAMS, jax.random.key(seed), jnp.asarray(controls))
    measured = jnp.asarray(controls) + 3  # control + n * measure
    got = rollout(MEASURED_BREAKOUT, MEASURED_PARAMS, jax.random.key(seed), measured)
    assert got.obs0.shape == (10, 10, 5)
    np.testing.assert_array_equal(got.obs0[..., :4], want.obs0)
    np.testing.assert_array_equal(got.obs0[..., 4], 1.0)
    np.testing.assert_array_equal(got.obs[..., :4], want.obs)
    np.testing.assert_array_equal(got.obs[..., 4], 1.0)
    np.testing.assert_array_equal(got.info["final_observation"][..., :4], want.info["final_observation"])
    np.testing.assert_allclose(got.reward, want.reward - 0.1, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(got.terminated, want.terminated)
    np.testing.assert_array_equal(got.truncated, want.truncated)


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**16), actions=st.lists(st.integers(0, 5), min_size=80, max_size=80))
def test_unmeasured_steps_show_the_last_measured_frame(rollout, seed, actions):
    """Without a measurement the frame shown is the last one measured (or the auto-reset's), its flag channel 0;
    with one it is the true frame, flag 1."""
    true_obs = rollout(BREAKOUT, BREAKOUT_PARAMS, jax.random.key(seed), jnp.asarray(actions) % 3).obs
    got = rollout(MEASURED_BREAKOUT, MEASURED_PARAMS, jax.random.key(seed), jnp.asarray(actions))
    done = got.terminated | got.truncated
    last = got.obs0[..., :4]
    for t, action in enumerate(actions):
        fresh = action >= 3 or done[t]
        np.testing.assert_array_equal(got.obs[t][..., 4], float(fresh))  # the flag, constant over the image
        if fresh:
            last = true_obs[t]
        np.testing.assert_array_equal(got.obs[t][..., :4], last)


def test_two_dimensional_observations_gain_a_channel_axis():
    catch, params = gymnax.make("Catch-bsuite")  # [10, 5]
    image = standard_observations(catch, params)
    assert isinstance(image, ChannelObservation) and image.observation_space(params).shape == (10, 5, 1)
    obs, state = image.reset(jax.random.key(0), params)
    plain, _ = catch.reset(jax.random.key(0), params)
    np.testing.assert_array_equal(obs[..., 0], plain)
    env, env_params = amjax.make("Catch-bsuite", cost=0.1)
    assert env.observation_space(env_params).shape == (10, 5, 2)
    env, env_params = amjax.make("DeepSea-bsuite", vanilla=True)
    assert env.observation_space(env_params).shape == (8, 8, 1)
    vector, vector_params = gymnax.make("CartPole-v1")
    with pytest.raises(TypeError, match="2-D Box"):
        ChannelObservation(vector, vector_params)


def test_every_option_appends_channels_inside_the_space():
    """flag 1 + since_measured 1 + last_action 3 + budget 1 + cost 1 channels after Breakout's 4, each constant over
    the image, every observation inside the space."""
    env, params = amjax.make(
        "Breakout-MinAtar", extra_obs=("since_measured", "last_action"), budget=3, cost_range=(0.0, 0.5)
    )
    space = env.observation_space(params)
    assert space.shape == (10, 10, 4 + 1 + 1 + 3 + 1 + 1)
    obs, state = env.reset(jax.random.key(0), params)
    for i in range(12):
        obs, state, *_ = env.step(jax.random.key(i), state, (i % 3) + 3 * (i % 2), params)
        assert space.contains(obs)
        extras = np.asarray(obs[..., 4:])
        np.testing.assert_array_equal(extras, np.broadcast_to(extras[0, 0], extras.shape))  # constant channels
        np.testing.assert_array_equal(extras[0, 0, 2:5], np.eye(3)[i % 3])  # the last control, one-hot


def test_instruments_read_channels():
    """SpaceInvaders' 6 channels as two instruments: reading one refreshes its channels only, at its price."""
    env, params = amjax.make(
        "SpaceInvaders-MinAtar", cost=0.05, instruments=((0, 1, 2), (3, 4, 5)), instrument_costs=(0.1, 0.2)
    )
    assert env.action_space(params).n == 4 * 4 and env.observation_space(params).shape == (10, 10, 8)
    obs, state = env.reset(jax.random.key(0), params)
    inner, inner_params = gymnax.make("SpaceInvaders-MinAtar")
    _, inner_state = inner.reset(jax.random.key(0), inner_params)
    start = np.asarray(obs[..., :6])
    for i in range(6):  # read nothing: the starting frame stays
        obs, state, reward, *_, info = env.step(jax.random.key(i), state, 0, params)
        _, inner_state, *_ = inner.step(jax.random.key(i), inner_state, 0, inner_params)
    np.testing.assert_array_equal(obs[..., :6], start)
    obs, state, reward, *_, info = env.step(jax.random.key(6), state, 1 * 4, params)  # mask 1: instrument 0
    inner_obs, *_ = inner.step(jax.random.key(6), inner_state, 0, inner_params)
    np.testing.assert_array_equal(obs[..., :3], inner_obs[..., :3])  # fresh
    np.testing.assert_array_equal(obs[..., 3:6], start[..., 3:6])  # still the starting frame's
    np.testing.assert_array_equal(obs[0, 0, 6:], [1.0, 0.0])  # the two flags
    assert float(info["cost"]) == pytest.approx(0.05 + 0.1)


def test_a_2d_observation_given_to_the_wrapper_directly_is_refused():
    catch, params = gymnax.make("Catch-bsuite")
    with pytest.raises(TypeError, match="amjax.make or amjax.wrap"):
        ActiveMeasure(catch, env_params=params)
    ActiveMeasure(catch, flag=False, env_params=params)  # nothing appended: any shape
