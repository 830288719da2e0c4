"""Instruments: the observation read in parts, each with its own flag, price and noise.

Checked against the paper's wrapper (one instrument holding every feature is that wrapper, bit for bit), a plain
Python loop over an always-measured run driven with the same keys (mode "last" hands the inner env the key
unchanged), the NumPy wrapper step for step, and the clear errors."""

from __future__ import annotations

import math

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import amjax
from amjax.agents import DQNConfig, PPOConfig
from amjax.agents.policies import Categorical, GaussianOutputs, HybridGaussian
from amjax.wrappers.gymnasium import ActiveMeasureWrapper
from amjax.wrappers.instruments import decode_mask, encode_mask

T = 40
N = 2  # CartPole's controls
CART, POLE = (0, 1), (2, 3)


def _made(**options):
    """CartPole-v0 with 7-step episodes (many auto-resets per rollout)."""
    env, params = amjax.make("CartPole-v0", **options)
    return env, params.replace(env_params=params.env_params.replace(max_steps_in_episode=7))


ALL_ON = {"instruments": "default", "extra_obs": ("since_measured",), "budget": 2.0}
INSTRUMENTS_ENV = _made(**ALL_ON)
ALWAYS_ENV = _made()  # the paper's wrapper, driven to measure every step: the true observations


def expected_readings(actions, budget, prices, cost, truth):
    """What the instruments must show and charge, from an always-measured run `truth` with the same keys."""
    horizon = math.log1p(7)
    shown, since, used = np.asarray(truth.obs0[:4]), np.zeros(2, int), 0
    out = {"obs": [], "flags": [], "since": [], "cost": [], "readings": [], "refused": []}
    for t, action in enumerate(actions):
        requested = np.array([(action // N) & 1, (action // N) >> 1], bool)
        readings = requested.copy()
        for j in range(2):  # served in order while the budget lasts
            readings[j] &= used < budget
            used += readings[j]
        true_obs = truth.info["final_observation"][t][:4]
        shown = shown.copy()
        for j, features in enumerate((CART, POLE)):
            if readings[j]:
                shown[list(features)] = true_obs[list(features)]
        since = np.where(readings, 0, since + 1)
        out["cost"].append(cost * readings.any() + prices @ readings)
        out["readings"].append(readings)
        out["refused"].append(requested & ~readings)
        done = truth.terminated[t] or truth.truncated[t]
        if done:  # the auto-reset's first observation is a free reading of every instrument
            shown, since, used = truth.obs[t][:4], np.zeros(2, int), 0
        out["obs"].append(shown)
        out["flags"].append(np.ones(2) if done else readings.astype(float))
        out["since"].append(np.minimum(np.log1p(since) / horizon, 1.0))
    return {k: np.asarray(v, np.float32 if k in ("obs", "cost", "since", "flags") else bool) for k, v in out.items()}


@settings(max_examples=20, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    actions=st.lists(st.integers(0, 4 * N - 1), min_size=T, max_size=T),
    budget=st.sampled_from([0.0, 1.0, 2.0, 3.0, 1000.0]),
    prices=st.lists(st.floats(0.0, 1.0, width=32), min_size=2, max_size=2),
    cost=st.floats(0.0, 1.0, width=32),
)
def test_readings_match_a_python_loop(rollout, seed, actions, budget, prices, cost):
    env, params = INSTRUMENTS_ENV  # one env object: one compiled rollout (cost, prices and budget are traced)
    params = params.replace(
        cost=jnp.float32(cost), budget=jnp.float32(budget), instrument_costs=jnp.asarray(prices, jnp.float32)
    )
    always_env, always_params = ALWAYS_ENV
    key = jax.random.key(seed)
    actions = np.asarray(actions)
    run = rollout(env, params, key, jnp.asarray(actions))
    truth = rollout(always_env, always_params, key, jnp.asarray(actions % N + N))
    expected = expected_readings(actions, budget, np.asarray(prices, np.float32), np.float32(cost), truth)

    # Observation: [obs (each feature as last read), one flag per instrument, steps since each was read, budget]
    np.testing.assert_array_equal(run.obs[:, :4], expected["obs"])
    np.testing.assert_array_equal(run.obs[:, 4:6], expected["flags"])
    np.testing.assert_allclose(run.obs[:, 6:8], expected["since"], atol=1e-6)
    assert run.obs0.tolist()[4:8] == [1.0, 1.0, 0.0, 0.0]
    assert env.observation_space(params).contains(jnp.asarray(run.obs))
    # Readings: carried out within the budget, charged exactly, the refused ones free.
    np.testing.assert_array_equal(run.info["readings"], expected["readings"])
    np.testing.assert_array_equal(run.info["refused"], expected["refused"])
    np.testing.assert_array_equal(run.info["measured"], expected["readings"].any(1))
    np.testing.assert_allclose(run.info["cost"], expected["cost"], rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(run.reward, truth.info["raw_reward"] - expected["cost"], atol=1e-5)
    episode = np.concatenate([[0], np.cumsum(run.terminated | run.truncated)[:-1]])
    for e in np.unique(episode):
        assert run.info["readings"][episode == e].sum() <= budget  # the budget is never exceeded


@pytest.mark.parametrize(
    "env_id, instrument, actions",
    [
        ("CartPole-v0", ((0, 1, 2, 3),), lambda rng: rng.integers(0, 4, T)),
        ("Pendulum-v1", ((0, 1, 2),), lambda rng: np.stack([rng.uniform(0, 1, T), rng.uniform(-2, 2, T)], 1)),
    ],
)
def test_one_instrument_is_the_paper_wrapper(rollout, env_id, instrument, actions):
    """One instrument holding every feature, priced 0, gives the paper's wrapper: same actions, same outputs."""
    paper_env, paper_params = amjax.make(env_id, cost=0.3)
    env, params = amjax.make(env_id, cost=0.3, instruments=instrument)
    assert env.num_actions == paper_env.num_actions
    acts = jnp.asarray(actions(np.random.default_rng(0)), jnp.float32 if env_id == "Pendulum-v1" else jnp.int32)
    run, paper = (rollout(e, p, jax.random.key(3), acts) for e, p in ((env, params), (paper_env, paper_params)))
    np.testing.assert_array_equal(run.obs, paper.obs)
    np.testing.assert_array_equal(run.reward, paper.reward)
    np.testing.assert_array_equal(run.info["measured"], paper.info["measured"])
    np.testing.assert_array_equal(run.state.last_obs, paper.state.last_obs)


def test_box_control_has_one_measure_entry_per_instrument(rollout):
    """Pendulum's [cos, sin] and [theta_dot] read apart: action [read angle, read rate, torque]."""
    env, params = amjax.make("Pendulum-v1", cost=0.1, instruments=((0, 1), (2,)), instrument_costs=(0.2, 0.05))
    space = env.action_space(params)
    assert space.shape == (3,) and space.low.tolist() == [0, 0, -2] and space.high.tolist() == [1, 1, 2]
    assert env.observation_space(params).shape == (5,)
    actions = jnp.asarray([[0.9, 0.1, 1.0], [0.1, 0.9, -1.0], [0.2, 0.3, 0.0], [0.6, 0.7, 2.0]], jnp.float32)
    run = rollout(env, params, jax.random.key(0), actions)
    np.testing.assert_array_equal(run.info["readings"], [[1, 0], [0, 1], [0, 0], [1, 1]])
    np.testing.assert_array_equal(run.obs[:, 3:], [[1, 0], [0, 1], [0, 0], [1, 1]])
    np.testing.assert_allclose(run.info["cost"], [0.3, 0.15, 0.0, 0.35], rtol=1e-6)
    np.testing.assert_array_equal(run.obs[1, :2], run.obs[0, :2])  # the angle is stale after a rate reading
    assert run.obs[2, 2] == run.obs[1, 2] != run.obs[0, 2]


def test_reading_noise_is_gaussian_per_instrument():
    """Instrument j's features are read as truth + N(0, noise_j^2); the other instrument's exactly."""
    env, params = amjax.make("CartPole-v0", instruments="default", instrument_noise=(0.0, 0.05))
    obs0, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(jax.random.key(1), 4000), params)
    keys = jax.random.split(jax.random.key(2), 4000)
    obs, *_ = jax.vmap(env.step, in_axes=(0, 0, None, None))(keys, state, 3 * N, params)
    truth = jax.vmap(lambda k, s: env._env.step(k, s.env_state, 0, params.env_params)[5]["final_observation"])(
        keys, state
    )
    error = np.asarray(obs[:, :4]) - np.asarray(truth)
    np.testing.assert_array_equal(error[:, :2], 0.0)
    assert np.std(error[:, 2:]) == pytest.approx(0.05, rel=0.05)
    assert abs(np.mean(error[:, 2:])) < 0.005


def test_prices_are_traced_and_vmap():
    """A batch of prices is one compiled program; each member charges its own."""
    env, params = amjax.make("CartPole-v0", cost=0.1, instruments="default")
    _, state = env.reset(jax.random.key(0), params)
    prices = jnp.asarray([[0.0, 0.0], [0.05, 0.3], [1.0, 2.0]])
    batched = jax.vmap(lambda p: params.replace(instrument_costs=p))(prices)
    step = jax.jit(jax.vmap(env.step, in_axes=(None, None, None, 0)))
    costs = [step(jax.random.key(1), state, N * mask, batched)[5]["cost"] for mask in (1, 2, 3)]
    np.testing.assert_allclose(np.stack(costs), [[0.1, 0.15, 1.1], [0.1, 0.4, 2.1], [0.1, 0.45, 3.1]], rtol=1e-6)
    assert step._cache_size() == 1


@pytest.mark.parametrize("seed", [0, 1])
def test_numpy_wrapper_matches_the_jax_wrapper(seed):
    """Gymnasium's CartPole through the NumPy wrapper, step for step as the JAX wrapper with every option on."""
    options = {
        "cost": 0.1,
        "extra_obs": ("since_measured", "last_action"),
        "budget": 30.0,
        "reward_timing": "on_measure",
        "instrument_costs": (0.05, 0.2),
    }
    env, params = amjax.make("CartPole-v0", instruments="default", **options)
    gym_env = ActiveMeasureWrapper(
        gymnasium.make("CartPole-v1", max_episode_steps=200), instruments=(CART, POLE), **options
    )
    assert gym_env.observation_space.shape == env.observation_space(params).shape
    assert gym_env.action_space.n == env.action_space(params).n == 8
    rng = np.random.default_rng(seed)
    obs, _ = gym_env.reset(seed=seed)
    j_obs, state = env.reset(jax.random.key(0), params)
    np.testing.assert_array_equal(obs[4:], np.asarray(j_obs)[4:])
    x, x_dot, theta, theta_dot = np.asarray(gym_env.unwrapped.state, np.float32)
    state = state.replace(
        env_state=state.env_state.replace(x=x, x_dot=x_dot, theta=theta, theta_dot=theta_dot),
        last_obs=jnp.asarray(obs[:4]),
    )
    counts = np.zeros(2)
    for t in range(200):
        x, x_dot, theta, theta_dot = gym_env.unwrapped.state
        control = int(theta + 0.5 * theta_dot + 0.05 * x + 0.1 * x_dot > 0)  # balances for 200 steps
        action = control + N * int(rng.integers(4))
        obs, reward, terminated, truncated, info = gym_env.step(action)
        j_obs, state, j_reward, j_term, j_trunc, j_info = env.step(jax.random.key(t), state, action, params)
        assert (terminated, truncated) == (bool(j_term), bool(j_trunc))
        j_seen = j_info["final_observation"] if terminated or truncated else j_obs
        np.testing.assert_allclose(obs, np.asarray(j_seen), atol=1e-5)
        np.testing.assert_array_equal(info["readings"], np.asarray(j_info["readings"]))
        np.testing.assert_array_equal(info["refused"], np.asarray(j_info["refused"]))
        assert info["cost"] == pytest.approx(float(j_info["cost"]), rel=1e-6, abs=1e-7)
        assert reward == pytest.approx(float(j_reward), abs=1e-5)
        counts += info["readings"]
        if terminated or truncated:
            break
    assert t == 199 and counts.sum() == 30  # the budget ran out within the episode, and both instruments were read
    assert counts.min() > 0


def test_mask_encoding_round_trips():
    masks = jnp.arange(16)
    np.testing.assert_array_equal(encode_mask(decode_mask(masks, 4)), masks)
    np.testing.assert_array_equal(decode_mask(5, 3), [True, False, True])


def test_policies_handle_instruments():
    """The actor-critic distributions over k instruments: Discrete pairs (control, mask), Box k Bernoullis."""
    # Discrete: 2 controls x 4 masks; control 1 most probable, its masks drawn with their conditional probabilities
    probs = np.array([0.05, 0.1, 0.05, 0.3, 0.05, 0.2, 0.05, 0.2])
    dist = Categorical(8, measure=True, readings=2)
    actions = jax.vmap(lambda k: dist.mode_sampling_measure(k, jnp.log(jnp.asarray(probs))))(
        jax.random.split(jax.random.key(0), 20_000)
    )
    actions = np.asarray(actions)
    assert np.all(actions % 2 == 1)
    np.testing.assert_allclose(
        np.bincount(actions // 2, minlength=4) / 20_000, np.array([0.1, 0.3, 0.2, 0.2]) / 0.8, atol=0.015
    )
    # Box: two independent Bernoullis; the log-probability is the sum of the parts
    box = HybridGaussian(1, measure=True, readings=2)
    out = GaussianOutputs(jnp.asarray([0.5]), jnp.asarray([-1.0]), jnp.asarray([2.0, -1.0]))
    action = jnp.asarray([1.0, 0.0, 0.7])
    gauss = jax.scipy.stats.norm.logpdf(0.7, 0.5, jnp.exp(-1.0))
    expected = gauss + jax.nn.log_sigmoid(2.0) + jax.nn.log_sigmoid(1.0)
    assert float(box.log_prob(out, action)) == pytest.approx(float(expected), rel=1e-5)
    np.testing.assert_array_equal(box.mode(out), [1.0, 0.0, 0.5])
    assert box.sample(jax.random.key(0), out).shape == (3,)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"instruments": ((0, 1), (2,))}, "exactly once"),
        ({"instruments": ((0, 1), (1, 2, 3))}, "exactly once"),
        ({"instruments": ((0, 1), ())}, "non-empty"),
        ({"instruments": "cart"}, "tuple of tuples"),
        ({"instruments": "default", "instrument_costs": (0.1,)}, "one number per instrument"),
        ({"instruments": "default", "instrument_noise": (0.1, -1.0)}, "instrument_noise"),
        ({"instrument_costs": (0.1, 0.2)}, "set instruments first"),
    ],
)
def test_bad_instruments_are_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        amjax.make("CartPole-v0", **kwargs)


def test_default_instruments_need_an_env_that_has_them():
    with pytest.raises(ValueError, match="no default instruments.*CartPole-v0"):
        amjax.make("MountainCar-v0", instruments="default")
    with pytest.raises(ValueError, match="vanilla"):
        amjax.make("CartPole-v0", vanilla=True, instruments="default")


@pytest.mark.parametrize(
    "fields, message",
    [
        ({"instruments": "default", "instrument_costs": (0.1, 0.2, 0.3)}, "3 values for 2 instruments"),
        ({"instrument_costs": (0.1,)}, "set instruments first"),
        ({"instruments": ((0, 1, 2),)}, "exactly once"),
        ({"instruments": "default", "vanilla": True}, "vanilla"),
        ({"instruments": "default", "instrument_costs": (0.1, -0.2)}, "instrument_costs"),
    ],
)
def test_configs_check_instruments(fields, message):
    for config in (DQNConfig, PPOConfig):
        with pytest.raises(ValueError, match=message):
            config(env_id="CartPole-v0", **fields).validate()


def test_numpy_wrapper_refuses_bad_instruments():
    with pytest.raises(ValueError, match="exactly once"):
        ActiveMeasureWrapper(gymnasium.make("CartPole-v1"), instruments=((0,), (1,)))
    with pytest.raises(ValueError, match="one number per instrument"):
        ActiveMeasureWrapper(gymnasium.make("CartPole-v1"), instruments=(CART, POLE), instrument_costs=(1.0,))


def test_measurement_maps_record_each_instrument(tmp_path):
    """A policy reading the cart every step and the pole every third: the map's per-instrument fractions."""
    from amjax import analysis

    env, params = amjax.make("CartPole-v0", instruments="default")

    def act(batch, count, key):
        count = jnp.where(batch.first, 0, count)
        pole = count % 3 == 0
        control = (batch.obs[:, 2] + 0.5 * batch.obs[:, 3] > 0).astype(jnp.int32)
        return control + N * (1 + 2 * pole), count + 1, None

    mmap = analysis.record_measurements(
        env, params, (act, jnp.zeros(4, jnp.int32)), jax.random.key(0), num_episodes=4, max_steps=60
    )
    assert mmap.readings.shape == (4, 60, 2)
    assert mmap.reading_fractions[0] == pytest.approx(1.0)
    assert mmap.reading_fractions[1] == pytest.approx(1 / 3, abs=0.02)
    assert set(np.unique(mmap.grid())) <= {1, 3, 4}
    fig = analysis.plot_measurement_map(
        {"cost 0.1": mmap}, instrument_names=("cart", "pole"), path=tmp_path / "map.png"
    )
    assert "pole 3" in fig.axes[0].get_title() and (tmp_path / "map.png").exists()
