"""Cost-conditioned environments (`cost_range`): each episode draws its cost from a range and shows it."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import amjax
from amjax.agents import DQNConfig, DRQNConfig, PPOConfig, PPORNNConfig

T = 60


def _made(**options):
    env, params = amjax.make("CartPole-v0", **options)
    return env, params.replace(env_params=params.env_params.replace(max_steps_in_episode=7))


CONDITIONED = _made(cost_range=(0.1, 0.5))
FIXED = _made(cost=0.3)


def test_each_episode_draws_its_cost_shows_it_and_is_charged_it(rollout):
    env, params = CONDITIONED
    actions = jnp.asarray(np.random.default_rng(0).integers(0, 4, T))
    run = rollout(env, params, jax.random.key(0), actions)
    shown = run.obs[:, -1]  # after a step: the cost of the episode the observation belongs to, [0.1, 0.5] -> [-1, 1]
    done = run.terminated | run.truncated
    episode_cost = run.state.episode_cost
    np.testing.assert_allclose(shown, (episode_cost - 0.3) / 0.2, atol=1e-5)
    np.testing.assert_allclose(run.obs0[-1], (run.state0.episode_cost - 0.3) / 0.2, atol=1e-5)
    charged = np.concatenate([[run.state0.episode_cost], episode_cost[:-1]])  # the cost in force during step t
    np.testing.assert_allclose(run.info["cost"], charged * run.info["measured"], rtol=1e-6)
    assert np.all((episode_cost >= 0.1) & (episode_cost <= 0.5))
    changes = episode_cost[1:] != episode_cost[:-1]
    np.testing.assert_array_equal(changes, done[1:])  # constant within an episode, redrawn at every reset
    assert env.observation_space(params).contains(jnp.asarray(run.obs))


def test_costs_are_uniform_over_the_range():
    env, params = CONDITIONED
    _, states = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(jax.random.key(1), 20_000), params)
    costs = np.asarray(states.episode_cost)
    assert costs.min() >= 0.1 and costs.max() <= 0.5
    np.testing.assert_allclose(np.histogram(costs, bins=4, range=(0.1, 0.5))[0] / 20_000, 0.25, atol=0.015)


def test_a_single_cost_range_is_the_fixed_cost_env(rollout):
    """cost_range=(c, c) is the env at cost c with 0 appended to every observation (same keys, same steps); a
    range's env scored at c (draw range (c, c), the scaling range kept) shows c scaled by the range."""
    fixed_env, fixed_params = FIXED
    actions = jnp.asarray(np.random.default_rng(1).integers(0, 4, T))
    fixed = rollout(fixed_env, fixed_params, jax.random.key(5), actions)
    single = _made(cost_range=(0.3, 0.3))
    env, params = CONDITIONED
    at_03 = (env, params.replace(cost_low=jnp.float32(0.3), cost_high=jnp.float32(0.3)))
    for (env, params), shown in ((single, 0.0), (at_03, 0.0)):
        run = rollout(env, params, jax.random.key(5), actions)
        np.testing.assert_array_equal(run.obs[:, :-1], fixed.obs)
        np.testing.assert_allclose(run.obs[:, -1], shown, atol=1e-6)
        np.testing.assert_array_equal(run.reward, fixed.reward)
    at_05 = params.replace(cost_low=jnp.float32(0.5), cost_high=jnp.float32(0.5))
    np.testing.assert_allclose(rollout(env, at_05, jax.random.key(5), actions).obs[:, -1], 1.0, atol=1e-6)


def test_a_cost_beyond_the_scaling_range_widens_the_bounds():
    env, params = CONDITIONED
    beyond = params.replace(cost_low=jnp.float32(0.7), cost_high=jnp.float32(0.7))  # scaled: 2
    obs, _ = env.reset(jax.random.key(0), beyond)
    np.testing.assert_allclose(obs[-1], 2.0, atol=1e-6)
    assert env.observation_space(beyond).contains(obs)
    space = env.observation_space(params)
    assert float(space.low[-1]) == -1.0 and float(space.high[-1]) == 1.0


def test_the_range_is_traced():
    env, params = CONDITIONED
    ranges = jnp.asarray([[0.1, 0.1], [0.3, 0.3], [0.5, 0.5]])  # scored at three costs, scaled by [0.1, 0.5]
    batched = jax.vmap(lambda r: params.replace(cost_low=r[0], cost_high=r[1]))(ranges)
    reset = jax.jit(jax.vmap(env.reset, in_axes=(None, 0)))
    obs, states = reset(jax.random.key(0), batched)
    np.testing.assert_allclose(obs[:, -1], [-1.0, 0.0, 1.0], atol=1e-6)
    np.testing.assert_allclose(states.episode_cost, [0.1, 0.3, 0.5], atol=1e-7)
    assert reset._cache_size() == 1


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"cost_range": (0.5, 0.1)}, "low <= high"),
        ({"cost_range": (0.1,)}, "a pair"),
        ({"cost_range": (-0.1, 0.2)}, "cost_range: got"),
        ({"cost_range": (0.1, 0.2), "cost": 0.3}, "cost: a cost-conditioned env"),
        ({"cost_range": (0.1, 0.2), "vanilla": True}, "vanilla"),
    ],
)
def test_bad_cost_ranges_are_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        amjax.make("CartPole-v0", **kwargs)


@pytest.mark.parametrize(
    "fields, message",
    [
        ({"cost_conditioned": True, "cost_low": 0.5, "cost_high": 0.1}, "cost_low: got 0.5"),
        ({"cost_conditioned": True, "cost_high": 0.5, "cost": 0.1}, "cost: a cost-conditioned run"),
        ({"cost_high": 0.5}, "set cost_conditioned=True"),
        ({"cost_conditioned": True, "vanilla": True}, "vanilla"),
    ],
)
def test_configs_check_the_cost_range(fields, message):
    for config in (DQNConfig, PPOConfig, DRQNConfig, PPORNNConfig):
        with pytest.raises(ValueError, match=message):
            config(**fields).validate()
