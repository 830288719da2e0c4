"""The wrapper's options beyond the paper: staleness features, a measurement budget, rewards paid on measurement.

Each is checked against the options-off wrapper driven with the same keys (mode "last" hands the inner env the
key unchanged, so both step the same CartPole) and a plain Python loop that applies the option's rule."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import amjax

T = 40
N = 2  # CartPole's controls
ALL_ON = {"extra_obs": ("since_measured", "last_action"), "budget": 2.0, "reward_timing": "on_measure"}


def _made(**options):
    """CartPole-v0 with 7-step episodes (many auto-resets per rollout)."""
    env, params = amjax.make("CartPole-v0", **options)
    return env, params.replace(env_params=params.env_params.replace(max_steps_in_episode=7))


OPTIONS_ENV = _made(**ALL_ON)
PLAIN_ENV = _made()


def expected_options(actions, budget, plain):
    """The features, refusals and payments the options must produce, from the options-off run `plain` (driven
    with the actions actually carried out)."""
    horizon = math.log1p(7)
    since, last, used, owed = 0, np.zeros(N), 0, 0.0
    out = {"since": [], "last": [], "left": [], "refused": [], "paid": [], "withheld": [], "cut": []}
    for t, action in enumerate(actions):
        control, requested = action % N, action >= N
        measured = requested and used < budget
        used += measured
        since = 0 if measured else since + 1
        last = np.eye(N)[control]
        owed += plain.info["raw_reward"][t]
        paid = owed if (measured or plain.terminated[t] or plain.truncated[t]) else 0.0
        owed -= paid
        out["refused"].append(requested and not measured)
        out["paid"].append(paid)
        out["cut"].append(paid if plain.truncated[t] and not (plain.terminated[t] or measured) else 0.0)
        out["withheld"].append(owed)
        if plain.terminated[t] or plain.truncated[t]:
            since, last, used = 0, np.zeros(N), 0
        out["since"].append(min(math.log1p(since) / horizon, 1.0))
        out["last"].append(last)
        out["left"].append(0.0 if budget == 0 else min(max(1.0 - used / budget, 0.0), 1.0))
    return {k: np.asarray(v) for k, v in out.items()}


def carried_out(actions, budget, done_after):
    """The actions with every measurement request beyond the budget turned into a plain control action."""
    carried, used = [], 0
    for t, action in enumerate(actions):
        measured = action >= N and used < budget
        used += measured
        carried.append(action % N + N * measured)
        if done_after[t]:
            used = 0
    return np.asarray(carried)


@settings(max_examples=20, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    actions=st.lists(st.integers(0, 2 * N - 1), min_size=T, max_size=T),
    budget=st.sampled_from([0.0, 1.0, 2.0, 3.0, 1000.0]),
    cost=st.floats(0.0, 1.0, width=32),
)
def test_options_match_a_python_loop(rollout, seed, actions, budget, cost):
    env, params = OPTIONS_ENV  # one env object for every example: one compiled rollout (cost, budget are traced)
    plain_env, plain_params = PLAIN_ENV
    params = params.replace(cost=jnp.float32(cost), budget=jnp.float32(budget))
    plain_params = plain_params.replace(cost=jnp.float32(cost))
    key = jax.random.key(seed)
    actions = np.asarray(actions)
    run = rollout(env, params, key, jnp.asarray(actions))
    done = run.terminated | run.truncated
    plain = rollout(plain_env, plain_params, key, jnp.asarray(carried_out(actions, budget, done)))
    expected = expected_options(actions, budget, plain)

    # Observation: the paper's [obs, flag], then since_measured, the one-hot last control, the budget left.
    np.testing.assert_allclose(run.obs[:, :5], plain.obs, atol=1e-6)
    np.testing.assert_allclose(run.obs[:, 5], expected["since"], atol=1e-6)
    np.testing.assert_array_equal(run.obs[:, 6:8], expected["last"])
    np.testing.assert_allclose(run.obs[:, 8], expected["left"], atol=1e-6)
    assert run.obs0.tolist()[5:] == [0.0, 0.0, 0.0, 1.0 if budget > 0 else 0.0]
    assert env.observation_space(params).contains(jnp.asarray(run.obs))
    # Budget: refused requests cost nothing and show the stale view.
    np.testing.assert_array_equal(run.info["refused"], expected["refused"])
    np.testing.assert_array_equal(run.info["measured"], plain.info["measured"])
    # Rewards: withheld until a measurement or the episode's end, so each episode's total is unchanged.
    np.testing.assert_allclose(run.info["raw_reward"], expected["paid"], atol=1e-5)
    np.testing.assert_allclose(run.info["withheld"], expected["withheld"], atol=1e-5)
    np.testing.assert_allclose(run.info["paid_at_truncation"], expected["cut"], atol=1e-5)
    np.testing.assert_allclose(run.reward, expected["paid"] - plain.info["cost"], atol=1e-5)
    episode = np.concatenate([[0], np.cumsum(done)[:-1]])
    finished = episode < episode[-1]
    for e in np.unique(episode[finished]):
        assert run.info["raw_reward"][episode == e].sum() == pytest.approx(plain.info["raw_reward"][episode == e].sum())


def test_options_off_is_the_paper_wrapper():
    env, params = amjax.make("CartPole-v0", cost=0.1)
    obs, state = env.reset(jax.random.key(0), params)
    assert obs.shape == (5,) and params.budget is None
    assert state.since_measured is state.last_control is state.measurements is state.withheld is None


def test_box_control_last_action_and_bounds():
    env, params = amjax.make("Pendulum-v1", extra_obs=("last_action",), budget=1.0)
    obs, state = env.reset(jax.random.key(0), params)
    space = env.observation_space(params)
    assert obs.shape == space.shape == (3 + 1 + 1 + 1,)  # obs, flag, torque, budget left
    obs, state, *_ = env.step(jax.random.key(1), state, jnp.array([1.0, 0.75]), params)
    assert float(obs[4]) == pytest.approx(0.75) and float(obs[5]) == 0.0  # measured once: budget spent
    assert space.contains(obs)


def test_budget_is_traced_and_vmaps():
    env, params = amjax.make("CartPole-v0", cost=0.2, budget=1.0)
    budgets = jnp.asarray([0.0, 1.0, 5.0])
    stacked = jax.tree.map(lambda x: jnp.broadcast_to(x, (3, *jnp.shape(x))), params).replace(budget=budgets)

    def measured_twice(params):
        _, state = env.reset(jax.random.key(0), params)
        _, state, r1, *_, info1 = env.step(jax.random.key(1), state, 2, params)
        _, state, r2, *_, info2 = env.step(jax.random.key(2), state, 2, params)
        return info1["measured"].astype(int) + info2["measured"].astype(int)

    np.testing.assert_array_equal(jax.vmap(measured_twice)(stacked), [0, 1, 2])


@pytest.mark.parametrize("instruments", [(), "default"])
def test_a_budget_allows_at_most_its_whole_number_of_measurements(rollout, instruments):
    """ "At most B": `amjax.make` refuses a fractional budget, and one set in the params by hand counts as its
    floor (2.5 allows 2 paid measurements an episode, not 3, and the fraction left is 0 once they are made)."""
    with pytest.raises(ValueError, match="budget: got 2.5; allowed values: whole numbers >= 0"):
        amjax.make("CartPole-v0", budget=2.5, instruments=instruments)
    env, params = amjax.make("CartPole-v0", budget=2.0, instruments=instruments)
    read = N * (3 if instruments else 1)  # control 0, every instrument read
    run = rollout(env, params.replace(budget=jnp.float32(2.5)), jax.random.key(0), jnp.full(6, read))
    readings = run.info["readings"].sum(-1) if instruments else run.info["measured"].astype(int)
    assert readings.sum() == 2 and not (run.terminated | run.truncated).any()
    # The fraction left: 1 - used / 2.5 while measurements remain, 0 once the floor is spent (both instruments read
    # at once spend it on the first step).
    left = [0.0] * 6 if instruments else [0.6] + [0.0] * 5
    np.testing.assert_allclose(run.obs[:, -1], left, atol=1e-6)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"extra_obs": ("since",)}, "extra_obs"),
        ({"extra_obs": "since_measured"}, "extra_obs"),
        ({"extra_obs": ("last_action", "last_action")}, "extra_obs"),
        ({"budget": -1.0}, "budget"),
        ({"budget": float("nan")}, "budget"),
        ({"budget": 0.5}, "budget: got 0.5; allowed values: whole numbers"),
        ({"budget": [1.0, 2.5]}, "budget"),
        ({"reward_timing": "later"}, "reward_timing"),
    ],
)
def test_bad_options_are_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        amjax.make("CartPole-v0", **kwargs)


def test_vanilla_takes_no_options():
    with pytest.raises(ValueError, match="vanilla"):
        amjax.make("CartPole-v0", vanilla=True, budget=3.0)
    with pytest.raises(ValueError, match="vanilla"):
        amjax.make("CartPole-v0", vanilla=True, extra_obs=("since_measured",))
