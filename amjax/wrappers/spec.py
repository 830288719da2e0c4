"""`MeasureSpec`: the measurement setting in one object, the one place its options are declared.

Static fields say how the environment is wrapped and the agent reads it (they set observation and action shapes, so
each value is its own compiled program); traced fields are the prices and noise levels that go into
`MeasureParams` (pytree leaves: a sweep stacks many values and vmaps one program over them).

Who takes it:
- `amjax.make(env_id, spec=MeasureSpec(...))`, or `spec.make(env_id)`: the checked route to `(env, params)`;
  `amjax.make`'s keyword arguments are a shorthand that builds one;
- the agent configs *are* one: `AgentConfig` subclasses `MeasureSpec`, so a config's `cost`, `flag`, `budget`,
  ... are these fields (no copies), `--set NAME=V` reaches them by name and `config.measure_spec()` is the
  setting alone;
- the sweep grid's `MEASURE_FIELDS` (the fields a vanilla run does not take) come from here;
- `ActiveMeasureWrapper.from_spec(gymnasium_env, spec)`: the NumPy wrapper for a Gymnasium env.

Adding an option: a field here (static or traced), its check in `check_measure`, its argument in `ActiveMeasure`
(passed by `wrap_env`) or its leaf in `MeasureParams` (filled by `measure_params`), and its tests.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from gymnax.environments.environment import Environment

from amjax.envs.registry import make_env
from amjax.validation import check_bool, check_choice, check_real, check_whole_number, is_traced
from amjax.wrappers.active_measure import (
    REWARD_TIMINGS,
    ActiveMeasure,
    AlwaysMeasured,
    MeasureParams,
    check_extra_obs,
    check_measure_setup,
)
from amjax.wrappers.instruments import check_instruments, resolve_instruments
from amjax.wrappers.observations import standard_observations

MEASURE_HEADS = ("joint", "factored")
# The traced fields' allowed values: >= 0, finite; "budget" a whole number. The instruments' are checked per
# instrument (`check_instrument_fields`).
_NONNEGATIVE = ("cost", "noise_std", "cost_low", "cost_high")


def static(default: Any) -> Any:
    """A field that sets a shape or a count: part of the compiled program, never vmapped."""
    return struct.field(pytree_node=False, default=default)


@struct.dataclass
class MeasureSpec:
    """The active-measure setting: static fields (a new program per value) and traced ones (leaves).

    Every field's default is the paper's setting (mode "last", the flag, one switch, immediate rewards)."""

    # -- static --------------------------------------------------------------------------------------
    mode: str = static("last")  # what an unmeasured step shows: "last", "random" or "noisy"
    flag: bool = static(True)  # append the fresh/stale flag to observations
    vanilla: bool = static(False)  # the plain env: no measure action, no cost (the paper's baseline)
    extra_obs: tuple[str, ...] = static(())  # "since_measured" and/or "last_action", appended after the flag
    budgeted: bool = static(False)  # enforce `budget` (and show the fraction left)
    reward_timing: str = static("immediate")  # or "on_measure": raw rewards paid at the next measurement
    # () (the paper's single switch), "default" (the env's split) or a tuple of observation-index tuples
    instruments: Any = static(())
    # "joint" (the paper's one output per (control, measure) pair) or "factored" (a control head and a measure head)
    measure_head: str = static("joint")
    # one agent for a range of costs: each episode's cost drawn from [cost_low, cost_high] and observed
    cost_conditioned: bool = static(False)
    # -- traced --------------------------------------------------------------------------------------
    cost: float = 0.0  # charged per measurement (with instruments: per step with any reading)
    noise_std: float = 0.0  # std of the observation noise in mode "noisy" (> 0 there; 0 elsewhere)
    budget: float = 0.0  # paid measurements allowed per episode (with budgeted=True; a whole number)
    instrument_costs: tuple[float, ...] = ()  # the price of each instrument (() = zeros)
    instrument_noise: tuple[float, ...] = ()  # the std of each instrument's reading noise (() = zeros)
    cost_low: float = 0.0  # with cost_conditioned, the range episodes draw their cost from
    cost_high: float = 0.0

    @classmethod
    def measure_fields(cls) -> tuple[str, ...]:
        """The names of the measurement fields (`MeasureSpec`'s own, not a subclass's)."""
        return tuple(f.name for f in dataclasses.fields(MeasureSpec))

    def measure_spec(self) -> MeasureSpec:
        """The measurement setting alone (of an agent config: without the agent's fields)."""
        return MeasureSpec(**{name: getattr(self, name) for name in MeasureSpec.measure_fields()})

    # -- checks ---------------------------------------------------------------------------------------

    def check_measure(self, env_id: str, env: Environment | None = None, env_params: Any = None) -> int:
        """Check every measurement field for `env_id` on concrete values, before anything compiles (traced values,
        under jit or vmap, are skipped: their caller checked them); returns the number of instruments (0: the
        paper's single switch). `env` / `env_params`: the plain env, if the caller already built it. ValueError
        naming the field and its allowed values otherwise."""
        if env is None:
            env, env_params = make_env(env_id)
        env = standard_observations(env, env_params)
        check_bool("flag", self.flag)
        check_bool("vanilla", self.vanilla)
        check_extra_obs(self.extra_obs)
        check_bool("budgeted", self.budgeted)
        check_choice("reward_timing", self.reward_timing, REWARD_TIMINGS)
        num_instruments = self.check_instrument_fields(env_id, env, env_params)
        check_choice("measure_head", self.measure_head, MEASURE_HEADS)
        check_bool("cost_conditioned", self.cost_conditioned)
        space = type(env.action_space(env_params)).__name__
        if self.measure_head == "factored" and (self.vanilla or space != "Discrete"):
            raise ValueError(
                "measure_head: 'factored' splits a Discrete control's (control, measure) pairs; "
                + (
                    "a vanilla run has no measure choice"
                    if self.vanilla
                    else f"{env_id}'s {space} control already has a measure entry of its own"
                )
                + "; allowed there: 'joint'"
            )
        for name in (*_NONNEGATIVE, "budget"):
            value = getattr(self, name)
            if is_traced(value):
                continue
            if name == "budget":
                check_whole_number(name, value)
            else:
                check_real(name, value, low=0.0)
        self.check_measure_setup()
        self.check_cost_range()
        if not self.budgeted and not is_traced(self.budget) and np.any(np.asarray(self.budget)):
            raise ValueError("budget: set budgeted=True to enforce a measurement budget (budget is ignored without)")
        return num_instruments

    def check_measure_setup(self) -> None:
        """mode, noise_std and vanilla as `amjax.make` checks them (`check_measure_setup`, one check for both; a
        noise_std of 0, the default, is unset); a vanilla run takes none of the measurement options."""
        cost_set = not is_traced(self.cost) and bool(np.any(np.asarray(self.cost)))
        options = {
            "cost": cost_set,
            "extra_obs": bool(self.extra_obs),
            "budgeted": self.budgeted,
            "reward_timing": self.reward_timing != "immediate",
            "instruments": self.instruments != (),
            "instrument_costs": is_given(self.instrument_costs),
            "instrument_noise": is_given(self.instrument_noise),
            "cost_conditioned": self.cost_conditioned,
        }
        check_measure_setup(self.vanilla, self.mode, self.noise_std, options)

    def check_cost_range(self) -> None:
        """With cost_conditioned: cost_low <= cost_high and no fixed cost; without: the range left at zero."""
        values = (self.cost, self.cost_low, self.cost_high)
        if any(is_traced(v) for v in values):
            return
        cost, low, high = (np.asarray(v) for v in values)
        if self.cost_conditioned:
            if np.any(low > high):
                raise ValueError(f"cost_low: got {low}, above cost_high {high}; allowed: cost_low <= cost_high")
            if np.any(cost):
                raise ValueError(
                    "cost: a cost-conditioned run draws each episode's cost from [cost_low, cost_high]; "
                    "allowed values: 0 (e.g. --cost 0 --set cost_conditioned=True --set cost_high=0.5)"
                )
        elif np.any(low) or np.any(high):
            raise ValueError(
                "cost_low, cost_high: set cost_conditioned=True to draw costs from a range (they are ignored without)"
            )

    def check_instrument_fields(self, env_id: str, env: Environment, env_params: Any) -> int:
        """Check `instruments` and their prices and noise (a tuple of one number >= 0 per instrument, () for zeros,
        or an array whose last axis has that length); returns the number of instruments."""
        instruments = resolve_instruments(env_id, self.instruments)
        instruments = check_instruments(instruments, env.observation_space(env_params).shape[-1])
        for name in ("instrument_costs", "instrument_noise"):
            value = getattr(self, name)
            if not isinstance(value, tuple | np.ndarray | jax.Array):
                raise ValueError(
                    f"{name}: got {value!r}; allowed values: a tuple of numbers >= 0, one per instrument, "
                    "or () for zeros"
                )
            length = len(value) if isinstance(value, tuple) else (np.shape(value)[-1:] or (1,))[0]
            if is_given(value) and length != len(instruments):
                raise ValueError(
                    f"{name}: got {length} values for {len(instruments)} instruments; allowed: one "
                    "number >= 0 per instrument, or () for zeros" + ("" if instruments else " (set instruments first)")
                )
            if is_given(value) and not is_traced(value):
                check_real(name, value, low=0.0)
        return len(instruments)

    # -- building the env -----------------------------------------------------------------------------

    def wrap_env(self, env_id: str, env: Environment | None = None, env_params: Any = None) -> tuple[Environment, Any]:
        """The wrapped environment (static fields only) and the *inner* env's params; unchecked (`make` checks).
        `env` / `env_params`: the plain env to wrap (`amjax.wrap`'s), else `make_env(env_id)`'s; `env_id` then
        names it (and picks its default instruments)."""
        if env is None:
            env, env_params = make_env(env_id)
        env = standard_observations(env, env_params)  # Discrete as one-hot, 2-D as a one-channel image
        if self.vanilla:
            return AlwaysMeasured(env, env_params), env_params
        wrapped = ActiveMeasure(
            env,
            mode=self.mode,
            flag=self.flag,
            env_params=env_params,
            extra_obs=self.extra_obs,
            budgeted=self.budgeted,
            reward_timing=self.reward_timing,
            instruments=resolve_instruments(env_id, self.instruments),
            cost_conditioned=self.cost_conditioned,
        )
        return wrapped, env_params

    def measure_params(self, env: Environment, env_params: Any) -> Any:
        """The params of `env` (from `wrap_env`): `MeasureParams` holding this spec's traced values (as they are:
        traced values stay traced, concrete ones become float32 arrays) around the inner `env_params`; a vanilla
        env's are the inner params."""
        if self.vanilla:
            return env_params
        k = len(env.instruments)

        def optional(value: Any) -> Any:
            return None if value is None else jnp.asarray(value, jnp.float32)

        def per_instrument(value: Any) -> Any:
            return None if not k else optional(value if is_given(value) else (0.0,) * k)

        low, high = (optional(self.cost_low), optional(self.cost_high)) if self.cost_conditioned else (None, None)
        return MeasureParams(
            env_params=env_params,
            cost=optional(self.cost),
            noise_std=optional(self.noise_std),
            budget=optional(self.budget) if self.budgeted else None,
            instrument_costs=per_instrument(self.instrument_costs),
            instrument_noise=per_instrument(self.instrument_noise),
            cost_low=low,  # the draw range; evaluating at another cost changes it ...
            cost_high=high,
            cost_scale_low=low,  # ... and keeps the training range the cost is scaled by
            cost_scale_high=high,
        )

    def make(self, env_id: str, env: Environment | None = None, env_params: Any = None) -> tuple[Environment, Any]:
        """`env_id` wrapped as this spec says, checked first; returns `(env, params)` as `amjax.make` does.
        `env` / `env_params`: a plain env to wrap instead of `make_env(env_id)`'s (`amjax.wrap`)."""
        if env is None:
            env, env_params = make_env(env_id)
        self.check_measure(env_id, env, env_params)
        env, env_params = self.wrap_env(env_id, env, env_params)
        return env, self.measure_params(env, env_params)


def is_given(value: Any) -> bool:
    """Whether instrument prices / noise were given (not the empty tuple that means zeros)."""
    return not (isinstance(value, tuple) and not value)
