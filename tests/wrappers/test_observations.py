"""Discrete observations (gymnax's FrozenLake-misc) as one-hot vectors: step by step against gymnax's own env, under
the active-measure wrapper with its options, and trained by the agents."""

from __future__ import annotations

import gymnax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import amjax
from amjax.wrappers.observations import OneHotObservation, standard_observations

LAKE, LAKE_PARAMS = gymnax.make("FrozenLake-misc")
ONE_HOT_LAKE = OneHotObservation(LAKE, LAKE_PARAMS)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**16), actions=st.lists(st.integers(0, 3), min_size=60, max_size=60))
def test_one_hot_steps_like_gymnax_frozen_lake(rollout, seed, actions):
    """Same keys, same actions: the one-hot env's observations are gymnax's, one-hot; rewards and ends equal."""
    want = rollout(LAKE, LAKE_PARAMS, jax.random.key(seed), jnp.asarray(actions))
    got = rollout(ONE_HOT_LAKE, LAKE_PARAMS, jax.random.key(seed), jnp.asarray(actions))
    np.testing.assert_array_equal(got.obs0, np.eye(16)[want.obs0])
    np.testing.assert_array_equal(got.obs, np.eye(16)[want.obs])
    np.testing.assert_array_equal(got.info["final_observation"], np.eye(16)[want.info["final_observation"]])
    for name in ("reward", "terminated", "truncated"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name))


def test_spaces_and_what_is_left_alone():
    inner, params = gymnax.make("FrozenLake-misc")
    env = standard_observations(inner, params)
    assert isinstance(env, OneHotObservation)
    assert env.observation_space(params).shape == (16,)
    assert env.action_space(params).n == 4
    cartpole, cartpole_params = gymnax.make("CartPole-v1")
    assert standard_observations(cartpole, cartpole_params) is cartpole  # Box observations: unchanged
    with pytest.raises(TypeError, match="Discrete observation space"):
        OneHotObservation(cartpole, cartpole_params)


def test_frozen_lake_takes_every_measurement_option():
    env, params = amjax.make("FrozenLake-misc", cost=0.05, extra_obs=("since_measured", "last_action"), budget=5)
    assert env.observation_space(params).shape == (16 + 1 + 1 + 4 + 1,)  # one-hot, flag, since, action, budget
    env, params = amjax.make("FrozenLake-misc", cost=0.05, instruments=((0, 1, 2, 3, 4, 5, 6, 7), tuple(range(8, 16))))
    assert env.action_space(params).n == 4 * 4 and env.observation_space(params).shape == (18,)
    env, params = amjax.make("FrozenLake-misc", vanilla=True)
    assert env.observation_space(params).shape == (16,)


def test_unmeasured_steps_show_the_last_measured_cell():
    env, params = amjax.make("FrozenLake-misc", cost=0.05)
    first, state = env.reset(jax.random.key(0), params)
    np.testing.assert_array_equal(first, [*np.eye(16)[0], 1.0])  # the start cell, fresh
    shown, ended = [first], [False]
    actions = [2, 2, 6, 1, 1, 5] * 3  # right, right, right + measure, down, down, down + measure
    for i, action in enumerate(actions):
        obs, state, _, terminated, truncated, info = env.step(jax.random.key(i), state, action, params)
        shown.append(np.asarray(obs))
        ended.append(bool(terminated | truncated))
        assert float(info["cost"]) == pytest.approx(0.05 if action >= 4 else 0.0)
    shown = np.array(shown)
    assert np.all(shown[:, :16].sum(axis=1) == 1.0)  # always one cell
    for i, action in enumerate(actions, start=1):
        if ended[i]:  # an auto-reset's first observation is a free measurement
            np.testing.assert_array_equal(shown[i], [*np.eye(16)[0], 1.0])
        elif action < 4:  # unmeasured: the cell last shown, flagged stale
            np.testing.assert_array_equal(shown[i, :16], shown[i - 1, :16])
            assert shown[i, 16] == 0.0
        else:
            assert shown[i, 16] == 1.0


@pytest.mark.slow
def test_ppo_and_dqn_train_on_frozen_lake(tmp_path):
    """The sweep runner trains both agents on the one-hot env; the rows hold real, bounded scores."""
    from amjax.sweep import SweepSpec, run_sweep

    spec = SweepSpec(
        envs=("FrozenLake-misc",),
        agents=("ppo", "dqn"),
        costs=(0.05,),
        seeds=(0,),
        total_timesteps=4096,
        eval_every=2048,
        eval_episodes=4,
    )
    result = run_sweep(spec, tmp_path / "lake", progress=False, devices=jax.devices()[:1])
    rows = result.results
    assert len(rows) == 2 * 2 and set(rows["agent"]) == {"ppo", "dqn"}
    # At most the goal's reward of 1 per episode, less what was paid for measurements.
    assert np.isfinite(rows["eval_return"]).all() and (rows["eval_return"] <= 1.0).all()
    assert ((rows["eval_measurements"] >= 0) & np.isfinite(rows["eval_measurements"])).all()
