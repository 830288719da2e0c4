"""Tests for the Gymnasium bridges in `amjax.wrappers.gymnasium`.

The NumPy `ActiveMeasureWrapper` around Gymnasium's own CartPole and Pendulum is stepped side by side
with the JAX `ActiveMeasure` started from the same physical state (gymnax's own test recipe: copy the
Gymnasium state into the gymnax `EnvState`). Gymnasium integrates in float64 and gymnax in float32
(gymnasium/envs/classic_control/cartpole.py stores `self.state` as float64); on short random-action
CartPole episodes the gap stays below 1e-6 (3e-7 measured), so those run free. The inverted pendulum is
unstable in open loop: on 200-step balanced episodes the gap reached 1e-2 to 2e-1 (measured, seeds 0-4),
so there, and on Pendulum, the physical state (not the wrapper's memory) is copied across before every
step, as gymnax's own tests do, and each step is compared at 1e-5.
"""

from __future__ import annotations

import ast
import functools
import pathlib
import warnings
from typing import Any

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from gymnasium.utils.seeding import np_random
from gymnax.environments import spaces as gymnax_spaces
from gymnax.environments.classic_control import cartpole, pendulum
from hypothesis import given, settings
from hypothesis import strategies as st

import amjax
from amjax.wrappers.gymnasium import (
    ActiveMeasureWrapper,
    GymnasiumEnv,
    gymnasium_space,
    to_gymnasium,
)

ATOL = 1e-5
# Every option beyond the paper at once (amjax.make's and ActiveMeasureWrapper's arguments).
OPTIONS = {"extra_obs": ("since_measured", "last_action"), "budget": 3.0, "reward_timing": "on_measure"}


# -- fixtures and helpers ----------------------------------------------------------------------------


@functools.cache
def made(env_id: str, **kwargs: Any) -> tuple[Any, Any]:
    """`amjax.make`, one env object per configuration: its compiled functions are shared by tests.

    The cost is traced, so tests vary it with `params.replace` without compiling again.
    """
    return amjax.make(env_id, **kwargs)


@pytest.fixture(scope="module")
def jax_cartpole() -> tuple[Any, Any]:
    """amjax's 200-step CartPole, mode "last"."""
    return made("CartPole-v0")


@pytest.fixture(scope="module")
def exported() -> tuple[GymnasiumEnv, Any, Any]:
    """CartPole-v0 at cost 0.2 as a Gymnasium env, plus the JAX env and params it wraps."""
    env, params = made("CartPole-v0")
    params = params.replace(cost=jnp.float32(0.2))
    return to_gymnasium(env, params), env, params


def gym_cartpole(**kwargs: Any) -> ActiveMeasureWrapper:
    """Gymnasium's CartPole with the paper's 200-step limit, wrapped."""
    return ActiveMeasureWrapper(gymnasium.make("CartPole-v1", max_episode_steps=200), **kwargs)


def cartpole_state(env: ActiveMeasureWrapper, time: Any) -> cartpole.EnvState:
    x, x_dot, theta, theta_dot = np.asarray(env.unwrapped.state, np.float32)
    return cartpole.EnvState(x=x, x_dot=x_dot, theta=theta, theta_dot=theta_dot, time=time)


def balance(state: np.ndarray) -> int:
    """A linear controller that keeps CartPole up for 200 steps (checked on seeds 0-4)."""
    x, x_dot, theta, theta_dot = state
    return int(theta + 0.5 * theta_dot + 0.05 * x + 0.1 * x_dot > 0)


def assert_same_step(gym_out: tuple, jax_out: tuple, cost: float) -> None:
    """One Gymnasium step against one JAX step; the JAX observation of a done step is in info."""
    obs, reward, terminated, truncated, info = gym_out
    j_obs, _, j_reward, j_terminated, j_truncated, j_info = jax_out
    assert (terminated, truncated) == (bool(j_terminated), bool(j_truncated))
    j_seen = j_info["final_observation"] if terminated or truncated else j_obs
    np.testing.assert_allclose(obs, np.asarray(j_seen), rtol=0, atol=ATOL)
    assert info["measured"] == bool(j_info["measured"])
    assert info["cost"] == pytest.approx(float(j_info["cost"]), rel=1e-6)
    assert info["cost"] == (cost if info["measured"] else 0.0)
    assert info["raw_reward"] == pytest.approx(float(j_info["raw_reward"]), rel=1e-5, abs=1e-5)
    assert reward == pytest.approx(float(j_reward), rel=1e-5, abs=1e-5)
    assert reward == pytest.approx(info["raw_reward"] - info["cost"])


class SpaceEnv(gymnasium.Env):
    """A do-nothing env with the given spaces."""

    def __init__(self, action_space: gymnasium.Space, observation_space: gymnasium.Space | None = None):
        self.action_space = action_space
        self.observation_space = observation_space or gymnasium.spaces.Box(-1, 1, (3,))

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple:
        super().reset(seed=seed)
        return self.observation_space.sample(), {}

    def step(self, action: Any) -> tuple:
        return self.observation_space.sample(), 0.0, False, False, {}


# -- 1. the NumPy wrapper against the JAX wrapper -----------------------------------------------------


@pytest.mark.parametrize("cost", [0.0, 0.2, 0.35])
@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_cartpole_trajectories_match_jax_wrapper(jax_cartpole, seed: int, cost: float) -> None:
    env, params = jax_cartpole
    params = params.replace(cost=jnp.float32(cost))
    gym_env = gym_cartpole(cost=cost)
    rng = np.random.default_rng(seed)
    for episode in range(2):
        obs, _ = gym_env.reset(seed=100 * seed + episode)
        assert obs[-1] == 1.0 and obs.dtype == np.float32
        state = amjax.MeasureState(env_state=cartpole_state(gym_env, 0), last_obs=jnp.asarray(obs[:-1]))
        measure_prob = rng.uniform(0.1, 0.9)
        for t in range(200):
            action = int(rng.integers(2)) + 2 * int(rng.random() < measure_prob)
            gym_out = gym_env.step(action)
            jax_out = env.step(jax.random.key(t), state, action, params)
            assert_same_step(gym_out, jax_out, cost)
            state = jax_out[1]
            if gym_out[2] or gym_out[3]:
                break


@pytest.mark.parametrize("seed", [0, 1])
def test_cartpole_truncation_matches_jax_wrapper(jax_cartpole, seed: int) -> None:
    env, params = jax_cartpole
    params = params.replace(cost=jnp.float32(0.1))
    gym_env = gym_cartpole(cost=0.1)
    obs, _ = gym_env.reset(seed=seed)
    state = amjax.MeasureState(env_state=cartpole_state(gym_env, 0), last_obs=jnp.asarray(obs[:-1]))
    rng = np.random.default_rng(seed)
    for t in range(200):
        # The physics (float64 there, float32 here) is copied across; the memory is the wrapper's.
        state = state.replace(env_state=cartpole_state(gym_env, t))
        action = balance(gym_env.unwrapped.state) + 2 * int(rng.random() < 0.3)
        gym_out = gym_env.step(action)
        jax_out = env.step(jax.random.key(t), state, action, params)
        assert_same_step(gym_out, jax_out, 0.1)
        state = jax_out[1]
        assert gym_out[3] == (t == 199) and not gym_out[2]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_options_match_the_jax_wrapper(seed: int) -> None:
    """Staleness features, the budget and rewards paid on measurement, step for step as the JAX wrapper's."""
    env, params = made("CartPole-v0", cost=0.2, **OPTIONS)
    gym_env = gym_cartpole(cost=0.2, **OPTIONS)
    rng = np.random.default_rng(seed)
    refused = withheld = 0
    for episode in range(3):
        obs, _ = gym_env.reset(seed=100 * seed + episode)
        j_obs, state = env.reset(jax.random.key(0), params)
        np.testing.assert_array_equal(obs[4:], np.asarray(j_obs)[4:])
        state = state.replace(env_state=cartpole_state(gym_env, 0), last_obs=jnp.asarray(obs[:4]))
        for t in range(200):
            action = int(rng.integers(2)) + 2 * int(rng.random() < 0.4)
            gym_out = gym_env.step(action)
            jax_out = env.step(jax.random.key(t), state, action, params)
            assert_same_step(gym_out, jax_out, 0.2)
            info, j_info = gym_out[4], jax_out[5]
            assert info["refused"] == bool(j_info["refused"])
            assert info["withheld"] == pytest.approx(float(j_info["withheld"]), abs=1e-5)
            assert info["paid_at_truncation"] == pytest.approx(float(j_info["paid_at_truncation"]), abs=1e-5)
            refused, withheld = refused + info["refused"], withheld + (info["withheld"] > 0)
            state = jax_out[1]
            if gym_out[2] or gym_out[3]:
                break
    assert refused and withheld  # both options did something


def test_since_measured_needs_a_time_limit() -> None:
    with pytest.raises(ValueError, match="extra_obs"):
        ActiveMeasureWrapper(SpaceEnv(gymnasium.spaces.Discrete(2)), extra_obs=("since_measured",))
    wrapped = ActiveMeasureWrapper(SpaceEnv(gymnasium.spaces.Discrete(3)), extra_obs=("last_action",), budget=2)
    assert wrapped.observation_space.shape == (3 + 1 + 3 + 1,)


def test_pendulum_box_actions_match_jax_wrapper() -> None:
    env, params = made("Pendulum-v1")
    params = params.replace(cost=jnp.float32(0.3))
    gym_env = ActiveMeasureWrapper(gymnasium.make("Pendulum-v1"), cost=0.3)
    assert gym_env.action_space == gymnasium.spaces.Box(
        np.array([0.0, -2.0], np.float32), np.array([1.0, 2.0], np.float32), dtype=np.float32
    )
    obs, _ = gym_env.reset(seed=7)
    last_obs = jnp.asarray(obs[:-1])
    rng = np.random.default_rng(7)
    for t in range(200):
        # The physics (float64 there, float32 here) is copied across; the memory is the wrapper's.
        theta, theta_dot = np.asarray(gym_env.unwrapped.state, np.float32)
        inner = pendulum.EnvState(theta=theta, theta_dot=theta_dot, last_u=jnp.float32(0), time=t)
        state = amjax.MeasureState(env_state=inner, last_obs=last_obs)
        action = np.array([rng.uniform(0, 1), rng.uniform(-2, 2)], np.float32)
        gym_out = gym_env.step(action)
        jax_out = env.step(jax.random.key(t), state, action, params)
        assert_same_step(gym_out, jax_out, 0.3)
        assert gym_out[4]["measured"] == (action[0] >= 0.5)
        last_obs = jax_out[1].last_obs
    assert gym_out[3]  # Pendulum-v1 truncates at 200 steps in both


def test_noisy_mode_is_true_state_plus_gaussian_noise() -> None:
    std = 0.05
    gym_env = gym_cartpole(mode="noisy", noise_std=std)
    rng = np.random.default_rng(0)
    residuals = []
    obs, _ = gym_env.reset(seed=0)
    while len(residuals) < 600:
        measure = int(rng.random() < 0.2)
        obs, _, terminated, truncated, info = gym_env.step(int(rng.integers(2)) + 2 * measure)
        true_obs = np.asarray(gym_env.unwrapped.state, np.float32)
        assert obs[-1] == measure
        if measure:
            np.testing.assert_array_equal(obs[:-1], true_obs)
        else:
            residuals.append(obs[:-1] - true_obs)
        if terminated or truncated:
            gym_env.reset()
    residuals = np.array(residuals)  # (n, 4); CartPole's bounds are far from these states
    n = len(residuals)
    np.testing.assert_array_less(np.abs(residuals.mean(0)), 4 * std / np.sqrt(n))
    np.testing.assert_allclose(residuals.std(0), std, rtol=0.15)


def test_noisy_mode_clips_to_the_observation_bounds() -> None:
    gym_env = gym_cartpole(mode="noisy", noise_std=100.0)
    space = gym_env.observation_space
    gym_env.reset(seed=1)
    seen = []
    for t in range(30):
        obs, _, terminated, truncated, _ = gym_env.step(t % 2)
        assert obs in space and obs[-1] == 0.0
        seen.append(obs)
        if terminated or truncated:
            gym_env.reset()
    seen = np.array(seen)
    # x and theta are bounded (+-4.8, +-0.418): most noisy draws land on a bound; velocities are not.
    assert np.mean(np.abs(seen[:, 0]) == space.high[0]) > 0.5
    assert np.mean(np.abs(seen[:, 2]) == space.high[2]) > 0.5
    assert np.abs(seen[:, 1]).max() > 50


def test_random_mode_samples_the_space_reproducibly() -> None:
    def views(seed: int) -> np.ndarray:
        gym_env = gym_cartpole(mode="random")
        gym_env.reset(seed=seed)
        out = []
        for t in range(200):
            obs, _, terminated, truncated, _ = gym_env.step(t % 2)
            assert obs in gym_env.observation_space and obs[-1] == 0.0
            out.append(obs)
            if terminated or truncated:
                gym_env.reset()
        return np.array(out)

    first = views(3)
    np.testing.assert_array_equal(first, views(3))
    assert not np.array_equal(first, views(4))
    # Bounded entries are uniform on [-4.8, 4.8] and [-0.418, 0.418]; unbounded ones are N(0, 1).
    assert first[:, 0].min() < -3 and first[:, 0].max() > 3
    assert np.abs(first[:, 2]).max() <= 0.41887903
    assert 0.7 < first[:, 1].std() < 1.3


def test_discrete_start_offsets_the_wrapped_actions() -> None:
    env = SpaceEnv(gymnasium.spaces.Discrete(3, start=-1))
    wrapped = ActiveMeasureWrapper(env)
    assert wrapped.action_space == gymnasium.spaces.Discrete(6, start=-1)
    assert wrapped.split_action(-1) == (-1, False)
    assert wrapped.split_action(1) == (1, False)
    assert wrapped.split_action(2) == (-1, True)
    assert wrapped.split_action(4) == (1, True)
    with pytest.raises(ValueError, match=r"integers in \[-1, 5\)"):
        wrapped.split_action(5)


# -- 2. the exported environment ----------------------------------------------------------------------

ADVISORY = "we recommend using a symmetric and normalized space"  # Pendulum's own [-2, 2] torque


NOISY = {"mode": "noisy", "noise_std": 0.3}


@pytest.mark.parametrize(
    ("env_id", "kwargs", "cost"),
    [
        ("CartPole-v0", {}, 0.2),
        ("CartPole-v0", {"vanilla": True}, None),
        ("CartPole-v0", NOISY, 0.25),
        ("Acrobot-v1", {}, 0.1),
        ("Pendulum-v1", {}, 0.1),
        ("CartPole-v0", OPTIONS, 0.2),
        ("CartPole-v0", (("instruments", "default"), ("instrument_noise", (0.0, 0.1))), 0.2),
        ("Pendulum-v1", (("instruments", ((0, 1), (2,))),), 0.1),
    ],
    ids=[
        "CartPole-v0",
        "CartPole-v0-vanilla",
        "CartPole-v0-noisy",
        "Acrobot-v1",
        "Pendulum-v1",
        "options",
        "instruments",
        "Pendulum-v1-instruments",
    ],
)
def test_exported_env_passes_check_env(env_id: str, kwargs: Any, cost: float | None) -> None:
    env, params = made(env_id, **dict(kwargs))  # (name, value) pairs where a value is a tuple (hashable for made)
    if cost is not None:
        params = params.replace(cost=jnp.float32(cost))
    gym_env = to_gymnasium(env, params)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(gym_env)  # with a spec: seeding determinism, gymnasium.make(spec), close
    messages = [str(w.message) for w in caught if ADVISORY not in str(w.message)]
    assert messages == []
    obs, _ = gym_env.reset(seed=0)
    assert obs.dtype == np.float32 and obs in gym_env.observation_space
    assert obs.flags.writeable  # arrays from jax.device_get are read-only; users may normalise in place


def test_exported_env_matches_a_manual_jax_loop() -> None:
    # The documented seeding: reset draws a uint32 from np_random, splits key(seed) into (reset, run).
    env, params = made("CartPole-v0", **NOISY)
    params = params.replace(cost=jnp.float32(0.25))
    gym_env = to_gymnasium(env, params)
    rng = np.random.default_rng(5)
    for seed in (5, 6):
        obs, _ = gym_env.reset(seed=seed)
        jax_seed = np_random(seed)[0].integers(0, 2**32, dtype=np.uint32)
        key_reset, key = jax.random.split(jax.random.key(jax_seed))
        j_obs, state = env.reset(key_reset, params)
        np.testing.assert_allclose(obs, j_obs, atol=1e-6)
        done = False
        while not done:
            action = int(rng.integers(4))
            gym_out = gym_env.step(action)
            key, key_step = jax.random.split(key)
            jax_out = env.step(key_step, state, action, params)
            assert_same_step(gym_out, jax_out, 0.25)
            state, done = jax_out[1], gym_out[2] or gym_out[3]


def test_exported_cartpole_v0_episodes_end_by_200_steps(exported) -> None:
    gym_env = exported[0]
    lengths = []
    gym_env.reset(seed=0)
    for episode in range(4):
        obs, _ = gym_env.reset()
        for t in range(1, 1000):
            # Always measure (fresh observation); balance in episodes 0 and 2, act at random else.
            control = balance(obs[:-1]) if episode % 2 == 0 else int(gym_env.np_random.integers(2))
            obs, reward, terminated, truncated, info = gym_env.step(control + 2)
            assert info["measured"] and reward == pytest.approx(1.0 - 0.2)
            assert truncated == (t == 200)
            if terminated or truncated:
                break
        lengths.append(t)
        with pytest.raises(RuntimeError, match="call reset"):
            gym_env.step(0)
    assert max(lengths) == 200 and min(lengths) < 200, lengths


def test_exported_env_refuses_bad_use(exported) -> None:
    gym_env, env, params = exported
    with pytest.raises(RuntimeError, match="call reset"):
        to_gymnasium(env, params).step(0)
    gym_env.reset(seed=0)
    for action in (4, -1, 1.0, True, "1", np.array([1, 2]), None):
        with pytest.raises(ValueError, match=r"action: got .*; allowed values: integers in \[0, 4\)"):
            gym_env.step(action)
    gym_env.step(np.int64(3))  # NumPy integers are fine (Stable-Baselines3 passes them)
    with pytest.raises(ValueError, match="options"):
        gym_env.reset(options={"low": -0.1})
    with pytest.raises(ValueError, match="seed"):
        gym_env.reset(seed=-1)
    with pytest.raises(ValueError, match="seed"):
        to_gymnasium(env, params, seed=-1)
    with pytest.raises(ValueError, match="render_mode"):
        GymnasiumEnv(env, params, render_mode="human")
    with pytest.raises(TypeError, match="gymnax-API environment"):
        to_gymnasium(gymnasium.make("CartPole-v1"), None)


def test_exported_env_refuses_batched_params() -> None:
    env, params = amjax.make("CartPole-v0", cost=[0.1, 0.2])
    with pytest.raises(ValueError, match="params: one environment's params"):
        to_gymnasium(env, params)


def test_exported_env_takes_new_params_of_the_same_structure() -> None:
    # The bridge hands its params to the compiled step packed (amjax.cores.TreeLayout); assigning new ones repacks.
    env, params = amjax.make("CartPole-v0", cost=0.1)
    gym_env = to_gymnasium(env, params, seed=0)
    gym_env.reset(seed=1)
    measured = 2  # CartPole's control 0, measured
    assert gym_env.step(measured)[1] == pytest.approx(0.9)
    gym_env.params = params.replace(cost=0.5)
    assert gym_env.step(measured)[1] == pytest.approx(0.5)
    gym_env.params = params.replace(cost=1)  # a Python int for a float32 leaf
    assert gym_env.step(measured)[1] == pytest.approx(0.0)
    with pytest.raises(ValueError, match=r"params: new params must have the structure.*leaf \.cost"):
        gym_env.params = params.replace(cost=jnp.zeros(3))
    assert gym_env.step(measured)[1] == pytest.approx(0.0)  # a refused assignment changes nothing


def test_exported_envs_on_one_env_object_share_one_compiled_step() -> None:
    env, params = amjax.make("CartPole-v0", cost=0.1)
    first, second = to_gymnasium(env, params, seed=0), to_gymnasium(env, params.replace(cost=0.3), seed=1)
    for gym_env in (first, second):
        gym_env.reset()
        gym_env.step(2)
    assert first._compiled_step is second._compiled_step
    other_env, other_params = amjax.make("CartPole-v0", cost=0.1)
    assert to_gymnasium(other_env, other_params)._compiled_step is not first._compiled_step


def test_exported_box_actions_are_checked() -> None:
    env, params = made("Pendulum-v1")
    gym_env = to_gymnasium(env, params.replace(cost=jnp.float32(0.1)), seed=0)
    gym_env.reset()
    bad = ([0.5], [0.5, 2.5], [1.5, 0.0], [np.nan, 0.0], [[0.5, 0.0]], "x")
    for action in bad:
        with pytest.raises(ValueError, match=r"action: got .*; allowed values: arrays of shape \(2,\)"):
            gym_env.step(action)
    obs, reward, *_, info = gym_env.step([0.75, -2.0])  # a list and float64 are fine
    assert info["measured"] and info["cost"] == pytest.approx(0.1)


def test_gymnasium_space_conversion() -> None:
    box = gymnax_spaces.Box(0.0, jnp.array([1.0, 2.0]), (2,), jnp.float32)  # scalar low, array high
    assert gymnasium_space(box) == gymnasium.spaces.Box(
        np.zeros(2, np.float32), np.array([1.0, 2.0], np.float32), dtype=np.float32
    )
    assert gymnasium_space(gymnax_spaces.Discrete(5)) == gymnasium.spaces.Discrete(5)
    with pytest.raises(TypeError, match="allowed: gymnax Discrete, Box"):
        gymnasium_space(gymnax_spaces.Dict({"a": gymnax_spaces.Discrete(2)}))


# -- 3. invariants over random action sequences (hypothesis) -----------------------------------------


def check_invariants(gym_env: gymnasium.Env, actions: list[int], cost: float, n: int) -> None:
    """Cost charged iff measured; flag = measured; a stale view is the last measured observation."""
    obs, _ = gym_env.reset(seed=0)
    assert obs[-1] == 1.0
    last = obs[:-1]
    for action in actions:
        obs, reward, terminated, truncated, info = gym_env.step(action)
        measured = action >= n
        assert info["measured"] is measured
        assert info["cost"] == pytest.approx(cost * measured, rel=1e-6)
        assert reward == pytest.approx(info["raw_reward"] - cost * measured, rel=1e-6)
        assert obs[-1] == float(measured)
        if measured:
            if isinstance(gym_env, ActiveMeasureWrapper):
                true_obs = np.asarray(gym_env.unwrapped.state, np.float32)
                np.testing.assert_array_equal(obs[:-1], true_obs)
            last = obs[:-1]
        else:
            np.testing.assert_array_equal(obs[:-1], last)
        if terminated or truncated:
            obs, _ = gym_env.reset()
            assert obs[-1] == 1.0
            last = obs[:-1]


ACTIONS = st.lists(st.integers(0, 3), min_size=20, max_size=80)  # most run past an episode end
COSTS = st.floats(0.0, 2.0, allow_nan=False)
FAST = settings(max_examples=30, deadline=None)


@FAST
@given(actions=ACTIONS, cost=COSTS)
def test_numpy_wrapper_invariants(actions: list[int], cost: float) -> None:
    check_invariants(gym_cartpole(cost=cost), actions, cost, n=2)


@FAST
@given(actions=ACTIONS, cost=COSTS)
def test_exported_env_invariants(exported, actions: list[int], cost: float) -> None:
    _, env, params = exported
    gym_env = to_gymnasium(env, params.replace(cost=jnp.float32(cost)))  # same compile
    check_invariants(gym_env, actions, float(np.float32(cost)), n=2)


# -- 4. argument checks ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("kwargs", "named"),
    [
        ({"cost": -0.1}, "cost"),
        ({"cost": float("nan")}, "cost"),
        ({"cost": float("inf")}, "cost"),
        ({"cost": "high"}, "cost"),
        ({"mode": "stale"}, "mode"),
        ({"mode": "noisy"}, "noise_std"),
        ({"mode": "noisy", "noise_std": -1.0}, "noise_std"),
        ({"mode": "noisy", "noise_std": float("nan")}, "noise_std"),
        ({"mode": "noisy", "noise_std": float("inf")}, "noise_std"),
        ({"mode": "last", "noise_std": 0.1}, "noise_std"),
        ({"mode": "random", "noise_std": 0.1}, "noise_std"),
        ({"mode": "noisy", "noise_std": 0.0}, "noise_std"),
        ({"budget": 2.5}, "budget"),
        ({"flag": "yes"}, "flag"),
    ],
)
def test_bad_arguments_give_the_same_errors_as_amjax_make(kwargs: dict, named: str) -> None:
    with pytest.raises((ValueError, TypeError)) as from_make:
        amjax.make("CartPole-v0", **kwargs)
    with pytest.raises(from_make.type) as from_wrapper:
        gym_cartpole(**kwargs)
    assert str(from_wrapper.value) == str(from_make.value)
    assert str(from_wrapper.value).startswith(named)


def test_array_cost_is_refused() -> None:
    with pytest.raises(ValueError, match="cost: got .*one finite number"):
        gym_cartpole(cost=[0.1, 0.2])


@pytest.mark.parametrize(
    ("action_space", "observation_space", "match"),
    [
        (gymnasium.spaces.MultiDiscrete([2, 2]), None, "allowed: Discrete, Box"),
        (gymnasium.spaces.MultiBinary(2), None, "allowed: Discrete, Box"),
        (gymnasium.spaces.Box(-1, 1, (2, 2)), None, "1-D floating Box"),
        (gymnasium.spaces.Box(-1, 1, (2,), dtype=np.int64), None, "1-D floating Box"),
        (gymnasium.spaces.Discrete(2), gymnasium.spaces.Discrete(4), "allowed: Box"),
        (
            gymnasium.spaces.Discrete(2),
            gymnasium.spaces.Dict({"a": gymnasium.spaces.Box(-1, 1, (2,))}),
            "allowed: Box",
        ),
        (gymnasium.spaces.Discrete(2), gymnasium.spaces.Box(-1, 1, (2, 2)), "ReshapeObservation"),
    ],
)
def test_unsupported_spaces_are_refused(action_space, observation_space, match: str) -> None:
    with pytest.raises(TypeError, match=match):
        ActiveMeasureWrapper(SpaceEnv(action_space, observation_space))


def test_image_observations_work_without_the_flag() -> None:
    env = SpaceEnv(gymnasium.spaces.Discrete(2), gymnasium.spaces.Box(0, 255, (2, 2), np.uint8))
    wrapped = ActiveMeasureWrapper(env, flag=False)
    obs, _ = wrapped.reset(seed=0)
    first = obs.copy()
    obs += 1  # a caller normalising in place must not change what the wrapper remembers
    stale, *_ = wrapped.step(1)
    assert obs.shape == (2, 2) and obs.dtype == np.float32
    np.testing.assert_array_equal(stale, first)


@pytest.mark.parametrize("seed", [0, 1])
def test_image_observations_match_the_jax_wrapper(seed: int) -> None:
    """An image (MinAtar's Breakout exported to Gymnasium, plain) under the NumPy wrapper with the flag and the
    options: step for step the JAX wrapper's observations (the frame, then constant channels), rewards and ends.
    ("since_measured" is left out: the exported env's spec has no time limit, which the NumPy wrapper scales by.)"""
    options = {"extra_obs": ("last_action",), "budget": 3.0, "reward_timing": "on_measure"}
    gym_env = ActiveMeasureWrapper(to_gymnasium(*made("Breakout-MinAtar", vanilla=True)), cost=0.2, **options)
    jax_env = to_gymnasium(*made("Breakout-MinAtar", cost=0.2, **options))
    assert gym_env.observation_space == jax_env.observation_space
    assert gym_env.observation_space.shape == (10, 10, 4 + 1 + 3 + 1)
    rng = np.random.default_rng(seed)
    obs, _ = gym_env.reset(seed=seed)
    j_obs, _ = jax_env.reset(seed=seed)
    np.testing.assert_array_equal(obs, j_obs)
    for _ in range(150):
        action = int(rng.integers(6))
        out, j_out = gym_env.step(action), jax_env.step(action)
        np.testing.assert_allclose(out[0], j_out[0], rtol=0, atol=ATOL)
        assert out[1] == pytest.approx(j_out[1], abs=1e-5) and out[2:4] == j_out[2:4]
        assert out[4]["measured"] == j_out[4]["measured"]
        if out[2] or out[3]:
            break


def test_numpy_wrapper_refuses_bad_actions() -> None:
    gym_env = gym_cartpole(cost=0.1)
    with pytest.raises(RuntimeError, match="reset"):
        gym_env.step(0)
    gym_env.reset(seed=0)
    for action in (4, -1, 2.0, False, "0", np.array([0, 1]), None):
        with pytest.raises(ValueError, match=r"action: got .*; allowed values: integers in \[0, 4\)"):
            gym_env.step(action)
    pendulum_env = ActiveMeasureWrapper(gymnasium.make("Pendulum-v1"))
    pendulum_env.reset(seed=0)
    for action in ([0.5], [0.5, 0.0, 0.0], [-0.1, 0.0], [0.5, -2.5], [0.5, np.inf]):
        with pytest.raises(ValueError, match=r"action: got .*; allowed values: arrays of shape \(2,\)"):
            pendulum_env.step(action)


def _module_level(tree: ast.Module) -> list[ast.AST]:
    """The nodes of a module outside function bodies."""
    nodes, stack = [], list(tree.body)
    while stack:
        node = stack.pop()
        if not isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda):
            nodes.append(node)
            stack.extend(ast.iter_child_nodes(node))
    return nodes


def test_only_the_bridge_imports_gymnasium() -> None:
    """`gymnasium` is an optional extra: no other amjax module imports it when imported (an import
    inside a function, run only on demand, is fine). gymnax 1.0.1 itself still imports it."""
    package = pathlib.Path(amjax.__file__).parent
    importers = []
    for path in package.rglob("*.py"):
        for node in _module_level(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0:
                names = [node.module or ""]
            if any(name == "gymnasium" or name.startswith("gymnasium.") for name in names):
                importers.append(path.relative_to(package).as_posix())
    assert set(importers) <= {"wrappers/gymnasium.py"}, importers


@pytest.mark.slow
def test_stable_baselines3_trains_on_the_exported_env() -> None:
    """Stable-Baselines3's own env checker passes and PPO runs unchanged (imports torch: marked slow)."""
    sb3 = pytest.importorskip("stable_baselines3")
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    env, params = made("CartPole-v0")
    gym_env = to_gymnasium(env, params.replace(cost=jnp.float32(0.2)), seed=0)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sb3_check_env(gym_env)
    assert [str(w.message) for w in caught] == []
    model = sb3.PPO("MlpPolicy", gym_env, n_steps=64, batch_size=32, n_epochs=1, seed=0, device="cpu")
    model.learn(total_timesteps=256)
    obs, _ = gym_env.reset(seed=1)
    action, _ = model.predict(obs, deterministic=True)
    assert gym_env.action_space.contains(int(action))
