"""The active-measure wrapper: every action also chooses whether to measure, and measuring costs.

An action is a pair (control, measure). For a `Discrete(n)` environment the wrapped space is `Discrete(2n)` and
`action = control + n * measure`; for a `Box(d)` environment it is `Box(1 + d)` whose first entry, in [0, 1],
measures iff it is >= 0.5. The state remembers the last measured observation. Without a measurement the agent sees,
by `mode`:
- "last": the remembered observation (the paper's setting);
- "random": a sample of the observation space (uniform where bounded, as Gymnasium's `Box.sample`);
- "noisy": the true observation + N(0, noise_std^2), clipped to the space's bounds.
With `flag=True` a 1 (fresh) or 0 (stale) is appended to the observation. A reset, including the auto-reset inside
`step`, counts as a free measurement of the first observation. The reward is `raw_reward - cost * measured`.
Keys: in mode "last" `step` hands its key to the inner environment unchanged (always measuring is then exactly
the plain environment under the same keys); the other modes split it into the inner env's key and the view's.

`cost` and `noise_std` are leaves of `MeasureParams` (traced, vmappable); `mode`, `flag` and the inner environment
are static (attributes of the wrapper object, which is a static argument of the jitted `reset`/`step`).
"""

from __future__ import annotations

from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct
from gymnax.environments import spaces
from gymnax.environments.environment import Environment
from gymnax.wrappers.purerl import GymnaxWrapper

from amjax.validation import check_bool, check_choice

MODES = ("last", "random", "noisy")
# gymnax writes "unbounded" as +-finfo(float32).max (e.g. CartPole's velocities); treat such bounds as infinite.
UNBOUNDED = 1e30


@struct.dataclass
class MeasureParams:
    """Traced parameters of the active-measure MDP (all leaves; vmap over any of them)."""

    env_params: Any
    cost: jax.Array  # charged per measurement, subtracted from the reward
    noise_std: jax.Array  # std of the observation noise in mode "noisy" (unused otherwise)


@struct.dataclass
class MeasureState:
    """The inner environment's state plus the last measured observation (without the flag)."""

    env_state: Any
    last_obs: jax.Array


def decode_discrete(action: jax.Array, num_controls: int) -> tuple[jax.Array, jax.Array]:
    """Split `control + num_controls * measure` into (control, measure). Out-of-range actions wrap."""
    action = jnp.asarray(action, jnp.int32)
    return action % num_controls, action >= num_controls


def sample_box(key: jax.Array, low: jax.Array, high: jax.Array) -> jax.Array:
    """Sample a Box like Gymnasium's `Box.sample`: uniform where bounded, normal/exponential where not."""
    low_finite = low > -UNBOUNDED
    high_finite = high < UNBOUNDED
    key_u, key_n, key_e = jax.random.split(key, 3)
    shape = jnp.broadcast_shapes(low.shape, high.shape)
    safe_low = jnp.where(low_finite, low, 0.0)
    safe_high = jnp.where(high_finite, high, 1.0)
    uniform = safe_low + (safe_high - safe_low) * jax.random.uniform(key_u, shape)
    normal = jax.random.normal(key_n, shape)
    exponential = jax.random.exponential(key_e, shape)
    return jnp.select(
        [low_finite & high_finite, low_finite, high_finite],
        [uniform, safe_low + exponential, safe_high - exponential],
        normal,
    )


class ActiveMeasure(GymnaxWrapper):
    """Active-measure wrapper for a gymnax environment (see the module docstring)."""

    def __init__(
        self,
        env: Environment,
        mode: str = "last",
        flag: bool = True,
        env_params: Any = None,
    ):
        super().__init__(env)
        check_choice("mode", mode, MODES)
        check_bool("flag", flag)
        self.mode = mode
        self.flag = flag
        # The inner params behind `default_params` (and so behind reset/step with params=None): the registry's
        # for an id, e.g. CartPole-v0's 200-step limit, not the inner env class's own defaults.
        env_params = env.default_params if env_params is None else env_params
        self._env_params = env_params
        self._inner_action_space = env.action_space(env_params)
        if not isinstance(self._inner_action_space, spaces.Discrete | spaces.Box):
            raise TypeError(
                f"env: the active-measure wrapper needs a Discrete or Box action space, got "
                f"{type(self._inner_action_space).__name__}; allowed: Discrete, Box"
            )
        if isinstance(self._inner_action_space, spaces.Box) and len(
            self._inner_action_space.shape
        ) > 1:
            raise TypeError("env: a Box action space must be 1-D to gain a measure dimension")
        obs_space = env.observation_space(env_params)
        if not isinstance(obs_space, spaces.Box):
            raise TypeError(
                f"env: the active-measure wrapper needs a Box observation space, got "
                f"{type(obs_space).__name__}; allowed: Box"
            )
        if flag and len(obs_space.shape) != 1:
            raise TypeError(
                f"flag=True appends to a 1-D observation, but its shape is {obs_space.shape}; "
                "use flag=False or flatten the observation"
            )

    # -- spaces -------------------------------------------------------------------------------

    @property
    def num_controls(self) -> int:
        """Number of control actions of the inner (Discrete) environment."""
        return int(self._inner_action_space.n)

    @property
    def num_actions(self) -> int:
        """2n for Discrete(n); for Box(d), the action dimension 1 + d (as gymnax counts it)."""
        if isinstance(self._inner_action_space, spaces.Discrete):
            return 2 * self.num_controls
        return 1 + self._inner_action_space.shape[0]

    def action_space(self, params: MeasureParams | None = None) -> spaces.Space:
        inner = self._env.action_space(None if params is None else params.env_params)
        if isinstance(inner, spaces.Discrete):
            return spaces.Discrete(2 * inner.n)
        low = jnp.broadcast_to(jnp.asarray(inner.low, jnp.float32), inner.shape)
        high = jnp.broadcast_to(jnp.asarray(inner.high, jnp.float32), inner.shape)
        return spaces.Box(
            jnp.concatenate([jnp.zeros(1), low]),
            jnp.concatenate([jnp.ones(1), high]),
            (inner.shape[0] + 1,),
            jnp.float32,
        )

    def _obs_bounds(self, params: MeasureParams) -> tuple[jax.Array, jax.Array]:
        space = self._env.observation_space(params.env_params)
        low = jnp.broadcast_to(jnp.asarray(space.low, jnp.float32), space.shape)
        high = jnp.broadcast_to(jnp.asarray(space.high, jnp.float32), space.shape)
        return low, high

    def observation_space(self, params: MeasureParams | None = None) -> spaces.Box:
        low, high = self._obs_bounds(self.default_params if params is None else params)
        if not self.flag:
            return spaces.Box(low, high, low.shape, jnp.float32)
        return spaces.Box(
            jnp.append(low, 0.0), jnp.append(high, 1.0), (low.shape[0] + 1,), jnp.float32
        )

    @property
    def default_params(self) -> MeasureParams:
        return MeasureParams(
            env_params=self._env_params,
            cost=jnp.float32(0.0),
            noise_std=jnp.float32(0.0),
        )

    @property
    def name(self) -> str:
        return f"ActiveMeasure({self._env.name})"

    # -- dynamics -------------------------------------------------------------------------------

    def split_action(self, action: jax.Array) -> tuple[jax.Array, jax.Array]:
        """(control action for the inner env, measure flag) of a wrapped action."""
        if isinstance(self._inner_action_space, spaces.Discrete):
            return decode_discrete(action, self.num_controls)
        action = jnp.asarray(action, jnp.float32)
        return action[1:], action[0] >= 0.5

    def _with_flag(self, obs: jax.Array, fresh: jax.Array) -> jax.Array:
        obs = jnp.asarray(obs, jnp.float32)
        if not self.flag:
            return obs
        # Pad, then write the flag with a select: XLA fuses this with the surrounding selects, whereas a
        # concatenate with a traced flag is a separate, unvectorised pass over a [batch, d + 1] array on CPU
        # (it made a batch of wrapped CartPole steps 1.7x slower than the plain env).
        is_flag = jnp.arange(obs.shape[0] + 1) == obs.shape[0]
        return jnp.where(is_flag, jnp.asarray(fresh, jnp.float32), jnp.pad(obs, (0, 1)))

    def _unmeasured_view(
        self, key: jax.Array, last_obs: jax.Array, true_obs: jax.Array, params: MeasureParams
    ) -> jax.Array:
        if self.mode == "last":
            return last_obs
        low, high = self._obs_bounds(params)
        if self.mode == "random":
            return sample_box(key, low, high)
        noise = params.noise_std * jax.random.normal(key, true_obs.shape)
        return jnp.clip(true_obs + noise, low, high)

    @partial(jax.jit, static_argnames=("self",))
    def reset(
        self, key: jax.Array, params: MeasureParams | None = None
    ) -> tuple[jax.Array, MeasureState]:
        params = self.default_params if params is None else params
        obs, env_state = self._env.reset(key, params.env_params)
        obs = jnp.asarray(obs, jnp.float32)
        return self._with_flag(obs, True), MeasureState(env_state=env_state, last_obs=obs)

    @partial(jax.jit, static_argnames=("self",))
    def step(
        self,
        key: jax.Array,
        state: MeasureState,
        action: jax.Array,
        params: MeasureParams | None = None,
    ) -> tuple[jax.Array, MeasureState, jax.Array, jax.Array, jax.Array, dict[str, Any]]:
        params = self.default_params if params is None else params
        if self.mode == "last":  # the stale view needs no randomness: the inner env gets the key as it came
            key_env = key_view = key
        else:
            key_env, key_view = jax.random.split(key)
        control, measured = self.split_action(action)
        obs, env_state, raw_reward, terminated, truncated, info = self._env.step(
            key_env, state.env_state, control, params.env_params
        )
        done = jnp.logical_or(terminated, truncated)
        true_obs = jnp.asarray(info["final_observation"], jnp.float32)  # before any auto-reset
        unmeasured = self._unmeasured_view(key_view, state.last_obs, true_obs, params)
        seen = jnp.where(measured, true_obs, unmeasured)
        remembered = jnp.where(measured, true_obs, state.last_obs)
        # On an episode boundary the auto-reset's first observation is a free measurement.
        reset_obs = jnp.asarray(obs, jnp.float32)
        next_obs = self._with_flag(jnp.where(done, reset_obs, seen), done | measured)
        next_state = MeasureState(env_state=env_state, last_obs=jnp.where(done, reset_obs, remembered))
        cost = params.cost * measured
        raw_reward = jnp.asarray(raw_reward, jnp.float32)
        info = {
            **info,
            "final_observation": self._with_flag(seen, measured),
            "raw_reward": raw_reward,
            "cost": cost,
            "measured": measured,
        }
        return next_obs, next_state, raw_reward - cost, terminated, truncated, info


class AlwaysMeasured(GymnaxWrapper):
    """The plain environment with the active-measure info keys (cost 0, measured), for vanilla baselines.

    `env_params` (default: the inner env's own) are its `default_params`, used when reset/step get none.
    """

    def __init__(self, env: Environment, env_params: Any = None):
        super().__init__(env)
        self._env_params = env.default_params if env_params is None else env_params

    @property
    def default_params(self) -> Any:
        return self._env_params

    @partial(jax.jit, static_argnames=("self",))
    def reset(self, key: jax.Array, params: Any = None) -> tuple[jax.Array, Any]:
        return self._env.reset(key, self.default_params if params is None else params)

    @partial(jax.jit, static_argnames=("self",))
    def step(
        self, key: jax.Array, state: Any, action: jax.Array, params: Any = None
    ) -> tuple[jax.Array, Any, jax.Array, jax.Array, jax.Array, dict[str, Any]]:
        params = self.default_params if params is None else params
        obs, state, reward, terminated, truncated, info = self._env.step(key, state, action, params)
        reward = jnp.asarray(reward, jnp.float32)
        info = {**info, "raw_reward": reward, "cost": jnp.float32(0.0), "measured": jnp.bool_(True)}
        return obs, state, reward, terminated, truncated, info
