"""The environment registry (`amjax.make_env`, `amjax.make`, `amjax.envs.register`) and, as gymnax's tests do,
amjax's environments against Gymnasium's reference implementations step for step."""

from __future__ import annotations

import functools
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import struct
from gymnax.environments import environment, spaces

import amjax
from amjax.envs import registry

# -- episode lengths -------------------------------------------------------------------------------------------


def balancing_run(env, params, num_steps: int):
    """`num_steps` always-measured steps of a CartPole under a simple balancing controller (jitted scan)."""

    @jax.jit
    def run(params):
        obs, state = env.reset(jax.random.key(0), params)

        def step(carry, key):
            obs, state = carry
            control = (obs[2] + 0.5 * obs[3] > 0).astype(jnp.int32)  # push towards the lean
            obs, state, _, terminated, truncated, info = env.step(key, state, control + 2, params)
            return (obs, state), (terminated, truncated, info["final_observation"])

        keys = jax.random.split(jax.random.key(1), num_steps)
        return jax.lax.scan(step, (obs, state), keys)[1]

    return jax.device_get(run(params))


def episode_lengths(done: np.ndarray) -> list[int]:
    ends = np.flatnonzero(done) + 1
    return list(np.diff(np.concatenate([[0], ends])))


@pytest.mark.parametrize(("env_id", "max_steps"), [("CartPole-v0", 200), ("CartPole-v1", 500)])
def test_cartpole_episodes_are_truncated_at_the_gymnasium_limit(env_id, max_steps):
    env, params = amjax.make(env_id)
    assert params.env_params.max_steps_in_episode == max_steps
    terminated, truncated, _ = balancing_run(env, params, 2 * max_steps + 50)
    lengths = episode_lengths(terminated | truncated)
    assert lengths[:2] == [max_steps, max_steps], "the controller balances until the time limit"
    np.testing.assert_array_equal(np.flatnonzero(truncated), [max_steps - 1, 2 * max_steps - 1])
    assert not terminated.any()


@pytest.mark.parametrize("vanilla", [False, True])
def test_default_params_are_the_registered_ones(vanilla):
    # reset/step without params use `env.default_params`: CartPole-v0's, not gymnax CartPole's 500 steps.
    env, params = amjax.make("CartPole-v0", vanilla=vanilla)
    default = env.default_params if vanilla else env.default_params.env_params
    assert default.max_steps_in_episode == 200
    _, state = env.reset(jax.random.key(0))
    state = state.replace(time=199) if vanilla else state.replace(env_state=state.env_state.replace(time=199))
    _, _, _, terminated, truncated, _ = env.step(jax.random.key(1), state, 0)
    assert bool(truncated) and not bool(terminated)


def test_acrobot_is_registered():
    assert {"CartPole-v0", "CartPole-v1", "Acrobot-v1"} <= set(amjax.registered_envs())
    env, params = amjax.make_env("Acrobot-v1")
    assert env.name == "Acrobot-v1" and params.max_steps_in_episode == 500
    assert env.action_space(params).n == 3 and env.observation_space(params).shape == (6,)
    wrapped, wrapped_params = amjax.make("Acrobot-v1", cost=0.1)
    assert wrapped.action_space(wrapped_params).n == 6
    assert wrapped.observation_space(wrapped_params).shape == (7,)


@pytest.mark.parametrize("make", [amjax.make_env, amjax.make])
def test_unknown_id_names_env_id_and_the_allowed_values(make):
    with pytest.raises(ValueError, match="env_id: unknown environment 'CartPole-v9'; allowed values: ") as error:
        make("CartPole-v9")
    for known in ("CartPole-v0", "CartPole-v1", "Acrobot-v1", "LunarLander-v3", "Pendulum-v1"):
        assert known in str(error.value)


# -- registering a custom environment --------------------------------------------------------------------------


@struct.dataclass
class CorridorState(environment.EnvState):
    position: jax.Array
    time: int


@struct.dataclass
class CorridorParams(environment.EnvParams):
    goal: int = 3
    max_steps_in_episode: int = 10


class Corridor(environment.Environment[CorridorState, CorridorParams]):
    """A minimal gymnax env: walk right (action 1) from 0 to `goal`; -1 per step."""

    @property
    def default_params(self) -> CorridorParams:
        return CorridorParams()

    def step_env(self, key, state, action, params):
        position = state.position + 2 * action - 1
        state = CorridorState(position=position, time=state.time + 1)
        obs = jnp.array([position], jnp.float32)
        return obs, state, jnp.float32(-1.0), position >= params.goal, {}

    def reset_env(self, key, params):
        state = CorridorState(position=jnp.int32(0), time=0)
        return jnp.zeros(1, jnp.float32), state

    def action_space(self, params=None):
        return spaces.Discrete(2)

    def observation_space(self, params):
        return spaces.Box(-10.0, 10.0, (1,), jnp.float32)


@pytest.fixture
def clean_registry(monkeypatch):
    monkeypatch.setattr(registry, "_CUSTOM_ENVS", {})


def test_register_a_custom_gymnax_env(clean_registry):
    amjax.envs.register("Corridor-v0", lambda: (Corridor(), CorridorParams(goal=2)))
    assert "Corridor-v0" in amjax.registered_envs()
    env, params = amjax.make("Corridor-v0", cost=0.5)
    assert params.env_params.goal == 2
    assert env.action_space(params).n == 4

    obs, state = env.reset(jax.random.key(0), params)
    np.testing.assert_array_equal(obs, [0.0, 1.0])
    rewards, flags, ends = [], [], []
    for action in (3, 1, 3):  # right measured, right unmeasured (reaches the goal), right measured
        obs, state, reward, terminated, _, _ = env.step(jax.random.key(1), state, action, params)
        rewards.append(float(reward))
        flags.append(float(obs[-1]))
        ends.append(bool(terminated))
    assert ends == [False, True, False]
    assert rewards == [-1.5, -1.0, -1.5]
    assert flags == [1.0, 1.0, 1.0]  # measured; first obs after the auto-reset; measured
    np.testing.assert_array_equal(obs, [1.0, 1.0])  # one step right of the reset position


def test_register_refuses_an_empty_id(clean_registry):
    with pytest.raises(ValueError, match="env_id"):
        amjax.envs.register("", lambda: (Corridor(), CorridorParams()))


# -- against Gymnasium, step for step --------------------------------------------------------------------------
# Like gymnax's own tests: copy Gymnasium's state into the JAX env, step both with the same controls, compare.


def gymnasium_env(env_id: str, seed: int):
    gym = pytest.importorskip("gymnasium")  # an optional dependency: skip only these tests without it
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # Gymnasium warns that CartPole-v0 is out of date
        reference = gym.make(env_id)
    obs, _ = reference.reset(seed=seed)
    return reference, obs


def cartpole_state(state, s):
    env_state = state.env_state.replace(
        x=jnp.float32(s[0]), x_dot=jnp.float32(s[1]), theta=jnp.float32(s[2]), theta_dot=jnp.float32(s[3])
    )
    return state.replace(env_state=env_state)


def acrobot_state(state, s):
    env_state = state.env_state.replace(
        joint_angle1=jnp.float32(s[0]),
        joint_angle2=jnp.float32(s[1]),
        velocity_1=jnp.float32(s[2]),
        velocity_2=jnp.float32(s[3]),
    )
    return state.replace(env_state=env_state)


@functools.cache
def made(env_id: str):
    return amjax.make(env_id)  # one wrapper object per id: its jitted step compiles once


def compare_with_gymnasium(env_id, seed, policy, set_state, resync: bool) -> int:
    """Step amjax's `env_id` (always measuring) and Gymnasium's side by side until done; returns the length.

    With `resync`, Gymnasium's state is copied in before every step (each transition is compared from the
    same state); without, only after the reset (the whole trajectory must agree).
    """
    env, params = made(env_id)
    reference, gym_obs = gymnasium_env(env_id, seed)
    _, state = env.reset(jax.random.key(seed), params)
    state = set_state(state, reference.unwrapped.state)
    state = state.replace(last_obs=jnp.asarray(gym_obs))
    rng = np.random.default_rng(seed)
    key = jax.random.key(seed)
    for t in range(1000):
        control = policy(gym_obs, rng)
        if resync:
            state = set_state(state, reference.unwrapped.state)
        gym_obs, gym_reward, gym_terminated, gym_truncated, _ = reference.step(control)
        key, step_key = jax.random.split(key)
        obs, state, reward, terminated, truncated, info = env.step(step_key, state, control + env.num_controls, params)
        seen = np.asarray(info["final_observation"])  # pre-reset, with the flag
        np.testing.assert_allclose(seen[:-1], gym_obs, atol=1e-4, rtol=0, err_msg=f"obs at step {t}")
        assert seen[-1] == 1.0 and obs[-1] == 1.0
        assert float(info["raw_reward"]) == gym_reward, f"reward at step {t}"
        assert float(reward) == gym_reward  # cost 0
        assert (bool(terminated), bool(truncated)) == (gym_terminated, gym_truncated), f"done at step {t}"
        if gym_terminated or gym_truncated:
            return t + 1
    raise AssertionError("Gymnasium's episode never ended")


def random_control(num_controls):
    return lambda obs, rng: int(rng.integers(num_controls))


def cartpole_balance(obs, rng):
    return int(obs[2] + 0.5 * obs[3] > 0) if rng.random() > 0.1 else int(rng.integers(2))


def acrobot_pump(obs, rng):
    # Torque with the second joint's velocity: reaches the goal height in about 100 steps.
    return (2 if obs[5] > 0 else 0) if rng.random() > 0.2 else int(rng.integers(3))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_cartpole_v0_matches_gymnasium_over_random_episodes(seed):
    # Random controls topple the pole in tens of steps; over that, float32 (amjax) and float64 (Gymnasium)
    # stay within 1e-4 without re-copying the state.
    length = compare_with_gymnasium("CartPole-v0", seed, random_control(2), cartpole_state, resync=False)
    assert length < 200


def test_cartpole_v0_matches_gymnasium_until_truncation():
    # A balanced pole is an unstable equilibrium: run free for 200 steps, float32 vs float64 round-off grows
    # past 1e-4 (about step 120 here). So Gymnasium's state is copied in before each step, as gymnax's tests do.
    length = compare_with_gymnasium("CartPole-v0", 3, cartpole_balance, cartpole_state, resync=True)
    assert length == 200, "the balancing controller reaches the 200-step truncation"


@pytest.mark.parametrize(
    ("seed", "policy", "expected_length"),
    [(0, random_control(3), 500), (1, acrobot_pump, None), (2, acrobot_pump, None)],
)
def test_acrobot_v1_matches_gymnasium(seed, policy, expected_length):
    # Both integrate one rk4 step of dt = 0.2 and observe (cos, sin, cos, sin, dtheta1, dtheta2), but the double
    # pendulum is chaotic: run free, float32 vs float64 round-off grows to ~1e-2 within ~120 steps of an energetic
    # swing. So, as gymnax's own tests do, Gymnasium's state is copied in before every step and each transition is
    # compared to 1e-4; the trajectory is still Gymnasium's, over whole episodes (time limit and goal both reached).
    length = compare_with_gymnasium("Acrobot-v1", seed, policy, acrobot_state, resync=True)
    if expected_length is None:
        assert length < 500, "the pumping controller reaches the goal (terminated)"
    else:
        assert length == expected_length
