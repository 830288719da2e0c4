"""Per-episode statistics (`EpisodeStats`) against a plain Python loop over the same transitions."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

import amjax
from amjax.wrappers import EpisodeStats

T = 40  # steps per rollout: one compiled program for every hypothesis example

CARTPOLE, CARTPOLE_PARAMS = amjax.make("CartPole-v0")
STATS = EpisodeStats(CARTPOLE)
VANILLA, VANILLA_PARAMS = amjax.make("CartPole-v0", vanilla=True)
VANILLA_STATS = EpisodeStats(VANILLA)


def with_max_steps(params, max_steps: int):
    return params.replace(env_params=params.env_params.replace(max_steps_in_episode=max_steps))


def python_loop_episodes(run) -> tuple[list[tuple[float, float, int, int]], tuple[float, float, int, int]]:
    """(finished episodes, the unfinished one) as (costed return, raw return, length, measurements)."""
    finished = []
    costed, raw, length, measurements = 0.0, 0.0, 0, 0
    for t in range(len(run.reward)):
        costed += float(run.reward[t])
        raw += float(run.info["raw_reward"][t])
        length += 1
        measurements += int(run.info["measured"][t])
        if run.terminated[t] or run.truncated[t]:
            finished.append((costed, raw, length, measurements))
            costed, raw, length, measurements = 0.0, 0.0, 0, 0
    return finished, (costed, raw, length, measurements)


def reported_episodes(run) -> list[tuple[float, float, int, int]]:
    """The totals `EpisodeStats` reports on the steps where an episode ended."""
    episode, done = run.info["episode"], run.info["episode_done"]
    return [
        (
            float(episode.costed_return[t]),
            float(episode.raw_return[t]),
            int(episode.length[t]),
            int(episode.measurements[t]),
        )
        for t in np.flatnonzero(done)
    ]


def assert_same_episodes(got, expected):
    assert len(got) == len(expected)
    for (g_costed, g_raw, g_len, g_meas), (e_costed, e_raw, e_len, e_meas) in zip(got, expected, strict=True):
        assert (g_len, g_meas) == (e_len, e_meas)
        np.testing.assert_allclose([g_costed, g_raw], [e_costed, e_raw], rtol=1e-5, atol=1e-5)


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    actions=st.lists(st.integers(0, 3), min_size=T, max_size=T),
    cost=st.floats(0.0, 2.0, width=32),
    max_steps=st.sampled_from([6, 200]),  # many truncations, or terminations only
)
def test_episode_totals_match_a_python_loop(rollout, seed, actions, cost, max_steps):
    params = with_max_steps(CARTPOLE_PARAMS, max_steps).replace(cost=jnp.float32(cost))
    run = rollout(STATS, params, jax.random.key(seed), jnp.asarray(actions))
    done = run.terminated | run.truncated
    np.testing.assert_array_equal(run.info["episode_done"], done)
    if max_steps == 6:
        assert done.sum() >= T // 6

    expected, unfinished = python_loop_episodes(run)
    assert_same_episodes(reported_episodes(run), expected)
    # Costed return = raw return - cost * paid measurements, per finished episode.
    for costed, raw, _, measurements in expected:
        np.testing.assert_allclose(costed, raw - np.float32(cost) * measurements, rtol=1e-5, atol=1e-5)
    # The running totals after the last step are the unfinished episode's (zero right after a boundary).
    last = run.state.totals
    assert (int(last.length[-1]), int(last.measurements[-1])) == unfinished[2:]
    np.testing.assert_allclose([last.costed_return[-1], last.raw_return[-1]], unfinished[:2], rtol=1e-5, atol=1e-5)
    assert sum(episode[2] for episode in expected) + unfinished[2] == T


def test_statistics_do_not_change_the_transitions(rollout):
    params = with_max_steps(CARTPOLE_PARAMS, 6).replace(cost=jnp.float32(0.2))
    actions = jnp.asarray(np.random.default_rng(0).integers(0, 4, T))
    key = jax.random.key(0)
    run = rollout(STATS, params, key, actions)
    plain = rollout(CARTPOLE, params, key, actions)
    np.testing.assert_array_equal(run.obs0, plain.obs0)
    np.testing.assert_array_equal(run.obs, plain.obs)
    np.testing.assert_array_equal(run.reward, plain.reward)
    np.testing.assert_array_equal(run.terminated, plain.terminated)
    np.testing.assert_array_equal(run.truncated, plain.truncated)
    assert int(run.state0.totals.length) == 0 and float(run.state0.totals.costed_return) == 0.0


def test_vanilla_episodes_measure_every_step(rollout):
    controls = jnp.zeros(T, jnp.int32)  # always push left: the pole falls within about 10 steps
    run = rollout(VANILLA_STATS, VANILLA_PARAMS, jax.random.key(1), controls)
    episodes = reported_episodes(run)
    assert len(episodes) >= 3
    assert_same_episodes(episodes, python_loop_episodes(run)[0])
    for costed, raw, length, measurements in episodes:
        assert measurements == length
        assert costed == raw == length  # CartPole pays 1 per step, vanilla charges nothing
