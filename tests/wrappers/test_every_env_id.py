"""Every environment of gymnax's registry, and the listed ids of the other JAX suites (Craftax, xland-minigrid: the
optional extras), under `amjax.make` with the options it can carry: reset and step under jit and a vmap over costs,
observations inside the space, the costed reward; and the Gymnasium bridge of each through Gymnasium's own
`check_env`."""

from __future__ import annotations

import warnings

import gymnax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from gymnax.environments import spaces

import amjax
from amjax.envs import suites
from amjax.envs.registry import make_env
from amjax.wrappers.gymnasium import to_gymnasium
from amjax.wrappers.observations import standard_observations

# MNISTBandit-bsuite downloads MNIST when it is built (CI has no network): every other gymnax id is tested.
GYMNAX_IDS = [env_id for env_id in gymnax.registered_envs if env_id != "MNISTBandit-bsuite"]
# Craftax's step takes about a minute to compile on 2 cores: its ids run in the slow tier.
SUITE_IDS = [
    pytest.param(
        env_id,
        marks=[pytest.mark.skipif(not suites.installed(suite), reason=suites.SUITES[suite])]
        + ([pytest.mark.slow] if suite == "craftax" else []),
    )
    for suite, ids in suites.LISTED.items()
    for env_id in ids
]
IDS = [*GYMNAX_IDS, *SUITE_IDS]
OPTIONS = {"extra_obs": ("since_measured", "last_action"), "budget": 4, "reward_timing": "on_measure"}
STEPS = 40


def _random_rollout(env, params, key):
    """Reset, then `STEPS` random actions from the action space; every observation and the step's outputs."""
    reset_key, run_key = jax.random.split(key)
    obs, state = env.reset(reset_key, params)
    space = env.action_space(params)

    def step(state, key):
        action_key, step_key = jax.random.split(key)
        action = space.sample(action_key)
        obs, state, reward, terminated, truncated, info = env.step(step_key, state, action, params)
        return state, (obs, reward, info["raw_reward"], info["cost"], info["measured"], terminated | truncated)

    return obs, jax.lax.scan(step, state, jax.random.split(run_key, STEPS))[1]


@pytest.mark.parametrize("env_id", IDS)
def test_every_gymnax_id_steps_under_jit_and_vmap(env_id):
    env, params = amjax.make(env_id, **OPTIONS)
    costs = jnp.array([0.0, 0.05, 0.3])
    batched = jax.vmap(lambda cost: params.replace(cost=cost))(costs)
    first, (obs, reward, raw, cost, measured, done) = jax.jit(
        jax.vmap(_random_rollout, (None, 0, 0)), static_argnums=0
    )(env, batched, jax.random.split(jax.random.key(0), len(costs)))
    space = env.observation_space(params)
    assert isinstance(space, spaces.Box) and first.shape == (len(costs), *space.shape)
    low, high = np.broadcast_to(space.low, space.shape), np.broadcast_to(space.high, space.shape)
    for frames in (np.asarray(first), np.asarray(obs).reshape(-1, *space.shape)):
        assert np.isfinite(frames).all() and (frames >= low).all() and (frames <= high).all()
    np.testing.assert_allclose(reward, raw - cost, rtol=0, atol=1e-5)  # the costed reward
    np.testing.assert_allclose(cost, np.asarray(measured) * costs[:, None], rtol=0, atol=1e-7)
    assert np.asarray(measured).any() and not np.asarray(measured).all()  # random actions, at most 4 per episode
    # The flag (the first value appended after the observation) is 1 exactly on measured steps and episode starts.
    features = np.asarray(obs).reshape(*obs.shape[:2], -1, space.shape[-1])[:, :, 0, :]
    np.testing.assert_array_equal(features[..., _inner_width(env_id)], np.asarray(measured | done, np.float32))


def _inner_width(env_id):
    """The width of the inner observation's feature axis (a vector's length, an image's channels) as the wrapper
    reads it: Discrete observations one-hot, 2-D ones with one channel."""
    inner, inner_params = make_env(env_id)
    return standard_observations(inner, inner_params).observation_space(inner_params).shape[-1]


ADVISORY = "we recommend using a symmetric and normalized space"  # native action bounds such as [-2, 2] torques


# Craftax's bridge is the same code as xland-minigrid's: its minute of compiling is spent once, in the test above.
@pytest.mark.parametrize("env_id", [*GYMNAX_IDS, *(p for p in SUITE_IDS if not p.values[0].startswith("craftax"))])
def test_every_gymnax_id_passes_gymnasiums_check_env(env_id):
    env, params = amjax.make(env_id, cost=0.1)
    gym_env = to_gymnasium(env, params)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(gym_env)
    messages = [str(w.message) for w in caught if ADVISORY not in str(w.message)]
    if env_id == "SimpleBandit-bsuite":  # its one observation is the constant 1: low == high, as it should be
        messages = [m for m in messages if "maximum and minimum values are equal" not in m]
    assert messages == []
    obs, _ = gym_env.reset(seed=0)
    assert obs in gym_env.observation_space and obs.shape == env.observation_space(params).shape
