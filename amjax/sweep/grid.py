"""Sweep grids: the cartesian product envs x agents x costs x seeds x hyperparameter values, split into groups
that share one compiled program (same env, agent and static fields); within a group everything is vmapped."""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import json
import math
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from amjax.agents import ALGORITHMS, AgentConfig
from amjax.agents.config import nearest_schedule
from amjax.envs.registry import make_env
from amjax.presets import ENV_PRESETS, for_agents
from amjax.validation import check_choice, check_positive_int, check_real
from amjax.wrappers.spec import MeasureSpec

# Fields that define the sweep's schedule and evaluation points: one value for the whole sweep.
SCHEDULE_FIELDS = ("total_timesteps", "eval_every", "eval_episodes")
# Fields the grid itself sets.
GRID_FIELDS = ("env_id", "cost", "vanilla")
# The measurement fields (`MeasureSpec`'s) a vanilla run (the plain env) does not take, so it is not multiplied by
# them: all but the grid's own (cost, vanilla) and the view settings every run shares (mode, flag).
MEASURE_FIELDS = tuple(name for name in MeasureSpec.measure_fields() if name not in (*GRID_FIELDS, "mode", "flag"))


@dataclass(frozen=True)
class SweepSpec:
    """What to train: every combination of the listed values.

    `hyperparams` maps a config field to the values to sweep (a list) or one value (anything else, a tuple such as
    `hidden=(64, 64)` included); it applies to every agent whose config has that field, and `"agent.field"` (e.g.
    `"ppo.num_envs"`) to that agent only, overriding an unscoped value of the same field. Traced fields (learning
    rate, gamma, ...) are vmapped within one compiled program; static fields (network widths, num_envs, ...) compile
    one program per value. `vanilla` adds, per env, agent and seed, a run on the plain environment (the paper's
    baseline; per combination of the other hyperparameters, not of the active-measure ones in `MEASURE_FIELDS`,
    which a plain env does not take). `env_defaults` maps an env id to hyperparameter values (same keys as
    `hyperparams`, one value each) that its configurations start from; `hyperparams` override them. None (the
    default) is each env's tuned presets (`amjax.presets.ENV_PRESETS`, what the commands apply), {} none.

    Seeds are paired by design: every configuration with seed s starts from `jax.random.PRNGKey(s)`, whatever its
    cost, agent or hyperparameters, so configurations that differ only in cost share their network initialisation,
    training env resets and action noise, and all configurations of one env and seed are tested on the same
    evaluation and re-scoring episodes. Differences between costs or agents at one seed are then paired
    comparisons, not differences of luck; independent replicates come from different seeds. Seeds are 32-bit
    (0 <= s < 2**32): `PRNGKey` keeps only the low 32 bits, so larger seeds would alias smaller ones.
    """

    envs: tuple[str, ...] = ("CartPole-v0",)
    agents: tuple[str, ...] = ("dqn", "ppo")
    costs: tuple[float, ...] = (0.0, 0.1, 0.2, 0.3)
    seeds: tuple[int, ...] = tuple(range(3))
    total_timesteps: int = 102_400
    eval_every: int = 10_240
    eval_episodes: int = 10
    vanilla: bool = False
    mode: str = "last"
    hyperparams: Mapping[str, Any] = field(default_factory=dict)
    env_defaults: Mapping[str, Mapping[str, Any]] | None = None

    def resolved_env_defaults(self) -> Mapping[str, Mapping[str, Any]]:
        """`env_defaults`, or (None) the tuned presets of this sweep's envs that have some."""
        if self.env_defaults is not None:
            return self.env_defaults
        return {env: dict(ENV_PRESETS[env]) for env in self.envs if env in ENV_PRESETS}

    def to_json(self) -> dict[str, Any]:
        """The spec as JSON (what a sweep folder's metadata holds), with `env_defaults` resolved."""
        data = dataclasses.asdict(self) | {"env_defaults": self.resolved_env_defaults()}
        return json.loads(json.dumps(data, default=list))

    def identity(self) -> dict[str, Any]:
        """What makes two specs the same sweep: `to_json` with each env's defaults cut to the keys that reach this
        sweep's agents (unscoped ones and those scoped to one of them), so that a preset added later for another
        agent does not change the identity of a folder made before it."""
        data = self.to_json()
        data["env_defaults"] = {
            env: kept for env, values in data["env_defaults"].items() if (kept := for_agents(values, self.agents))
        }
        return data

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> SweepSpec:
        """The spec `to_json` wrote (a cluster worker's, or a folder's metadata). JSON keeps no tuples, so they are
        restored by field: an `env_defaults` value is always one value, and a hyperparameter's list is a list of
        values unless the field holds tuples and the list is one such tuple (`is_swept`)."""
        data = dict(data)
        for name in ("envs", "agents", "costs", "seeds"):
            data[name] = tuple(data[name])
        fields = _fields_of(data["agents"])
        hyperparams = {}
        for key, value in data.get("hyperparams", {}).items():
            name = split_hyperparam(key)[1]
            swept = is_swept(name, value, fields.get(name))
            hyperparams[key] = [_tuples(v) for v in value] if swept else _tuples(value)
        data["hyperparams"] = hyperparams
        if data.get("env_defaults") is not None:
            data["env_defaults"] = {
                env: {key: _tuples(value) for key, value in values.items()}
                for env, values in data["env_defaults"].items()
            }
        return cls(**data)


def _tuples(value: Any) -> Any:
    """JSON lists back to (nested) tuples."""
    return tuple(_tuples(v) for v in value) if isinstance(value, list) else value


def _fields_of(agents: Sequence[str]) -> dict[str, dataclasses.Field]:
    """Config field name -> its dataclass field, over `agents` (the first agent that has it; unknown agents none)."""
    fields: dict[str, dataclasses.Field] = {}
    for agent in agents:
        if agent in ALGORITHMS:
            for name, f in ALGORITHMS[agent].config_type.__dataclass_fields__.items():
                fields.setdefault(name, f)
    return fields


def is_swept(name: str, value: Any, field_: dataclasses.Field | None) -> bool:
    """Whether a hyperparameter value read from JSON (where tuples became lists) is a list of values to sweep: a
    list, unless its field holds tuples (`field_`'s default is one) and the list is one such value (a list of
    scalars, or empty). `instruments` is one value when it is "default" or a list of index lists."""
    if not isinstance(value, list):
        return False
    if name == "instruments":  # one value: "default" or a list of index lists
        return all(v == "default" or (isinstance(v, list) and all(isinstance(w, list) for w in v)) for v in value)
    sequence_field = field_ is not None and isinstance(field_.default, tuple)
    return not sequence_field or (bool(value) and all(isinstance(v, list) for v in value))  # [] is ()


@dataclass(frozen=True)
class RunConfig:
    """One configuration of the grid: its identity, its seed and its full agent config (the one copy of its env,
    cost and every other field)."""

    config_id: str
    agent: str
    seed: int
    hyperparams: dict[str, Any]  # the swept values of this configuration (only the swept fields)
    config: AgentConfig

    @property
    def env(self) -> str:
        return self.config.env_id

    @property
    def vanilla(self) -> bool:
        return self.config.vanilla

    @property
    def cost(self) -> float:
        return float(self.config.cost)


def _as_values(name: str, value: Any) -> list[Any]:
    """A list holds the values to sweep; anything else (a tuple such as hidden=(64, 64) included) is one value."""
    if isinstance(value, list):
        if not value:
            raise ValueError(f"{name}: an empty list of values")
        return value
    return [value]


def split_hyperparam(name: str) -> tuple[str | None, str]:
    """`"ppo.num_envs"` -> ("ppo", "num_envs"); `"gamma"` -> (None, "gamma")."""
    agent, dot, field_name = name.rpartition(".")
    return (agent, field_name) if dot else (None, name)


def agent_hyperparams(spec: SweepSpec, agent: str) -> dict[str, tuple[str, Any]]:
    """The hyperparameters that apply to `agent`: config field -> (the spec's key, its value); scoped keys win."""
    return _applicable(spec.hyperparams, agent)


def _applicable(hyperparams: Mapping[str, Any], agent: str) -> dict[str, tuple[str, Any]]:
    fields = ALGORITHMS[agent].config_type.__dataclass_fields__
    chosen: dict[str, tuple[str, Any]] = {}
    for scoped in (False, True):
        for key, value in hyperparams.items():
            scope, name = split_hyperparam(key)
            if (scope is not None) == scoped and scope in (None, agent) and name in fields:
                chosen[name] = (key, value)
    return chosen


MAX_SEED = 2**32  # seeds are 32-bit (`jax.random.PRNGKey` without x64)
MAX_CONFIGS = 1_000_000  # configurations in one sweep


def validate_spec(spec: SweepSpec) -> None:
    """Check the whole spec on concrete values (before anything is written or compiled)."""
    if not spec.envs or not spec.agents or not spec.seeds:
        raise ValueError("envs, agents and seeds must each name at least one value")
    size = len(spec.envs) * len(spec.agents) * (len(spec.costs) + spec.vanilla) * len(spec.seeds)
    for value in spec.hyperparams.values():
        size *= len(value) if isinstance(value, list) else 1
    if size > MAX_CONFIGS:
        raise ValueError(
            f"the grid has {size:,} configurations; allowed: at most {MAX_CONFIGS:,} in one sweep "
            "(split it into several sweeps)"
        )
    for env_id in spec.envs:
        make_env(env_id)
    for agent in spec.agents:
        check_choice("agent", agent, sorted(ALGORITHMS))
    if not spec.costs and not spec.vanilla:
        raise ValueError("costs: give at least one cost (or vanilla runs)")
    for cost in spec.costs:
        check_real("cost", cost, low=0.0)
    for seed in spec.seeds:
        check_positive_int("seed", seed, minimum=0)
        if seed >= MAX_SEED:  # jax.random.PRNGKey keeps the low 32 bits: 2**32 + s would alias s
            raise ValueError(f"seed: got {seed}; allowed values: integers in [0, {MAX_SEED - 1}] (2**32 - 1)")
    if len(set(spec.seeds)) != len(spec.seeds):
        raise ValueError(f"seeds: repeated values in {list(spec.seeds)}")
    for key, value in spec.hyperparams.items():
        scope, name = split_hyperparam(key)
        if scope is not None:
            check_choice(f"hyperparameter {key!r}: agent", scope, sorted(ALGORITHMS))
            if scope not in spec.agents:
                raise ValueError(
                    f"hyperparameter {key!r}: agent {scope!r} is not in this sweep's agents {list(spec.agents)}"
                )
        if name in SCHEDULE_FIELDS:
            raise ValueError(
                f"{name} is set for the whole sweep (--steps / --eval-every / --eval-episodes), not as a hyperparameter"
            )
        if name in GRID_FIELDS or name == "mode":
            raise ValueError(f"{name} is a grid axis; use its own option, not a hyperparameter")
        agents = spec.agents if scope is None else (scope,)
        owners = [a for a in agents if name in ALGORITHMS[a].config_type.__dataclass_fields__]
        if not owners:
            raise ValueError(
                f"hyperparameter {key!r} belongs to none of the agents {list(agents)}; "
                f"allowed: {', '.join(sorted(_all_fields(agents)))}"
            )
        _as_values(key, value)
    for env_id, defaults in spec.resolved_env_defaults().items():
        for key, value in defaults.items():
            name = split_hyperparam(key)[1]
            if (
                isinstance(value, list)
                or name in SCHEDULE_FIELDS + GRID_FIELDS
                or name not in _all_fields(sorted(ALGORITHMS))
            ):
                raise ValueError(f"env_defaults[{env_id!r}][{key!r}]: allowed: one value of an agent config field")


def _all_fields(agents: Sequence[str]) -> set[str]:
    names = set()
    for agent in agents:
        names |= set(ALGORITHMS[agent].config_type.__dataclass_fields__)
    return names - set(SCHEDULE_FIELDS) - set(GRID_FIELDS) - {"mode", "noise_std", "flag"}


def config_id(env: str, agent: str, vanilla: bool, cost: float, seed: int, hp: Mapping[str, Any]) -> str:
    """A stable short id of a configuration (the same in every rerun of the same sweep)."""
    text = json.dumps([env, agent, vanilla, float(cost), int(seed), sorted(hp.items())], default=list)
    return hashlib.sha1(text.encode()).hexdigest()[:12]


def expand(spec: SweepSpec) -> list[RunConfig]:
    """Every configuration of the sweep, each with its validated agent config.

    The last spec's expansion is kept, so a command line that checks a spec and then runs it expands it once; the
    key is the spec's `repr` (it tells a tuple value from a list of values)."""
    key = repr(spec)
    if _last_expanded.get("key") != key:
        validate_spec(spec)
        runs = list(_runs(spec))
        checked: set[AgentConfig] = set()
        for run in runs:  # configurations that differ only in seed share one config
            if run.config not in checked:
                checked.add(run.config.validate())
        _last_expanded.update(key=key, runs=runs)
    return list(_last_expanded["runs"])


_last_expanded: dict[str, Any] = {}


def round_schedule(spec: SweepSpec) -> tuple[SweepSpec, str | None]:
    """`spec` with `total_timesteps` and `eval_every` rounded to the nearest valid values: whole updates of every
    agent of the sweep (their env steps per update differ: PPO's num_envs x num_steps, DQN's num_envs x
    train_freq, ...) and whole evaluation periods; plus a one-line note of what changed (None if nothing did).
    What a command line offers for any budget; the Python API stays strict."""
    validate_spec(spec)
    unit = math.lcm(*{_steps_per_update(run.config) for run in _runs(spec)})
    total, every = nearest_schedule(max(1, spec.total_timesteps), spec.eval_every, unit)
    if (total, every) == (spec.total_timesteps, spec.eval_every):
        return spec, None
    note = (
        f"steps {spec.total_timesteps:,} and eval-every {spec.eval_every:,} rounded to {total:,} and {every:,}: "
        f"whole updates of every agent (a multiple of {unit:,} env steps) and whole evaluation periods"
    )
    return dataclasses.replace(spec, total_timesteps=total, eval_every=every), note


def _steps_per_update(config: AgentConfig) -> int:
    """Env steps per update; where the fields that set it are invalid, the config's own checks name them."""
    try:
        steps = config.steps_per_update()
    except (TypeError, ValueError, ZeroDivisionError):
        steps = None
    if not isinstance(steps, int) or steps < 1:
        config.validate()  # each agent checks its own fields before the schedule
        raise ValueError(f"{type(config).__name__}: env steps per update must be a positive integer, got {steps!r}")
    return steps


def _runs(spec: SweepSpec) -> Iterator[RunConfig]:
    """The grid's configurations in order, their agent configs not yet validated."""
    for env, agent in itertools.product(spec.envs, spec.agents):
        config_type = ALGORITHMS[agent].config_type
        preset = spec.resolved_env_defaults().get(env, {})
        defaults = {name: value for name, (_, value) in _applicable(preset, agent).items()}
        applies = agent_hyperparams(spec, agent)  # field -> (spec key, value)
        own = {key: _as_values(key, value) for key, value in applies.values()}
        field_of = {key: name for name, (key, _) in applies.items()}
        settings = [(False, float(c)) for c in spec.costs] + ([(True, 0.0)] if spec.vanilla else [])
        plain = {key: values for key, values in own.items() if field_of[key] not in MEASURE_FIELDS}
        for vanilla, cost in settings:
            swept = plain if vanilla else own
            yield from _setting_runs(
                spec,
                env,
                agent,
                config_type,
                vanilla,
                cost,
                swept,
                field_of,
                {k: v for k, v in defaults.items() if not vanilla or k not in MEASURE_FIELDS},
            )


def _setting_runs(
    spec: SweepSpec,
    env: str,
    agent: str,
    config_type: type,
    vanilla: bool,
    cost: float,
    own: Mapping[str, Any],
    field_of: Mapping[str, str],
    defaults: Mapping[str, Any],
) -> Iterator[RunConfig]:
    """The runs of one (env, agent, vanilla, cost): every combination of `own`'s values, every seed."""
    for values, seed in itertools.product(itertools.product(*own.values()), spec.seeds):
        hp = dict(zip(own, values, strict=True))
        config = config_type(
            env_id=env,
            mode="last" if vanilla else spec.mode,  # the plain env shows every observation: no mode
            vanilla=vanilla,
            cost=cost,
            total_timesteps=spec.total_timesteps,
            eval_every=spec.eval_every,
            eval_episodes=spec.eval_episodes,
            **{**defaults, **{field_of[k]: tuple(v) if isinstance(v, list) else v for k, v in hp.items()}},
        )
        yield RunConfig(config_id(env, agent, vanilla, cost, seed, hp), agent, seed, hp, config)


def group_runs(runs: Sequence[RunConfig]) -> list[list[RunConfig]]:
    """Split runs into groups sharing every static field (one compiled program each), in grid order."""
    groups: dict[tuple[Any, ...], list[RunConfig]] = {}
    for run in runs:
        groups.setdefault(run.config.static_key(), []).append(run)
    return list(groups.values())
