"""The exact FrozenLake bounds of `experiments/frozen_lake.py`: its tabular model against gymnax's own lake, and its
solved policies played in amjax's wrapped env, where they must score what the solver says they score."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import gymnax
import jax
import jax.numpy as jnp
import numpy as np

import amjax

ROOT = Path(__file__).resolve().parents[2]


def _experiment():
    path = ROOT / "experiments" / "frozen_lake.py"
    spec = importlib.util.spec_from_file_location("_frozen_lake", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


FROZEN = _experiment()
LAKE = FROZEN.lake_model()


def test_model_matches_gymnax_transitions():
    """4,000 gymnax steps from each (cell, move): the frequencies of the next cell match the model's probabilities
    (1/3 each for the three slips) within 5 standard errors; the rewards and terminal cells match too."""
    env, params = gymnax.make(FROZEN.ENV_ID)
    samples = 4_000
    cells, moves = np.meshgrid(np.arange(16), np.arange(4), indexing="ij")
    keys = jax.random.split(jax.random.key(0), 16 * 4 * samples).reshape(16, 4, samples)

    def step(key, cell, move):
        state = env.reset_env(key, params)[1].replace(position=cell)
        _, state, reward, terminated, _ = env.step_env(key, state, move, params)
        return state.position, reward, terminated

    step_all = jax.jit(jax.vmap(jax.vmap(jax.vmap(step, (0, None, None)), (0, 0, 0)), (0, 0, 0)))
    to, reward, terminated = jax.device_get(step_all(keys, jnp.asarray(cells), jnp.asarray(moves)))
    freq = np.stack([np.eye(16)[to[:, a]].mean(axis=1) for a in range(4)])  # [a, s, s']
    se = np.sqrt(LAKE.transitions * (1 - LAKE.transitions) / samples)
    assert np.all(np.abs(freq - LAKE.transitions) <= 5 * se + 1e-12)
    np.testing.assert_array_equal(reward, LAKE.reward[to])
    np.testing.assert_array_equal(terminated, LAKE.terminal[to])


def test_vanilla_optimum_is_the_known_lake_value():
    """Cost 0, measuring always: the lake's own optimum, success in about 74% of episodes within 100 steps (the
    4x4 slippery lake's well-known optimal success rate), and better than any cost-charged class."""
    vanilla = FROZEN.solve(LAKE, 0.0, 0)
    assert 0.72 < vanilla.value < 0.76
    costed = [FROZEN.solve(LAKE, 0.05, gap).value for gap in (0, 1, 2, 3)]
    assert all(v < vanilla.value for v in costed)
    assert costed == sorted(costed)  # a looser cap on the gap between measurements never hurts


def test_solved_policy_scores_its_value_in_the_wrapped_env():
    """The solver's policy for cost 0.05 and up to 2 moves between measurements (it measures on about half the
    steps), played in `amjax.make("FrozenLake-misc", cost=0.05)` on 8,192 episodes: its mean costed return and
    measurements per episode match the solver's within 4 standard errors. This pins the solver's reading of the
    wrapper (the stale cell, the cost on measuring steps, the time limit) to the env."""
    cost, episodes, horizon, max_gap = 0.05, 8_192, FROZEN.TIME_LIMIT, 2
    bound = FROZEN.solve(LAKE, cost, max_gap)
    sizes = [16 * 4**k for k in range(max_gap + 1)]
    offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    table = np.zeros((horizon + 1, sum(sizes)), np.int32)  # [steps left, offset_k + node]: the action to take
    for left in range(1, horizon + 1):
        for k, size in enumerate(sizes):
            table[left, offsets[k] : offsets[k] + size] = bound.choice[left][k]
    table, offsets = jnp.asarray(table), jnp.asarray(offsets)
    env, params = amjax.make(FROZEN.ENV_ID, cost=cost)

    def episode(key):
        reset_key, key = jax.random.split(key)
        obs, state = env.reset(reset_key, params)

        def step(carry, key):
            state, depth, node, running, total, measured = carry
            left = horizon - state.env_state.time
            action = table[left, offsets[depth] + node]
            obs, state, reward, terminated, truncated, _ = env.step(key, state, action, params)
            measure = action >= 4
            fresh_node = jnp.argmax(obs[:16])
            depth, node = (
                jnp.where(measure, 0, depth + 1),
                jnp.where(measure, fresh_node, node * 4 + action % 4),
            )
            total = total + jnp.where(running, reward, 0.0)
            measured = measured + (running & measure).astype(jnp.int32)
            running = running & ~(terminated | truncated)
            return (state, depth, node, running, total, measured), None

        start = (state, jnp.int32(0), jnp.argmax(obs[:16]), jnp.bool_(True), jnp.float32(0.0), jnp.int32(0))
        (*_, total, measured), _ = jax.lax.scan(step, start, jax.random.split(key, horizon))
        return total, measured

    total, measured = jax.device_get(jax.jit(jax.vmap(episode))(jax.random.split(jax.random.key(1), episodes)))
    assert abs(total.mean() - bound.value) <= 4 * total.std() / np.sqrt(episodes)
    assert abs(measured.mean() - bound.measurements) <= 4 * measured.std() / np.sqrt(episodes) + 1e-9
