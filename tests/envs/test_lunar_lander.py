"""Tests of the pure-JAX LunarLander-v3 against Gymnasium's Box2D original.

T1 (exact game logic) and T2 (free-flight replay on Gymnasium's recorded draws) need
``box2d==2.3.10`` and are skipped without it. The statistical check (T3, heuristic controller,
1000 episodes per env) is too slow for the suite: run ``experiments/lunar_lander_stats.py``.
Compiled functions are cached at module level so each is compiled once.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from amjax.envs import lunar_lander as ll
from amjax.envs.lunar_lander import EnvParams, LunarLander, reference
from amjax.envs.lunar_lander import constants as llc


def _gymnasium():
    pytest.importorskip("Box2D")
    return reference.load_gymnasium_lunar_lander()


def _recorded_env(module, seed: int, continuous: bool = False):
    env = module.LunarLander(continuous=continuous)
    recorder = reference.DrawRecorder(np.random.default_rng(seed))
    env.np_random = recorder
    return env, recorder


def _reset(heights, init_force, params):
    # The module's own jitted reset/step, called as `reference.free_flight_replay` calls them, so the tests and the
    # replay share one compiled program each (each compile of the solver takes ~10 s of CPU).
    return reference.replay_reset(heights, init_force, params, velocity_iterations=ll.VELOCITY_ITERATIONS)


def _step(state, action, dispersion, params):
    return reference.replay_step(state, action, dispersion, params, False, ll.VELOCITY_ITERATIONS)


@functools.cache
def _jitted():
    return {
        "reset": _reset,
        "step": _step,
        "reward": jax.jit(ll.reward_and_termination),
        "decode": jax.jit(ll.decode_action, static_argnames="continuous"),
        "policy": jax.jit(ll.heuristic_action),
    }


# --- T1: exact game logic ----------------------------------------------------------------------
def test_terrain_matches_gymnasium() -> None:
    module = _gymnasium()
    for seed in range(5):
        env, rec = _recorded_env(module, seed)
        env.reset()
        edges = np.array([[tuple(v) for v in f.shape.vertices] for f in env.moon.fixtures[1:]])
        terrain = np.asarray(ll.terrain_from_heights(rec.draws[0]))
        np.testing.assert_allclose(edges[:, 0, 1], terrain[:-1], atol=1e-6)
        np.testing.assert_allclose(edges[:, 1, 1], terrain[1:], atol=1e-6)
        np.testing.assert_allclose(edges[:, 0, 0], ll.chunk_x()[:-1], atol=1e-6)
        assert (env.helipad_x1, env.helipad_x2, env.helipad_y) == (8.0, 12.0, ll.HELIPAD_Y)


def test_reset_observation_matches_gymnasium() -> None:
    """Reset step (initial push, leg snap by the joint position solver) to float32 rounding."""
    module = _gymnasium()
    for seed in range(5):
        env, rec = _recorded_env(module, seed)
        obs_g, _ = env.reset()
        obs_j, state = _jitted()["reset"](rec.draws[0], np.concatenate(rec.draws[1:3]), EnvParams())
        np.testing.assert_allclose(np.asarray(obs_j), obs_g, atol=1e-6)
        legs = np.array([[*leg.position, leg.angle] for leg in env.legs])
        origins = np.asarray(ll.body_origins(state.pos, state.angle))[1:]
        np.testing.assert_allclose(origins, legs[:, :2], atol=1e-4)
        np.testing.assert_allclose(np.asarray(state.angle)[1:], legs[:, 2], atol=1e-4)
        assert float(state.prev_shaping) == pytest.approx(env.prev_shaping, abs=1e-4)


def _gymnasium_transitions(module, n_random: int = 4, n_heuristic: int = 4):
    """(obs, prev_shaping, m_power, s_power, game_over, awake, reward, terminated) rows."""
    rows = []
    for seed in range(n_random + n_heuristic):
        env = module.LunarLander()
        obs, _ = env.reset(seed=seed)
        rng = np.random.default_rng(seed)
        for _ in range(1000):
            action = int(rng.integers(4)) if seed < n_random else module.heuristic(env, obs)
            prev = env.prev_shaping
            obs, reward, terminated, _, _ = env.step(action)
            m_power, s_power = float(action == 2), float(action in (1, 3))
            rows.append((obs, prev, m_power, s_power, env.game_over, env.lander.awake, reward, terminated))
            if terminated:
                break
    return rows


def test_reward_and_termination_match_gymnasium() -> None:
    """Shaping, fuel, crash (-100, incl. out of bounds) and sleep (+100) on Gymnasium's data."""
    rows = _gymnasium_transitions(_gymnasium())
    cols = [np.array(c) for c in zip(*rows, strict=True)]
    reward, terminated, _ = jax.vmap(_jitted()["reward"])(
        jnp.asarray(cols[0]),
        jnp.asarray(cols[1], jnp.float32),
        jnp.asarray(cols[2], jnp.float32),
        jnp.asarray(cols[3], jnp.float32),
        jnp.asarray(cols[4]),
        jnp.asarray(cols[5]),
    )
    np.testing.assert_allclose(np.asarray(reward), cols[6], atol=1e-3)
    np.testing.assert_array_equal(np.asarray(terminated), cols[7])
    finals = cols[6][cols[7]]
    assert set(np.round(finals)) == {-100.0, 100.0}, "need both crash and landing endings"


def test_action_decoding_matches_gymnasium() -> None:
    """m_power/s_power read back from Gymnasium's fuel penalty, discrete and continuous."""
    module = _gymnasium()

    def fuel(env, action) -> float:
        env.reset(seed=0)
        prev = env.prev_shaping
        obs, reward, *_ = env.step(action)
        shaping = float(ll.shaping(jnp.asarray(obs)))
        return shaping - prev - reward

    discrete = module.LunarLander()
    for action in range(4):
        m, s, direction = map(float, _jitted()["decode"](jnp.int32(action), continuous=False))
        assert fuel(discrete, action) == pytest.approx(0.3 * m + 0.03 * s, abs=1e-4)
        assert direction == {1: -1.0, 3: 1.0}.get(action, 0.0)
    continuous = module.LunarLander(continuous=True)
    for v in (-1.5, -1.0, -0.5, -0.2, 0.0, 1e-3, 0.3, 0.5, 0.51, 0.9, 1.0, 1.7):
        m, _, _ = map(float, _jitted()["decode"](jnp.array([v, 0.0]), continuous=True))
        assert fuel(continuous, np.array([v, 0.0])) == pytest.approx(0.3 * m, abs=1e-4)
        _, s, direction = map(float, _jitted()["decode"](jnp.array([-1.0, v]), continuous=True))
        assert fuel(continuous, np.array([-1.0, v])) == pytest.approx(0.03 * s, abs=1e-4)
        assert direction == (np.sign(v) if abs(v) > 0.5 else 0.0)


# --- T2: free flight on Gymnasium's recorded draws -------------------------------------------------
@pytest.mark.slow
def test_free_flight_replay_matches_gymnasium() -> None:
    """Random actions until Gymnasium's first ground contact: |obs diff| <= 1e-3 (measured
    ~5e-6: the joints are ported), per-step |reward diff| <= 1e-2. 200 seeds: the benchmark."""
    _gymnasium()
    n_steps = 0
    for seed in range(20):
        out = reference.free_flight_replay(seed)
        assert out["obs_diff"].max() <= 1e-3, seed
        assert out["reward_diff"].max(initial=0.0) <= 1e-2, seed
        n_steps += len(out["reward_diff"])
    assert n_steps > 20 * 40


# --- landing and sleep in the port ------------------------------------------------------------------
def test_heuristic_lands_and_sleeps() -> None:
    """Resting on the legs satisfies Box2D's 25-step sleep rule: +100 and termination."""
    params, fns = EnvParams(), _jitted()
    step = fns["step"]
    key = jax.random.PRNGKey(3)
    ends = []
    for episode in range(3):
        key, k_h, k_f = jax.random.split(key, 3)
        heights = jax.random.uniform(k_h, (12,), maxval=ll.H / 2)
        obs, state = fns["reset"](heights, jax.random.uniform(k_f, (2,), minval=-1e3, maxval=1e3), params)
        for _ in range(1000):
            key, k = jax.random.split(key)
            dispersion = jax.random.uniform(k, (2,), minval=-1.0, maxval=1.0)
            obs, state, reward, terminated, info = step(state, fns["policy"](obs), dispersion, params)
            if terminated:
                ends.append((float(reward), bool(info["landed"]), bool(obs[6] and obs[7])))
                break
        assert len(ends) == episode + 1, "episode did not terminate in 1000 steps"
    # The heuristic also crashes sometimes (Gymnasium ~5%, port ~7.5%): require landings.
    assert sum(end[:2] == (100.0, True) for end in ends) >= 2, ends


# --- API, jit and vmap ----------------------------------------------------------------------------
def test_spaces_and_metadata() -> None:
    env = LunarLander()
    assert env.name == "LunarLander-v3"
    assert env.num_actions == 4
    assert env.action_space(env.default_params).n == 4
    obs_space = env.observation_space(env.default_params)
    assert obs_space.shape == (8,)
    np.testing.assert_allclose(np.asarray(obs_space.low), ll.OBS_LOW)
    cont = LunarLander(continuous=True)
    assert cont.action_space(cont.default_params).shape == (2,)
    assert env.default_params.max_steps_in_episode == 1000


@pytest.mark.slow
def test_vmap_256_envs_300_steps_finite() -> None:
    """env.step (gymnax auto-reset) vmapped over 256 envs and over params (gravity, wind).

    Uses 30 solver velocity iterations instead of Box2D's 180 to fit the CPU budget: the code
    paths are the same, only the iteration count of the loop differs."""
    env = LunarLander(velocity_iterations=30)
    n = 256
    gravity = jnp.linspace(-11.5, -2.0, n)
    params = EnvParams(
        gravity=gravity,
        enable_wind=jnp.arange(n) % 2 == 0,
        wind_power=jnp.full(n, 15.0),
        turbulence_power=jnp.full(n, 1.5),
        max_steps_in_episode=jnp.full(n, 1000),
    )

    @jax.jit
    def rollout(key):
        obs, state = jax.vmap(env.reset)(jax.random.split(key, n), params)

        def body(carry, k):
            state, finite = carry
            ks = jax.random.split(k, n + 1)
            action = jax.random.randint(ks[0], (n,), 0, 4)
            obs, state, reward, term, trunc, _ = jax.vmap(env.step)(ks[1:], state, action, params)
            finite = finite & jnp.isfinite(obs).all() & jnp.isfinite(reward).all()
            return (state, finite), term | trunc

        (state, finite), done = jax.lax.scan(body, (state, jnp.bool_(True)), jax.random.split(key, 300))
        return obs, finite, done

    obs, finite, done = rollout(jax.random.PRNGKey(0))
    assert obs.shape == (n, 8) and obs.dtype == jnp.float32
    assert bool(finite)
    assert int(done.sum()) > n  # random play ends episodes (mostly crashes); auto-reset continues


def _short_episodes_rollout(step, env: LunarLander, n: int):
    """A 40-step rollout of `n` envs from the reset under random actions, stepped by `step` (vmapped and jitted,
    called from Python: a scan of so few envs would compile into one kernel under amjax's small-loop option, about
    3x longer), episodes cut at 15 steps so that every reset happens in free flight (no chaotic contacts); returns
    (obs, reward, done) per step."""
    params = env.default_params.replace(max_steps_in_episode=15)
    vmapped_step = jax.jit(jax.vmap(step, (0, 0, 0, None)))

    def rollout(key):
        _, state = jax.vmap(env.reset, (0, None))(jax.random.split(key, n), params)
        steps = []
        for step_key in jax.random.split(key, 40):
            keys = jax.random.split(step_key, n)
            action = jax.random.randint(step_key, (n,), 0, 4)
            obs, state, reward, term, trunc, _ = vmapped_step(keys, state, action, params)
            steps.append((obs, reward, term | trunc))
        return jax.tree.map(lambda *x: np.stack(x), *jax.device_get(steps))

    return rollout


@pytest.mark.slow
def test_auto_reset_matches_gymnax_select_both() -> None:
    """`LunarLander.step` resets a vmapped batch only on steps where some env is done; gymnax computes a reset
    every step and selects. Same keys, same results (to XLA's rounding: the two are different programs)."""
    from gymnax.environments import environment

    env = LunarLander(velocity_iterations=4)  # a short solver; the auto-reset logic is the same
    n, key = 8, jax.random.PRNGKey(4)
    obs, reward, done = _short_episodes_rollout(env.step, env, n)(key)
    gymnax_step = lambda *a: environment.Environment.step.__wrapped__(env, *a)  # noqa: E731
    ref_obs, ref_reward, ref_done = _short_episodes_rollout(gymnax_step, env, n)(key)
    assert done.sum() >= 2 * n and (done == ref_done).all()
    np.testing.assert_allclose(obs, ref_obs, atol=1e-5)
    np.testing.assert_allclose(reward, ref_reward, atol=1e-3)


@pytest.mark.slow
def test_large_batch_steps_in_groups(monkeypatch) -> None:
    """A vmapped batch of more than `STEP_GROUP` envs steps in groups (`in_groups`); each env's results are the
    same as with the whole batch at once (to XLA's rounding), auto-resets included."""
    from amjax.envs.lunar_lander import env as env_module

    env = LunarLander(velocity_iterations=4)  # a short solver; the grouping is the same
    # Three groups of the real size: with small groups XLA compiles the group loop as one kernel (3x longer).
    n, key = 3 * env_module.STEP_GROUP, jax.random.PRNGKey(5)

    def run(group):
        monkeypatch.setattr(env_module, "STEP_GROUP", group)  # read when `step` is traced
        _, state = jax.vmap(env.reset, (0, None))(jax.random.split(key, n), env.default_params)
        step_args = (jax.random.split(key, n), state, jnp.zeros(n, jnp.int32), env.default_params)
        step_jaxpr = str(jax.make_jaxpr(jax.vmap(env.step, (0, 0, 0, None)))(*step_args))
        return _short_episodes_rollout(env.step, env, n)(key), step_jaxpr

    (obs, reward, done), grouped_jaxpr = run(env_module.STEP_GROUP)
    (ref_obs, ref_reward, ref_done), whole_jaxpr = run(n)
    assert grouped_jaxpr.count("scan[") > whole_jaxpr.count("scan[")  # the groups are a loop: grouping took effect
    assert done.sum() >= 2 * n and (done == ref_done).all()
    np.testing.assert_allclose(obs, ref_obs, atol=1e-5)
    np.testing.assert_allclose(reward, ref_reward, atol=1e-3)


@pytest.mark.slow
def test_gpu_layout_steps_as_the_cpu_layout(monkeypatch) -> None:
    """`amjax.strategy`'s GPU layout of the step (the batch at once instead of in `STEP_GROUP` groups, the solves
    unmaterialised instead of behind conditionals) gives what the CPU layout gives, step by step from states spread
    over episodes (contacts and auto-resets included), to XLA's rounding."""
    from amjax import strategy
    from amjax.envs.lunar_lander import env as env_module

    monkeypatch.setattr(env_module, "STEP_GROUP", 64)  # read when `step` is traced: the CPU layout steps in groups
    lander = LunarLander(velocity_iterations=4)  # a short solver; the layouts are the same
    params = lander.default_params
    n, steps = 16, 100

    @jax.jit
    def collect(key):
        _, state = jax.vmap(lander.reset, (0, None))(jax.random.split(key, n), params)

        def body(state, key):
            keys = jax.random.split(key, n + 1)
            actions = jax.random.randint(keys[0], (n,), 0, 4)
            new_state = jax.vmap(lander.step, (0, 0, 0, None))(keys[1:], state, actions, params)[1]
            return new_state, (state, keys[1:], actions)

        return jax.lax.scan(body, state, jax.random.split(key, steps))[1]

    with strategy.use("cpu"):
        states, keys, actions = jax.tree.map(lambda x: x.reshape(steps * n, *x.shape[2:]), collect(jax.random.key(8)))
    assert int(jnp.any(states.touching[:, 1:], axis=(1, 2)).sum()) > 0 and int(jnp.sum(states.time == 0)) > n

    def step_all(name):
        def step(keys, states, actions):  # a new function per layout: JAX caches a traced function's program
            with strategy.use(name):
                return jax.vmap(lander.step, (0, 0, 0, None))(keys, states, actions, params)

        return jax.jit(step)(keys, states, actions), str(jax.make_jaxpr(step)(keys, states, actions))

    (obs, state, reward, terminated, truncated, _), gpu_jaxpr = step_all("gpu")
    (ref_obs, ref_state, ref_reward, ref_terminated, ref_truncated, _), cpu_jaxpr = step_all("cpu")
    assert gpu_jaxpr.count("cond[") < cpu_jaxpr.count("cond[")  # the solves' conditionals are gone
    assert (terminated == ref_terminated).all() and (truncated == ref_truncated).all()
    np.testing.assert_allclose(obs, ref_obs, atol=1e-4)
    np.testing.assert_allclose(reward, ref_reward, atol=1e-3)
    np.testing.assert_allclose(state.pos, ref_state.pos, atol=1e-4)


# --- parameter validation -------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("gravity", 0.0),
        ("gravity", -12.0),
        ("gravity", 3.0),
        ("gravity", float("nan")),
        ("wind_power", -0.1),
        ("wind_power", 20.5),
        ("turbulence_power", -1.0),
        ("turbulence_power", 2.01),
    ],
)
def test_validate_params_rejects_out_of_range(field: str, value: float) -> None:
    params = EnvParams().replace(**{field: value})
    with pytest.raises(ValueError, match=field):
        ll.validate_params(params)


def test_validate_params_accepts_valid_and_batched() -> None:
    ll.validate_params(EnvParams())
    ll.validate_params(EnvParams(gravity=-11.99, wind_power=20.0, turbulence_power=0.0))
    ll.validate_params(EnvParams(gravity=jnp.array([-1.0, -10.0])))
    with pytest.raises(ValueError, match="gravity"):
        ll.validate_params(EnvParams(gravity=jnp.array([-1.0, -13.0])))


# --- exact_free_flight: the joints' fixed point, and the compacted sweeps under vmap ------------


def _free_flight_states(seed: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Body angles (n, 3) with the legs around their limits (lower, inside, upper), so every limit state and motor
    mode occurs, and body velocities (n, 3, 3)."""
    rng = np.random.default_rng(seed)
    hull = rng.normal(size=n) * 0.3
    offsets = rng.uniform(-0.08, 0.08, (2, n)) + np.where(rng.random((2, n)) < 0.5, 0.0, 0.25)
    angles = np.stack(
        [
            hull,
            hull + llc.JOINT_REFERENCE[0] + llc.JOINT_LOWER[0] + offsets[0],
            hull + llc.JOINT_REFERENCE[1] + llc.JOINT_UPPER[1] - offsets[1],
        ],
        1,
    ).astype(np.float32)
    return angles, rng.normal(size=(n, 3, 3)).astype(np.float32)


def _joints_at(a: jax.Array, v: jax.Array) -> tuple[list, list, tuple]:
    """Limit states, the joints' constraints and the bodies' (vx, vy, w) of one state of `_free_flight_states`."""
    from amjax.envs.lunar_lander.joints import joint_constraint

    limit = [
        jnp.where(
            a[k + 1] - a[0] - llc.JOINT_REFERENCE[k] <= llc.JOINT_LOWER[k],
            llc.LIMIT_AT_LOWER,
            jnp.where(
                a[k + 1] - a[0] - llc.JOINT_REFERENCE[k] >= llc.JOINT_UPPER[k], llc.LIMIT_AT_UPPER, llc.LIMIT_INACTIVE
            ),
        )
        for k in range(2)
    ]
    joints = [joint_constraint(a[0], a[k + 1], k, limit[k]) for k in range(2)]
    return limit, joints, tuple((v[b, 0], v[b, 1], v[b, 2]) for b in range(3))


def test_exact_joint_solve_is_the_sweeps_fixed_point() -> None:
    """`solve_joints_exact` equals Box2D's joint sweeps run to convergence, for every limit state and motor mode."""
    from amjax.envs.lunar_lander.joints import joint_velocity, solve_joints_exact

    angles, velocities = _free_flight_states(0, 96)

    def solve(a, v, sweeps):
        limit, joints, bodies = _joints_at(a, v)
        zero = jnp.float32(0.0)

        def sweep(_, carry):
            bodies, impulses, motors = (list(x) for x in carry)
            for k in llc.JOINT_ORDER:
                bodies[0], bodies[k + 1], impulses[k], motors[k], _ = joint_velocity(
                    bodies[0], bodies[k + 1], joints[k], k, impulses[k], motors[k]
                )
            return tuple(bodies), tuple(impulses), tuple(motors)

        swept = jax.lax.fori_loop(0, sweeps, sweep, (bodies, ((zero,) * 3,) * 2, (zero,) * 2))[0]
        return jnp.stack(limit), jnp.array(solve_joints_exact(bodies, joints)[0]), jnp.array(swept)

    limits, exact, swept = jax.jit(jax.vmap(lambda a, v: solve(a, v, 20_000)))(angles, velocities)
    assert set(np.unique(np.asarray(limits))) == {llc.LIMIT_INACTIVE, llc.LIMIT_AT_LOWER, llc.LIMIT_AT_UPPER}
    np.testing.assert_allclose(np.asarray(exact), np.asarray(swept), atol=2e-4)


@pytest.mark.parametrize("solver", [{}, {"exact_free_flight": True}], ids=["default", "exact_free_flight"])
@pytest.mark.slow
def test_vmapped_equals_one_env_at_a_time(solver) -> None:
    """Under vmap the envs that finished an episode, the envs on the ground and the envs that need more position
    iterations run as compacted batches scattered back: each step of the batch gives what each env's step gives
    alone from the same state, contacts and auto-resets included. (Step by step: the batched and the one-env
    programs round differently in the last bit, which a long rollout can grow past any tolerance at a contact.)"""
    lander = LunarLander(**solver)
    params = lander.default_params
    n, steps = 24, 110

    def one_step(state, key, action):
        obs, state, reward, *_ = lander.step(key, state, action, params)
        return state, (obs, reward)

    @jax.jit
    def batched(key):
        _, state = jax.vmap(lander.reset, (0, None))(jax.random.split(key, n), params)

        def body(state, key):
            keys = jax.random.split(key, n + 1)
            actions = jax.random.randint(keys[0], (n,), 0, 4)
            new_state, (obs, reward) = jax.vmap(one_step)(state, keys[1:], actions)
            return new_state, (state, keys[1:], actions, obs, reward, jnp.any(new_state.touching[1:], axis=-1))

        return jax.lax.scan(body, state, jax.random.split(key, steps))[1]

    before, keys, actions, obs, reward, touching = batched(jax.random.PRNGKey(7))
    flat = jax.tree.map(lambda x: x.reshape(steps * n, *x.shape[2:]), (before, keys, actions))
    _, (obs_one, reward_one) = jax.jit(lambda xs: jax.lax.map(lambda x: one_step(*x), xs))(flat)
    assert 0 < int(jnp.any(touching, axis=0).sum()) < n  # some envs, not all, touched: the compacted paths ran
    assert int(jnp.sum(before.time == 0)) > n  # auto-resets happened after the first step
    np.testing.assert_allclose(np.asarray(obs).reshape(steps * n, -1), np.asarray(obs_one), atol=1e-4)
    np.testing.assert_allclose(np.asarray(reward).reshape(-1), np.asarray(reward_one), atol=1e-3)


def test_free_flight_sweeps_the_joints_alone() -> None:
    """A step without leg contacts sweeps only the joints (`_joints_only_gauss_seidel`), as Box2D's island holds
    only touching contacts: the full sweeps, with the six inactive contact solves in them, give the same result."""
    from amjax.envs.lunar_lander.contacts import contact_constraint
    from amjax.envs.lunar_lander.world import _gauss_seidel, _joints_only_gauss_seidel

    n = 32
    angles, velocities = _free_flight_states(3, n)
    rng = np.random.default_rng(4)
    warm = (rng.normal(size=(n, 2, 4)) * 0.3).astype(np.float32)
    contact_warm = (rng.normal(size=(n, 6, 4)) * 0.3).astype(np.float32)

    def solve(a, v, w, cw):
        limit, joints, bodies = _joints_at(a, v)
        jimp = tuple((w[k, 0], w[k, 1], jnp.where(limit[k] == llc.LIMIT_INACTIVE, 0.0, w[k, 2])) for k in range(2))
        jmot = tuple(jnp.clip(w[k, 3], -llc.JOINT_MAX_IMPULSE, llc.JOINT_MAX_IMPULSE) for k in range(2))
        cons = [
            contact_constraint(
                b,
                jnp.int32(0),
                jnp.bool_(True),
                jnp.array([0.0, 1.0]),
                jnp.zeros(2),
                jnp.zeros((2, 2)),
                (10.0, 5.0),
                a[b],
            )
            for b in llc.CONTACT_BODY_ORDER
            for _ in range(2)
        ]
        bodies_of = [con.pop("b") for con in cons]
        cimp = tuple(tuple(cw[i]) for i in range(len(cons)))
        operands = (bodies, joints, jimp, jmot, cons, cimp)
        full = _gauss_seidel(*operands, bodies=bodies_of, iterations=llc.VELOCITY_ITERATIONS)
        alone = _joints_only_gauss_seidel(llc.VELOCITY_ITERATIONS)(*operands)
        return [jnp.stack(jax.tree.leaves(x)) for x in (full, alone)]

    full, alone = jax.jit(jax.vmap(solve))(angles, velocities, warm, contact_warm)
    assert np.all(np.isfinite(np.asarray(full)))
    scale = np.abs(np.asarray(full)).max()
    np.testing.assert_allclose(np.asarray(alone), np.asarray(full), atol=1e-6 * scale)


def test_jumped_sweeps_equal_the_sweeps() -> None:
    """`jump_sweeps`: the jumps (matrix powers of one sweep's affine map) give what Box2D's 180 sweeps give where
    they cover every sweep; where not, `world_step` sweeps instead."""
    from amjax.envs.lunar_lander.world import JUMP_SEGMENTS, _gauss_seidel, _jumped_sweeps

    n = 64
    angles, velocities = _free_flight_states(1, n)
    warm = (np.random.default_rng(2).normal(size=(n, 2, 4)) * 0.3).astype(np.float32)  # impulses (x, y, limit, motor)

    def solve(a, v, w):
        limit, joints, bodies = _joints_at(a, v)
        jimp = tuple((w[k, 0], w[k, 1], jnp.where(limit[k] == llc.LIMIT_INACTIVE, 0.0, w[k, 2])) for k in range(2))
        jmot = tuple(jnp.clip(w[k, 3], -llc.JOINT_MAX_IMPULSE, llc.JOINT_MAX_IMPULSE) for k in range(2))
        swept = _gauss_seidel(bodies, joints, jimp, jmot, [], (), bodies=[], iterations=llc.VELOCITY_ITERATIONS)
        jumped, agree = _jumped_sweeps(
            bodies, joints, jimp, jmot, iterations=llc.VELOCITY_ITERATIONS, segments=JUMP_SEGMENTS
        )
        flat = [jnp.stack(jax.tree.leaves(x[:3])) for x in (swept, jumped)]
        # A reset's impulses start as constants (unvarying under shard_map).
        zero = (jnp.float32(0),) * 3
        from_rest = _jumped_sweeps(
            bodies, joints, (zero, zero), zero[:2], iterations=llc.VELOCITY_ITERATIONS, segments=JUMP_SEGMENTS
        )[0][0]
        return flat[0], flat[1], agree & jnp.all(jnp.isfinite(jnp.stack(jax.tree.leaves(from_rest))))

    # Inside shard_map with its default check_vma, as a user who splits envs over devices runs it.
    spec = jax.sharding.PartitionSpec("envs")
    mesh = jax.sharding.Mesh(np.array(jax.devices()), ("envs",))
    sharded = jax.shard_map(jax.vmap(solve), mesh=mesh, in_specs=spec, out_specs=spec)
    swept, jumped, agree = jax.jit(sharded)(angles, velocities, warm)
    agree = np.asarray(agree)
    assert agree.mean() > 0.5  # the jump is what runs, for most states
    scale = np.abs(np.asarray(swept)[agree]).max()
    np.testing.assert_allclose(np.asarray(jumped)[agree], np.asarray(swept)[agree], atol=2e-5 * scale)


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"jump_sweeps": 1}, "jump_sweeps"),
        ({"exact_free_flight": "yes"}, "exact_free_flight"),
        ({"velocity_iterations": 0}, "velocity_iterations"),
        ({"exact_free_flight": True, "jump_sweeps": True}, "exact_free_flight and jump_sweeps"),
    ],
)
def test_solver_settings_are_checked(kwargs: dict, name: str) -> None:
    with pytest.raises(ValueError, match=name):
        LunarLander(**kwargs)
