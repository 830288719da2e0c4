"""Gymnasium bridges: active measurement for any Gymnasium env, and amjax envs as Gymnasium envs.

- `ActiveMeasureWrapper`: the active-measure MDP of `amjax.wrappers.active_measure.ActiveMeasure`,
  in NumPy, around any `gymnasium.Env` with a Discrete or 1-D Box action space and a Box observation
  space (for systems not written in JAX, e.g. a lab instrument behind a Gymnasium interface).
- `to_gymnasium` / `GymnasiumEnv`: a gymnax-API environment and its params (e.g. from `amjax.make`)
  as a `gymnasium.Env` that passes `gymnasium.utils.env_checker.check_env`, for Stable-Baselines3,
  Tianshou and the like.

Gymnasium is a core dependency (gymnax 1.0.1 imports it in gymnax/environments/spaces.py); of amjax's own
modules only this one imports it.
"""

from __future__ import annotations

import re
from functools import lru_cache, partial
from typing import Any, ClassVar

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
from gymnasium import spaces as gym_spaces
from gymnasium.envs.registration import EnvSpec
from gymnax.environments import spaces as gymnax_spaces

from amjax.cores import TreeLayout, jit_one_kernel
from amjax.validation import check_bool, check_choice, check_positive_int, check_real, check_whole_number
from amjax.wrappers.active_measure import (
    REWARD_TIMINGS,
    UNBOUNDED,
    append_features,
    check_extra_obs,
    check_measure_setup,
)
from amjax.wrappers.instruments import check_instrument_values, check_instruments, feature_owner, resolve_instruments
from amjax.wrappers.spec import MeasureSpec, is_given

__all__ = ["ActiveMeasureWrapper", "GymnasiumEnv", "gymnasium_space", "to_gymnasium"]

# Spawn key that separates the wrapper's view stream from the inner env's `np_random` (same seed).
_VIEW_STREAM = 0x616D


# -- argument and action checks -------------------------------------------------------------------


def check_measure_args(cost: Any, mode: str, flag: bool, noise_std: Any) -> tuple[float, float]:
    """Validate the active-measure arguments as `amjax.make` does (`check_measure_setup`, the same check);
    returns (cost, noise_std)."""
    check_bool("flag", flag)
    cost = _one_number("cost", cost)
    check_measure_setup(False, mode, noise_std)
    return cost, 0.0 if noise_std is None else _one_number("noise_std", noise_std)


def _one_number(name: str, value: Any) -> float:
    """One finite number >= 0, or ValueError naming `name`."""
    array = check_real(name, value, low=0.0)
    if array.ndim != 0:
        raise ValueError(f"{name}: got {value!r}; allowed values: one finite number >= 0 (one environment)")
    return float(array)


def check_action(space: gym_spaces.Space, action: Any) -> Any:
    """`action` as a value of `space` (int for Discrete), or ValueError naming what is allowed."""
    if isinstance(space, gym_spaces.Discrete):
        start, stop = int(space.start), int(space.start + space.n)
        allowed = f"integers in [{start}, {stop})"
        array = np.asarray(action) if not isinstance(action, bool) else np.asarray(action, object)
        if array.dtype.kind not in "iu" or array.size != 1 or array.ndim > 1:
            raise ValueError(f"action: got {action!r}; allowed values: {allowed}")
        value = int(array.reshape(()))
        if not start <= value < stop:
            raise ValueError(f"action: got {action!r}; allowed values: {allowed}")
        return value
    if isinstance(space, gym_spaces.Box):
        allowed = f"arrays of shape {space.shape} with entries in [{space.low.tolist()}, {space.high.tolist()}]"
        try:
            array = np.asarray(action, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"action: got {action!r}; allowed values: {allowed}") from None
        if array.shape != space.shape or not np.all(np.isfinite(array)):
            raise ValueError(f"action: got {action!r}; allowed values: {allowed}")
        array = array.astype(space.dtype)
        if np.any(array < space.low) or np.any(array > space.high):
            raise ValueError(f"action: got {action!r}; allowed values: {allowed}")
        return array
    raise TypeError(f"action space {space} is not supported; allowed: Discrete, Box")


def sample_box(rng: np.random.Generator, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """NumPy twin of `active_measure.sample_box`, like Gymnasium's `Box.sample` (spaces/box.py).

    Uniform where bounded, shifted exponential where half-bounded, normal where unbounded; a bound
    of magnitude >= 1e30 (gymnax writes "unbounded" as +-finfo(float32).max) counts as infinite.
    """
    low = np.asarray(low, np.float64)
    high = np.asarray(high, np.float64)
    low_finite = low > -UNBOUNDED
    high_finite = high < UNBOUNDED
    safe_low = np.where(low_finite, low, 0.0)
    safe_high = np.where(high_finite, high, 1.0)
    uniform = safe_low + (safe_high - safe_low) * rng.uniform(size=low.shape)
    normal = rng.standard_normal(size=low.shape)
    exponential = rng.exponential(size=low.shape)
    return np.select(
        [low_finite & high_finite, low_finite, high_finite],
        [uniform, safe_low + exponential, safe_high - exponential],
        normal,
    )


# -- 1. the active-measure wrapper for any Gymnasium env ------------------------------------------


class ActiveMeasureWrapper(gymnasium.Wrapper[np.ndarray, Any, Any, Any]):
    """Active measurement for a Gymnasium env, with the semantics of the JAX `ActiveMeasure`.

    Every action also chooses whether to measure. Discrete(n) becomes Discrete(2n) with
    `action = control + n * measure` (offset by the space's `start`); a 1-D Box(d) becomes
    Box(1 + d) whose first entry, in [0, 1], measures iff it is >= 0.5. A measured step shows the
    true observation and remembers it; an unmeasured one shows, by `mode`, the remembered
    observation ("last"), a sample of the observation space ("random", see `sample_box`) or the
    true observation + N(0, noise_std^2) clipped to the space's bounds ("noisy"). `reset` is a free
    measurement. With `flag=True` a 1 (fresh) / 0 (stale) is appended. Observations are float32.
    The reward is `raw_reward - cost * measured`; `info` gains `raw_reward`, `cost` (charged this
    step) and `measured`. "random" and "noisy" draw from a generator seeded by `reset(seed=...)`
    (else by the env's `np_random_seed`) in a stream apart from the env's own `np_random`, so
    wrapping does not change the env's randomness.

    Args:
      env: a Gymnasium env with a Discrete or 1-D Box action space and a Box observation space: a vector, or
        (with `flag` or the options) an image [height, width, channels] too, which keeps its shape and gains the
        appended values as constant channels, as in the JAX wrapper (a 2-D observation needs its channel axis
        first: `gymnasium.wrappers.ReshapeObservation(env, (height, width, 1))`).
      cost: charged per measurement (one finite number >= 0).
      mode: "last", "random" or "noisy".
      flag: append the measured flag to the observation.
      noise_std: standard deviation for mode "noisy" (required there, > 0; elsewhere None or 0), checked with
        `amjax.make`'s check.
      extra_obs: `amjax.make`'s staleness features, with the same meaning and observation layout
        ("since_measured" scales by the env's time limit, `env.spec.max_episode_steps`, which it then needs).
      budget: `amjax.make`'s per-episode budget of measurements (a whole number), with the same info keys.
      reward_timing: `amjax.make`'s reward timing; with "on_measure", `info["paid_at_truncation"]` is what a
        target that bootstraps at a truncation leaves out (as `amjax.wrappers.active_measure` explains).
      instruments: `amjax.make`'s instruments, a tuple of observation-index tuples ("default" needs the env id,
        so pass the indices); the action encoding and layout are the JAX wrapper's, and `info["readings"]`
        holds the k readings made.
      instrument_costs: the instruments' prices (k numbers, default zeros).
      instrument_noise: the instruments' reading noise stds (k numbers, default zeros), drawn from the wrapper's
        own generator, so it matches the JAX wrapper in distribution, not draw for draw.
    """

    def __init__(
        self,
        env: gymnasium.Env,
        cost: Any = 0.0,
        mode: str = "last",
        flag: bool = True,
        noise_std: Any = None,
        extra_obs: tuple[str, ...] = (),
        budget: Any = None,
        reward_timing: str = "immediate",
        instruments: tuple[tuple[int, ...], ...] = (),
        instrument_costs: Any = None,
        instrument_noise: Any = None,
    ):
        super().__init__(env)
        self.cost, self.noise_std = check_measure_args(cost, mode, flag, noise_std)
        self.mode = mode
        self.flag = bool(flag)
        self.extra_obs = check_extra_obs(extra_obs)
        check_choice("reward_timing", reward_timing, REWARD_TIMINGS)
        self.reward_timing = reward_timing
        self.budget = None if budget is None else _one_number("budget", check_whole_number("budget", budget))
        self._horizon = env.spec.max_episode_steps if env.spec is not None else None
        if "since_measured" in self.extra_obs and not self._horizon:
            raise ValueError(
                "extra_obs: 'since_measured' scales by the episode's time limit, and this env has "
                "none (env.spec.max_episode_steps); wrap it in gymnasium's TimeLimit first"
            )
        inner_action = env.action_space
        inner_obs = env.observation_space
        if not isinstance(inner_obs, gym_spaces.Box):
            raise TypeError(
                f"env: the active-measure wrapper needs a Box observation space, got "
                f"{type(inner_obs).__name__}; allowed: Box"
            )
        appends = self.flag or self.extra_obs or self.budget is not None or instruments
        if appends and len(inner_obs.shape) not in (1, 3):
            raise TypeError(
                f"flag=True (and extra_obs, budget, instruments) need a vector or an image [height, width, channels] "
                f"observation, but its shape is {inner_obs.shape}; give a 2-D one a channel axis "
                "(gymnasium.wrappers.ReshapeObservation), or use flag=False"
            )
        # An instrument reads features: entries of a vector, channels of an image.
        self.instruments = check_instruments(instruments, inner_obs.shape[-1] if instruments else 0)
        # Measure choices per step (1: the paper's switch, which reads every feature) and the one reading each
        # feature.
        self._readings = max(1, len(self.instruments))
        self._owner = feature_owner(self.instruments) if self.instruments else np.zeros(inner_obs.shape, np.int32)
        self.instrument_costs, self.instrument_noise = (
            np.zeros(self._readings) if value is None else check_instrument_values(name, value, len(self.instruments))
            for name, value in (("instrument_costs", instrument_costs), ("instrument_noise", instrument_noise))
        )
        masks = 2**self._readings
        if isinstance(inner_action, gym_spaces.Discrete):
            self._num_controls = int(inner_action.n)
            self._start = int(inner_action.start)
            self.action_space = gym_spaces.Discrete(masks * inner_action.n, start=inner_action.start)
        elif isinstance(inner_action, gym_spaces.Box):
            if len(inner_action.shape) != 1 or inner_action.dtype.kind != "f":
                raise TypeError(
                    f"env: a Box action space must be 1-D and floating to gain a measure "
                    f"dimension, got {inner_action}; allowed: Discrete, 1-D floating Box"
                )
            dtype = inner_action.dtype
            self.action_space = gym_spaces.Box(
                np.concatenate([np.zeros(self._readings, dtype), inner_action.low]),
                np.concatenate([np.ones(self._readings, dtype), inner_action.high]),
                dtype=dtype,
            )
        else:
            raise TypeError(
                f"env: the active-measure wrapper needs a Discrete or Box action space, got "
                f"{type(inner_action).__name__}; allowed: Discrete, Box"
            )
        self._inner_action_space = inner_action
        with np.errstate(over="ignore"):  # float64 bounds beyond float32's range become +-inf
            self._low = inner_obs.low.astype(np.float32)
            self._high = inner_obs.high.astype(np.float32)
        extra_low, extra_high = (
            [np.zeros(self._readings)] if self.flag else [],
            [np.ones(self._readings)] if self.flag else [],
        )
        for name in self.extra_obs:
            if name == "last_action" and isinstance(inner_action, gym_spaces.Box):
                extra_low.append(inner_action.low)
                extra_high.append(inner_action.high)
            else:
                size = self._num_controls if name == "last_action" else self._readings
                extra_low.append(np.zeros(size))
                extra_high.append(np.ones(size))
        if self.budget is not None:
            extra_low.append(np.zeros(1))
            extra_high.append(np.ones(1))
        low, high = self._low, self._high
        if extra_low:
            low = append_features(low, np.concatenate(extra_low), np)
            high = append_features(high, np.concatenate(extra_high), np)
        self.observation_space = gym_spaces.Box(low.astype(np.float32), high.astype(np.float32), dtype=np.float32)
        self._last_obs: np.ndarray | None = None
        self._view_rng: np.random.Generator | None = None
        self._restart_counters()

    @classmethod
    def from_spec(cls, env: gymnasium.Env, spec: MeasureSpec) -> ActiveMeasureWrapper:
        """The wrapper for a `MeasureSpec` (or an agent config's setting), e.g. to run a policy trained in JAX on
        the Gymnasium original. `instruments="default"` takes the defaults of `env.spec.id`. Settings this wrapper
        does not have are refused: `vanilla` (the plain env is `env` itself) and `cost_conditioned`; the
        spec's values must be single numbers (not batched). `measure_head` is the agent's and changes no env."""
        for name in ("vanilla", "cost_conditioned"):
            if getattr(spec, name):
                raise ValueError(
                    f"{name}: ActiveMeasureWrapper has no {name} setting; allowed: {name}=False"
                    + (" (the plain env is the Gymnasium env itself)" if name == "vanilla" else "")
                )
        instruments = spec.instruments
        if instruments == "default":
            instruments = resolve_instruments(env.spec.id if env.spec is not None else "", instruments)

        def given(value: Any) -> Any:  # () means zeros here, None there
            return value if is_given(value) else None

        return cls(
            env,
            cost=spec.cost,
            mode=spec.mode,
            flag=spec.flag,
            noise_std=spec.noise_std,
            extra_obs=spec.extra_obs,
            budget=spec.budget if spec.budgeted else None,
            reward_timing=spec.reward_timing,
            instruments=instruments,
            instrument_costs=given(spec.instrument_costs),
            instrument_noise=given(spec.instrument_noise),
        )

    def _restart_counters(self) -> None:
        """The options' counters at an episode's start (`_since` per instrument)."""
        self._since, self._used, self._owed = np.zeros(self._readings, np.int64), 0, 0.0
        if isinstance(self._inner_action_space, gym_spaces.Discrete):
            self._last_control = np.zeros(self._num_controls, np.float32)
        else:
            self._last_control = np.zeros(self._inner_action_space.shape, np.float32)

    def _observe(self, obs: np.ndarray, fresh: bool) -> np.ndarray:
        """`obs`, the flag, then the options' features (as the JAX wrapper lays them out)."""
        features = []
        for name in self.extra_obs:
            if name == "since_measured":
                features.append(np.minimum(np.log1p(self._since) / np.log1p(self._horizon), 1.0))
            else:
                features.append(self._last_control)
        if self.budget is not None:
            left = 1.0 - self._used / self.budget if self.budget > 0 else 0.0
            features.append([min(max(left, 0.0), 1.0)])
        shown = self._with_flag(obs, fresh)
        return append_features(shown, np.concatenate(features, dtype=np.float32), np) if features else shown

    def split_action(self, action: Any) -> tuple[Any, np.ndarray]:
        """(control for the inner env, the readings requested: one bool per instrument, or one) of a wrapped
        action; ValueError if invalid."""
        action = check_action(self.action_space, action)
        k = self._readings
        if isinstance(self._inner_action_space, gym_spaces.Discrete):
            mask, control = divmod(int(action) - self._start, self._num_controls)
            return self._start + control, (mask >> np.arange(k)) & 1 == 1
        return action[k:], np.asarray(action[:k] >= 0.5)

    def _with_flag(self, obs: np.ndarray, fresh: Any) -> np.ndarray:
        # A copy either way: a caller mutating the observation must not touch the memory.
        flags = np.broadcast_to(np.asarray(fresh, np.float32), (self._readings,))
        return append_features(obs, flags, np) if self.flag else obs.copy()

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Reset the env; the first observation is a free measurement (flag 1) and is remembered."""
        obs, info = self.env.reset(seed=seed, options=options)
        if seed is not None or self._view_rng is None:
            entropy = seed if seed is not None else self.env.np_random_seed
            self._view_rng = (
                np.random.default_rng(np.random.SeedSequence(entropy, spawn_key=(_VIEW_STREAM,)))
                if entropy >= 0  # -1: the env's generator was set by hand, its seed is unknown
                else np.random.default_rng()
            )
        self._last_obs = np.array(obs, np.float32)  # a copy: envs may reuse their buffers
        self._restart_counters()
        return self._observe(self._last_obs, True), info

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Step with a wrapped action; see the class docstring for what is seen and charged."""
        if self._last_obs is None or self._view_rng is None:
            raise RuntimeError("step: call reset() before the first step")
        control, requested = self.split_action(action)
        readings = requested.copy()
        if self.budget is not None:  # instruments are served in their order while the budget lasts
            before = self._used + np.cumsum(requested) - requested
            readings &= before < self.budget
        measured = bool(readings.any())
        obs, raw_reward, terminated, truncated, info = self.env.step(control)
        true_obs = np.array(obs, np.float32)  # a copy: envs may reuse their buffers
        if self.mode == "last":
            unmeasured = self._last_obs
        elif self.mode == "random":
            unmeasured = sample_box(self._view_rng, self._low, self._high).astype(np.float32)
        else:
            noise = self.noise_std * self._view_rng.standard_normal(true_obs.shape)
            unmeasured = np.clip(true_obs + noise, self._low, self._high).astype(np.float32)
        fresh = readings[self._owner]
        reading = true_obs
        if self.instrument_noise.any():
            noise = self.instrument_noise[self._owner] * self._view_rng.standard_normal(true_obs.shape)
            reading = np.clip(true_obs + noise, self._low, self._high).astype(np.float32)
        seen = np.where(fresh, reading, unmeasured).astype(np.float32)
        self._last_obs = np.where(fresh, reading, self._last_obs).astype(np.float32)
        raw_reward = float(raw_reward)
        cost = self.cost * measured + float(self.instrument_costs @ readings) if measured else 0.0
        self._since = np.where(readings, 0, self._since + 1)
        self._used += int(readings.sum())
        if isinstance(self._inner_action_space, gym_spaces.Discrete):
            self._last_control = np.eye(self._num_controls, dtype=np.float32)[control - self._start]
        else:
            self._last_control = np.asarray(control, np.float32)
        info = {**info, "cost": cost, "measured": measured}
        if self.instruments:
            info["readings"] = readings
        if self.reward_timing == "on_measure":
            self._owed += raw_reward
            raw_reward = self._owed if (measured or terminated or truncated) else 0.0
            info["paid_at_truncation"] = raw_reward if (truncated and not (terminated or measured)) else 0.0
            self._owed -= raw_reward
            info["withheld"] = self._owed
        if self.budget is not None:
            refused = requested & ~readings
            info["refused"] = refused if self.instruments else bool(refused[0])
        info["raw_reward"] = raw_reward
        return self._observe(seen, readings), raw_reward - cost, terminated, truncated, info


# -- 2. amjax / gymnax environments as Gymnasium environments -------------------------------------


def gymnasium_space(space: gymnax_spaces.Space) -> gym_spaces.Space:
    """Convert a gymnax Discrete or Box space to Gymnasium's.

    gymnax's own `gymnax_space_to_gym_space` tests `low.size` when converting `high` (a scalar low
    with an array high fails); this broadcasts both bounds to the shape in the space's dtype, so
    Gymnasium does not warn about lowered precision. gymnax's +-finfo(float32).max "unbounded"
    bounds are kept: they are finite, so `check_env`'s "Box ... is infinity" warnings do not fire.
    """
    if isinstance(space, gymnax_spaces.Discrete):
        return gym_spaces.Discrete(int(space.n))
    if isinstance(space, gymnax_spaces.Box):
        dtype = np.dtype(space.dtype)
        shape = tuple(space.shape)
        low = np.broadcast_to(np.asarray(space.low, dtype), shape).copy()
        high = np.broadcast_to(np.asarray(space.high, dtype), shape).copy()
        return gym_spaces.Box(low, high, shape, dtype)
    raise TypeError(f"space: cannot convert {type(space).__name__}; allowed: gymnax Discrete, Box")


def _obs_to_numpy(obs: Any, space: gym_spaces.Space) -> Any:
    if isinstance(space, gym_spaces.Discrete):
        return np.int64(obs)
    return np.array(obs, space.dtype)  # a writable copy: arrays from `jax.device_get` are read-only


def _packed_keys(info: dict[Any, Any]) -> list[Any]:
    """Info keys whose values (0-d bool or <= 32-bit float) travel exactly in one float32 vector."""
    return [
        name
        for name, value in info.items()
        if jnp.ndim(value) == 0
        and (value.dtype == jnp.bool_ or jnp.issubdtype(value.dtype, jnp.floating))
        and jnp.dtype(value.dtype).itemsize <= 4
    ]


def _raw_reset(env: Any, seed: jax.Array, params: Any) -> tuple[Any, Any, jax.Array]:
    key_reset, key_next = jax.random.split(jax.random.key(seed))
    obs, state = env.reset(key_reset, params)
    return obs, state, key_next


# Module-level jitted functions keyed (statically) on the environment object and the layouts of its packed carry
# (key and state) and params (`amjax.cores.TreeLayout`): every `GymnasiumEnv` built on one env object (e.g. the
# copies in a vectorised env) shares one compiled reset and step. The carry and the params cross each call as one
# uint32 vector each, not as their 20-odd leaves (each leaf costs about 2 us in and out of a call).
@partial(jax.jit, static_argnums=(0, 1, 2))
def _reset(
    env: Any, carry: TreeLayout, params: TreeLayout, seed: jax.Array, params_words: jax.Array
) -> tuple[Any, jax.Array]:
    obs, state, key = _raw_reset(env, seed, params.unpack(params_words))
    return obs, carry.pack((key, state))


@partial(jax.jit, static_argnums=0)
def _pack_params(layout: TreeLayout, params: Any) -> jax.Array:
    return layout.pack(params)


def _raw_step(
    env: Any, key: jax.Array, state: Any, action: jax.Array, params: Any
) -> tuple[Any, Any, jax.Array, jax.Array, jax.Array, jax.Array, dict[Any, Any]]:
    key, key_step = jax.random.split(key)
    obs, state, reward, terminated, truncated, info = env.step(key_step, state, action, params)
    info = {name: jnp.asarray(value) for name, value in info.items()}
    final = info.pop("final_observation", None)
    if final is None or jnp.shape(final) != jnp.shape(obs):
        raise TypeError(
            "env: its step must report the pre-reset observation as info['final_observation'], "
            "shaped like the observation (the gymnax 1.0 API)"
        )
    # gymnax auto-resets inside `step`; Gymnasium shows the episode's last observation instead.
    obs = jnp.where(jnp.logical_or(terminated, truncated), final, obs)
    return obs, state, key, reward, terminated, truncated, info


def _packed_step(
    env: Any, key: jax.Array, state: Any, action: jax.Array, params: Any
) -> tuple[Any, Any, jax.Array, jax.Array, dict[Any, Any]]:
    """`_raw_step` with reward, terminated, truncated and the scalar info values packed in one
    float32 vector: one device-to-host copy instead of ten (about 0.2 ms a step saved on CPU)."""
    obs, state, key, reward, terminated, truncated, info = _raw_step(env, key, state, action, params)
    packed_keys = _packed_keys(info)
    scalars = [reward, terminated, truncated, *(info[name] for name in packed_keys)]
    packed = jnp.stack([jnp.asarray(value, jnp.float32) for value in scalars])
    rest = {name: value for name, value in info.items() if name not in packed_keys}
    return obs, state, key, packed, rest


def _carried_step(
    env: Any, carry: TreeLayout, params: TreeLayout, carry_words: jax.Array, action: jax.Array, params_words: jax.Array
) -> tuple[Any, jax.Array, jax.Array, dict[Any, Any]]:
    """`_packed_step` on the packed carry and params; returns (obs, next carry, scalars, other info)."""
    key, state = carry.unpack(carry_words)
    obs, state, key, scalars, rest = _packed_step(env, key, state, action, params.unpack(params_words))
    return obs, carry.pack((key, state)), scalars, rest


@lru_cache(maxsize=64)  # bounded like jax.jit's own cache of static arguments: a program per env object and layouts
def _step(env: Any, carry: TreeLayout, params: TreeLayout) -> Any:
    """`_carried_step` of `env`, compiled as one kernel (`amjax.cores.jit_one_kernel`: one env's step is small
    operations, each launched apart otherwise)."""
    return jit_one_kernel(partial(_carried_step, env, carry, params))


class GymnasiumEnv(gymnasium.Env[Any, Any]):
    """A gymnax-API environment (plain, `ActiveMeasure` or `AlwaysMeasured`) as a `gymnasium.Env`.

    Seeding: `reset(seed=...)` seeds `np_random`; each reset draws a 32-bit JAX seed from it, splits
    it into the reset key and a key carried (and split once per step) through the episode.

    Stepping: the environment's own `step` (not `step_env`: a gymnax wrapper such as `ActiveMeasure`
    overrides `step` only, and `step_env` would reach the inner env). gymnax auto-resets inside
    `step`, so on a terminated/truncated step the observation returned is
    `info['final_observation']` (for `ActiveMeasure` the view of the last step, flag included), the
    auto-reset state is discarded, and `step` raises RuntimeError until `reset` is called: a
    Gymnasium env does not auto-reset.

    Outputs: NumPy observations in the space's dtype, float rewards, bool `terminated`/`truncated`,
    `info` values as Python scalars or arrays (without `final_observation`, which is the
    observation). Actions outside the action space raise ValueError. `params` stay traced: a new
    cost is not a new compile, and every instance on the same env object shares the compiled reset
    and step.
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": []}

    def __init__(
        self,
        env: Any,
        params: Any,
        *,
        seed: int | None = None,
        render_mode: str | None = None,
    ):
        if render_mode is not None:
            raise ValueError(f"render_mode: got {render_mode!r}; allowed values: None (no rendering)")
        for method in ("reset", "step", "action_space", "observation_space"):
            if not callable(getattr(env, method, None)):
                raise TypeError(
                    f"env: expected a gymnax-API environment (reset, step, action_space, "
                    f"observation_space), got {type(env).__name__} without {method!r}"
                )
        self.gymnax_env = env
        # Required: an amjax env's `default_params` have cost 0, not the cost `amjax.make` was given.
        # On the device once: Python numbers among the leaves would be copied over at every step.
        self._params_layout = TreeLayout.of(params)
        self.params = params
        self.action_space = gymnasium_space(env.action_space(self.params))
        self.observation_space = gymnasium_space(env.observation_space(self.params))
        if not isinstance(self.action_space, gym_spaces.Discrete | gym_spaces.Box):
            raise TypeError(f"env: action space {self.action_space}; allowed: Discrete, Box")
        self._check_shapes()
        name = re.sub(r"[^\w.-]+", "-", str(getattr(env, "name", type(env).__name__))).strip("-")
        self.spec = EnvSpec(
            id=f"amjax/{name or 'env'}",
            entry_point=partial(GymnasiumEnv, env, params),
            nondeterministic=False,
        )
        if seed is not None:
            super().reset(seed=check_positive_int("seed", seed, minimum=0))
        self._carry: jax.Array | None = None  # the episode's key and state, packed (`_carry_layout`)

    @property
    def params(self) -> Any:
        """The env params every step uses (on the device). Assigning new ones with the same structure, shapes and
        dtypes (e.g. `.replace(cost=0.5)` on these) changes the next steps and resets without a new compile; the
        action and observation spaces and `spec` keep the params the env was built with."""
        return self._params

    @params.setter
    def params(self, params: Any) -> None:
        try:
            self._params_layout.check(params)
        except ValueError as error:
            raise ValueError(
                f"params: new params must have the structure, shapes and dtypes of the env's params ({error})"
            ) from None
        self._params = jax.device_put(params)
        self._params_words = _pack_params(self._params_layout, self._params)  # what the programs take

    def _check_shapes(self) -> None:
        """Trace reset and step (no compile) to refuse batched params, e.g. `make(cost=[...])`; set the layout of the
        packed carry (key and state) and look up the compiled step."""
        env = self.gymnax_env
        obs, state, key = jax.eval_shape(partial(_raw_reset, env), np.uint32(0), self.params)
        self._carry_layout = TreeLayout.of((key, state))
        self._compiled_step = _step(env, self._carry_layout, self._params_layout)  # looked up once, not per step
        action = jax.ShapeDtypeStruct(self.action_space.shape, self._jax_action(0).dtype)
        out = jax.eval_shape(partial(_raw_step, env), key, state, action, self.params)
        step_obs, reward, terminated, truncated, info = out[0], *out[3:]
        obs_shape = self.observation_space.shape
        shapes = (obs.shape, step_obs.shape, reward.shape, terminated.shape, truncated.shape)
        if shapes != (obs_shape, obs_shape, (), (), ()):
            raise ValueError(
                f"params: one environment's params expected (observation shape {obs_shape}, "
                f"scalar reward and done flags), got observation shape {step_obs.shape} and "
                f"reward shape {reward.shape}: were they built for a batch (e.g. an array cost)?"
            )
        # How `_step` packs info (the same rule at trace time): key -> Python type to restore.
        self._packed_info = {name: bool if info[name].dtype == jnp.bool_ else float for name in _packed_keys(info)}

    def _jax_action(self, action: Any) -> np.ndarray:
        if isinstance(self.action_space, gym_spaces.Discrete):
            return np.asarray(action, np.int32)
        return np.asarray(action, self.action_space.dtype)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
        """Start an episode; `options` must be None or empty (amjax envs take no reset options)."""
        if options:
            raise ValueError(f"options: got {options!r}; allowed values: None or {{}}")
        if seed is not None:
            check_positive_int("seed", seed, minimum=0)
        super().reset(seed=seed)
        jax_seed = self.np_random.integers(0, 2**32, dtype=np.uint32)
        layouts = (self._carry_layout, self._params_layout)
        obs, self._carry = _reset(self.gymnax_env, *layouts, jax_seed, self._params_words)
        return _obs_to_numpy(jax.device_get(obs), self.observation_space), {}

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        """One transition; after a terminated or truncated step, `reset` must come next."""
        if self._carry is None:
            raise RuntimeError(
                "step: no episode is running (call reset() first, and again after an episode terminated or truncated)"
            )
        action = self._jax_action(check_action(self.action_space, action))
        obs, carry, packed, rest = self._compiled_step(self._carry, action, self._params_words)
        obs, packed, rest = jax.device_get((obs, packed, rest))
        packed = packed.tolist()
        terminated, truncated = bool(packed[1]), bool(packed[2])
        info = {name: kind(value) for (name, kind), value in zip(self._packed_info.items(), packed[3:], strict=True)}
        for name, value in rest.items():
            info[name] = value.item() if np.ndim(value) == 0 else np.asarray(value)
        self._carry = None if terminated or truncated else carry
        return _obs_to_numpy(obs, self.observation_space), packed[0], terminated, truncated, info


def to_gymnasium(env: Any, params: Any, *, seed: int | None = None) -> GymnasiumEnv:
    """A gymnax-API environment and its params as a `gymnasium.Env` (see `GymnasiumEnv`).

    For example `to_gymnasium(*amjax.make("CartPole-v0", cost=0.2), seed=0)`; `seed` seeds
    `np_random` for the resets that do not pass one.
    """
    return GymnasiumEnv(env, params, seed=seed)
