"""`amjax.wrap`: a JAX environment of the user's own, with gymnax's API, as an active-measure MDP.

A toy environment defined here (a gymnax `Environment` subclass, and the same written without gymnax's base class)
goes through the wrapper with each option; a gymnax env object wrapped by hand equals the one `amjax.make` builds
from its id."""

from __future__ import annotations

import gymnax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import struct
from gymnax.environments import environment, spaces
from hypothesis import given, settings
from hypothesis import strategies as st

import amjax


@struct.dataclass
class WalkState(environment.EnvState):
    position: jax.Array
    time: int


@struct.dataclass
class WalkParams(environment.EnvParams):
    max_steps_in_episode: int = 20
    step_size: float = 0.5


class Walk(environment.Environment):
    """A 1-D walk: action 0 steps left, 1 right, with a little noise; reward -|position|; ends past |position| 3.
    The observation is (position, time / max_steps)."""

    @property
    def default_params(self) -> WalkParams:
        return WalkParams()

    def step_env(self, key, state, action, params):
        noise = 0.1 * jax.random.normal(key)
        position = state.position + params.step_size * (2 * action - 1) + noise
        state = WalkState(position=position, time=state.time + 1)
        terminated = jnp.abs(position) > 3.0
        return self.get_obs(state, params), state, -jnp.abs(position), terminated, {}

    def reset_env(self, key, params):
        state = WalkState(position=jax.random.uniform(key, minval=-1.0, maxval=1.0), time=0)
        return self.get_obs(state, params), state

    def get_obs(self, state, params=None):
        params = self.default_params if params is None else params
        return jnp.array([state.position, state.time / params.max_steps_in_episode], jnp.float32)

    def is_truncated(self, state, params):
        return state.time >= params.max_steps_in_episode

    def action_space(self, params=None):
        return spaces.Discrete(2)

    def observation_space(self, params=None):
        return spaces.Box(jnp.array([-4.0, 0.0]), jnp.array([4.0, 1.0]), (2,), jnp.float32)


class BareWalk:
    """`Walk` without gymnax's base class: its own `reset` and auto-resetting `step`, as gymnax 1.0 defines them."""

    def __init__(self):
        self.walk = Walk()
        self.default_params = self.walk.default_params

    def reset(self, key, params=None):
        return self.walk.reset_env(key, self.default_params if params is None else params)

    def step(self, key, state, action, params=None):
        params = self.default_params if params is None else params
        step_key, reset_key = jax.random.split(key)
        obs, next_state, reward, terminated, _ = self.walk.step_env(step_key, state, action, params)
        truncated = self.walk.is_truncated(next_state, params)
        done = terminated | truncated
        reset_obs, reset_state = self.walk.reset_env(reset_key, params)
        state = jax.tree.map(lambda r, s: jnp.where(done, r, s), reset_state, next_state)
        info = {"final_observation": obs}
        return jnp.where(done, reset_obs, obs), state, reward, terminated, truncated, info

    def action_space(self, params=None):
        return self.walk.action_space(params)

    def observation_space(self, params=None):
        return self.walk.observation_space(params)


def _rollout(env, params, actions, seed=0):
    """Observations, rewards and info of a jitted scan from reset under `actions`."""

    def step(state, action_key):
        action, key = action_key
        obs, state, reward, _, _, info = env.step(key, state, action, params)
        return state, (obs, reward, info["cost"], info["measured"])

    obs, state = env.reset(jax.random.key(seed), params)
    keys = jax.random.split(jax.random.key(seed + 1), len(actions))
    _, out = jax.jit(lambda s: jax.lax.scan(step, s, (jnp.asarray(actions), keys)))(state)
    return obs, out


@pytest.mark.parametrize("make_env", [Walk, BareWalk], ids=["gymnax-subclass", "bare"])
def test_wrapped_walk_measures_at_a_cost(make_env):
    env, params = amjax.wrap(make_env(), cost=0.25)
    assert env.action_space(params).n == 4  # (left, right) x (skip, measure)
    assert env.observation_space(params).shape == (3,)  # position, time, fresh flag
    first, (obs, reward, cost, measured) = _rollout(env, params, [1, 3, 1, 1, 2])  # right, right + measure, ...
    assert first[-1] == 1.0  # a reset is a free measurement
    np.testing.assert_array_equal(measured, [False, True, False, False, True])
    np.testing.assert_allclose(cost, [0.0, 0.25, 0.0, 0.0, 0.25])
    np.testing.assert_array_equal(obs[:, -1], [0, 1, 0, 0, 1])  # the flag
    np.testing.assert_array_equal(obs[0, :2], first[:2])  # unmeasured: the reset's observation again
    np.testing.assert_array_equal(obs[2, :2], obs[1, :2])  # and then the measured one
    assert not np.array_equal(obs[4, :2], obs[1, :2])


def test_bare_env_steps_like_its_gymnax_twin():
    """Without gymnax's base class the wrapper sees the same env: same observations, rewards and costs."""
    actions = [1, 2, 3, 0, 1, 3] * 8  # 48 steps: episodes end (20-step limit) and reset inside the rollout
    twins = [amjax.wrap(env, cost=0.1, extra_obs=("since_measured",), budget=4) for env in (Walk(), BareWalk())]
    outs = [_rollout(env, params, actions) for env, params in twins]
    for a, b in zip(jax.tree.leaves(outs[0]), jax.tree.leaves(outs[1]), strict=True):
        np.testing.assert_array_equal(a, b)


@settings(max_examples=10, deadline=None)
@given(
    mode=st.sampled_from(["last", "random", "noisy"]),
    extra_obs=st.sampled_from([(), ("since_measured",), ("since_measured", "last_action")]),
    budget=st.sampled_from([None, 2]),
    instruments=st.sampled_from([(), ((0,), (1,))]),
)
def test_every_option_jits_and_vmaps_over_costs(mode, extra_obs, budget, instruments):
    noise = 0.2 if mode == "noisy" else None
    options = {"mode": mode, "noise_std": noise, "extra_obs": extra_obs, "budget": budget, "instruments": instruments}
    env, params = amjax.wrap(Walk(), **options)
    measure_all = env.action_space(params).n - 1  # right, every instrument read

    def rollout(cost):
        return _rollout(env, params.replace(cost=cost), [measure_all] * 5)

    first, (obs, reward, cost, measured) = jax.vmap(rollout)(jnp.array([0.0, 0.5]))
    assert obs.shape == (2, 5, *env.observation_space(params).shape)
    assert first.shape == (2, *env.observation_space(params).shape)
    np.testing.assert_allclose(cost[0], 0.0)
    # A budget of 2 readings: two steps of the single switch, one step reading both instruments.
    paid_steps = 5 if budget is None else budget // max(1, len(instruments))
    paid = [0.5] * paid_steps + [0.0] * (5 - paid_steps)
    np.testing.assert_allclose(cost[1], paid)


def test_wrapped_gymnax_object_equals_make_by_id():
    """`wrap(*gymnax.make(id), name=id)` is `amjax.make(id)`: same params, spaces and rollout; the name gives
    it the id's default instruments."""
    options = {"cost": 0.2, "instruments": "default", "instrument_costs": (0.1, 0.3)}
    by_id = amjax.make("CartPole-v1", **options)
    by_object = amjax.wrap(*gymnax.make("CartPole-v1"), name="CartPole-v1", **options)
    assert jax.tree.structure(by_id[1]) == jax.tree.structure(by_object[1])
    for a, b in zip(jax.tree.leaves(by_id[1]), jax.tree.leaves(by_object[1]), strict=True):
        np.testing.assert_array_equal(a, b)
    assert by_id[0].action_space(by_id[1]).n == by_object[0].action_space(by_object[1]).n == 8
    actions = np.random.default_rng(0).integers(0, 8, 60)
    for a, b in zip(
        jax.tree.leaves(_rollout(*by_id, actions)), jax.tree.leaves(_rollout(*by_object, actions)), strict=True
    ):
        np.testing.assert_array_equal(a, b)


def test_spec_or_keywords_build_the_same_wrapped_env():
    spec = amjax.MeasureSpec(cost=0.3, mode="noisy", noise_std=0.1, budgeted=True, budget=3.0)
    by_spec = amjax.wrap(Walk(), spec=spec)
    by_keywords = amjax.wrap(Walk(), cost=0.3, mode="noisy", noise_std=0.1, budget=3)
    actions = [3, 1, 3, 3, 2, 0, 3, 3]
    for a, b in zip(
        jax.tree.leaves(_rollout(*by_spec, actions)), jax.tree.leaves(_rollout(*by_keywords, actions)), strict=True
    ):
        np.testing.assert_array_equal(a, b)


def test_env_params_given_are_used():
    short = WalkParams(max_steps_in_episode=3)
    env, params = amjax.wrap(Walk(), short, cost=0.1)
    assert params.env_params.max_steps_in_episode == 3
    _, state = env.reset(jax.random.key(0), params)
    for i in range(3):
        _, state, _, terminated, truncated, _ = env.step(jax.random.key(i), state, 1, params)
    assert bool(truncated) or bool(terminated)


class NoStep:
    default_params = None

    def reset(self, key, params=None):
        return jnp.zeros(2), None

    def action_space(self, params=None):
        return spaces.Discrete(2)

    def observation_space(self, params=None):
        return spaces.Box(-1.0, 1.0, (2,), jnp.float32)


@pytest.mark.parametrize(
    "call, error, words",
    [
        (lambda: amjax.wrap(NoStep()), TypeError, ["env", "NoStep", "step", "gymnax"]),
        (lambda: amjax.wrap(object(), cost=0.1), TypeError, ["reset", "default_params"]),
        (lambda: amjax.wrap(Walk(), costs=0.1), TypeError, ["costs", "not a measurement option", "cost"]),
        (lambda: amjax.wrap(Walk(), cost=-1.0), ValueError, ["cost"]),
        (lambda: amjax.wrap(Walk(), instruments="default"), ValueError, ["Walk", "no default instruments"]),
        (lambda: amjax.wrap(Walk(), instruments=((0,),)), ValueError, ["instruments"]),
        (
            lambda: amjax.wrap(Walk(), spec=amjax.MeasureSpec(cost=0.1), cost=0.2),
            ValueError,
            ["spec", "cost"],
        ),
    ],
    ids=["no-step", "not-an-env", "unknown-option", "negative-cost", "no-default-instruments", "bad-split", "both"],
)
def test_bad_input_names_the_argument(call, error, words):
    with pytest.raises(error) as caught:
        call()
    for word in words:
        assert word in str(caught.value)


def test_vanilla_wraps_too():
    env, params = amjax.wrap(Walk(), vanilla=True)
    assert env.action_space(params).n == 2
    _, (obs, _, cost, measured) = _rollout(env, params, [0, 1, 1])
    assert bool(np.all(measured)) and not np.any(cost)


@pytest.mark.slow
def test_registered_walk_trains_in_a_sweep(tmp_path, monkeypatch):
    """An env of your own given an id trains in the sweep runner like a built-in one (same process)."""
    from amjax.envs import registry
    from amjax.sweep import SweepSpec, run_sweep

    monkeypatch.setattr(registry, "_CUSTOM_ENVS", {})
    amjax.register("Walk-v0", lambda: (Walk(), WalkParams()))
    spec = SweepSpec(
        envs=("Walk-v0",),
        agents=("ppo",),
        costs=(0.1,),
        seeds=(0,),
        total_timesteps=2048,
        eval_every=1024,
        eval_episodes=2,
    )
    result = run_sweep(spec, tmp_path / "walk", progress=False, devices=jax.devices()[:1])
    assert len(result.results) == 2 and np.isfinite(result.results["eval_return"]).all()
    assert (result.results["eval_return"] < 0).all()  # -|position| per step: every return is negative
