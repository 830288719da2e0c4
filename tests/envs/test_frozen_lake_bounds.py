"""The exact FrozenLake bounds of `experiments/frozen_lake.py`: its tabular models against the envs (gymnax's lake,
and the semi-slippery lake of Act-Then-Measure that the experiment registers), and its solved policies played in
amjax's wrapped env, where they must score what the solver says they score."""

from __future__ import annotations

import runpy
from pathlib import Path
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import amjax
from amjax.envs.registry import make_env

ROOT = Path(__file__).resolve().parents[2]
FROZEN = SimpleNamespace(**runpy.run_path(str(ROOT / "experiments" / "frozen_lake.py")))  # not installed: by path
FROZEN.register_semi_slippery()
LAKE = FROZEN.lake_model()


N_CELLS, N_MOVES = LAKE.reward.size, LAKE.transitions.shape[0]


@pytest.mark.parametrize("env_id", list(FROZEN.DYNAMICS))
def test_model_matches_the_env_transitions(env_id):
    """4,000 env steps from each (cell, move): the frequencies of the next cell match the model's probabilities (1/3
    for each of three slips; 1/2 for one cell or two) within 5 standard errors; the rewards and terminal cells
    match too."""
    lake = FROZEN.lake_model(FROZEN.DYNAMICS[env_id])
    env, params = make_env(env_id)
    samples = 4_000
    cells, moves = np.meshgrid(np.arange(N_CELLS), np.arange(N_MOVES), indexing="ij")
    keys = jax.random.split(jax.random.key(0), N_CELLS * N_MOVES * samples).reshape(N_CELLS, N_MOVES, samples)

    def step(key, cell, move):
        state = env.reset_env(key, params)[1].replace(position=cell)
        _, state, reward, terminated, _ = env.step_env(key, state, move, params)
        return state.position, reward, terminated

    step_all = jax.jit(jax.vmap(jax.vmap(jax.vmap(step, (0, None, None)), (0, 0, 0)), (0, 0, 0)))
    to, reward, terminated = jax.device_get(step_all(keys, jnp.asarray(cells), jnp.asarray(moves)))
    freq = np.stack([np.eye(N_CELLS)[to[:, a]].mean(axis=1) for a in range(N_MOVES)])  # [a, s, s']
    se = np.sqrt(lake.transitions * (1 - lake.transitions) / samples)
    assert np.all(np.abs(freq - lake.transitions) <= 5 * se + 1e-12)
    np.testing.assert_array_equal(reward, lake.reward[to])
    np.testing.assert_array_equal(terminated, lake.terminal[to])


def _plain_value_iteration(lake, horizon):
    """The fully observed lake's optimal value from the start, written out the textbook way."""
    values = np.zeros(lake.reward.size)
    for _ in range(horizon):
        future = lake.reward + np.where(lake.terminal, 0.0, values)  # [s']: what entering s' is worth
        values = (lake.transitions @ future).max(axis=0)
    return values[lake.start]


def test_vanilla_optimum_matches_plain_value_iteration():
    """Cost 0, measuring always: the belief solver's value is the textbook one, 0.7442 within 100 steps and 14/17
    with no time limit (3,000 steps); the capped classes at cost 0.05 are nested, so their values only rise."""
    for horizon in (FROZEN.TIME_LIMIT, 3_000):
        assert FROZEN.solve(LAKE, 0.0, 0, horizon).value == pytest.approx(
            _plain_value_iteration(LAKE, horizon), abs=1e-9
        )
    assert FROZEN.solve(LAKE, 0.0, 0).value == pytest.approx(0.7442, abs=1e-4)
    assert FROZEN.solve(LAKE, 0.0, 0, 3_000).value == pytest.approx(14 / 17, abs=1e-9)
    costed = [FROZEN.solve(LAKE, 0.05, gap).value for gap in (0, 1, 2, 3)]
    assert costed == sorted(costed)


def test_never_measure_is_the_best_of_its_sixteen_policies():
    """The memoryless never-measure policy: left from the fresh start, then down on every stale view, reaches the
    goal in 5.4% of episodes; every other pair of moves does worse."""
    value, _, first, then = FROZEN.never_measure(LAKE)
    assert (FROZEN.MOVE_NAMES[first], FROZEN.MOVE_NAMES[then]) == ("left", "down")
    assert value == pytest.approx(0.0543, abs=1e-4)


def test_solved_policies_score_their_values_in_the_wrapped_env():
    """Two solved policies played in `amjax.make("FrozenLake-misc")`, 8,192 episodes each, in one compiled program:
    the one for cost 0.05 and up to 2 moves between measurements (it measures on about 27% of steps and its
    episodes are short) and the vanilla one at cost 0 (it measures always, walks about 44 steps and is cut by the
    time limit in about 4% of episodes). Mean costed return and measurements per episode match the solver's within
    4 standard errors, which pins its reading of the wrapper (the cost on every measuring step, the episode's last
    included; the 100-step limit) to the env; and on every step the observation is what the solver assumes: the
    true cell with flag 1 after a measurement, the last measured cell with flag 0 otherwise."""
    episodes, horizon, max_gap = 8_192, FROZEN.TIME_LIMIT, 2
    sizes = [N_CELLS * N_MOVES**k for k in range(max_gap + 1)]
    offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    costs = (0.05, 0.0)
    bounds = [FROZEN.solve(LAKE, 0.05, max_gap), FROZEN.solve(LAKE, 0.0, 0)]
    tables = np.zeros((len(bounds), horizon + 1, sum(sizes)), np.int32)  # [policy, steps left, offset_k + node]
    for i, bound in enumerate(bounds):
        for left in range(1, horizon + 1):
            for k, part in enumerate(bound.choice[left]):  # the vanilla policy has depth 0 only: it always measures
                tables[i, left, offsets[k] : offsets[k] + sizes[k]] = part
    env, params = amjax.make(FROZEN.ENV_ID, cost=0.0)
    offsets = jnp.asarray(offsets)

    def episode(table, cost, key):
        params_c = params.replace(cost=cost)
        reset_key, key = jax.random.split(key)
        obs, state = env.reset(reset_key, params_c)

        def step(carry, key):
            state, depth, node, shown, running, total, measured, wrong_views = carry
            action = table[horizon - state.env_state.time, offsets[depth] + node]
            obs, state, reward, terminated, truncated, _ = env.step(key, state, action, params_c)
            measure, done = action >= N_MOVES, terminated | truncated
            cell, flag = jnp.argmax(obs[:N_CELLS]), obs[N_CELLS]
            view_ok = jnp.where(
                measure, (cell == state.env_state.position) & (flag == 1), (cell == shown) & (flag == 0)
            )
            wrong_views = wrong_views + (running & ~done & ~view_ok).astype(jnp.int32)
            depth = jnp.where(measure, 0, depth + 1)
            node = jnp.where(measure, cell, node * N_MOVES + action % N_MOVES)
            shown = jnp.where(measure, cell, shown)
            total = total + jnp.where(running, reward, 0.0)
            measured = measured + (running & measure).astype(jnp.int32)
            running = running & ~done
            return (state, depth, node, shown, running, total, measured, wrong_views), None

        cell = jnp.argmax(obs[:N_CELLS])
        zero = jnp.int32(0)
        start = (state, zero, cell, cell, jnp.bool_(True), jnp.float32(0.0), zero, zero)
        (*_, total, measured, wrong_views), _ = jax.lax.scan(step, start, jax.random.split(key, horizon))
        return total, measured, wrong_views

    keys = jax.random.split(jax.random.key(1), (len(bounds), episodes))
    play = jax.jit(jax.vmap(jax.vmap(episode, (None, None, 0))))
    total, measured, wrong_views = jax.device_get(play(jnp.asarray(tables), jnp.asarray(costs), keys))
    assert wrong_views.sum() == 0
    for i, bound in enumerate(bounds):
        assert abs(total[i].mean() - bound.value) <= 4 * total[i].std() / np.sqrt(episodes)
        assert abs(measured[i].mean() - bound.measurements) <= 4 * measured[i].std() / np.sqrt(episodes)
