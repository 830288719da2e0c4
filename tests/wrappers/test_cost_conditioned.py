"""Cost-conditioned environments (`cost_range`): each episode draws its cost from a range and shows it."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import amjax
from amjax.agents import DQNConfig, PPOConfig

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
    shown = run.obs[:, -1]  # after a step: the cost of the episode the observation belongs to
    done = run.terminated | run.truncated
    episode_cost = run.state.episode_cost
    np.testing.assert_array_equal(shown, episode_cost)
    assert run.obs0[-1] == run.state0.episode_cost
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
    """cost_range=(c, c) is the env at cost c, with c appended to every observation (same keys, same steps)."""
    env, params = CONDITIONED
    params = params.replace(cost_low=jnp.float32(0.3), cost_high=jnp.float32(0.3))
    fixed_env, fixed_params = FIXED
    actions = jnp.asarray(np.random.default_rng(1).integers(0, 4, T))
    run, fixed = (rollout(e, p, jax.random.key(5), actions) for e, p in ((env, params), (fixed_env, fixed_params)))
    np.testing.assert_array_equal(run.obs[:, :-1], fixed.obs)
    np.testing.assert_allclose(run.obs[:, -1], 0.3)
    np.testing.assert_array_equal(run.reward, fixed.reward)


def test_the_range_is_traced():
    env, params = CONDITIONED
    ranges = jnp.asarray([[0.0, 0.0], [0.2, 0.2], [1.0, 1.0]])
    batched = jax.vmap(lambda r: params.replace(cost_low=r[0], cost_high=r[1]))(ranges)
    reset = jax.jit(jax.vmap(env.reset, in_axes=(None, 0)))
    obs, _ = reset(jax.random.key(0), batched)
    np.testing.assert_allclose(obs[:, -1], [0.0, 0.2, 1.0])
    assert reset._cache_size() == 1


@pytest.mark.parametrize("kwargs, message", [
    ({"cost_range": (0.5, 0.1)}, "low <= high"),
    ({"cost_range": (0.1,)}, "a pair"),
    ({"cost_range": (-0.1, 0.2)}, "cost_range: got"),
    ({"cost_range": (0.1, 0.2), "cost": 0.3}, "cost: a cost-conditioned env"),
    ({"cost_range": (0.1, 0.2), "vanilla": True}, "vanilla"),
])
def test_bad_cost_ranges_are_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        amjax.make("CartPole-v0", **kwargs)


@pytest.mark.parametrize("fields, message", [
    ({"cost_conditioned": True, "cost_low": 0.5, "cost_high": 0.1}, "cost_low: got 0.5"),
    ({"cost_conditioned": True, "cost_high": 0.5, "cost": 0.1}, "cost: a cost-conditioned run"),
    ({"cost_high": 0.5}, "set cost_conditioned=True"),
    ({"cost_conditioned": True, "vanilla": True}, "vanilla"),
])
def test_configs_check_the_cost_range(fields, message):
    for config in (DQNConfig, PPOConfig):
        with pytest.raises(ValueError, match=message):
            config(**fields).validate()
