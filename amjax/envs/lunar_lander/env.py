"""Gymnasium's game logic on the Box2D port: actions, engines, wind, observation, reward, and the gymnax env."""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from gymnax.environments import environment, spaces

from amjax.batching import in_groups, select_compacted
from amjax.cores import warn_if_xla_options_late
from amjax.envs.lunar_lander.collide import body_origins, terrain_from_heights
from amjax.envs.lunar_lander.constants import (
    CHUNKS,
    FPS,
    HELIPAD_Y,
    ILLEGAL_KEY,
    INITIAL_RANDOM,
    INV_I,
    INV_MASS,
    LEG_AWAY,
    LEG_DOWN,
    LEG_SIGN,
    LOCAL_CENTER,
    MAIN_ENGINE_POWER,
    MAIN_ENGINE_Y_LOCATION,
    OBS_HIGH,
    OBS_LOW,
    SCALE,
    SIDE_ENGINE_AWAY,
    SIDE_ENGINE_HEIGHT,
    SIDE_ENGINE_POWER,
    VELOCITY_ITERATIONS,
    H,
    W,
)
from amjax.envs.lunar_lander.fusion import vary_together
from amjax.envs.lunar_lander.state import EnvParams, EnvState
from amjax.envs.lunar_lander.world import world_step

# Under vmap, the envs that finished an episode are reset in chunks of this fraction of the envs (random actions end
# about 1% of episodes per step).
RESET_CAPACITY = 1 / 32
# A vmapped `step` over more envs than this runs them in groups of about this many (`amjax.batching.in_groups`): the
# solver's single-kernel loops stream every env's state through memory once per sweep, and past a few hundred envs
# per core that no longer stays in cache (2026-11-27, 2-core AMD EPYC: 2,048 envs per core ran 111 k env-steps/s
# against 195 k at 512; docs/lunar_lander.md). Each env's arithmetic is the same either way.
STEP_GROUP = 512


# --- game logic (Gymnasium LunarLander.step) ------------------------------------------------------
def decode_action(action: jax.Array, continuous: bool) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(m_power, s_power, direction) exactly as Gymnasium decodes discrete/continuous actions."""
    if continuous:
        act = jnp.clip(jnp.asarray(action, jnp.float32), -1.0, 1.0)
        m_power = jnp.where(act[0] > 0, (jnp.clip(act[0], 0.0, 1.0) + 1.0) * 0.5, 0.0)
        side = jnp.abs(act[1]) > 0.5
        s_power = jnp.where(side, jnp.clip(jnp.abs(act[1]), 0.5, 1.0), 0.0)
        direction = jnp.where(side, jnp.sign(act[1]), 0.0)
    else:
        act = jnp.asarray(action, jnp.int32)
        m_power = jnp.where(act == 2, 1.0, 0.0)
        side = (act == 1) | (act == 3)
        s_power = jnp.where(side, 1.0, 0.0)
        direction = jnp.where(side, act - 2, 0).astype(jnp.float32)
    return m_power.astype(jnp.float32), s_power.astype(jnp.float32), direction


def _engine_impulses(state: EnvState, m_power, s_power, direction, dispersion):
    """Apply Gymnasium's main/side engine impulses to the hull (b2Body::ApplyLinearImpulse)."""
    pos = body_origins(state.pos, state.angle)[0]
    ang = state.angle[0]
    tip = jnp.stack([jnp.sin(ang), jnp.cos(ang)])
    side = jnp.stack([-tip[1], tip[0]])
    d = jnp.asarray(dispersion, jnp.float32) / SCALE
    # Main engine.
    off = MAIN_ENGINE_Y_LOCATION / SCALE + 2 * d[0]
    mx = tip[0] * off + side[0] * d[1]
    my = -tip[1] * off - side[1] * d[1]
    main_point = pos + jnp.stack([mx, my])
    main_imp = jnp.stack([-mx, -my]) * MAIN_ENGINE_POWER * m_power
    # Side engines (the 17-vs-SIDE_ENGINE_HEIGHT quirk is Gymnasium's).
    lat = 3 * d[1] + direction * SIDE_ENGINE_AWAY / SCALE
    sx = tip[0] * d[0] + side[0] * lat
    sy = -tip[1] * d[0] - side[1] * lat
    side_point = pos + jnp.stack([sx - tip[0] * 17 / SCALE, sy + tip[1] * SIDE_ENGINE_HEIGHT / SCALE])
    side_imp = jnp.stack([-sx, -sy]) * SIDE_ENGINE_POWER * s_power
    vel, omega = state.vel, state.omega
    for point, imp in ((main_point, main_imp), (side_point, side_imp)):
        r = point - state.pos[0]
        vel = vel.at[0].add(INV_MASS[0] * imp)
        omega = omega.at[0].add(INV_I[0] * (r[0] * imp[1] - r[1] * imp[0]))
    return state.replace(vel=vel, omega=omega)


def observation(state: EnvState) -> jax.Array:
    """Gymnasium's 8-dim observation."""
    pos = body_origins(state.pos, state.angle)[0]
    vel = state.vel[0]
    return jnp.stack(
        [
            (pos[0] - W / 2) / (W / 2),
            (pos[1] - (HELIPAD_Y + LEG_DOWN / SCALE)) / (H / 2),
            vel[0] * (W / 2) / FPS,
            vel[1] * (H / 2) / FPS,
            state.angle[0],
            20.0 * state.omega[0] / FPS,
            state.leg_contact[0].astype(jnp.float32),
            state.leg_contact[1].astype(jnp.float32),
        ]
    ).astype(jnp.float32)


def shaping(obs: jax.Array) -> jax.Array:
    """Gymnasium's potential: distance, speed, tilt and leg-contact terms."""
    return (
        -100 * jnp.sqrt(obs[0] ** 2 + obs[1] ** 2)
        - 100 * jnp.sqrt(obs[2] ** 2 + obs[3] ** 2)
        - 100 * jnp.abs(obs[4])
        + 10 * obs[6]
        + 10 * obs[7]
    )


def reward_and_termination(
    obs: jax.Array, prev_shaping: jax.Array, m_power, s_power, game_over, awake
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(reward, terminated, shaping) with Gymnasium's -100 crash / +100 sleep overrides."""
    shp = shaping(obs)
    reward = shp - prev_shaping - m_power * 0.30 - s_power * 0.03
    crashed = game_over | (jnp.abs(obs[0]) >= 1.0)
    reward = jnp.where(crashed, -100.0, reward)
    reward = jnp.where(~awake, 100.0, reward)
    return reward.astype(jnp.float32), crashed | ~awake, shp


def _wind(state: EnvState, params: EnvParams):
    on = jnp.asarray(params.enable_wind) & ~(state.leg_contact[0] | state.leg_contact[1])

    def mag(idx):
        idx = idx.astype(jnp.float32)
        return jnp.tanh(jnp.sin(0.02 * idx) + jnp.sin(np.float32(math.pi * 0.01) * idx))

    force = jnp.where(on, mag(state.wind_idx) * params.wind_power, 0.0)
    torque = jnp.where(on, mag(state.torque_idx) * params.turbulence_power, 0.0)
    state = state.replace(wind_idx=state.wind_idx + on, torque_idx=state.torque_idx + on)
    return state, force, torque


def _physics_step(
    state,
    m_power,
    s_power,
    direction,
    dispersion,
    extra_force,
    params,
    contacts=True,
    velocity_iterations=VELOCITY_ITERATIONS,
    exact_free_flight=False,
    jump_sweeps=False,
):
    state, wind_f, wind_t = _wind(state, params)
    state = _engine_impulses(state, m_power, s_power, direction, dispersion)
    force = jnp.zeros((3, 2), jnp.float32).at[0].set(extra_force + jnp.stack([wind_f, 0.0]))
    torque = jnp.zeros(3, jnp.float32).at[0].set(wind_t)
    gravity = jnp.asarray(params.gravity, jnp.float32)
    return world_step(state, force, torque, gravity, contacts, velocity_iterations, exact_free_flight, jump_sweeps)


def initial_state(heights: jax.Array, wind_offsets: jax.Array | None = None) -> EnvState:
    """World right after Gymnasium's reset() built it (before the reset step)."""
    x0, y0 = np.float32(W / 2), np.float32(H)
    origins = np.array([[x0, y0]] + [[W / 2 - i * LEG_AWAY / SCALE, H] for i in LEG_SIGN], np.float32)
    angle = np.array([0.0] + [i * 0.05 for i in LEG_SIGN], np.float32)
    wind = jnp.zeros(2, jnp.int32) if wind_offsets is None else jnp.asarray(wind_offsets, jnp.int32)
    return EnvState(
        pos=jnp.asarray(origins + LOCAL_CENTER),
        angle=jnp.asarray(angle),
        vel=jnp.zeros((3, 2), jnp.float32),
        omega=jnp.zeros(3, jnp.float32),
        joint_impulse=jnp.zeros((2, 3), jnp.float32),
        motor_impulse=jnp.zeros(2, jnp.float32),
        limit_state=jnp.zeros(2, jnp.int32),
        sleep_time=jnp.zeros(3, jnp.float32),
        contact_edge=jnp.full((3, 2), -1, jnp.int32),
        touching=jnp.zeros((3, 2), bool),
        contact_key=jnp.full((3, 2, 2), ILLEGAL_KEY, jnp.int32),
        normal_impulse=jnp.zeros((3, 2, 2), jnp.float32),
        tangent_impulse=jnp.zeros((3, 2, 2), jnp.float32),
        leg_contact=jnp.zeros(2, bool),
        game_over=jnp.bool_(False),
        awake=jnp.bool_(True),
        terrain_y=terrain_from_heights(heights),
        prev_shaping=jnp.float32(0.0),
        wind_idx=wind[0],
        torque_idx=wind[1],
        time=0,
    )


def reset_from_draws(
    heights: jax.Array,
    init_force: jax.Array,
    params: EnvParams,
    wind_offsets: jax.Array | None = None,
    velocity_iterations: int = VELOCITY_ITERATIONS,
    exact_free_flight: bool = False,
    jump_sweeps: bool = False,
) -> tuple[jax.Array, EnvState]:
    """Gymnasium's reset given its draws: 12 heights ~U(0, H/2), force ~U(+-1000)^2, and (wind
    only) two integers in [-9999, 9999). Runs the reset step (nop action) like Gymnasium."""
    state = initial_state(heights, wind_offsets)
    zero = jnp.float32(0.0)
    state = _physics_step(
        state,
        zero,
        zero,
        zero,
        jnp.zeros(2, jnp.float32),
        jnp.asarray(init_force, jnp.float32),
        params,
        contacts=False,
        velocity_iterations=velocity_iterations,
        exact_free_flight=exact_free_flight,
        jump_sweeps=jump_sweeps,
    )
    obs = observation(state)
    # Fields that start as constants vary with the draws, as shard_map's check_vma expects of loop carries.
    return obs, vary_together(state.replace(prev_shaping=shaping(obs), time=0))


def step_from_draws(
    state: EnvState,
    action: jax.Array,
    dispersion: jax.Array,
    params: EnvParams,
    continuous: bool = False,
    velocity_iterations: int = VELOCITY_ITERATIONS,
    exact_free_flight: bool = False,
    jump_sweeps: bool = False,
) -> tuple[jax.Array, EnvState, jax.Array, jax.Array, dict[str, jax.Array]]:
    """Gymnasium's step given the two per-step U(-1, 1) dispersion draws."""
    m_power, s_power, direction = decode_action(action, continuous)
    state = _physics_step(
        state,
        m_power,
        s_power,
        direction,
        dispersion,
        jnp.zeros(2, jnp.float32),
        params,
        velocity_iterations=velocity_iterations,
        exact_free_flight=exact_free_flight,
        jump_sweeps=jump_sweeps,
    )
    obs = observation(state)
    reward, terminated, shp = reward_and_termination(
        obs, state.prev_shaping, m_power, s_power, state.game_over, state.awake
    )
    state = state.replace(prev_shaping=shp, time=state.time + 1)
    info = {"landed": ~state.awake, "crashed": terminated & state.awake}
    return obs, state, reward, terminated, info


class LunarLander(environment.Environment[EnvState, EnvParams]):
    """LunarLander-v3 (discrete, or continuous with ``continuous=True``) in pure JAX.

    Solver settings (static), see docs/lunar_lander.md:

    - ``velocity_iterations``: Box2D's Gauss-Seidel sweeps per step, 180 as Gymnasium calls it (fewer run faster and
      deviate from Box2D);
    - ``jump_sweeps`` (default ``False``): a step without leg contacts computes the sweeps' result in jumps (the
      sweeps that share a clamp pattern are one affine map, taken as its matrix power), checked, and swept as Box2D
      does where two jumps do not cover them; steps with a leg on the ground sweep, gathered into a smaller batch
      under vmap. Agrees with Box2D as closely as the sweeps do; about 2x faster than the default for one env
      inside ``lax.scan``, 1.2x at 4,096 envs, no faster at 1,024 (steady state), slower to compile;
    - ``exact_free_flight`` (default ``False``): a step without leg contacts takes the fixed point the sweeps
      converge to instead, which Box2D's 180 sweeps do not reach (drifts from Gymnasium by ~1e-2). Not with
      ``jump_sweeps``: the two replace the same sweeps.

    With both off (the default) every step of every env sweeps, literally as Box2D does (a step without leg
    contacts sweeps the joints alone, as Box2D's island holds only touching contacts).
    """

    def __init__(
        self,
        continuous: bool = False,
        velocity_iterations: int = VELOCITY_ITERATIONS,
        exact_free_flight: bool = False,
        jump_sweeps: bool = False,
    ):
        super().__init__()
        if isinstance(velocity_iterations, bool) or int(velocity_iterations) < 1:
            raise ValueError(f"velocity_iterations must be an int >= 1, got {velocity_iterations!r}")
        for name, value in (("exact_free_flight", exact_free_flight), ("jump_sweeps", jump_sweeps)):
            if not isinstance(value, bool):
                raise ValueError(f"{name} must be True or False, got {value!r}")
        if exact_free_flight and jump_sweeps:
            raise ValueError("exact_free_flight and jump_sweeps: choose one (both replace the free-flight sweeps)")
        warn_if_xla_options_late("LunarLander")
        self.continuous = bool(continuous)
        self.velocity_iterations = int(velocity_iterations)
        self.exact_free_flight = exact_free_flight
        self.jump_sweeps = jump_sweeps
        self.obs_shape = (8,)

    @property
    def default_params(self) -> EnvParams:
        return EnvParams()

    @property
    def name(self) -> str:
        return "LunarLander-v3"

    @property
    def num_actions(self) -> int:
        return 2 if self.continuous else 4

    def step(
        self,
        key: jax.Array,
        state: EnvState,
        action: int | float | jax.Array,
        params: EnvParams | None = None,
    ) -> tuple[jax.Array, EnvState, jax.Array, jax.Array, jax.Array, dict[Any, Any]]:
        """gymnax's ``Environment.step`` (same keys, same outputs) with a cheaper auto-reset.

        gymnax computes a reset (terrain and Gymnasium's reset physics step) on every step and selects it where
        an episode ended; here a vmapped batch computes resets only for the members that are done, gathered in
        chunks of ``RESET_CAPACITY`` of the envs (``select_compacted``). A batch of more than ``STEP_GROUP`` envs
        steps in groups of about that many.
        """
        params = self.default_params if params is None else params
        return in_groups(self._step_auto_reset, STEP_GROUP, keep_unbatched=True)(key, state, action, params)

    def _step_auto_reset(
        self, key: jax.Array, state: EnvState, action: int | float | jax.Array, params: EnvParams
    ) -> tuple[jax.Array, EnvState, jax.Array, jax.Array, jax.Array, dict[Any, Any]]:
        key_step, key_reset = jax.random.split(key)
        obs_st, state_st, reward, terminated, info = self.step_env(key_step, state, action, params)
        truncated = self.is_truncated(state_st, params)
        done = jnp.logical_or(terminated, truncated)
        obs, state = select_compacted(
            done,
            lambda key, params, _: self.reset_env(key, params),
            lambda key, params, stepped: stepped,
            key_reset,
            params,
            (obs_st, state_st),
            capacity=RESET_CAPACITY,
        )
        info = {**info, "terminated": terminated, "truncated": truncated, "final_observation": obs_st}
        return obs, state, reward, terminated, truncated, info

    def step_env(
        self, key: jax.Array, state: EnvState, action: int | float | jax.Array, params: EnvParams
    ) -> tuple[jax.Array, EnvState, jax.Array, jax.Array, dict[Any, Any]]:
        dispersion = jax.random.uniform(key, (2,), jnp.float32, -1.0, 1.0)
        obs, state, reward, terminated, info = step_from_draws(
            state,
            action,
            dispersion,
            params,
            self.continuous,
            self.velocity_iterations,
            self.exact_free_flight,
            self.jump_sweeps,
        )
        info = {**info, "discount": 1.0 - terminated.astype(jnp.float32)}
        return obs, state, reward, terminated, info

    def reset_env(self, key: jax.Array, params: EnvParams) -> tuple[jax.Array, EnvState]:
        k_h, k_f, k_w = jax.random.split(key, 3)
        heights = jax.random.uniform(k_h, (CHUNKS + 1,), jnp.float32, 0.0, H / 2)
        force = jax.random.uniform(k_f, (2,), jnp.float32, -INITIAL_RANDOM, INITIAL_RANDOM)
        wind = jax.random.randint(k_w, (2,), -9999, 9999)
        return reset_from_draws(
            heights, force, params, wind, self.velocity_iterations, self.exact_free_flight, self.jump_sweeps
        )

    def get_obs(self, state: EnvState, params: EnvParams | None = None, key: Any = None) -> jax.Array:
        return observation(state)

    def is_terminated(self, state: EnvState, params: EnvParams) -> jax.Array:
        obs = observation(state)
        return state.game_over | (jnp.abs(obs[0]) >= 1.0) | ~state.awake

    def action_space(self, params: EnvParams | None = None) -> spaces.Discrete | spaces.Box:
        if self.continuous:
            return spaces.Box(-1.0, 1.0, (2,), jnp.float32)
        return spaces.Discrete(4)

    def observation_space(self, params: EnvParams | None = None) -> spaces.Box:
        return spaces.Box(jnp.asarray(OBS_LOW), jnp.asarray(OBS_HIGH), (8,), jnp.float32)


def heuristic_action(obs: jax.Array, continuous: bool = False) -> jax.Array:
    """Gymnasium's ``heuristic()`` demo controller, ported to JAX (one observation)."""
    angle_targ = jnp.clip(obs[0] * 0.5 + obs[2] * 1.0, -0.4, 0.4)
    hover_targ = 0.55 * jnp.abs(obs[0])
    angle_todo = (angle_targ - obs[4]) * 0.5 - obs[5] * 1.0
    hover_todo = (hover_targ - obs[1]) * 0.5 - obs[3] * 0.5
    legs = (obs[6] != 0) | (obs[7] != 0)
    angle_todo = jnp.where(legs, 0.0, angle_todo)
    hover_todo = jnp.where(legs, -obs[3] * 0.5, hover_todo)
    if continuous:
        return jnp.clip(jnp.stack([hover_todo * 20 - 1, -angle_todo * 20]), -1.0, 1.0)
    return jnp.where(
        (hover_todo > jnp.abs(angle_todo)) & (hover_todo > 0.05),
        2,
        jnp.where(angle_todo < -0.05, 3, jnp.where(angle_todo > 0.05, 1, 0)),
    ).astype(jnp.int32)
