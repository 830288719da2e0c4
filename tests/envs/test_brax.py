"""brax environments through amjax ("brax:<env_name>[:<backend>]", `amjax.envs.brax_env`), and gymnax's Box-action
environments through `amjax.make`.

The adapter is checked against brax's own env stepped with the same keys and (clipped) actions: a slow Python
loop over brax's jitted `reset`/`step` that does gymnax's auto-reset by hand. Each brax env compiles once here (a
batch of rollouts in one program) and the tests share that run; compiling brax's physics takes seconds per env.
"""

from __future__ import annotations

import functools
import re
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from gymnax.environments import spaces

import amjax
from amjax.envs import brax_env
from train.cli import build_parser, spec_from_args
from train.cli import main as train_main

STEPS = 45
BATCH = 2
# Per env: the episode limit of the run (reacher never terminates, so a short limit makes it truncate).
MAX_STEPS = {"inverted_pendulum": 1000, "reacher": 15}


def needs_brax():
    return pytest.importorskip("brax")


@functools.partial(jax.jit, static_argnums=0)
def batched_rollout(env, params, reset_keys, step_keys, actions):
    """A batch of rollouts (reset, then `lax.scan` of steps), vmapped over keys and actions."""

    def one(reset_key, keys, actions):
        obs0, state0 = env.reset(reset_key, params)

        def step(state, xs):
            key, action = xs
            obs, state, reward, terminated, truncated, info = env.step(key, state, action, params)
            return state, (obs, reward, terminated, truncated, info)

        return obs0, state0, jax.lax.scan(step, state0, (keys, actions))[1]

    return jax.vmap(one)(reset_keys, step_keys, actions)


@functools.cache
def brax_run(env_name: str):
    """amjax's `brax:<env_name>` run for BATCH members of STEPS steps, with actions uniform in [-2, 2] (half of
    them outside the action space), as NumPy: (env, params, inputs, outputs)."""
    needs_brax()
    env, params = amjax.make_env(f"brax:{env_name}")
    params = params.replace(max_steps_in_episode=MAX_STEPS[env_name])
    key_reset, key_steps, key_actions = jax.random.split(jax.random.key(0), 3)
    reset_keys = jax.random.split(key_reset, BATCH)
    step_keys = jax.random.split(key_steps, (BATCH, STEPS))
    actions = jax.random.uniform(key_actions, (BATCH, STEPS, env.action_size), minval=-2.0, maxval=2.0)
    obs0, state0, (obs, reward, terminated, truncated, info) = batched_rollout(
        env, params, reset_keys, step_keys, actions
    )
    inputs = {"reset_keys": reset_keys, "step_keys": step_keys, "actions": np.asarray(actions)}
    outputs = jax.device_get(
        {
            "obs0": obs0,
            "state0": state0,
            "obs": obs,
            "reward": reward,
            "terminated": terminated,
            "truncated": truncated,
            "info": info,
        }
    )
    return env, params, inputs, outputs


@functools.cache
def brax_functions(env: brax_env.BraxEnv):
    """brax's own reset and step of the env amjax wraps, jitted alone."""
    return jax.jit(env.brax_env.reset), jax.jit(env.brax_env.step)


# -- against brax, step for step ---------------------------------------------------------------------------------


@pytest.mark.parametrize("env_name", sorted(MAX_STEPS))
@pytest.mark.slow
def test_matches_brax_step_for_step(env_name):
    env, params, inputs, out = brax_run(env_name)
    reset, step = brax_functions(env)
    assert (np.abs(inputs["actions"]) > 1).any(), "some actions are outside [-1, 1], to be clipped"
    for member in range(BATCH):
        state, time = reset(inputs["reset_keys"][member]), 0
        np.testing.assert_array_equal(out["obs0"][member], state.obs)
        for t in range(STEPS):
            action = np.clip(inputs["actions"][member, t], -1.0, 1.0)
            state, time = step(state, jnp.asarray(action)), time + 1
            where = f"{env_name}, member {member}, step {t}"
            # Same computation, compiled in a different program (a scan, vmapped): XLA may fuse it differently,
            # so float32 rounding may differ in the last bits.
            np.testing.assert_allclose(
                out["info"]["final_observation"][member, t], state.obs, rtol=1e-5, atol=1e-5, err_msg=where
            )
            np.testing.assert_allclose(out["reward"][member, t], state.reward, rtol=1e-5, atol=1e-5, err_msg=where)
            assert out["terminated"][member, t] == bool(state.done), where
            assert out["truncated"][member, t] == (time >= params.max_steps_in_episode), where
            if state.done or time >= params.max_steps_in_episode:
                # gymnax's auto-reset: a fresh reset from the second half of the step's key.
                state, time = reset(jax.random.split(inputs["step_keys"][member, t])[1]), 0
            np.testing.assert_allclose(out["obs"][member, t], state.obs, rtol=1e-5, atol=1e-5, err_msg=where)


@pytest.mark.slow
def test_episodes_end_by_termination_and_by_truncation():
    *_, pendulum = brax_run("inverted_pendulum")
    *_, reacher = brax_run("reacher")
    # Random pushes topple the pendulum (brax's done: |angle| > 0.2) within the run; never the 1000-step limit.
    assert pendulum["terminated"].sum(axis=1).min() >= 2 and not pendulum["truncated"].any()
    np.testing.assert_array_equal(pendulum["info"]["discount"], 1.0 - pendulum["terminated"])
    # Reacher never terminates: it is truncated at the limit (15 steps), with discount 1 (not a terminal state).
    expected = np.zeros(STEPS, bool)
    expected[MAX_STEPS["reacher"] - 1 :: MAX_STEPS["reacher"]] = True
    for member in range(BATCH):
        np.testing.assert_array_equal(reacher["truncated"][member], expected)
    assert not reacher["terminated"].any()
    np.testing.assert_array_equal(reacher["info"]["discount"], 1.0)
    np.testing.assert_array_equal(reacher["info"]["truncated"], reacher["truncated"])
    assert {"metrics/reward_dist", "metrics/reward_ctrl"} <= set(reacher["info"])


@pytest.mark.parametrize("env_name", sorted(MAX_STEPS))
@pytest.mark.slow
def test_every_reset_draws_fresh_randomness(env_name):
    # brax's own AutoResetWrapper would restart every episode from the same first state; here each reset, the first
    # and the automatic ones, of each member differs from all the others.
    *_, out = brax_run(env_name)
    starts = [out["obs0"][member] for member in range(BATCH)]
    for member, t in zip(*np.nonzero(out["terminated"] | out["truncated"]), strict=True):
        starts.append(out["obs"][member, t])
    assert len(starts) >= 2 * BATCH + 2
    distances = [np.abs(a - b).max() for i, a in enumerate(starts) for b in starts[i + 1 :]]
    assert min(distances) > 0


def test_spaces_and_state():
    env, params, _, out = brax_run("reacher")
    assert env.name == "brax:reacher" and env.num_actions == 2
    action_space, obs_space = env.action_space(params), env.observation_space(params)
    assert isinstance(action_space, spaces.Box) and action_space.shape == (2,)
    assert (action_space.low, action_space.high) == (-1.0, 1.0)
    np.testing.assert_array_equal(env.brax_env.sys.actuator.ctrl_range, [[-1, 1], [-1, 1]])
    assert obs_space.shape == (11,) and obs_space.high == np.finfo(np.float32).max == -obs_space.low
    # inverted_pendulum's actuator range is [-3, 3]; brax maps [-1, 1] onto it in its step.
    pendulum, pendulum_params = amjax.make_env("brax:inverted_pendulum")
    assert (pendulum.action_space(pendulum_params).low, pendulum.action_space(pendulum_params).high) == (-1.0, 1.0)
    np.testing.assert_array_equal(pendulum.brax_env.sys.actuator.ctrl_range, [[-3, 3]])
    # The state: brax's, each leaf strongly typed, plus the step counter.
    assert isinstance(out["state0"], brax_env.BraxState)
    assert out["state0"].brax_state.reward.dtype == np.float32
    np.testing.assert_array_equal(out["state0"].time, 0)


def test_make_env_returns_one_env_object_per_id():
    needs_brax()
    # One object per id: reset/step compile once however many times the id is made.
    assert amjax.make_env("brax:reacher")[0] is amjax.make_env("brax:reacher")[0]


def test_env_first_made_inside_a_trace_works_later():
    # A saved policy's `eval_shape` (and any jitted function) may make the env first; the model's arrays must not be
    # cached as that trace's tracers.
    needs_brax()
    brax_env._cached_env.cache_clear()
    jax.eval_shape(lambda key: amjax.make_env("brax:inverted_pendulum")[0].reset(key)[0], jax.random.key(0))
    env, params = amjax.make_env("brax:inverted_pendulum")
    obs, _ = jax.jit(env.reset)(jax.random.key(0), params)
    assert obs.shape == (4,) and np.isfinite(obs).all()


@pytest.mark.parametrize("backend", brax_env.BACKENDS)
def test_every_backend_builds(backend):
    needs_brax()
    env, params = amjax.make_env(f"brax:inverted_pendulum:{backend}")
    assert env.brax_env.backend == backend and env.name == f"brax:inverted_pendulum:{backend}"
    assert env.observation_space(params).shape == (4,) and env.action_space(params).shape == (1,)


def test_listed_in_registered_envs():
    needs_brax()
    assert {"brax:inverted_pendulum", "brax:inverted_double_pendulum", "brax:reacher"} <= set(amjax.registered_envs())


# -- the active-measure wrapper on top -------------------------------------------------------------------------


def check_box_measuring(env_id, plain_env, plain_params, plain_out, reset_key, step_keys, controls, cost):
    """`amjax.make(env_id, cost=cost)` with Box(1 + d) actions whose first entry alternates below / at / above 0.5:
    the cost is charged iff it is >= 0.5, a measured step shows the plain env's observation (same keys, mode
    "last"), an unmeasured one the last measured observation with flag 0. `plain_out` is the plain env's rollout
    (obs0, info final_observation, reward) with the same keys and controls."""
    env, params = amjax.make(env_id, cost=cost)
    d = controls.shape[-1]
    space = env.action_space(params)
    plain_space = plain_env.action_space(plain_params)
    assert isinstance(space, spaces.Box) and space.shape == (1 + d,)
    np.testing.assert_array_equal(space.low, np.concatenate([[0.0], np.broadcast_to(plain_space.low, (d,))]))
    np.testing.assert_array_equal(space.high, np.concatenate([[1.0], np.broadcast_to(plain_space.high, (d,))]))
    measure = np.resize([0.2, 0.5, 0.4999, 1.0, 0.0, 0.7], len(controls)).astype(np.float32)
    actions = np.concatenate([measure[:, None], controls], axis=1)
    obs0, _, (obs, reward, terminated, truncated, info) = jax.device_get(
        batched_rollout(env, params, reset_key[None], step_keys[None], actions[None])
    )
    obs0, obs, reward, info = obs0[0], obs[0], reward[0], jax.tree.map(lambda x: x[0], info)
    done = terminated[0] | truncated[0]
    measured = measure >= 0.5
    np.testing.assert_array_equal(info["measured"], measured)
    np.testing.assert_allclose(info["raw_reward"], plain_out["reward"], rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(reward, plain_out["reward"] - cost * measured, rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(obs0[:-1], plain_out["obs0"])
    shown = info["final_observation"]  # the pre-reset view, flag last
    np.testing.assert_array_equal(shown[:, -1], measured)
    last = plain_out["obs0"]
    for t in range(len(controls)):
        true_obs = plain_out["final_observation"][t]
        np.testing.assert_allclose(shown[t, :-1], true_obs if measured[t] else last, rtol=1e-5, atol=1e-5)
        last = obs[t, :-1] if done[t] else (true_obs if measured[t] else last)
    return done


@pytest.mark.slow
def test_brax_env_through_make_charges_only_measurements():
    plain, params, inputs, out = brax_run("inverted_pendulum")
    plain_out = {
        "obs0": out["obs0"][0],
        "final_observation": out["info"]["final_observation"][0],
        "reward": out["reward"][0],
    }
    controls = inputs["actions"][0]
    done = check_box_measuring(
        "brax:inverted_pendulum",
        plain,
        params,
        plain_out,
        inputs["reset_keys"][0],
        inputs["step_keys"][0],
        controls,
        cost=0.2,
    )
    assert done.any(), "the run crosses an auto-reset"


@pytest.mark.parametrize("env_id", ["Pendulum-v1", "MountainCarContinuous-v0"])
def test_gymnax_box_env_through_make_charges_only_measurements(env_id):
    plain, params = amjax.make_env(env_id)
    d = plain.action_space(params).shape[0]
    key_reset, key_steps, key_actions = jax.random.split(jax.random.key(1), 3)
    step_keys = jax.random.split(key_steps, 12)
    controls = np.asarray(jax.random.uniform(key_actions, (12, d), minval=-1.0, maxval=1.0))
    obs0, _, (_, reward, *_, info) = jax.device_get(
        batched_rollout(plain, params, key_reset[None], step_keys[None], controls[None])
    )
    plain_out = {"obs0": obs0[0], "final_observation": info["final_observation"][0], "reward": reward[0]}
    check_box_measuring(env_id, plain, params, plain_out, key_reset, step_keys, controls, cost=0.1)


# -- clear errors ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("env_id", "message"),
    [
        (
            "brax:reacher:warp",
            "env_id: unknown brax backend 'warp' in 'brax:reacher:warp'; allowed values: "
            "generalized, positional, spring, mjx",
        ),
        ("brax:", "env_id: got 'brax:'; allowed values: 'brax:<env_name>' or 'brax:<env_name>:<backend>'"),
        ("brax:reacher:spring:x", "env_id: got 'brax:reacher:spring:x'"),
    ],
)
def test_malformed_ids_and_unknown_backends_are_refused(env_id, message):
    with pytest.raises(ValueError, match="^" + re.escape(message)):
        amjax.make(env_id, cost=0.1)


def test_unknown_brax_name_lists_brax_names():
    needs_brax()
    with pytest.raises(
        ValueError,
        match="env_id: unknown brax environment 'cartpole' in 'brax:cartpole'; allowed "
        "values: ant, .*inverted_pendulum, .*reacher",
    ) as error:
        amjax.make_env("brax:cartpole")
    assert "walker2d" in str(error.value)


def test_backend_an_env_does_not_support_is_refused():
    needs_brax()
    with pytest.raises(ValueError, match="env_id: brax refused 'brax:swimmer:spring': Unsupported backend"):
        amjax.make_env("brax:swimmer:spring")


def test_unknown_id_error_mentions_the_brax_scheme():
    with pytest.raises(ValueError, match=r"'brax:<env_name>\[:<backend>\]' for any brax environment"):
        amjax.make_env("Reacher-v5")


@pytest.fixture
def without_brax(monkeypatch):
    """brax (and its submodules) made unimportable, as if not installed."""
    for name in [name for name in sys.modules if name == "brax" or name.startswith("brax.")] + ["brax"]:
        monkeypatch.setitem(sys.modules, name, None)


@pytest.mark.parametrize("env_id", ["brax:reacher", "brax:inverted_pendulum:spring"])
def test_without_brax_a_brax_id_says_how_to_install_it(without_brax, env_id):
    # Also for an id made before (the env objects are cached).
    with pytest.raises(ImportError, match=rf"^env_id '{env_id}' needs brax, .*: pip install \"amjax-rl\[brax\]\"$"):
        amjax.make(env_id, cost=0.1)
    assert not brax_env.brax_installed()
    assert not any(name.startswith("brax:") for name in amjax.registered_envs())
    env, params = amjax.make("Pendulum-v1", cost=0.1)  # the rest of amjax works
    assert env.action_space(params).shape == (2,)


def test_sweep_command_takes_any_brax_id():
    """`python -m train sweep --env` takes every id `amjax.make` does, a backend included (not only the listed ids)."""
    needs_brax()
    args = build_parser().parse_args(
        ["sweep", "--env", "brax:reacher:spring", "brax:hopper", "--agent", "ppo", "--out", "unused"]
    )
    assert spec_from_args(args).envs == ("brax:reacher:spring", "brax:hopper")


@pytest.mark.parametrize(
    ("env_id", "message"),
    [("brax:reacher:warp", "--env: unknown brax backend 'warp'"), ("brax:cartpole", "--env: unknown brax environment")],
)
def test_sweep_command_refuses_bad_brax_ids(tmp_path, capsys, env_id, message):
    needs_brax()
    with pytest.raises(SystemExit) as exit_info:
        train_main(["sweep", "--env", env_id, "--agent", "ppo", "--out", str(tmp_path / "never")])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and message in err and "Traceback" not in err
    assert not (tmp_path / "never").exists()
