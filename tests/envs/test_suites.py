"""The other JAX suites behind the gymnax API (amjax/envs/suites.py; optional extras): each adapter steps as the
suite's own env under the same keys, ends episodes at the suite's time limit as truncated, refuses unknown names
and missing suites clearly, and trains in a sweep. (tests/wrappers/test_every_env_id.py runs the listed ids through
every option, jit, vmap and Gymnasium's check_env.)"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import amjax
from amjax.envs import suites
from amjax.envs.registry import make_env, registered_envs

STEPS = 30


@pytest.mark.slow
def test_craftax_steps_as_craftax(rollout):
    """Same keys: the adapter's reset is Craftax's `reset_env(key)`, each step Craftax's `step_env` with the first
    half of the step's key (gymnax's split); death and lava are terminations, the time limit is not."""
    pytest.importorskip("craftax")
    from craftax.craftax_env import make_craftax_env_from_name

    env, params = make_env("craftax:Craftax-Classic-Symbolic-v1")
    craftax = make_craftax_env_from_name("Craftax-Classic-Symbolic-v1", auto_reset=False)
    actions = jnp.asarray(np.random.default_rng(0).integers(0, 17, STEPS))
    got = rollout(env, params, jax.random.key(3), actions)
    want, state = jax.jit(craftax.reset_env)(jax.random.split(jax.random.key(3))[0], craftax.default_params)
    np.testing.assert_allclose(got.obs0, want, rtol=0, atol=1e-6)  # one program against another: float rounding
    step = jax.jit(craftax.step_env)
    for t in range(STEPS):
        key = jax.random.split(got.step_keys[t])[0]
        want, state, want_reward, done, _ = step(key, state, actions[t], craftax.default_params)
        np.testing.assert_allclose(got.obs[t], want, rtol=0, atol=1e-6)
        assert float(got.reward[t]) == pytest.approx(float(want_reward))
        assert bool(got.terminated[t]) == bool(done) and not bool(got.truncated[t])
        if done:
            break
    assert env.observation_space(params).shape == (1345,) and env.action_space(params).n == 17


def test_xminigrid_steps_as_xminigrid_one_hot(rollout):
    """The adapter's view is xland-minigrid's 7 x 7 view with its tile and colour ids one-hot; rewards and the goal
    (a termination) are xland-minigrid's."""
    pytest.importorskip("xminigrid")
    import xminigrid
    from xminigrid.core.constants import NUM_COLORS, NUM_TILES

    env, params = make_env("xminigrid:MiniGrid-Empty-8x8")
    grid, grid_params = xminigrid.make("MiniGrid-Empty-8x8")
    actions = jnp.asarray(np.random.default_rng(1).integers(0, 6, STEPS))
    got = rollout(env, params, jax.random.key(5), actions)
    timestep = grid.reset(grid_params, jax.random.split(jax.random.key(5))[0])
    step = jax.jit(grid.step)

    def one_hot(view):
        return np.concatenate([np.eye(NUM_TILES)[view[..., 0]], np.eye(NUM_COLORS)[view[..., 1]]], -1)

    np.testing.assert_array_equal(got.obs0, one_hot(np.asarray(timestep.observation)))
    for t in range(STEPS):
        timestep = step(grid_params, timestep, actions[t])
        np.testing.assert_array_equal(got.obs[t], one_hot(np.asarray(timestep.observation)))
        assert float(got.reward[t]) == pytest.approx(float(timestep.reward))
        assert bool(got.terminated[t]) == bool(timestep.discount == 0)
        if timestep.last():
            break
    assert env.observation_space(params).shape == (7, 7, NUM_TILES + NUM_COLORS)


@pytest.mark.parametrize(
    "env_id",
    ["xminigrid:MiniGrid-Empty-8x8", pytest.param("craftax:Craftax-Classic-Symbolic-v1", marks=pytest.mark.slow)],
)
def test_the_time_limit_truncates_and_resets(rollout, env_id):
    """A limit of 5 steps (a traced param: the program the step tests above compiled, reused) truncates every
    fifth step and never terminates while the agent stands still."""
    pytest.importorskip(suites.suite_of(env_id))
    env, params = make_env(env_id)
    got = rollout(env, params.replace(max_steps_in_episode=5), jax.random.key(0), jnp.zeros(STEPS, jnp.int32))
    ended = np.flatnonzero(got.terminated | got.truncated)
    np.testing.assert_array_equal(ended, np.arange(4, STEPS, 5))
    assert got.truncated[ended].all() and not got.terminated.any()
    assert env_id in registered_envs()


def test_bad_ids_name_what_is_allowed(monkeypatch):
    with pytest.raises(ValueError, match="xland-minigrid has no 'MiniGrid-Nowhere'; allowed: xminigrid:"):
        if not suites.installed("xminigrid"):
            pytest.skip(suites.SUITES["xminigrid"])
        make_env("xminigrid:MiniGrid-Nowhere")
    monkeypatch.setattr(suites, "installed", lambda suite: False)
    with pytest.raises(ImportError, match=r'needs craftax, an optional dependency: pip install "amjax-rl\[craftax\]"'):
        amjax.make("craftax:Craftax-Unknown-v1")


@pytest.mark.slow
def test_dqn_trains_on_xminigrid(tmp_path):
    """The sweep runner trains Dueling DQN (the CNN body, picked from the 7 x 7 view) on an adapted env; the rows
    hold real, bounded scores (xland-minigrid pays at most 1 per episode, less the measurements). PPO's CNN in a
    sweep: tests/agents/test_torso.py."""
    pytest.importorskip("xminigrid")
    from amjax.sweep import SweepSpec, run_sweep

    spec = SweepSpec(
        envs=("xminigrid:MiniGrid-Empty-5x5",),
        agents=("dqn",),
        costs=(0.01,),
        seeds=(0,),
        total_timesteps=2048,
        eval_every=1024,
        eval_episodes=4,
    )
    rows = run_sweep(spec, tmp_path / "grid", progress=False, devices=jax.devices()[:1]).results
    assert len(rows) == 2 and set(rows["agent"]) == {"dqn"}
    assert np.isfinite(rows["eval_return"]).all() and (rows["eval_return"] <= 1.0).all()
