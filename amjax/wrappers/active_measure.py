"""The active-measure wrapper: every action also chooses whether to measure, and measuring costs.

An action is a pair (control, measure). For a `Discrete(n)` environment the wrapped space is `Discrete(2n)` and
`action = control + n * measure`; for a `Box(d)` environment it is `Box(1 + d)` whose first entry, in [0, 1],
measures iff it is >= 0.5. The state remembers the last measured observation. Without a measurement the agent sees,
by `mode`:
- "last": the remembered observation (the paper's setting);
- "random": a sample of the observation space (uniform where bounded, as Gymnasium's `Box.sample`);
- "noisy": the true observation + N(0, noise_std^2), clipped to the space's bounds.
With `flag=True` a 1 (fresh) or 0 (stale) is appended to the observation. Observations are vectors [d] or images
[height, width, channels] (`amjax.make` gives a 2-D observation a channel axis, `observations.py`): an image
keeps its shape and everything the wrapper appends (the flag and the options' features below) is added as
constant channels, one per value, so a convolutional torso reads them at every pixel. A reset, including the
auto-reset inside `step`, counts as a free measurement of the first observation. The reward is
`raw_reward - cost * measured`.

Options beyond the paper (each off by default; off, the state, observation and reward are the paper's):
- `extra_obs`: features appended after the flag, giving a memoryless agent what it cannot remember.
  "since_measured": steps since the shown observation was measured, as log(1 + k) / log(1 + max_steps) in [0, 1];
  "last_action": the last control action (one-hot for Discrete, the action itself for Box; zeros after a reset).
- `budgeted`: at most `MeasureParams.budget` paid measurements per episode (traced, like the cost; a whole number:
  `amjax.make` and the configs refuse fractions, and one set by hand counts as its floor). A request beyond it is
  not carried out (no cost, the stale view, `info["refused"]`), and the remaining fraction of the budget is appended
  to the observation (after the extra features).
- `reward_timing="on_measure"`: the raw reward of an unmeasured step is withheld and paid, summed, at the next
  measurement or at the episode's end (for outcomes known only when looked at). `info["raw_reward"]` is what was
  paid, so episode totals are unchanged; `info["withheld"]` is what is still owed. `info["paid_at_truncation"]` is
  the part of the reward paid only because a time limit cut the episode on an unmeasured step (0 otherwise): a
  learner that bootstraps there from the value of the pre-reset view, which already counts what is owed (the next
  measurement would pay it), leaves it out of its target (`amjax.agents.rollout.step_envs` does), or counts it twice.
- `instruments`: the observation split into k instruments read separately (`amjax/wrappers/instruments.py`: the
  action encoding, defaults per env). Each has a flag (k flags replace the one), a price
  (`MeasureParams.instrument_costs`) and a reading noise std (`MeasureParams.instrument_noise`, Gaussian, clipped
  to the observation's bounds); `cost` is then charged once per step on which any instrument is read (the cost of
  taking a sample at all), and "since_measured" counts per instrument. `info["readings"]` holds the k choices
  carried out; `info["measured"]` is whether any was. The budget counts readings.
- `cost_conditioned`: each episode draws its cost uniformly from [`MeasureParams.cost_low`, `cost_high`] (traced;
  redrawn at every reset and auto-reset, charged in place of `cost`) and the cost is appended, last, to the
  observation, scaled from the training range [`cost_scale_low`, `cost_scale_high`] to [-1, 1] (0 for a single
  cost), so one agent can learn every cost of the range at once. To score it at cost c, set the draw range to
  (c, c) and keep the scaling range.
Keys: in mode "last" `step` hands its key to the inner environment unchanged (always measuring is then exactly
the plain environment under the same keys); the other modes split it into the inner env's key and the view's. The
wrapper's other draws (instrument reading noise, an episode's cost) come from its own stream,
`fold_in(key, WRAPPER_STREAM)` of the `reset` or `step` key, which no environment reaches: an environment derives
its keys with small splits and folds (`split(key, n)[i]`, which in this jax equals `fold_in(key, i)`: gymnax's
auto-reset key is `fold_in(key, 1)`, LunarLander's wind key at reset `fold_in(key, 2)`), so a reading's noise tells
nothing about the next episode's start, nor an episode's cost about its wind.

`cost` and `noise_std` are leaves of `MeasureParams` (traced, vmappable); `mode`, `flag` and the inner environment
are static (attributes of the wrapper object, which is a static argument of the jitted `reset`/`step`).
`check_measure_setup` is the one check of mode, noise_std and vanilla that `amjax.make`, the agent configs and the
NumPy wrapper share.
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

from amjax.validation import check_bool, check_choice, check_real, is_traced
from amjax.wrappers.instruments import (
    check_instruments,
    decode_mask,
    feature_owner,
    served_readings,
)
from amjax.wrappers.observations import env_name

MODES = ("last", "random", "noisy")
EXTRA_OBS = ("since_measured", "last_action")
REWARD_TIMINGS = ("immediate", "on_measure")
# gymnax writes "unbounded" as +-finfo(float32).max (e.g. CartPole's velocities); treat such bounds as infinite.
UNBOUNDED = 1e30
# `fold_in` data of the wrapper's own stream of draws, far beyond any split an environment makes of its key; within
# it, `fold_in(own, READING_DRAW)` draws the reading noise and `fold_in(own, COST_DRAW)` an episode's cost.
WRAPPER_STREAM = 0x616D6561  # "amea"
READING_DRAW, COST_DRAW = 0, 1


def wrapper_key(key: jax.Array, draw: int) -> jax.Array:
    """The key of one of the wrapper's own draws (`READING_DRAW`, `COST_DRAW`) at the `reset` / `step` key `key`: a
    stream apart from every key the inner environment derives from `key` (see the module docstring)."""
    return jax.random.fold_in(jax.random.fold_in(key, WRAPPER_STREAM), draw)


@struct.dataclass
class MeasureParams:
    """Traced parameters of the active-measure MDP (all leaves; vmap over any of them)."""

    env_params: Any
    cost: jax.Array  # charged per measurement, subtracted from the reward
    noise_std: jax.Array  # std of the observation noise in mode "noisy" (unused otherwise)
    budget: Any = None  # paid measurements allowed per episode (a wrapper with budgeted=True only)
    instrument_costs: Any = None  # [k] price of reading each instrument (a wrapper with instruments only)
    instrument_noise: Any = None  # [k] std of each instrument's reading noise (a wrapper with instruments only)
    cost_low: Any = None  # an episode's cost is drawn from [cost_low, cost_high] (cost_conditioned only)
    cost_high: Any = None
    # The observed cost is scaled from [cost_scale_low, cost_scale_high] (the training range) to [-1, 1], 0 when the
    # two are equal; evaluating at another cost changes the draw range and keeps this one (cost_conditioned only).
    cost_scale_low: Any = None
    cost_scale_high: Any = None


@struct.dataclass
class MeasureState:
    """The inner environment's state plus the last measured observation (without the flag); the options' counters
    are None unless their option is on (no leaves, no cost)."""

    env_state: Any
    last_obs: jax.Array
    since_measured: Any = None  # steps since the last measurement ("since_measured"; [k] with instruments)
    last_control: Any = None  # the last control action, one-hot for Discrete ("last_action")
    measurements: Any = None  # paid measurements this episode (budgeted)
    withheld: Any = None  # raw reward not yet paid (reward_timing="on_measure")
    episode_cost: Any = None  # this episode's cost per measurement (cost_conditioned)


def decode_discrete(action: jax.Array, num_controls: int) -> tuple[jax.Array, jax.Array]:
    """Split `control + num_controls * measure` into (control, measure). Out-of-range actions wrap."""
    action = jnp.asarray(action, jnp.int32)
    return action % num_controls, action >= num_controls


def scaled_cost(cost: jax.Array, low: jax.Array, high: jax.Array) -> jax.Array:
    """The cost as the agent sees it: the scaling range [low, high] mapped to [-1, 1] (0 for a single cost, so a
    single-cost range adds an input that is always 0: the fixed-cost network, one dead input wider)."""
    width = jnp.where(high > low, high - low, 1.0)
    return jnp.where(high > low, 2.0 * (cost - low) / width - 1.0, 0.0).astype(jnp.float32)


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


def append_features(obs: Any, features: Any, xp: Any = jnp) -> Any:
    """`features` [m] after `obs`: concatenated to a vector, or as m constant channels of an image [h, w, c]. `xp`:
    the array library (jax.numpy, or numpy for the Gymnasium wrapper)."""
    features = xp.asarray(features, obs.dtype)
    if obs.ndim == 1:
        return xp.concatenate([obs, features])
    return xp.concatenate([obs, xp.broadcast_to(features, (*obs.shape[:-1], features.shape[0]))], -1)


class ActiveMeasure(GymnaxWrapper):
    """Active-measure wrapper for a gymnax environment (see the module docstring)."""

    def __init__(
        self,
        env: Environment,
        mode: str = "last",
        flag: bool = True,
        env_params: Any = None,
        extra_obs: tuple[str, ...] = (),
        budgeted: bool = False,
        reward_timing: str = "immediate",
        instruments: tuple[tuple[int, ...], ...] = (),
        cost_conditioned: bool = False,
    ):
        super().__init__(env)
        check_choice("mode", mode, MODES)
        check_bool("flag", flag)
        check_bool("budgeted", budgeted)
        check_bool("cost_conditioned", cost_conditioned)
        check_choice("reward_timing", reward_timing, REWARD_TIMINGS)
        extra_obs = check_extra_obs(extra_obs)
        self.mode = mode
        self.flag = flag
        self.extra_obs = extra_obs
        self.budgeted = budgeted
        self.reward_timing = reward_timing
        self.cost_conditioned = cost_conditioned
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
        if isinstance(self._inner_action_space, spaces.Box) and len(self._inner_action_space.shape) > 1:
            raise TypeError("env: a Box action space must be 1-D to gain a measure dimension")
        obs_space = env.observation_space(env_params)
        if not isinstance(obs_space, spaces.Box):
            raise TypeError(
                f"env: the active-measure wrapper needs a Box observation space, got "
                f"{type(obs_space).__name__}; allowed: Box"
            )
        if (flag or extra_obs or budgeted or instruments or cost_conditioned) and len(obs_space.shape) not in (1, 3):
            raise TypeError(
                f"flag=True (and extra_obs, budgeted, instruments, cost_conditioned) need a vector or an image "
                f"[height, width, channels] observation, but its shape is {obs_space.shape}; wrap it with "
                "amjax.make or amjax.wrap (they give a 2-D observation a channel axis), or use flag=False"
            )
        # An instrument reads features: entries of a vector, channels of an image.
        self.instruments = check_instruments(instruments, obs_space.shape[-1] if instruments else 0)
        self._owner = feature_owner(self.instruments)  # [features]: the instrument reading each

    @property
    def num_instruments(self) -> int:
        """Measure choices per step: k instruments, or 1 (the paper's single switch)."""
        return max(1, len(self.instruments))

    @property
    def _appends(self) -> bool:
        """Whether anything is appended after the flag."""
        return bool(self.extra_obs) or self.budgeted or self.cost_conditioned

    # -- spaces -------------------------------------------------------------------------------

    @property
    def num_controls(self) -> int:
        """Number of control actions of the inner (Discrete) environment."""
        return int(self._inner_action_space.n)

    @property
    def num_actions(self) -> int:
        """2n for Discrete(n) (n 2^k with k instruments); for Box(d), the action dimension 1 + d (k + d)."""
        if isinstance(self._inner_action_space, spaces.Discrete):
            return 2**self.num_instruments * self.num_controls
        return self.num_instruments + self._inner_action_space.shape[0]

    def action_space(self, params: MeasureParams | None = None) -> spaces.Space:
        inner = self._env.action_space(None if params is None else params.env_params)
        k = self.num_instruments
        if isinstance(inner, spaces.Discrete):
            return spaces.Discrete(2**k * inner.n)
        low = jnp.broadcast_to(jnp.asarray(inner.low, jnp.float32), inner.shape)
        high = jnp.broadcast_to(jnp.asarray(inner.high, jnp.float32), inner.shape)
        return spaces.Box(
            jnp.concatenate([jnp.zeros(k), low]),
            jnp.concatenate([jnp.ones(k), high]),
            (inner.shape[0] + k,),
            jnp.float32,
        )

    def _obs_bounds(self, params: MeasureParams) -> tuple[jax.Array, jax.Array]:
        space = self._env.observation_space(params.env_params)
        low = jnp.broadcast_to(jnp.asarray(space.low, jnp.float32), space.shape)
        high = jnp.broadcast_to(jnp.asarray(space.high, jnp.float32), space.shape)
        return low, high

    def observation_space(self, params: MeasureParams | None = None) -> spaces.Box:
        params = self.default_params if params is None else params
        low, high = self._obs_bounds(params)
        if self.flag:
            k = self.num_instruments
            low, high = append_features(low, jnp.zeros(k)), append_features(high, jnp.ones(k))
        if self._appends:
            extra_low, extra_high = self._extra_bounds(params)
            low, high = append_features(low, extra_low), append_features(high, extra_high)
        return spaces.Box(low, high, low.shape, jnp.float32)

    def _extra_bounds(self, params: MeasureParams) -> tuple[jax.Array, jax.Array]:
        """Bounds of the features appended after the flag."""
        low, high = [], []
        for name in self.extra_obs:
            if name == "last_action" and isinstance(self._inner_action_space, spaces.Box):
                inner = self._env.action_space(params.env_params)
                low.append(jnp.broadcast_to(jnp.asarray(inner.low, jnp.float32), inner.shape))
                high.append(jnp.broadcast_to(jnp.asarray(inner.high, jnp.float32), inner.shape))
            else:
                size = self.num_controls if name == "last_action" else self.num_instruments
                low.append(jnp.zeros(size))
                high.append(jnp.ones(size))
        if self.budgeted:
            low.append(jnp.zeros(1))
            high.append(jnp.ones(1))
        if self.cost_conditioned:  # [-1, 1], widened when the draw range leaves the scaling range
            scale = (params.cost_scale_low, params.cost_scale_high)
            low.append(jnp.minimum(-1.0, scaled_cost(params.cost_low, *scale)).reshape(1))
            high.append(jnp.maximum(1.0, scaled_cost(params.cost_high, *scale)).reshape(1))
        return jnp.concatenate(low), jnp.concatenate(high)

    @property
    def default_params(self) -> MeasureParams:
        return MeasureParams(
            env_params=self._env_params,
            cost=jnp.float32(0.0),
            noise_std=jnp.float32(0.0),
            budget=jnp.float32(jnp.inf) if self.budgeted else None,
            instrument_costs=jnp.zeros(len(self.instruments)) if self.instruments else None,
            instrument_noise=jnp.zeros(len(self.instruments)) if self.instruments else None,
            cost_low=jnp.float32(0.0) if self.cost_conditioned else None,
            cost_high=jnp.float32(0.0) if self.cost_conditioned else None,
            cost_scale_low=jnp.float32(0.0) if self.cost_conditioned else None,
            cost_scale_high=jnp.float32(0.0) if self.cost_conditioned else None,
        )

    @property
    def name(self) -> str:
        return f"ActiveMeasure({env_name(self._env)})"

    # -- dynamics -------------------------------------------------------------------------------

    def split_action(self, action: jax.Array) -> tuple[jax.Array, jax.Array]:
        """(control action for the inner env, measure flag) of a wrapped action; with instruments the flag is
        [k], one per instrument."""
        k = len(self.instruments)
        if isinstance(self._inner_action_space, spaces.Discrete):
            if not k:
                return decode_discrete(action, self.num_controls)
            action = jnp.asarray(action, jnp.int32) % self.num_actions
            return action % self.num_controls, decode_mask(action // self.num_controls, k)
        action = jnp.asarray(action, jnp.float32)
        if not k:
            return action[1:], action[0] >= 0.5
        return action[k:], action[:k] >= 0.5

    def _with_flag(self, obs: jax.Array, fresh: jax.Array) -> jax.Array:
        obs = jnp.asarray(obs, jnp.float32)
        if not self.flag:
            return obs
        if self.instruments or obs.ndim > 1:  # one flag per instrument; an image's as channels
            flags = jnp.broadcast_to(jnp.asarray(fresh, jnp.float32), (self.num_instruments,))
            return append_features(obs, flags)
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

    def _initial_counters(self, key: Any = None, params: MeasureParams | None = None) -> dict[str, Any]:
        """The options' counters at an episode's start (None for options that are off); with cost_conditioned,
        the episode's cost drawn from `key` (None: zero, for `_counters_after` to overwrite)."""
        zero = jnp.int32(0)
        if "last_action" not in self.extra_obs:
            last_control = None
        elif isinstance(self._inner_action_space, spaces.Discrete):
            last_control = jnp.zeros(self.num_controls, jnp.float32)
        else:
            last_control = jnp.zeros(self._inner_action_space.shape, jnp.float32)
        since = jnp.zeros(len(self.instruments), jnp.int32) if self.instruments else zero  # per instrument
        return {
            "since_measured": since if "since_measured" in self.extra_obs else None,
            "last_control": last_control,
            "measurements": zero if self.budgeted else None,
            "withheld": jnp.float32(0.0) if self.reward_timing == "on_measure" else None,
            "episode_cost": self._draw_cost(key, params) if self.cost_conditioned else None,
        }

    @staticmethod
    def _draw_cost(key: Any, params: MeasureParams | None) -> jax.Array:
        """An episode's cost, uniform in [cost_low, cost_high], from the wrapper's own stream of `key` (the reset or
        step key)."""
        if key is None:
            return jnp.float32(0.0)
        u = jax.random.uniform(wrapper_key(key, COST_DRAW), (), jnp.float32)
        return params.cost_low + u * (params.cost_high - params.cost_low)

    def _observe(self, obs: jax.Array, fresh: jax.Array, counters: dict[str, Any], params: MeasureParams) -> jax.Array:
        """The agent's observation: `obs`, the flag, then the features the options append."""
        obs = self._with_flag(obs, fresh)
        if not self._appends:
            return obs
        features = []
        for name in self.extra_obs:
            if name == "since_measured":
                horizon = jnp.asarray(params.env_params.max_steps_in_episode, jnp.float32)
                since = jnp.log1p(counters["since_measured"].astype(jnp.float32)) / jnp.log1p(horizon)
                features.append(jnp.minimum(since, 1.0).reshape(-1))
            else:
                features.append(counters["last_control"])
        if self.budgeted:
            used = counters["measurements"].astype(jnp.float32)
            left = jnp.where(params.budget > 0, 1.0 - used / params.budget, 0.0)
            left = jnp.where(used < jnp.floor(params.budget), left, 0.0)  # a hand-set fraction: spent at its floor
            features.append(jnp.clip(left, 0.0, 1.0)[None])
        if self.cost_conditioned:
            seen = scaled_cost(counters["episode_cost"], params.cost_scale_low, params.cost_scale_high)
            features.append(jnp.reshape(seen, (1,)))
        return append_features(obs, jnp.concatenate(features))

    @partial(jax.jit, static_argnames=("self",))
    def reset(self, key: jax.Array, params: MeasureParams | None = None) -> tuple[jax.Array, MeasureState]:
        params = self.default_params if params is None else params
        obs, env_state = self._env.reset(key, params.env_params)
        obs = jnp.asarray(obs, jnp.float32)
        counters = self._initial_counters(key, params)
        return self._observe(obs, True, counters, params), MeasureState(env_state, obs, **counters)

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
        control, measured = self.split_action(action)  # measured: [k] with instruments
        if self.budgeted:
            requested = measured
            if self.instruments:
                measured = served_readings(requested, state.measurements, params.budget)
            else:
                measured = requested & (state.measurements < jnp.floor(params.budget))
        obs, env_state, raw_reward, terminated, truncated, info = self._env.step(
            key_env, state.env_state, control, params.env_params
        )
        done = jnp.logical_or(terminated, truncated)
        true_obs = jnp.asarray(info["final_observation"], jnp.float32)  # before any auto-reset
        unmeasured = self._unmeasured_view(key_view, state.last_obs, true_obs, params)
        if self.instruments:  # each feature refreshes with its instrument, read with that instrument's noise
            any_read = measured.any()
            fresh = measured[self._owner]
            low, high = self._obs_bounds(params)
            draws = jax.random.normal(wrapper_key(key, READING_DRAW), true_obs.shape)
            noise = params.instrument_noise[self._owner] * draws
            reading = jnp.clip(true_obs + noise, low, high)
            cost = self._base_cost(state, params) * any_read + (params.instrument_costs * measured).sum()
        else:
            any_read = fresh = measured
            reading = true_obs
            cost = self._base_cost(state, params) * measured
        seen = jnp.where(fresh, reading, unmeasured)
        remembered = jnp.where(fresh, reading, state.last_obs)
        # On an episode boundary the auto-reset's first observation is a free measurement.
        reset_obs = jnp.asarray(obs, jnp.float32)
        raw_reward = jnp.asarray(raw_reward, jnp.float32)
        counters = self._counters_after(state, control, measured)
        paid = raw_reward
        if self.reward_timing == "on_measure":  # owed rewards are paid on a measurement or at the episode's end
            owed = state.withheld + raw_reward
            paid = jnp.where(any_read | done, owed, 0.0)
            counters["withheld"] = owed - paid
        shown = self._observe(seen, measured, counters, params)  # the pre-reset observation
        fresh_counters = self._initial_counters(key, params)  # the next episode's
        next_counters = jax.tree.map(lambda start, now: jnp.where(done, start, now), fresh_counters, counters)
        if self._appends or self.instruments:
            next_obs = jnp.where(done, self._observe(reset_obs, True, fresh_counters, params), shown)
        else:  # the paper's observation, in the form XLA fuses best (see `_with_flag`)
            next_obs = self._with_flag(jnp.where(done, reset_obs, seen), done | measured)
        next_state = MeasureState(env_state, jnp.where(done, reset_obs, remembered), **next_counters)
        info = {**info, "final_observation": shown, "cost": cost, "measured": any_read, "raw_reward": paid}
        if self.instruments:
            info["readings"] = measured
        if self.reward_timing == "on_measure":
            info["withheld"] = counters["withheld"]
            cut_stale = truncated & ~terminated & ~any_read
            info["paid_at_truncation"] = jnp.where(cut_stale, owed, 0.0)
        if self.budgeted:
            info["refused"] = requested & ~measured
        return next_obs, next_state, paid - cost, terminated, truncated, info

    def _base_cost(self, state: MeasureState, params: MeasureParams) -> jax.Array:
        """The cost per measurement: this episode's draw with cost_conditioned, else `params.cost`."""
        return state.episode_cost if self.cost_conditioned else params.cost

    def _counters_after(self, state: MeasureState, control: jax.Array, measured: jax.Array) -> dict[str, Any]:
        """The options' counters after this step (before an auto-reset restarts them); `step` sets the reward
        owed (`withheld`)."""
        counters = self._initial_counters()
        counters["episode_cost"] = state.episode_cost
        if counters["since_measured"] is not None:
            counters["since_measured"] = jnp.where(measured, 0, state.since_measured + 1)
        if counters["last_control"] is not None:
            if isinstance(self._inner_action_space, spaces.Discrete):
                counters["last_control"] = jax.nn.one_hot(control, self.num_controls, dtype=jnp.float32)
            else:
                counters["last_control"] = jnp.asarray(control, jnp.float32)
        if counters["measurements"] is not None:
            counters["measurements"] = state.measurements + measured.astype(jnp.int32).sum()
        return counters


def check_measure_setup(vanilla: Any, mode: Any, noise_std: Any, options: dict[str, bool] | None = None) -> None:
    """The one check of the view settings that `amjax.make`, the agent configs (`AgentConfig.validate`) and the
    NumPy `ActiveMeasureWrapper` share, on concrete values before anything is compiled.

    `vanilla` and `mode` must be allowed values. A vanilla run (the plain env) hides no state: mode "last", no
    noise_std and none of `options` (the caller's active-measure arguments, by name, True where set). Mode "noisy"
    needs noise_std > 0 (0 would show the true state unmeasured: a vanilla run with a useless measure action); the
    other modes take none. noise_std None or 0 is unset (a config's default is 0.0); an array (for vmap) is checked
    element-wise; a traced one is skipped (its caller checked the concrete values). ValueError naming the argument
    otherwise."""
    check_bool("vanilla", vanilla)
    check_choice("mode", mode, MODES)
    traced = is_traced(noise_std)
    std = None if noise_std is None or traced else check_real("noise_std", noise_std, low=0.0)
    std_set = std is not None and bool(std.any())
    if vanilla:
        given = [
            name for name, on in (("mode", mode != "last"), ("noise_std", std_set), *(options or {}).items()) if on
        ]
        if given:
            raise ValueError(
                f"vanilla: a vanilla run is the plain env and never hides a state, so it takes no "
                f"{', '.join(given)}; allowed: vanilla=False, or those left at their defaults (mode "
                "'last', no noise_std, no measurement options)"
            )
        return
    if mode == "noisy" and not traced and (std is None or not bool((std > 0).all())):
        raise ValueError(
            f"noise_std: mode 'noisy' needs noise_std, finite numbers > 0 (got {noise_std!r}; 0 shows the "
            "true state unmeasured)"
        )
    if mode != "noisy" and std_set:
        raise ValueError(f"noise_std: only used with mode 'noisy' (mode is {mode!r}); allowed here: 0 or None")


def check_extra_obs(extra_obs: Any) -> tuple[str, ...]:
    """`extra_obs` as a tuple of distinct names from `EXTRA_OBS`; ValueError naming the allowed ones otherwise."""
    if isinstance(extra_obs, str) or not isinstance(extra_obs, tuple | list):
        raise ValueError(
            f"extra_obs: got {extra_obs!r}; allowed values: a tuple of names from {EXTRA_OBS}, "
            "e.g. ('since_measured',), or ()"
        )
    for name in extra_obs:
        check_choice("extra_obs", name, EXTRA_OBS)
    if len(set(extra_obs)) != len(extra_obs):
        raise ValueError(f"extra_obs: repeated names in {list(extra_obs)}")
    return tuple(extra_obs)


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
