"""Tests of the CSTR-v0 environment (`amjax.envs.reactor`).

As gymnax's tests do, the JAX env is checked transition by transition against a slow, obviously-correct reference:
the same ODE in float64, integrated by scipy's Radau (rtol = atol = 1e-9) from the JAX state with the same coolant
temperature held over the step. Compiled functions are cached at module level so each is compiled once.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.integrate import solve_ivp
from scipy.optimize import fsolve

from amjax.envs import registry
from amjax.envs.reactor import ReactorParams, ReactorState, StirredTankReactor

ENV = StirredTankReactor()
PARAMS = ENV.default_params
LEVELS = np.asarray(PARAMS.coolant_levels, np.float64)

# Tolerances against the float64 reference, from the measured errors (substeps = 40, h = 1.25e-3 min) with margin.
# Transitions that stay inside [320, 380] K: RK4's truncation error is < 1e-8 there, what is left is float32
# rounding (T is integrated as a deviation from Tf, so about one ulp(350 K) = 3e-5 K): measured max 2e-5 K on T and
# 5e-7 mol/L on Ca.
T_TOL_INSIDE, CA_TOL_INSIDE = 1e-4, 5e-6  # K, mol/L
# The step on which the reactor ignites (T from 365-380 K to 400-480 K within 0.05 min, k(T) up to ~1e3 /min) is
# stiff for a fixed-step explicit scheme; over the envelope of reachable states (Ca <= 0.6 at T >= 365 K) the
# measured max error is 5e-4 relative on T and 1.2e-3 mol/L on Ca (it falls as substeps^-4: 60 substeps give
# 8e-5 and 2e-4). Such a step terminates the episode either way, with a reward near 0.
T_RTOL_IGNITION, CA_TOL_IGNITION = 1e-3, 2.5e-3


# --- the reference ------------------------------------------------------------------------------------------------
def reference_rhs(t: float, x: np.ndarray, tc: float, p: ReactorParams = PARAMS) -> list[float]:
    ca, temp = x
    rate = p.k0 * np.exp(-p.e_over_r / temp) * ca
    dilution = p.q / p.volume
    return [
        dilution * (p.caf - ca) - rate,
        dilution * (p.tf - temp)
        + p.neg_delta_h / (p.rho * p.cp) * rate
        + p.ua / (p.volume * p.rho * p.cp) * (tc - temp),
    ]


def reference_step(ca: float, temp: float, action: int) -> tuple[float, float, float, bool]:
    """(Ca, T, reward, terminated) after one step of the reference."""
    sol = solve_ivp(
        reference_rhs,
        (0.0, PARAMS.dt),
        [float(ca), float(temp)],
        args=(LEVELS[action],),
        method="Radau",
        rtol=1e-9,
        atol=1e-9,
    )
    ca, temp = sol.y[:, -1]
    reward = 1.0 - min(1.0, abs(ca - PARAMS.ca_setpoint) / 0.2)
    return ca, temp, reward, not (PARAMS.t_low <= temp <= PARAMS.t_high)


def steady_state(guess: tuple[float, float], tc: float = 300.0) -> np.ndarray:
    return fsolve(lambda x: reference_rhs(0.0, x, tc), guess, xtol=1e-12)


def _hand_controller(obs: jax.Array) -> jax.Array:
    """Proportional on T and Ca: Tc = 300 - 12 (T - 350) + 400 (Ca - 0.5), the nearest coolant level."""
    tc = 300.0 - 12.0 * 10.0 * obs[1] + 400.0 * 0.1 * obs[0]
    return jnp.argmin(jnp.abs(PARAMS.coolant_levels - tc))


# --- compiled helpers ---------------------------------------------------------------------------------------------
@functools.cache
def _jitted():
    step_env = jax.jit(ENV.step_env)
    step = jax.jit(ENV.step)

    @functools.partial(jax.jit, static_argnames="num_steps")
    def rollout(key, state, actions, params, num_steps, use_plan=True, t_target=350.0):
        """Transitions of `step_env` (no auto-reset) from `state`: action `actions[t]` where `use_plan[t]`, else the
        hand controller steering T to `t_target`."""

        def body(s, xs):
            k, planned, use = xs
            obs = ENV.get_obs(s.replace(temp=s.temp + 350.0 - t_target), params)
            a = jnp.where(use, planned, _hand_controller(obs))
            _, s2, r, term, _ = ENV.step_env(k, s, a, params)
            return s2, (s.ca, s.temp, s2.ca, s2.temp, r, term, a)

        use_plan = jnp.broadcast_to(use_plan, (num_steps,))
        return jax.lax.scan(body, state, (jax.random.split(key, num_steps), actions, use_plan))[1]

    return step_env, step, rollout


def _state(ca: float, temp: float, time: int = 0) -> ReactorState:
    return ReactorState(ca=jnp.float32(ca), temp=jnp.float32(temp), time=time)


def _sticky_actions(rng: np.random.Generator, n: int, keep: float = 0.8) -> np.ndarray:
    actions = [rng.integers(5)]
    for _ in range(n - 1):
        actions.append(actions[-1] if rng.random() < keep else rng.integers(5))
    return np.asarray(actions, np.int32)


def collect_transitions(seeds=range(8)) -> dict[str, np.ndarray]:
    """Transitions (up to and including the first termination) of episodes from the reset distribution: sticky
    random actions; always the coldest / the hottest coolant; the hand controller with 30% random actions, steering
    T to 350 K (long episodes near the set-point) or to 370 K (the region near 380 K and the runaway from it)."""
    _, _, rollout = _jitted()
    runs = [(_sticky_actions(np.random.default_rng(s), 200), True, 350.0) for s in seeds]
    runs += [(np.zeros(200, np.int32), True, 350.0), (np.full(200, 4, np.int32), True, 350.0)]
    for t_target in (350.0, 370.0):
        for s in seeds:
            rng = np.random.default_rng(100 + s)
            runs.append((rng.integers(0, 5, 200).astype(np.int32), rng.random(200) < 0.3, t_target))
    names = ("ca", "temp", "ca_next", "temp_next", "reward", "term", "action")
    out = {k: [] for k in names}
    for i, (actions, use_plan, t_target) in enumerate(runs):
        key_reset, key_run = jax.random.split(jax.random.key(i))
        _, state = ENV.reset(key_reset, PARAMS)
        cols = jax.device_get(rollout(key_run, state, jnp.asarray(actions), PARAMS, 200, use_plan, t_target))
        term = np.asarray(cols[5])
        n = int(np.argmax(term)) + 1 if term.any() else len(term)
        for name, col in zip(names, cols, strict=True):
            out[name].append(np.asarray(col)[:n])
    return {k: np.concatenate(v) for k, v in out.items()}


def envelope_transitions() -> dict[str, np.ndarray]:
    """One step from a grid over the hot edge of the reachable states (Ca up to 0.6 at 365-380 K; the most seen
    in 4e6 random-policy steps is 0.63 above 360 K, 0.57 above 370 K, 0.54 above 378 K) with the coldest and the
    hottest coolant: the ignition steps, the hardest for the integrator."""
    ca, temp, action = (x.ravel() for x in np.meshgrid([0.4, 0.5, 0.6], np.linspace(365, 380, 16), [0, 4]))
    states = ReactorState(ca=jnp.float32(ca), temp=jnp.float32(temp), time=jnp.zeros(ca.size, jnp.int32))
    step = jax.vmap(ENV.step_env, in_axes=(None, 0, 0, None))
    _, nxt, reward, term, _ = jax.device_get(jax.jit(step)(jax.random.key(0), states, jnp.int32(action), PARAMS))
    return {
        "ca": np.float32(ca),
        "temp": np.float32(temp),
        "action": action,
        "ca_next": nxt.ca,
        "temp_next": nxt.temp,
        "reward": reward,
        "term": term,
    }


# --- tests --------------------------------------------------------------------------------------------------------
def compare_with_reference() -> dict[str, np.ndarray]:
    """The JAX transitions of `collect_transitions` and `envelope_transitions` beside the reference's."""
    parts = [collect_transitions(), envelope_transitions()]
    tr = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    ref = np.array([reference_step(*args) for args in zip(tr["ca"], tr["temp"], tr["action"], strict=True)])
    tr.update(ca_ref=ref[:, 0], temp_ref=ref[:, 1], reward_ref=ref[:, 2], term_ref=ref[:, 3].astype(bool))
    return tr


@pytest.mark.slow
def test_matches_scipy_step_by_step() -> None:
    tr = compare_with_reference()
    # The episodes cover the cold and the runaway terminations and the region near 380 K.
    assert (tr["term"] & (tr["temp_next"] < 320)).sum() >= 3 and (tr["term"] & (tr["temp_next"] > 450)).sum() >= 10
    assert (tr["temp"] > 375).sum() >= 20 and len(tr["temp"]) > 1500
    np.testing.assert_array_equal(tr["term"], tr["term_ref"])
    inside = ~tr["term_ref"]
    np.testing.assert_allclose(tr["temp_next"][inside], tr["temp_ref"][inside], rtol=0, atol=T_TOL_INSIDE)
    np.testing.assert_allclose(tr["ca_next"][inside], tr["ca_ref"][inside], rtol=0, atol=CA_TOL_INSIDE)
    np.testing.assert_allclose(tr["reward"][inside], tr["reward_ref"][inside], rtol=0, atol=CA_TOL_INSIDE / 0.2)
    np.testing.assert_allclose(tr["temp_next"], tr["temp_ref"], rtol=T_RTOL_IGNITION)
    np.testing.assert_allclose(tr["ca_next"], tr["ca_ref"], rtol=0, atol=CA_TOL_IGNITION)
    np.testing.assert_allclose(tr["reward"], tr["reward_ref"], rtol=0, atol=CA_TOL_IGNITION / 0.2)


def test_steady_states() -> None:
    step_env, _, rollout = _jitted()
    key = jax.random.key(0)
    hold = jnp.full(100, 2, jnp.int32)  # Tc = 300 K
    # The nominal low-conversion point (0.877, 324.5) is steady and stable: 5 minutes later it is still there.
    low = steady_state((0.877, 324.5))
    assert np.all(np.abs(low - (0.877, 324.5)) < (1e-3, 0.05)), low
    cols = rollout(key, _state(0.877, 324.5), hold, PARAMS, 100)
    assert abs(float(cols[2][-1]) - low[0]) < 1e-4 and abs(float(cols[3][-1]) - low[1]) < 1e-2
    # The nominal middle point (0.5, 350.0) is steady (one step moves it by < 1e-3 K) ...
    mid = steady_state((0.5, 350.0))
    assert np.all(np.abs(mid - (0.5, 350.0)) < (1e-3, 0.01)), mid
    _, s, *_ = step_env(key, _state(0.5, 350.0), 2, PARAMS)
    assert abs(float(s.temp) - 350.0) < 1e-3 and abs(float(s.ca) - 0.5) < 1e-5
    # ... but unstable: +-0.002 K perturbations grow at the unstable eigenvalue (+2.83 /min; measured between 1 and
    # 2 minutes on their half-difference, which cancels float32's offset of the fixed point), one to runaway, the
    # other to extinction.
    hot, cold = (np.asarray(rollout(key, _state(mid[0], mid[1] + eps), hold, PARAMS, 100)[3]) for eps in (2e-3, -2e-3))
    half_diff = (hot - cold) / 2
    growth = np.log(half_diff[39] / half_diff[19]) / (20 * PARAMS.dt)
    assert 2.7 < growth < 3.0, growth
    assert hot.max() > 380 and cold.min() < 330


def test_reset_distribution_and_spaces() -> None:
    obs, state = jax.jit(jax.vmap(ENV.reset, in_axes=(0, None)))(jax.random.split(jax.random.key(0), 20_000), PARAMS)
    ca, temp = np.asarray(state.ca), np.asarray(state.temp)
    assert ca.min() >= 0.45 and ca.max() <= 0.55 and temp.min() >= 345 and temp.max() <= 355
    assert abs(ca.mean() - 0.5) < 2e-3 and abs(temp.mean() - 350.0) < 0.2
    np.testing.assert_allclose([ca.std(), temp.std()], [0.1 / 12**0.5, 10 / 12**0.5], rtol=0.02)
    assert abs(np.corrcoef(ca, temp)[0, 1]) < 0.03  # independent draws
    assert (np.asarray(state.time) == 0).all() and obs.dtype == jnp.float32 and obs.shape == (20_000, 2)
    np.testing.assert_allclose(np.asarray(obs), np.stack([(ca - 0.5) / 0.1, (temp - 350) / 10], 1), atol=1e-5)
    assert bool(jax.vmap(ENV.observation_space(PARAMS).contains)(obs).all())
    one = jax.tree.map(lambda x: x[0], state)
    assert ENV.state_space(PARAMS).contains(one)
    assert ENV.name == "CSTR-v0" and ENV.num_actions == 5 and ENV.action_space(PARAMS).n == 5
    assert ENV.observation_space(PARAMS).shape == (2,)
    env, params = registry.make_env("CSTR-v0")
    assert isinstance(env, StirredTankReactor) and isinstance(params, ReactorParams)
    with pytest.raises(ValueError, match="substeps"):
        StirredTankReactor(substeps=0)


def test_vmap_over_params_one_program() -> None:
    _, _, rollout = _jitted()
    params = jax.tree.map(lambda *x: jnp.stack(x), PARAMS, PARAMS.replace(tf=345.0))
    actions = jnp.full(40, 2, jnp.int32)
    both = jax.jit(jax.vmap(lambda p: rollout(jax.random.key(0), _state(0.5, 350.0), actions, p, 40)[3]))
    temps = np.asarray(both(params))
    assert temps[0, -1] > temps[1, -1] + 1.0  # the colder feed drifts towards extinction
    np.testing.assert_allclose(
        temps[1], rollout(jax.random.key(0), _state(0.5, 350.0), actions, PARAMS.replace(tf=345.0), 40)[3], atol=1e-4
    )
    both(jax.tree.map(lambda x: x + 1, params))  # other values, same shapes: no new compile
    assert both._cache_size() == 1


@settings(max_examples=60, deadline=None)
@given(ca=st.floats(0.0, 0.7), temp=st.floats(320.0, 380.0), action=st.integers(0, 4), seed=st.integers(0, 2**16))
def test_invariants(ca: float, temp: float, action: int, seed: int) -> None:
    # From any state with Ca <= 0.7 (those reachable from the reset distribution have Ca <= 0.64 above 360 K) and
    # any action: Ca stays in [0, Caf], T finite, the reward in [0, 1], the observation in its box. (Far hotter
    # states, e.g. Ca > 0.78 at T > 365 K, ignite too fast for the fixed-step integrator: see the module docstring.)
    step_env, step, _ = _jitted()
    obs, s, reward, terminated, _ = step_env(jax.random.key(seed), _state(ca, temp), action, PARAMS)
    assert 0.0 <= float(s.ca) <= PARAMS.caf and np.isfinite(float(s.temp))
    assert 0.0 <= float(reward) <= 1.0 and np.all(np.abs(np.asarray(obs)) <= 5.0)
    assert bool(terminated) == (not 320.0 <= float(s.temp) <= 380.0) and int(s.time) == 1
    obs, s, reward, terminated, truncated, info = step(jax.random.key(seed), _state(ca, temp, 5), action, PARAMS)
    assert ENV.state_space(PARAMS).contains(s) and not bool(truncated)  # auto-reset keeps the state valid
    assert int(s.time) == (0 if bool(terminated) else 6)


def test_termination_and_truncation() -> None:
    _, step, _ = _jitted()
    key = jax.random.key(0)
    # Runaway: from 379.9 K with the hottest coolant the reactor leaves [320, 380] K; gymnax auto-resets.
    obs, s, reward, terminated, truncated, info = step(key, _state(0.4, 379.9, 17), 4, PARAMS)
    assert bool(terminated) and not bool(truncated) and float(info["final_observation"][1]) > 3.0
    assert int(s.time) == 0 and 345 <= float(s.temp) <= 355 and float(reward) >= 0.0
    # Extinction: from 320.1 K with the coldest coolant.
    obs, s, reward, terminated, truncated, info = step(key, _state(0.9, 320.1, 17), 0, PARAMS)
    assert bool(terminated) and float(info["final_observation"][1]) < -3.0 and int(s.time) == 0
    # Truncation: the stable cold state never terminates; the 200th step truncates (and resets), not the 199th.
    obs, s, _, terminated, truncated, _ = step(key, _state(0.877, 324.5, 198), 2, PARAMS)
    assert not bool(terminated) and not bool(truncated) and int(s.time) == 199
    obs, s, _, terminated, truncated, info = step(key, s, 2, PARAMS)
    assert not bool(terminated) and bool(truncated) and int(s.time) == 0 and float(info["final_observation"][1]) < -2


def test_hand_controller_holds_the_unstable_point_and_open_loop_does_not() -> None:
    def episode(key, closed_loop):
        key_reset, key_run = jax.random.split(key)
        obs, state = ENV.reset(key_reset, PARAMS)

        def body(carry, k):
            obs, state, done, ret, term = carry
            action = jnp.where(closed_loop, _hand_controller(obs), 2)
            obs, state, reward, terminated, truncated, _ = ENV.step(k, state, action, PARAMS)
            return (obs, state, done | terminated | truncated, ret + ~done * reward, term | (~done & terminated)), None

        carry = (obs, state, jnp.bool_(False), jnp.float32(0.0), jnp.bool_(False))
        return jax.lax.scan(body, carry, jax.random.split(key_run, 200))[0][3:]

    run = jax.jit(jax.vmap(episode, in_axes=(0, None)))
    keys = jax.random.split(jax.random.key(0), 100)
    returns, terminated = map(np.asarray, run(keys, True))
    assert returns.mean() > 190 and not terminated.any()
    returns, terminated = map(np.asarray, run(keys, False))
    assert returns.mean() < 50 and terminated.mean() > 0.3
