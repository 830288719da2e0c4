"""StirredTankReactor: hold an exothermic CSTR at its open-loop-unstable middle steady state (gymnax API).

A first-order irreversible reaction A -> B in a jacketed continuous stirred-tank reactor, states the concentration
Ca (mol/L) and the temperature T (K), input the coolant temperature Tc (K), time in minutes:

    dCa/dt = q/V (Caf - Ca) - k(T) Ca
    dT/dt  = q/V (Tf - T) + (-dH)/(rho Cp) k(T) Ca + UA/(V rho Cp) (Tc - T),    k(T) = k0 exp(-(E/R) / T)

The constants (q = 100 L/min, V = 100 L, rho = 1000 g/L, Cp = 0.239 J/(g K), -dH = 5e4 J/mol, E/R = 8750 K,
k0 = 7.2e10 1/min, UA = 5e4 J/(min K), Caf = 1 mol/L, Tf = 350 K) are those of the exothermic CSTR of Seborg, Edgar,
Mellichamp & Doyle, "Process Dynamics and Control" (Wiley), Example 2.5 (so attributed by Kantor's ND Pyomo
Cookbook, "Exothermic CSTR"); the same values are in APMonitor's http://byu.apmonitor.com/wiki/uploads/Apps/cstr.apm
(citing Henson & Seborg, "Nonlinear Process Control", 1997) and PC-Gym's `src/pcgym/models/cstr.py`
(github.com/MaximilianB2/pc-gym). All are `ReactorParams` fields, so they are traced and can be vmapped.

Task: keep Ca at `ca_setpoint` = 0.5 mol/L. At Tc = 300 K the steady states are (0.877, 324.5 K), stable,
(0.5, 350.0 K), a saddle with unstable eigenvalue +2.83 /min, and (0.209, 369.7 K), an unstable focus: without
feedback the reactor runs away past 380 K within ~0.5 min or falls back to the cold state.

- Actions: Discrete(5), the coolant temperature `coolant_levels[a]` = (285, 292.5, 300, 307.5, 315) K, held for
  `dt` = 0.05 min. (Narrower levels, +-5 K, cannot hold it: from the hot corner of the reset distribution,
  (0.55, 355 K), even Tc = 290 K runs away; 285 K is needed.)
- Reset: Ca ~ U(0.45, 0.55), T ~ U(345, 355), independent.
- Reward (on the state after the step): 1 - min(1, |Ca - ca_setpoint| / 0.2), in [0, 1].
- Terminated when T leaves [t_low, t_high] = [320, 380] K (a safety interlock against runaway or extinction);
  truncated after `max_steps_in_episode` = 200 steps (gymnax's `is_truncated`).
- Observation (float32, clipped to [-5, 5]): [(Ca - ca_setpoint) / 0.1, (T - 350) / 10]. Feature 0 is the
  concentration, in a plant measured by a slow, expensive lab assay; feature 1 the temperature, from a cheap
  thermocouple: the env's two natural "instruments" for active measurement.

Integration: `substeps` (static, default 40) classical RK4 steps per `dt`, float32. Against scipy's Radau in float64
a step that stays inside [320, 380] K agrees to ~1 ulp (2e-5 K, 5e-7 mol/L); the step on which the reactor ignites
(to 400-480 K, k(T) up to ~1e3 /min) is stiff, and agrees to 5e-4 relative on T and 1e-3 mol/L on Ca over the
reachable states (10 substeps would give errors of 10-40 K there). States no policy can reach from the reset
distribution, such as Ca > 0.78 at T > 365 K, ignite too fast for a fixed step: the result is not meaningful.

The registry serves it as "CSTR-v0": `amjax.make("CSTR-v0", cost=0.1)`.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from flax import struct
from gymnax.environments import environment, spaces

CA_SCALE = 0.1  # mol/L per unit of observation feature 0
T_REF, T_SCALE = 350.0, 10.0  # K: observation feature 1 is (T - T_REF) / T_SCALE
REWARD_BAND = 0.2  # mol/L: |Ca - ca_setpoint| at which the reward reaches 0
OBS_BOUND = 5.0


@struct.dataclass
class ReactorState(environment.EnvState):
    ca: jax.Array  # concentration of A, mol/L
    temp: jax.Array  # reactor temperature, K
    time: int


@struct.dataclass
class ReactorParams(environment.EnvParams):
    max_steps_in_episode: int = 200
    dt: float = 0.05  # minutes per step
    q: float = 100.0  # feed flow, L/min
    volume: float = 100.0  # L
    rho: float = 1000.0  # density, g/L
    cp: float = 0.239  # heat capacity, J/(g K)
    neg_delta_h: float = 5e4  # heat of reaction -dH, J/mol
    e_over_r: float = 8750.0  # activation energy over the gas constant, K
    k0: float = 7.2e10  # pre-exponential factor, 1/min
    ua: float = 5e4  # heat-transfer coefficient times area, J/(min K)
    caf: float = 1.0  # feed concentration, mol/L
    tf: float = 350.0  # feed temperature, K
    ca_setpoint: float = 0.5  # mol/L
    t_low: float = 320.0  # K: below it the reaction is extinguished (terminated)
    t_high: float = 380.0  # K: above it the reactor runs away (terminated)
    coolant_levels: jax.Array = struct.field(
        default_factory=lambda: jnp.array([285.0, 292.5, 300.0, 307.5, 315.0], jnp.float32)
    )  # K, one per action: 5 values (the number of actions is static)


def derivatives(ca: jax.Array, temp: jax.Array, tc: jax.Array, params: ReactorParams) -> tuple[jax.Array, jax.Array]:
    """(dCa/dt, dT/dt) of the reactor at coolant temperature `tc`, per minute."""
    rate = params.k0 * jnp.exp(-params.e_over_r / temp) * ca
    dilution = params.q / params.volume
    dca = dilution * (params.caf - ca) - rate
    dtemp = (
        dilution * (params.tf - temp)
        + params.neg_delta_h / (params.rho * params.cp) * rate
        + params.ua / (params.volume * params.rho * params.cp) * (tc - temp)
    )
    return dca, dtemp


def integrate(
    ca: jax.Array, temp: jax.Array, tc: jax.Array, params: ReactorParams, substeps: int
) -> tuple[jax.Array, jax.Array]:
    """(Ca, T) after `params.dt` minutes at constant `tc`: `substeps` classical RK4 steps.

    T is carried as its deviation from the feed temperature, so the float32 rounding of the summed increments is
    that of a number of order 10 K, not 350 K (it cuts the error of a step about tenfold, to ~1 ulp of T)."""
    h = params.dt / substeps

    def f(x):
        return derivatives(x[0], params.tf + x[1], tc, params)

    def rk4(_, x):
        k1 = f(x)
        k2 = f((x[0] + 0.5 * h * k1[0], x[1] + 0.5 * h * k1[1]))
        k3 = f((x[0] + 0.5 * h * k2[0], x[1] + 0.5 * h * k2[1]))
        k4 = f((x[0] + h * k3[0], x[1] + h * k3[1]))
        return tuple(
            xi + h / 6.0 * (a + 2.0 * b + 2.0 * c + d) for xi, a, b, c, d in zip(x, k1, k2, k3, k4, strict=True)
        )

    ca, dev = jax.lax.fori_loop(0, substeps, rk4, (ca, temp - params.tf))
    return ca, params.tf + dev


class StirredTankReactor(environment.Environment[ReactorState, ReactorParams]):
    def __init__(self, substeps: int = 40):
        if not isinstance(substeps, int) or substeps < 1:
            raise ValueError(f"substeps must be a positive int (static), got {substeps!r}")
        self.substeps = substeps

    @property
    def default_params(self) -> ReactorParams:
        return ReactorParams()

    def reset_env(self, key: jax.Array, params: ReactorParams) -> tuple[jax.Array, ReactorState]:
        key_ca, key_temp = jax.random.split(key)
        ca = jax.random.uniform(key_ca, minval=0.45, maxval=0.55)
        temp = jax.random.uniform(key_temp, minval=345.0, maxval=355.0)
        state = ReactorState(ca=ca, temp=temp, time=0)
        return self.get_obs(state, params), state

    def step_env(
        self, key: jax.Array, state: ReactorState, action: Any, params: ReactorParams
    ) -> tuple[jax.Array, ReactorState, jax.Array, jax.Array, dict[str, Any]]:
        tc = jnp.asarray(params.coolant_levels, jnp.float32)[jnp.asarray(action)]
        ca, temp = integrate(
            jnp.asarray(state.ca, jnp.float32), jnp.asarray(state.temp, jnp.float32), tc, params, self.substeps
        )
        state = state.replace(ca=ca, temp=temp, time=state.time + 1)
        reward = 1.0 - jnp.minimum(1.0, jnp.abs(ca - params.ca_setpoint) / REWARD_BAND)
        return self.get_obs(state, params), state, reward, self.is_terminated(state, params), {}

    def get_obs(self, state: ReactorState, params: ReactorParams | None = None, key: Any = None) -> jax.Array:
        params = self.default_params if params is None else params
        obs = jnp.stack([(state.ca - params.ca_setpoint) / CA_SCALE, (state.temp - T_REF) / T_SCALE])
        return jnp.clip(obs, -OBS_BOUND, OBS_BOUND).astype(jnp.float32)

    def is_terminated(self, state: ReactorState, params: ReactorParams) -> jax.Array:
        # Written so that a non-finite temperature also terminates.
        return ~((state.temp >= params.t_low) & (state.temp <= params.t_high))

    @property
    def name(self) -> str:
        return "CSTR-v0"

    @property
    def num_actions(self) -> int:
        return 5

    def action_space(self, params: ReactorParams | None = None) -> spaces.Discrete:
        return spaces.Discrete(5)

    def observation_space(self, params: ReactorParams) -> spaces.Box:
        return spaces.Box(-OBS_BOUND, OBS_BOUND, (2,), jnp.float32)

    def state_space(self, params: ReactorParams) -> spaces.Dict:
        return spaces.Dict(
            {
                "ca": spaces.Box(0.0, params.caf, (), jnp.float32),
                "temp": spaces.Box(params.t_low, params.t_high, (), jnp.float32),
                "time": spaces.Discrete(params.max_steps_in_episode + 1),
            }
        )


__all__ = ["ReactorParams", "ReactorState", "StirredTankReactor", "derivatives", "integrate"]
