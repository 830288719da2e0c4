"""The active-measure wrapper (`amjax.make` -> `ActiveMeasure` / `AlwaysMeasured`).

Most checks compare the wrapper against the plain gymnax environment stepped with the key the wrapper hands it (the
key itself in mode "last", `split(key)[0]` in the modes that draw a view), or against a plain Python loop that
applies the wrapper's rules to those true observations.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from gymnax.environments import spaces
from gymnax.environments.classic_control.cartpole import CartPole
from gymnax.wrappers.purerl import GymnaxWrapper
from hypothesis import given, settings
from hypothesis import strategies as st

import amjax
from amjax.envs import registry
from amjax.wrappers.active_measure import ActiveMeasure, MeasureParams

T = 40  # steps per hypothesis rollout: one compiled program for every example

CARTPOLE, CARTPOLE_PARAMS = amjax.make("CartPole-v0")
INNER_CARTPOLE, _ = amjax.make_env("CartPole-v0")


def short_episodes(params: MeasureParams, max_steps: int = 5) -> MeasureParams:
    """The same params with episodes truncated after `max_steps` steps (many auto-resets per rollout)."""
    return params.replace(env_params=params.env_params.replace(max_steps_in_episode=max_steps))


SHORT = short_episodes(CARTPOLE_PARAMS)


def inner_rollout(rollout, inner_keys, wrapped_run, env, env_params, key, controls, mode="last"):
    """The plain env driven with the same reset key and the keys the wrapper (in `mode`) passed to it."""
    return rollout(env, env_params, key, controls, step_keys=inner_keys(wrapped_run.step_keys, mode))


# -- always measuring is the plain environment --------------------------------------------------------------


@pytest.mark.parametrize("max_steps", [5, 200])
def test_always_measuring_reproduces_the_inner_env(rollout, inner_keys, max_steps):
    params = short_episodes(CARTPOLE_PARAMS, max_steps).replace(cost=jnp.float32(0.25))
    controls = np.random.default_rng(max_steps).integers(0, 2, T)
    key = jax.random.key(max_steps)
    run = rollout(CARTPOLE, params, key, jnp.asarray(controls + 2))  # control + n * measure
    plain = inner_rollout(rollout, inner_keys, run, INNER_CARTPOLE, params.env_params, key, controls)

    if max_steps == 200:
        assert plain.terminated.any(), "random controls topple the pole within T steps: an auto-reset"
    else:
        assert plain.truncated.sum() == T // max_steps
    np.testing.assert_allclose(run.obs0, np.append(plain.obs0, 1.0), atol=1e-6)
    np.testing.assert_allclose(run.obs[:, :-1], plain.obs, atol=1e-6)
    np.testing.assert_array_equal(run.obs[:, -1], 1.0)
    np.testing.assert_allclose(run.info["final_observation"][:, :-1], plain.info["final_observation"], atol=1e-6)
    np.testing.assert_array_equal(run.info["raw_reward"], plain.reward)
    np.testing.assert_allclose(run.reward, plain.reward - 0.25, atol=1e-6)
    np.testing.assert_array_equal(run.terminated, plain.terminated)
    np.testing.assert_array_equal(run.truncated, plain.truncated)


# -- "last" mode against a plain Python loop ----------------------------------------------------------------


def reference_last_mode(measure: np.ndarray, plain) -> dict[str, np.ndarray]:
    """What the wrapper must show in mode "last", computed step by step from the true observations."""
    memory = plain.obs0
    expected = {"obs": [], "flag": [], "final_obs": [], "memory": []}
    for t, measured in enumerate(measure):
        true_obs = plain.info["final_observation"][t]  # before any auto-reset
        seen = true_obs if measured else memory
        if measured:
            memory = true_obs
        expected["final_obs"].append(np.append(seen, float(measured)))
        if plain.terminated[t] or plain.truncated[t]:
            memory = plain.obs[t]  # the reset's first observation is a free measurement
            expected["obs"].append(plain.obs[t])
            expected["flag"].append(1.0)
        else:
            expected["obs"].append(seen)
            expected["flag"].append(float(measured))
        expected["memory"].append(memory)
    return {name: np.asarray(values) for name, values in expected.items()}


@settings(max_examples=30, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    actions=st.lists(st.integers(0, 3), min_size=T, max_size=T),
    cost=st.floats(0.0, 5.0, width=32),
)
def test_last_mode_matches_a_python_loop(rollout, inner_keys, seed, actions, cost):
    actions = np.asarray(actions)
    measure = actions >= 2
    key = jax.random.key(seed)
    run = rollout(CARTPOLE, SHORT.replace(cost=jnp.float32(cost)), key, jnp.asarray(actions))
    plain = inner_rollout(rollout, inner_keys, run, INNER_CARTPOLE, SHORT.env_params, key, actions % 2)
    done = run.terminated | run.truncated
    assert done.sum() >= T // 5

    # The cost is charged iff measured; the raw reward is the inner env's.
    np.testing.assert_array_equal(run.info["measured"], measure)
    np.testing.assert_array_equal(run.info["cost"], np.float32(cost) * measure)
    np.testing.assert_array_equal(run.info["raw_reward"], plain.reward)
    np.testing.assert_allclose(run.reward, plain.reward - np.float32(cost) * measure, rtol=1e-6)
    np.testing.assert_array_equal(run.terminated, plain.terminated)
    np.testing.assert_array_equal(run.truncated, plain.truncated)

    # Observations, flags and the remembered observation equal the Python loop's.
    expected = reference_last_mode(measure, plain)
    np.testing.assert_allclose(run.obs0, np.append(plain.obs0, 1.0), atol=1e-6)
    np.testing.assert_allclose(run.obs[:, :-1], expected["obs"], atol=1e-6)
    np.testing.assert_array_equal(run.obs[:, -1], expected["flag"])
    np.testing.assert_allclose(run.info["final_observation"], expected["final_obs"], atol=1e-6)
    np.testing.assert_allclose(run.state.last_obs, expected["memory"], atol=1e-6)

    # The same facts read off the wrapper's own outputs alone (exact: no second program involved).
    fresh = np.concatenate([[run.obs0[:-1]], run.obs[:, :-1]])  # obs before step t is fresh[t]
    last_fresh = 0
    for t in range(T):
        if done[t] or measure[t]:
            assert run.obs[t, -1] == 1.0, f"step {t}: flag must be 1 (measured or first obs of an episode)"
        else:
            assert run.obs[t, -1] == 0.0, f"step {t}: flag must be 0 on an unmeasured step"
            np.testing.assert_array_equal(run.obs[t, :-1], fresh[last_fresh], err_msg=f"stale obs, step {t}")
        if done[t]:
            # Memory reset: the new episode's first obs is what the state now remembers.
            np.testing.assert_array_equal(run.state.last_obs[t], run.obs[t, :-1])
        if done[t] or measure[t]:
            last_fresh = t + 1


# -- Box action spaces ---------------------------------------------------------------------------------------


def test_box_action_env_measures_iff_first_entry_at_least_half(inner_keys):
    env, params = amjax.make("Pendulum-v1", cost=0.3)
    inner, _ = amjax.make_env("Pendulum-v1")
    space = env.action_space(params)
    assert isinstance(space, spaces.Box) and space.shape == (2,)
    np.testing.assert_array_equal(space.low, [0.0, -2.0])
    np.testing.assert_array_equal(space.high, [1.0, 2.0])
    assert env.observation_space(params).shape == (4,)

    measure_entries = jnp.array([0.0, 0.25, 0.4999, 0.5, 0.5001, 1.0])
    torque = jnp.float32(1.3)
    actions = jnp.stack([measure_entries, jnp.full_like(measure_entries, torque)], axis=1)
    key = jax.random.key(1)

    @jax.jit
    def steps(params):
        obs0, state = env.reset(jax.random.key(0), params)
        step = jax.vmap(env.step, in_axes=(None, None, 0, None))
        obs, _, reward, _, _, info = step(key, state, actions, params)
        inner_key = key  # mode "last" passes its key to the inner env unchanged
        true_obs, *_ = inner.step(inner_key, state.env_state, torque[None], params.env_params)
        return obs0, obs, reward, info, true_obs

    obs0, obs, reward, info, true_obs = jax.device_get(steps(params))
    measured = np.array([False, False, False, True, True, True])
    np.testing.assert_array_equal(info["measured"], measured)
    np.testing.assert_array_equal(obs[:, -1], measured.astype(np.float32))
    np.testing.assert_allclose(reward, info["raw_reward"] - 0.3 * measured, atol=1e-6)
    # The control is the rest of the action: measured obs are the inner env's step with torque [1.3],
    # unmeasured ones the remembered reset observation.
    np.testing.assert_allclose(obs[measured, :-1], np.broadcast_to(true_obs, (3, 3)), atol=1e-6)
    np.testing.assert_array_equal(obs[~measured, :-1], np.broadcast_to(obs0[:-1], (3, 3)))


# -- modes "random" and "noisy" ------------------------------------------------------------------------------

RANDOM_CARTPOLE, RANDOM_PARAMS = amjax.make("CartPole-v0", mode="random")
NOISY_CARTPOLE, NOISY_PARAMS = amjax.make("CartPole-v0", mode="noisy", noise_std=0.1)
SHORT_RANDOM = short_episodes(RANDOM_PARAMS, 4)
SHORT_NOISY = short_episodes(NOISY_PARAMS, 4)
OBS_HIGH = np.asarray(INNER_CARTPOLE.observation_space(CARTPOLE_PARAMS.env_params).high)  # x, theta bounded


def hidden_views(rollout, inner_keys, env, params, num_rollouts: int):
    """The unmeasured views (final_observation without flag) and the true obs of `num_rollouts` x T steps.

    Never measures, so every step's final observation is the mode's stand-in for the true one; reuses the
    T-step rollout program the other tests compile.
    """
    views, truths = [], []
    controls = np.random.default_rng(0).integers(0, 2, (num_rollouts, T))
    for i in range(num_rollouts):
        key = jax.random.key(1000 + i)
        run = rollout(env, params, key, jnp.asarray(controls[i]))
        plain = inner_rollout(rollout, inner_keys, run, INNER_CARTPOLE, params.env_params, key, controls[i], env.mode)
        np.testing.assert_array_equal(run.info["final_observation"][:, -1], 0.0)
        views.append(run.info["final_observation"][:, :-1])
        truths.append(plain.info["final_observation"])
    return np.concatenate(views), np.concatenate(truths)


def test_random_mode_samples_the_observation_space(rollout, inner_keys):
    view, true = hidden_views(rollout, inner_keys, RANDOM_CARTPOLE, SHORT_RANDOM, num_rollouts=50)
    assert len(view) == 2000
    assert np.all(np.abs(view) <= OBS_HIGH), "samples must lie in the bounds"
    assert len(np.unique(view, axis=0)) == len(view), "different keys must give different samples"
    assert not np.any(np.isclose(view, true).all(axis=1)), "a sample is not the true observation"
    # Bounded dims (x, theta) are uniform on [-high, high]: std high / sqrt(3), within 10%; the unbounded
    # velocities are N(0, 1) as Gymnasium's Box.sample draws them.
    np.testing.assert_allclose(view.std(axis=0), [4.8 / np.sqrt(3), 1.0, OBS_HIGH[2] / np.sqrt(3), 1.0], rtol=0.1)
    assert np.all(np.abs(view.mean(axis=0)) < 5 * view.std(axis=0) / np.sqrt(len(view))), "centred samples"
    bounded = view[:, [0, 2]]
    assert np.all(bounded.max(axis=0) > 0.95 * OBS_HIGH[[0, 2]]), "uniform samples reach the bounds"
    assert np.all(bounded.min(axis=0) < -0.95 * OBS_HIGH[[0, 2]])


def test_noisy_mode_adds_gaussian_noise_with_the_given_std(rollout, inner_keys):
    sigma = 0.05
    params = SHORT_NOISY.replace(noise_std=jnp.float32(sigma))  # traced: no recompile
    view, true = hidden_views(rollout, inner_keys, NOISY_CARTPOLE, params, num_rollouts=50)
    noise = view - true
    assert np.all(np.abs(true) < OBS_HIGH - 6 * sigma), "far from the bounds: no clipping here"
    np.testing.assert_allclose(noise.std(axis=0), sigma, rtol=0.1)
    assert np.all(np.abs(noise.mean(axis=0)) < 5 * sigma / np.sqrt(len(noise)))
    assert len(np.unique(noise, axis=0)) == len(noise)

    # noise_std 0 gives the true observation.
    view, true = hidden_views(rollout, inner_keys, NOISY_CARTPOLE, params.replace(noise_std=jnp.float32(0.0)), 2)
    np.testing.assert_allclose(view, true, atol=1e-6)


def test_noisy_mode_clips_to_the_observation_bounds(rollout, inner_keys):
    params = SHORT_NOISY.replace(noise_std=jnp.float32(3.0))
    view, _ = hidden_views(rollout, inner_keys, NOISY_CARTPOLE, params, num_rollouts=5)
    assert np.all(np.abs(view) <= OBS_HIGH)
    theta = view[:, 2]  # bounds +-0.42 rad: noise of std 3 must hit them
    assert np.any(theta == OBS_HIGH[2]) and np.any(theta == -OBS_HIGH[2])
    assert np.abs(view[:, [1, 3]]).max() > 3.0, "unbounded dims are not clipped"


@pytest.mark.parametrize(
    ("env", "params"),
    [(CARTPOLE, short_episodes(CARTPOLE_PARAMS, 4)), (RANDOM_CARTPOLE, SHORT_RANDOM), (NOISY_CARTPOLE, SHORT_NOISY)],
    ids=["last", "random", "noisy"],
)
def test_final_observation_is_the_wrapped_pre_reset_observation(rollout, inner_keys, env, params):
    actions = np.random.default_rng(3).integers(0, 4, T)
    measure = actions >= 2
    key = jax.random.key(3)
    run = rollout(env, params, key, jnp.asarray(actions))
    plain = inner_rollout(rollout, inner_keys, run, INNER_CARTPOLE, params.env_params, key, actions % 2, env.mode)
    done = run.terminated | run.truncated
    final = run.info["final_observation"]
    assert done.sum() >= 8 and (done & measure).any() and (done & ~measure).any()

    # Without a boundary the final observation is the observation.
    np.testing.assert_array_equal(final[~done], run.obs[~done])
    # On a boundary: obs is the fresh reset obs; final_observation is what the agent would have seen.
    np.testing.assert_allclose(run.obs[done, :-1], plain.obs[done], atol=1e-6)
    np.testing.assert_array_equal(run.obs[done, -1], 1.0)
    np.testing.assert_array_equal(final[:, -1], measure)
    np.testing.assert_allclose(final[done & measure, :-1], plain.info["final_observation"][done & measure], atol=1e-6)
    hidden = final[done & ~measure, :-1]
    true_hidden = plain.info["final_observation"][done & ~measure]
    assert not np.allclose(hidden, true_hidden, atol=1e-6), "an unmeasured final obs must not be the truth"
    if env is NOISY_CARTPOLE:
        assert np.all(np.abs(hidden - true_hidden) < 6 * 0.1)


# -- vmap and jit ----------------------------------------------------------------------------------------------

LANES = 1000
LANE_ACTIONS = jnp.tile(jnp.array([0, 3]), 10)  # measure every other step


@pytest.fixture(scope="module")
def lanes_rollout(scan_steps_fn):
    """One program: `LANES` rollouts of `LANE_ACTIONS`, lane i with keys[i] and params.cost[i]."""
    axes = MeasureParams(env_params=None, cost=0, noise_std=None)

    def lane(key, params):
        reset_key, steps_key = jax.random.split(key)
        step_keys = jax.random.split(steps_key, len(LANE_ACTIONS))
        outputs = scan_steps_fn(CARTPOLE, params, reset_key, step_keys, LANE_ACTIONS)[2]
        obs, _, reward, _, _, info = outputs
        return obs, reward, info["raw_reward"]

    return jax.jit(jax.vmap(lane, in_axes=(0, axes)))


def test_vmap_over_1000_costs_in_one_program(lanes_rollout):
    costs = np.linspace(0.0, 2.0, LANES)
    _, params = amjax.make("CartPole-v0", cost=costs)
    assert params.cost.shape == (LANES,)
    keys = jnp.broadcast_to(jax.random.key(0), (LANES,))
    obs, reward, raw = jax.device_get(lanes_rollout(keys, params))
    assert reward.shape == (LANES, len(LANE_ACTIONS))
    np.testing.assert_array_equal(raw, np.broadcast_to(raw[0], raw.shape))  # same key: same dynamics
    measured = np.asarray(LANE_ACTIONS) >= 2
    expected = raw - costs[:, None].astype(np.float32) * measured
    np.testing.assert_allclose(reward, expected, atol=1e-5)
    assert len(np.unique(reward.sum(axis=1))) == LANES, "each lane must be charged its own cost"


def test_vmap_over_keys_gives_different_trajectories(lanes_rollout):
    _, params = amjax.make("CartPole-v0", cost=np.full(LANES, 0.5))
    keys = jax.random.split(jax.random.key(7), LANES)
    obs, _, _ = jax.device_get(lanes_rollout(keys, params))
    assert len(np.unique(obs.reshape(LANES, -1), axis=0)) == LANES, "every key its own trajectory"
    again, _, _ = jax.device_get(lanes_rollout(keys, params))
    np.testing.assert_array_equal(obs, again)  # and the same key the same one
    assert lanes_rollout._cache_size() == 1, "the costs test and this one share one compiled program"


def test_jit_compiles_once_for_different_costs():
    traces = []

    def step_with(params):
        traces.append(1)  # runs only while tracing
        obs, state = CARTPOLE.reset(jax.random.key(0), params)
        return CARTPOLE.step(jax.random.key(1), state, 3, params)[2]

    compiled = jax.jit(step_with)
    rewards = [float(compiled(amjax.make("CartPole-v0", cost=c)[1])) for c in (0.0, 0.1, 0.7, 3.0)]
    assert len(traces) == 1 and compiled._cache_size() == 1
    np.testing.assert_allclose(rewards, [1.0, 0.9, 0.3, -2.0], atol=1e-6)

    # The wrapper's own jitted step does not recompile for a new cost either.
    _, state = CARTPOLE.reset(jax.random.key(0), CARTPOLE_PARAMS)
    CARTPOLE.step(jax.random.key(1), state, 3, CARTPOLE_PARAMS.replace(cost=jnp.float32(0.4)))
    size = type(CARTPOLE).step._cache_size()
    for c in (0.2, 0.9):
        CARTPOLE.step(jax.random.key(1), state, 3, amjax.make("CartPole-v0", cost=c)[1])
    assert type(CARTPOLE).step._cache_size() == size


# -- vanilla -----------------------------------------------------------------------------------------------------


def test_vanilla_is_the_plain_env_with_the_same_info_keys(rollout):
    env, params = amjax.make("CartPole-v0", vanilla=True)
    space = env.action_space(params)
    assert isinstance(space, spaces.Discrete) and space.n == 2
    assert env.observation_space(params).shape == (4,)
    controls = jnp.asarray(np.random.default_rng(1).integers(0, 2, T))
    key = jax.random.key(2)
    run = rollout(env, SHORT.env_params, key, controls)
    plain = rollout(INNER_CARTPOLE, SHORT.env_params, key, controls)
    wrapped = rollout(CARTPOLE, SHORT, key, controls + 2)

    assert set(run.info) == set(wrapped.info)
    assert run.obs.shape == (T, 4)
    np.testing.assert_array_equal(run.info["cost"], 0.0)
    np.testing.assert_array_equal(run.info["measured"], True)
    np.testing.assert_array_equal(run.reward, run.info["raw_reward"])
    np.testing.assert_array_equal(run.obs, plain.obs)  # same keys: vanilla does not split them
    np.testing.assert_array_equal(run.reward, plain.reward)
    assert (run.terminated | run.truncated).sum() >= 5


# -- bad input ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("cost", [-0.1, float("nan"), float("inf"), -float("inf"), [0.1, -1.0]])
def test_bad_cost_is_refused(cost):
    with pytest.raises(ValueError, match=r"cost: .*allowed values: finite numbers in \[0.0, inf\]"):
        amjax.make("CartPole-v0", cost=cost)


@pytest.mark.parametrize("noise_std", [-0.1, float("nan"), float("inf")])
def test_bad_noise_std_is_refused(noise_std):
    with pytest.raises(ValueError, match=r"noise_std: .*allowed values: finite numbers in \[0.0, inf\]"):
        amjax.make("CartPole-v0", mode="noisy", noise_std=noise_std)


def test_noise_std_goes_with_noisy_mode_only():
    with pytest.raises(ValueError, match="noise_std.*noisy"):
        amjax.make("CartPole-v0", mode="noisy")
    for mode in ("last", "random"):
        with pytest.raises(ValueError, match="noise_std.*noisy"):
            amjax.make("CartPole-v0", mode=mode, noise_std=0.1)


def test_unknown_mode_and_bad_flags_are_refused():
    with pytest.raises(ValueError, match="mode: got 'stale'; allowed values: 'last', 'random', 'noisy'"):
        amjax.make("CartPole-v0", mode="stale")
    with pytest.raises(ValueError, match="flag: got 'yes'; allowed values: True, False"):
        amjax.make("CartPole-v0", flag="yes")
    with pytest.raises(ValueError, match="vanilla"):
        amjax.make("CartPole-v0", vanilla=True, cost=0.1)
    with pytest.raises(ValueError, match="vanilla"):
        amjax.make("CartPole-v0", vanilla=True, mode="noisy", noise_std=0.1)


class TupleActionCartPole(CartPole):
    def action_space(self, params=None):
        return spaces.Tuple([spaces.Discrete(2), spaces.Discrete(2)])


class DictActionCartPole(CartPole):
    def action_space(self, params=None):
        return spaces.Dict({"push": spaces.Discrete(2)})


class MatrixActionCartPole(CartPole):
    def action_space(self, params=None):
        return spaces.Box(-1.0, 1.0, (2, 2))


@pytest.mark.parametrize("env_class", [TupleActionCartPole, DictActionCartPole])
def test_unsupported_action_space_is_refused(env_class):
    with pytest.raises(TypeError, match=r"env: .*Discrete or Box action space.*allowed: Discrete, Box"):
        ActiveMeasure(env_class())


def test_unsupported_action_space_is_refused_through_make(monkeypatch):
    monkeypatch.setattr(registry, "_CUSTOM_ENVS", {})
    amjax.envs.register("TupleCartPole-v0", lambda: (TupleActionCartPole(), CartPole().default_params))
    with pytest.raises(TypeError, match=r"env: .*got Tuple; allowed: Discrete, Box"):
        amjax.make("TupleCartPole-v0")


def test_matrix_box_action_space_is_refused():
    with pytest.raises(TypeError, match="env: a Box action space must be 1-D"):
        ActiveMeasure(MatrixActionCartPole())


def test_flag_needs_a_vector_or_an_image():
    """An image takes the flag as a channel (tests/wrappers/test_images.py); an observation that is neither a
    vector nor an image [height, width, channels] is refused, naming the way out."""
    env, params = amjax.make("Breakout-MinAtar")
    assert env.observation_space(params).shape == (10, 10, 5)
    env, params = amjax.make("Breakout-MinAtar", flag=False)
    assert env.observation_space(params).shape == (10, 10, 4)
    volume, volume_params = amjax.make("Breakout-MinAtar", vanilla=True)
    with pytest.raises(TypeError, match=r"vector or an image .*\(1, 10, 10, 4\).*amjax.make or amjax.wrap"):
        ActiveMeasure(VolumeObservation(volume), env_params=volume_params)


class VolumeObservation(GymnaxWrapper):
    """An env whose observations are 4-D ([1, 10, 10, 4]): neither a vector nor an image."""

    def observation_space(self, params=None):
        space = self._env.observation_space(params)
        return spaces.Box(0.0, 1.0, (1, *space.shape), jnp.float32)
