"""`amjax.make`: an environment id -> an active-measure environment and its params."""

from __future__ import annotations

from typing import Any

import jax.numpy as jnp
from gymnax.environments.environment import Environment

from amjax.envs.registry import make_env
from amjax.validation import check_bool, check_real, check_whole_number
from amjax.wrappers.active_measure import (
    ActiveMeasure,
    AlwaysMeasured,
    MeasureParams,
    check_measure_setup,
)
from amjax.wrappers.instruments import check_instrument_values, resolve_instruments


def make(
    env_id: str,
    cost: Any = 0.0,
    mode: str = "last",
    flag: bool = True,
    noise_std: Any = None,
    vanilla: bool = False,
    extra_obs: tuple[str, ...] = (),
    budget: Any = None,
    reward_timing: str = "immediate",
    instruments: Any = (),
    instrument_costs: Any = None,
    instrument_noise: Any = None,
    cost_range: Any = None,
) -> tuple[Environment, Any]:
    """Build `env_id` wrapped as an active-measure MDP; returns `(env, params)`.

    Args:
      env_id: "CartPole-v0" (200 steps, the paper's), "CartPole-v1", "Acrobot-v1", "LunarLander-v3", any
        gymnax id, `"brax:<env_name>[:<backend>]"` for a brax environment (needs `pip install "amjax-rl[brax]"`;
        docs/brax.md), or one added with `amjax.envs.register`.
      cost: charged per measurement (>= 0, finite). A number or an array of numbers (then vmap over params).
      mode: what the agent sees without measuring: "last" (the last measured observation), "random"
        (a sample of the observation space) or "noisy" (true observation + N(0, noise_std^2)).
      flag: append 1 (fresh) / 0 (stale) to the observation.
      noise_std: standard deviation for mode "noisy" (required there, > 0; elsewhere None or 0). These three are
        checked by `check_measure_setup`, the agent configs' check too.
      vanilla: return the plain environment instead (always measured, cost 0, same info keys); it takes mode
        "last" and none of the other measurement arguments.
      extra_obs: features appended to the observation after the flag: "since_measured" (steps since the shown
        observation was measured, log-scaled to [0, 1]) and/or "last_action" (the last control action).
      budget: at most this many paid measurements per episode (a whole number >= 0, e.g. 3 or 3.0; a number or an
        array, traced like the cost);
        requests beyond it are not carried out, and the remaining fraction is appended to the observation. None:
        no budget.
      reward_timing: "immediate" (the paper's) or "on_measure": the raw reward of unmeasured steps is withheld and
        paid, summed, at the next measurement or at the episode's end.
      instruments: read the observation in parts: a tuple of instruments, each a tuple of observation indices,
        together holding every index once (e.g. ((0, 1), (2, 3)) for CartPole's cart and pole), or "default"
        (`amjax.wrappers.instruments.DEFAULT_INSTRUMENTS`). The action then picks a control and a subset of
        instruments (Discrete(n) -> Discrete(n 2^k), `control + n * mask`); each instrument has its own flag.
        () is the paper's single switch.
      instrument_costs: the price of reading each instrument (k numbers >= 0, traced; default zeros); `cost` is
        then charged once per step on which any instrument is read.
      instrument_noise: the std of each instrument's Gaussian reading noise (k numbers >= 0, traced; default 0).
      cost_range: (low, high): each episode draws its cost uniformly from [low, high] (traced; `cost` must then be
        0) and the cost, scaled from [low, high] to [-1, 1] (0 when low = high), is appended, last, to the
        observation, for one agent conditioned on every cost of the range. To score such an agent at cost c, keep
        the scaling range and draw c: `params.replace(cost_low=c, cost_high=c)`. None: the fixed `cost`.
    """
    check_bool("flag", flag)
    cost = check_real("cost", cost, low=0.0)
    options = {
        "cost": bool(cost.any()),
        "extra_obs": bool(extra_obs),
        "budget": budget is not None,
        "reward_timing": reward_timing != "immediate",
        "instruments": instruments != (),
        "instrument_costs": instrument_costs is not None,
        "instrument_noise": instrument_noise is not None,
        "cost_range": cost_range is not None,
    }
    check_measure_setup(vanilla, mode, noise_std, options)  # the agent configs' check too
    if vanilla:
        return wrap(env_id, vanilla=True)
    if budget is not None:  # extra_obs and reward_timing: the wrapper checks them
        budget = check_whole_number("budget", budget)
    noise_std = 0.0 if noise_std is None else check_real("noise_std", noise_std, low=0.0)
    if cost_range is not None:
        cost_range = check_cost_range(cost_range, cost)
    wrapped, env_params = wrap(
        env_id,
        mode,
        flag,
        extra_obs=extra_obs,
        budgeted=budget is not None,
        reward_timing=reward_timing,
        instruments=instruments,
        cost_conditioned=cost_range is not None,
    )
    k = len(wrapped.instruments)
    prices = {
        name: ([0.0] * k if k else None) if value is None else check_instrument_values(name, value, k, batched=True)
        for name, value in (("instrument_costs", instrument_costs), ("instrument_noise", instrument_noise))
    }
    return wrapped, measure_params(env_params, cost, noise_std, budget, **prices, cost_range=cost_range)


def check_cost_range(cost_range: Any, cost: Any) -> tuple[Any, Any]:
    """(low, high) with 0 <= low <= high, finite (arrays allowed, for vmap), and no fixed `cost` beside it."""
    if not isinstance(cost_range, tuple | list) or len(cost_range) != 2:
        raise ValueError(
            f"cost_range: got {cost_range!r}; allowed values: a pair (low, high) of finite numbers "
            "with 0 <= low <= high"
        )
    low, high = (check_real("cost_range", value, low=0.0) for value in cost_range)
    if (low > high).any():
        raise ValueError(f"cost_range: got {cost_range!r}; allowed values: low <= high")
    if check_real("cost", cost, low=0.0).any():
        raise ValueError("cost: a cost-conditioned env draws each episode's cost from cost_range; allowed: 0")
    return low, high


def wrap(
    env_id: str,
    mode: str = "last",
    flag: bool = True,
    vanilla: bool = False,
    extra_obs: tuple[str, ...] = (),
    budgeted: bool = False,
    reward_timing: str = "immediate",
    instruments: Any = (),
    cost_conditioned: bool = False,
) -> tuple[Environment, Any]:
    """The wrapped environment and the *inner* env's params, unchecked (`make` checks its arguments first).

    The trainers call this with a config's static fields and build the params from its traced cost and noise with
    `measure_params`, so traced values go straight into the params."""
    env, env_params = make_env(env_id)
    if vanilla:
        return AlwaysMeasured(env, env_params), env_params
    wrapped = ActiveMeasure(
        env,
        mode,
        flag,
        env_params,
        extra_obs,
        budgeted,
        reward_timing,
        resolve_instruments(env_id, instruments),
        cost_conditioned,
    )
    return wrapped, env_params


def measure_params(
    env_params: Any,
    cost: Any,
    noise_std: Any,
    budget: Any = None,
    instrument_costs: Any = None,
    instrument_noise: Any = None,
    cost_range: Any = None,
) -> MeasureParams:
    """`MeasureParams` around the inner env's params; `cost`, `noise_std`, `budget` (None: no budget) and the
    instruments' prices and noise ([k]; None: no instruments) and the cost range ((low, high); None: a fixed cost)
    may be traced (float32 arrays)."""

    def optional(value: Any) -> Any:
        return None if value is None else jnp.asarray(value, jnp.float32)

    low, high = (None, None) if cost_range is None else map(optional, cost_range)
    return MeasureParams(
        env_params=env_params,
        cost=jnp.asarray(cost, jnp.float32),
        noise_std=jnp.asarray(noise_std, jnp.float32),
        budget=optional(budget),
        instrument_costs=optional(instrument_costs),
        instrument_noise=optional(instrument_noise),
        cost_low=low,  # the draw range; evaluating at another cost changes it ...
        cost_high=high,
        cost_scale_low=low,  # ... and keeps the training range the cost is scaled by
        cost_scale_high=high,
    )
