"""`MeasureSpec`: the one declaration of the measurement setting.

`amjax.make`'s keyword arguments, `make(spec=...)`, the agent configs (which subclass the spec), the sweep grid and
the Gymnasium wrapper must all build the same environment from the same setting."""

from __future__ import annotations

import dataclasses

import gymnasium
import jax
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import amjax
from amjax.agents import ALGORITHMS, training_env
from amjax.agents.config import AgentConfig
from amjax.sweep.grid import GRID_FIELDS, MEASURE_FIELDS
from amjax.wrappers.gymnasium import ActiveMeasureWrapper
from amjax.wrappers.spec import MeasureSpec


def _leaves_equal(a, b) -> bool:
    same_shape = jax.tree.structure(a) == jax.tree.structure(b)
    return same_shape and all(np.array_equal(x, y) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True))


def _rollout(env, params, actions):
    """Observations and rewards of a jitted scan from reset(key 0) under `actions`."""

    def step(carry, action_key):
        state, key = carry
        action, step_key = action_key
        obs, state, reward, _, _, _ = env.step(step_key, state, action, params)
        return (state, key), (obs, reward)

    obs, state = env.reset(jax.random.key(0), params)
    keys = jax.random.split(jax.random.key(1), len(actions))
    _, (observations, rewards) = jax.jit(lambda s: jax.lax.scan(step, s, (actions, keys)))((state, keys[0]))
    return np.asarray(obs), np.asarray(observations), np.asarray(rewards)


# One setting as `amjax.make` keywords and as a spec, drawn together.
@st.composite
def settings_pair(draw):
    extra_obs = tuple(draw(st.sets(st.sampled_from(("since_measured", "last_action")))))
    budget = draw(st.sampled_from((None, 0, 3)))
    instruments = draw(st.sampled_from(((), "default")))
    prices = draw(st.sampled_from((None, (0.05, 0.2)))) if instruments else None
    conditioned = draw(st.booleans())
    cost = 0.0 if conditioned else draw(st.sampled_from((0.0, 0.1, 0.3)))
    mode = draw(st.sampled_from(("last", "random", "noisy")))
    noise = 0.2 if mode == "noisy" else None
    timing = draw(st.sampled_from(("immediate", "on_measure")))
    flag = draw(st.booleans())
    keywords = dict(
        cost=cost,
        mode=mode,
        flag=flag,
        noise_std=noise,
        extra_obs=extra_obs,
        budget=budget,
        reward_timing=timing,
        instruments=instruments,
        instrument_costs=prices,
        cost_range=(0.0, 0.5) if conditioned else None,
    )
    spec = MeasureSpec(
        mode=mode,
        flag=flag,
        extra_obs=extra_obs,
        budgeted=budget is not None,
        reward_timing=timing,
        instruments=instruments,
        cost_conditioned=conditioned,
        cost=cost,
        noise_std=noise or 0.0,
        budget=budget or 0,
        instrument_costs=prices or (),
        cost_high=0.5 if conditioned else 0.0,
    )
    return keywords, spec


@settings(max_examples=12, deadline=None)
@given(pair=settings_pair())
@pytest.mark.slow
def test_make_keywords_and_spec_build_the_same_env(pair):
    keywords, spec = pair
    env_a, params_a = amjax.make("CartPole-v0", **keywords)
    env_b, params_b = amjax.make("CartPole-v0", spec=spec)
    env_c, params_c = spec.make("CartPole-v0")
    assert _leaves_equal(params_a, params_b) and _leaves_equal(params_b, params_c)
    assert env_a.observation_space(params_a).shape == env_b.observation_space(params_b).shape
    assert env_a.action_space(params_a).n == env_b.action_space(params_b).n
    actions = jax.random.randint(jax.random.key(2), (30,), 0, env_a.action_space(params_a).n)
    for a, b in zip(_rollout(env_a, params_a, actions), _rollout(env_b, params_b, actions), strict=True):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("agent", sorted(ALGORITHMS))
def test_a_config_is_its_spec(agent):
    """An agent config's measurement fields are the spec's own (inherited, not redeclared) and it trains on the env
    `make(spec=config)` builds."""
    config_type = ALGORITHMS[agent].config_type
    assert issubclass(config_type, MeasureSpec)
    declared_below = {
        name
        for klass in config_type.__mro__
        if klass is not MeasureSpec and issubclass(klass, MeasureSpec)
        for name in klass.__dict__.get("__annotations__", {})
    }
    assert not declared_below & set(MeasureSpec.measure_fields())  # no copies of the spec's fields
    config = config_type(cost=0.2, extra_obs=("since_measured",), budgeted=True, budget=5, instruments="default")
    assert config.measure_spec() == MeasureSpec(
        cost=0.2, extra_obs=("since_measured",), budgeted=True, budget=5, instruments="default"
    )
    env, params, _ = training_env(config)
    made_env, made_params = amjax.make(config.env_id, spec=config)
    assert _leaves_equal(params, made_params)
    assert env.observation_space(params).shape == made_env.observation_space(made_params).shape


def test_static_and_traced_fields():
    static = {"mode", "flag", "vanilla", "extra_obs", "budgeted", "reward_timing", "instruments", "measure_head"}
    static |= {"cost_conditioned"}
    fields = {f.name: f.metadata.get("pytree_node", True) for f in dataclasses.fields(MeasureSpec)}
    assert {name for name, traced in fields.items() if not traced} == static
    assert set(AgentConfig.static_fields()) >= static and set(AgentConfig.traced_fields()) >= set(fields) - static
    # traced fields vmap: one program over several costs
    specs = jax.tree.map(lambda *xs: np.stack(xs), *(MeasureSpec(cost=c) for c in (0.1, 0.2, 0.3)))
    env, inner = specs.wrap_env("CartPole-v0")
    params = jax.vmap(lambda s: s.measure_params(env, inner))(specs)
    np.testing.assert_allclose(params.cost, [0.1, 0.2, 0.3])


def test_grid_measure_fields_come_from_the_spec():
    assert set(MEASURE_FIELDS) == set(MeasureSpec.measure_fields()) - set(GRID_FIELDS) - {"mode", "flag"}


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        (MeasureSpec(budget=2), "budget: set budgeted=True"),
        (MeasureSpec(mode="noisy"), "noise_std: mode 'noisy' needs noise_std"),
        (MeasureSpec(vanilla=True, cost=0.1), "vanilla: a vanilla run"),
        (MeasureSpec(instruments=((0, 1),)), "instruments:"),
        (MeasureSpec(instruments="default", instrument_costs=(0.1,)), "instrument_costs: got 1 values for 2"),
        (MeasureSpec(cost_conditioned=True, cost=0.1, cost_high=0.5), "cost: a cost-conditioned run"),
        (MeasureSpec(measure_head="split"), "measure_head:"),
        (MeasureSpec(reward_timing="later"), "reward_timing:"),
    ],
)
def test_bad_specs_name_the_field(spec, message):
    with pytest.raises(ValueError, match=message):
        spec.make("CartPole-v0")
    with pytest.raises(ValueError, match=message):
        amjax.make("CartPole-v0", spec=spec)


def test_spec_and_keywords_together_are_refused():
    with pytest.raises(ValueError, match="spec: given with cost, budget"):
        amjax.make("CartPole-v0", cost=0.1, budget=3, spec=MeasureSpec())
    with pytest.raises(TypeError, match="spec: got dict"):
        amjax.make("CartPole-v0", spec={"cost": 0.1})


def test_gymnasium_wrapper_from_spec():
    spec = MeasureSpec(cost=0.1, instruments="default", instrument_costs=(0.0, 0.3), budgeted=True, budget=4)
    spec = spec.replace(extra_obs=("since_measured",))
    from_spec = ActiveMeasureWrapper.from_spec(gymnasium.make("CartPole-v1"), spec)
    by_keywords = ActiveMeasureWrapper(
        gymnasium.make("CartPole-v1"),
        cost=0.1,
        instruments=((0, 1), (2, 3)),
        instrument_costs=(0.0, 0.3),
        budget=4,
        extra_obs=("since_measured",),
    )
    assert from_spec.observation_space == by_keywords.observation_space
    assert from_spec.action_space == by_keywords.action_space
    obs_a, _ = from_spec.reset(seed=3)
    obs_b, _ = by_keywords.reset(seed=3)
    for action in [7, 1, 4, 2, 6, 0, 5, 3]:
        step_a, step_b = from_spec.step(action), by_keywords.step(action)
        np.testing.assert_array_equal(step_a[0], step_b[0])
        assert step_a[1:4] == step_b[1:4]
    # The JAX wrapper of the same spec has the same spaces.
    env, params = spec.make("CartPole-v1")
    assert from_spec.observation_space.shape == env.observation_space(params).shape
    assert from_spec.action_space.n == env.action_space(params).n
    for name in ("vanilla", "cost_conditioned"):
        with pytest.raises(ValueError, match=f"{name}: ActiveMeasureWrapper has no {name}"):
            ActiveMeasureWrapper.from_spec(gymnasium.make("CartPole-v1"), MeasureSpec(**{name: True}))
