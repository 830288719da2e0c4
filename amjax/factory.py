"""`amjax.make`: an environment id -> an active-measure environment and its params; `amjax.wrap`: the same for an
environment object of your own (any gymnax-API env)."""

from __future__ import annotations

import inspect
from typing import Any

from gymnax.environments.environment import Environment

from amjax.validation import check_bool, check_real, check_whole_number
from amjax.wrappers.active_measure import check_measure_setup
from amjax.wrappers.instruments import check_instrument_values
from amjax.wrappers.spec import MeasureSpec


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
    *,
    spec: MeasureSpec | None = None,
) -> tuple[Environment, Any]:
    """Build `env_id` wrapped as an active-measure MDP; returns `(env, params)`.

    The measurement arguments below are a shorthand for a `MeasureSpec` (`amjax.wrappers.spec`, where every option
    is declared once); `make(env_id, spec=MeasureSpec(...))` takes one directly (an agent config is one too:
    `make(config.env_id, spec=config)` builds the env that config trains on).

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
      spec: the whole measurement setting as one `MeasureSpec` (checked by `MeasureSpec.check_measure`); the other
        measurement arguments must then be left at their defaults.
    """
    return _wrapped(env_id, None, None, locals())


def wrap(
    env: Any, env_params: Any = None, *, name: str | None = None, spec: MeasureSpec | None = None, **options: Any
) -> tuple[Environment, Any]:
    """Wrap `env`, a JAX environment of your own, as an active-measure MDP; returns `(env, params)` as
    `amjax.make` does, with every measurement option.

    Args:
      env: any environment with gymnax 1.0's API (`reset(key, params)`, `step(key, state, action, params)`
        returning `(obs, state, reward, terminated, truncated, info)` with `info["final_observation"]`,
        `observation_space(params)`, `action_space(params)`, `default_params`): a subclass of gymnax's
        `Environment` has all of it. A Discrete or 1-D Box action space, a Box observation space.
      env_params: its params (default: `env.default_params`).
      name: what errors and `instruments="default"` call it (default: the class name).
      spec: the measurement setting as one `MeasureSpec` (as `amjax.make` takes it); or instead:
      **options: `amjax.make`'s measurement keywords (`cost=0.1, mode="noisy", noise_std=0.1, budget=3, ...`).
    """
    missing = [attr for attr in ("reset", "step", "observation_space", "action_space") if not hasattr(env, attr)]
    if env_params is None and not hasattr(env, "default_params"):
        missing.append("default_params")
    if missing:
        raise TypeError(
            f"env: a {type(env).__name__} lacks {', '.join(missing)}; allowed: an environment with gymnax 1.0's API "
            "(a subclass of gymnax.environments.environment.Environment has it), with env_params given if it has "
            "no default_params"
        )
    keywords = _measure_keywords()
    unknown = sorted(set(options) - set(keywords))
    if unknown:
        raise TypeError(f"{', '.join(unknown)}: not a measurement option; allowed: {', '.join(keywords)}, spec")
    env_params = env.default_params if env_params is None else env_params
    return _wrapped(name or type(env).__name__, env, env_params, {**keywords, **options, "spec": spec})


def _wrapped(env_id: str, env: Any, env_params: Any, arguments: dict[str, Any]) -> tuple[Environment, Any]:
    """`make`'s work for its `arguments`: `env_id` built from the registry, or `env` (with `env_params`) wrapped
    under that name."""
    if arguments["spec"] is not None:
        return _make_from_spec(env_id, env, env_params, arguments)
    flag, mode, vanilla, noise_std = (arguments[k] for k in ("flag", "mode", "vanilla", "noise_std"))
    extra_obs, budget, reward_timing, instruments = (
        arguments[k] for k in ("extra_obs", "budget", "reward_timing", "instruments")
    )
    instrument_costs, instrument_noise, cost_range = (
        arguments[k] for k in ("instrument_costs", "instrument_noise", "cost_range")
    )
    check_bool("flag", flag)
    cost = check_real("cost", arguments["cost"], low=0.0)
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
    if budget is not None:  # extra_obs and reward_timing: the wrapper checks them
        budget = check_whole_number("budget", budget)
    noise_std = 0.0 if noise_std is None else check_real("noise_std", noise_std, low=0.0)
    if cost_range is not None:
        cost_range = check_cost_range(cost_range, cost)
    low, high = (0.0, 0.0) if cost_range is None else cost_range
    spec = MeasureSpec(
        mode=mode,
        flag=flag,
        vanilla=vanilla,
        extra_obs=extra_obs,
        budgeted=budget is not None,
        reward_timing=reward_timing,
        instruments=instruments,
        cost_conditioned=cost_range is not None,
        cost=cost,
        noise_std=noise_std,
        budget=0.0 if budget is None else budget,
        cost_low=low,
        cost_high=high,
    )
    # The wrapper checks extra_obs, reward_timing and the instruments.
    env, env_params = spec.wrap_env(env_id, env, env_params)
    given = {"instrument_costs": instrument_costs, "instrument_noise": instrument_noise}
    k = 0 if vanilla else len(env.instruments)
    spec = spec.replace(
        **{
            name: check_instrument_values(name, value, k, batched=True)
            for name, value in given.items()
            if value is not None
        }
    )
    return env, spec.measure_params(env, env_params)


def _measure_keywords() -> dict[str, Any]:
    """`make`'s measurement keywords (all but `env_id` and `spec`) and their defaults."""
    return {name: p.default for name, p in inspect.signature(make).parameters.items() if name not in ("env_id", "spec")}


def _make_from_spec(env_id: str, env: Any, env_params: Any, arguments: dict[str, Any]) -> tuple[Environment, Any]:
    """`make(env_id, spec=spec)` (or `wrap(env, spec=spec)`): the spec checked and built, once no other
    measurement argument is given."""
    spec = arguments["spec"]
    if not isinstance(spec, MeasureSpec):
        raise TypeError(f"spec: got {type(spec).__name__}; allowed: a MeasureSpec (or an agent config)")
    given = [
        name
        for name, default in _measure_keywords().items()
        if not (arguments[name] is default or _equal(arguments[name], default))
    ]
    if given:
        raise ValueError(
            f"spec: given with {', '.join(given)}; allowed: the measurement setting either as a spec or as "
            "arguments (set those fields in the spec instead)"
        )
    return spec.measure_spec().make(env_id, env, env_params)


def _equal(value: Any, default: Any) -> bool:
    """Whether an argument is its default (a plain value equal to it; an array counts as given)."""
    return isinstance(value, bool | int | float | str | tuple) and value == default


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
