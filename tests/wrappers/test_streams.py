"""The wrapper's own random draws (instrument reading noise, an episode's cost, the unmeasured view) come from a
stream apart from the inner env's: never from a key the inner env derives from the one it is handed (in this jax
`fold_in(k, i) == split(k, n)[i]`, so `fold_in(key, 1)` is gymnax's auto-reset key), and never from each other's."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import amjax

N = 4000  # steps (one per env of a batch); |correlation| of independent draws is about 1 / sqrt(N) = 0.016
MAX_CORRELATION = 0.07


def _one_step_episodes(**options):
    """CartPole-v0 whose episodes last one step (every step truncates and auto-resets) and a jitted batch step."""
    env, params = amjax.make("CartPole-v0", **options)
    params = params.replace(env_params=params.env_params.replace(max_steps_in_episode=1))
    _, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(jax.random.key(1), N), params)
    return env, params, state, jax.jit(jax.vmap(env.step, in_axes=(0, 0, None, None)))


def _correlations(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per column, the correlation of a[:, j] with b[:, j]."""
    return np.array([np.corrcoef(a[:, j], b[:, j])[0, 1] for j in range(a.shape[1])])


def _inner_keys(key: jax.Array) -> list[jax.Array]:
    """The keys an environment handed `key` can reach with small splits and folds, two levels deep: the key itself,
    split(key, n)[i] for n <= 4 (the same keys as fold_in(key, i)) and the same again from each of those."""
    level1 = [jax.random.fold_in(key, i) for i in range(4)]
    level2 = [jax.random.fold_in(k, i) for k in level1 for i in range(4)]
    return [key, *level1, *level2]


def test_reading_noise_is_independent_of_the_next_episodes_start():
    """An episode's last reading (its noise drawn at the step that truncates it) tells nothing about the start of
    the next episode (the inner env's auto-reset draw of the same step)."""
    env, params, state, step = _one_step_episodes(instruments="default", instrument_noise=(0.05, 0.05))
    keys = jax.random.split(jax.random.key(2), N)
    read_all = 3 * 2  # both instruments, control 0
    obs, _, _, _, truncated, info = step(keys, state, read_all, params)
    *_, exact = step(keys, state, read_all, params.replace(instrument_noise=jnp.zeros(2)))
    assert np.asarray(truncated).all()
    noise = np.asarray(info["final_observation"][:, :4] - exact["final_observation"][:, :4])
    assert np.std(noise) == pytest.approx(0.05, rel=0.05)
    next_start = np.asarray(obs[:, :4])  # the auto-reset's first observation
    assert np.abs(_correlations(noise, next_start)).max() < MAX_CORRELATION


@pytest.mark.parametrize("mode", ["last", "noisy"])
def test_wrapper_draws_use_no_key_of_the_inner_env(mode):
    """The reading noise and the next episode's cost are not drawn from any key the inner env can reach from its
    step key (in mode "last" the inner env is handed the step key itself, in the others its first split)."""
    noise = {"noise_std": 0.1} if mode == "noisy" else {}
    env, params = amjax.make(
        "CartPole-v0", mode=mode, instruments="default", instrument_noise=(1.0, 1.0), cost_range=(0.0, 1.0), **noise
    )
    params = params.replace(env_params=params.env_params.replace(max_steps_in_episode=1))
    _, state = env.reset(jax.random.key(3), params)
    for seed in range(3):
        key = jax.random.key(10 + seed)
        *_, info = env.step(key, state, 3 * 2, params)
        *_, exact = env.step(key, state, 3 * 2, params.replace(instrument_noise=jnp.zeros(2)))
        _, next_state, *_ = env.step(key, state, 3 * 2, params)
        noise = np.asarray(info["final_observation"][:4] - exact["final_observation"][:4])
        inner_key = key if mode == "last" else jax.random.split(key)[0]
        for candidate in _inner_keys(inner_key):
            assert not np.allclose(noise, np.asarray(jax.random.normal(candidate, (4,))), atol=1e-3)
            assert float(next_state.episode_cost) != float(jax.random.uniform(candidate, ()))


def test_the_cost_draw_at_reset_uses_no_key_of_the_inner_reset():
    """LunarLander's reset draws its wind from split(key, 3)[2] = fold_in(key, 2): an episode's cost must come from
    elsewhere (so must every env's reset draws, whatever keys it splits)."""
    env, params = amjax.make("CartPole-v0", cost_range=(0.0, 1.0))
    for seed in range(4):
        key = jax.random.key(seed)
        _, state = env.reset(key, params)
        for candidate in _inner_keys(key):
            assert float(state.episode_cost) != float(jax.random.uniform(candidate, ()))


def test_reading_noise_and_the_noisy_view_are_independent():
    """In mode "noisy" a feature read by its instrument and the same feature left unread (shown with the view's
    noise) carry independent errors."""
    env, params, state, step = _one_step_episodes(
        mode="noisy", noise_std=0.05, instruments="default", instrument_noise=(0.05, 0.05)
    )
    keys = jax.random.split(jax.random.key(4), N)
    *_, read = step(keys, state, 3 * 2, params)  # both instruments read
    *_, unread = step(keys, state, 0, params)  # neither
    *_, exact = step(keys, state, 3 * 2, params.replace(instrument_noise=jnp.zeros(2)))
    truth = np.asarray(exact["final_observation"][:, :4])
    reading_error = np.asarray(read["final_observation"][:, :4]) - truth
    view_error = np.asarray(unread["final_observation"][:, :4]) - truth
    for error in (reading_error, view_error):
        assert np.std(error) == pytest.approx(0.05, rel=0.05)
    assert np.abs(_correlations(reading_error, view_error)).max() < MAX_CORRELATION
