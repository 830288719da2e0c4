"""Agent configs: frozen pytree dataclasses whose static fields set shapes and whose traced fields are leaves.

A field declared with `static(...)` is part of the pytree's structure: changing it compiles a new program (env id,
counts, network widths, buffer size). Every other field is a leaf: a sweep stacks many values of it and `vmap`s the
same compiled program over them (cost, learning rate, gamma, epsilons, ...).
"""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar, Self

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from amjax.agents.networks import TORSOS, pick_torso
from amjax.envs.registry import make_env
from amjax.validation import check_choice, check_positive_int, check_real, check_whole_number, is_traced
from amjax.wrappers.instruments import resolve_instruments
from amjax.wrappers.spec import MEASURE_HEADS, MeasureSpec, static

__all__ = [
    "MAX_EPISODES",
    "MAX_STEPS",
    "MAX_WIDTH",
    "MEASURE_HEADS",
    "AgentConfig",
    "nearest_schedule",
    "stack_configs",
    "static",
    "unstack_config",
]
_BOUNDS = {
    "positive": {"low": 0.0, "low_inclusive": False},
    "nonnegative": {"low": 0.0},
    "unit": {"low": 0.0, "high": 1.0},
    "probability": {"low": 0.0, "high": 1.0, "low_inclusive": False, "high_inclusive": False},
    "count": {"low": 0.0},  # whole numbers (check_whole_number)
}


MAX_STEPS = 2**31 - 1  # env-step counters are int32
MAX_EPISODES = 65_536  # test episodes run side by side: one batch of envs per configuration
MAX_WIDTH = 65_536  # a network layer's width


def nearest_schedule(total_timesteps: int, eval_every: int, unit: int) -> tuple[int, int]:
    """The valid (total_timesteps, eval_every) nearest the given ones: eval_every a multiple of `unit` (env steps
    per update) no larger than the budget, total_timesteps a multiple of eval_every."""
    every = max(unit, round(min(eval_every, total_timesteps) / unit) * unit)
    return max(every, round(total_timesteps / every) * every), every


@struct.dataclass
class AgentConfig(MeasureSpec):
    """Fields every agent shares: the environment, the measurement setting (`MeasureSpec`'s fields: mode, flag,
    vanilla, cost, budget, ..., inherited, not copied) and the training / evaluation budget."""

    env_id: str = static("CartPole-v0")
    total_timesteps: int = static(100_000)  # env steps per configuration (all parallel envs together)
    eval_every: int = static(10_000)  # env steps between greedy evaluations
    eval_episodes: int = static(10)  # test episodes per evaluation
    rescore_episodes: int = static(100)  # fresh test episodes that re-score the best policy at the end of a sweep
    # Under vmap (a sweep), train about this many configurations at a time between evaluations (`lax.map` over
    # groups, `vmap` within one; 0: all at once). Speed only: a group's working set can stay in a core's cache.
    # Results agree with ungrouped training to float rounding (which a long run amplifies, as any change of batch).
    train_group: int = static(0)
    # The network's body: "auto" (a CNN for an image observation [height, width, channels], an MLP otherwise),
    # "mlp" or "cnn" (`networks.pick_torso`; the agent's `hidden` widths are the Dense layers after either).
    torso: str = static("auto")

    # The allowed range of each traced field of a subclass: "positive" (> 0), "nonnegative" (>= 0), "unit"
    # ([0, 1]), "probability" ((0, 1)) or "count" (whole numbers >= 0); every value must be finite.
    # Static fields that hold network widths (a tuple of layer sizes), declared by the agents' configs.
    WIDTH_FIELDS: ClassVar[tuple[str, ...]] = ()
    TRACED_BOUNDS: ClassVar[dict[str, str]] = {}
    # The env action spaces (gymnax space class names) the agent handles.
    ACTION_SPACES: ClassVar[tuple[str, ...]] = ("Discrete",)

    # -- introspection ----------------------------------------------------------------------------

    @classmethod
    def static_fields(cls) -> tuple[str, ...]:
        return tuple(f.name for f in dataclasses.fields(cls) if not f.metadata.get("pytree_node", True))

    @classmethod
    def traced_fields(cls) -> tuple[str, ...]:
        return tuple(f.name for f in dataclasses.fields(cls) if f.metadata.get("pytree_node", True))

    def to_dict(self) -> dict[str, Any]:
        """Every field as JSON-ready Python values (traced leaves as floats, tuples as lists)."""

        def plain(value: Any) -> Any:
            if isinstance(value, tuple | list):
                return [plain(v) for v in value]
            if isinstance(value, bool | int | float | str) or value is None:
                return value
            return np.asarray(value).item()

        return {f.name: plain(getattr(self, f.name)) for f in dataclasses.fields(self)}

    @classmethod
    def from_dict(cls, fields: dict[str, Any]) -> AgentConfig:
        """The config `to_dict` wrote (lists become tuples); unknown fields are refused."""
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(fields) - known)
        if unknown:
            raise ValueError(f"fields: {cls.__name__} has no field(s) {', '.join(unknown)}")

        def frozen(value: Any) -> Any:  # JSON lists back to (nested) tuples
            return tuple(frozen(v) for v in value) if isinstance(value, list) else value

        return cls(**{k: frozen(v) for k, v in fields.items()})

    def static_key(self) -> tuple[Any, ...]:
        """Everything that needs its own compiled program (configs with equal keys share one)."""
        return (type(self).__name__, *(getattr(self, name) for name in self.static_fields()))

    # -- checks -----------------------------------------------------------------------------------

    def validate(self) -> Self:
        """Check every field on concrete values (before compiling); returns self. The agent's own fields
        (`check_fields`) are checked first, then the environment, the traced fields and the schedule."""
        self.check_fields()
        env, env_params = make_env(self.env_id)  # raises on an unknown id, listing the known ones
        space = type(env.action_space(env_params)).__name__
        if space not in self.ACTION_SPACES:
            raise ValueError(
                f"env_id: {self.env_id} has a {space} action space; {type(self).__name__} handles "
                f"{' and '.join(self.ACTION_SPACES)} (for Box control use PPO: agent ppo or ppo-rnn)"
            )
        self.check_measure(self.env_id, env, env_params)
        check_choice("torso", self.torso, TORSOS)
        if self.torso == "cnn":  # "auto" and "mlp" take any observation
            wrapped, inner_params = self.wrap_env(self.env_id, env, env_params)
            pick_torso(self.torso, wrapped.observation_space(self.measure_params(wrapped, inner_params)).shape)
        for name, kind in self.TRACED_BOUNDS.items():
            value = getattr(self, name)
            if is_traced(value):
                continue  # under vmap/jit: the caller checked the concrete values
            if kind == "count":
                check_whole_number(name, value)
            else:
                check_real(name, value, **_BOUNDS[kind])
        check_positive_int("total_timesteps", self.total_timesteps, maximum=MAX_STEPS)
        check_positive_int("eval_every", self.eval_every, maximum=MAX_STEPS)
        check_positive_int("eval_episodes", self.eval_episodes, maximum=MAX_EPISODES)
        check_positive_int("rescore_episodes", self.rescore_episodes, maximum=MAX_EPISODES)
        check_positive_int("train_group", self.train_group, minimum=0)
        for name in self.WIDTH_FIELDS:  # network widths: tuples of positive integers
            value = getattr(self, name)
            if not isinstance(value, tuple | list) or not all(
                isinstance(v, int | np.integer) and not isinstance(v, bool) and 1 <= v <= MAX_WIDTH for v in value
            ):
                raise ValueError(
                    f"{name}: got {value!r}; allowed values: a tuple of integers in [1, {MAX_WIDTH:,}], "
                    "e.g. (64, 64), or () for none"
                )
        steps = self.steps_per_update()
        if self.eval_every % steps or self.total_timesteps % self.eval_every:
            total, every = nearest_schedule(self.total_timesteps, self.eval_every, steps)
            raise ValueError(
                f"eval_every={self.eval_every} must be a multiple of the env steps per update ({steps}) "
                f"and divide total_timesteps={self.total_timesteps}; nearest valid values: eval_every={every}, "
                f"total_timesteps={total} (the command line rounds them for you)"
            )
        return self

    def check_fields(self) -> None:
        """Check the fields an agent adds (overridden by each config class; call `super().check_fields()`)."""

    # -- derived quantities (static) ---------------------------------------------------------------

    def steps_per_update(self) -> int:
        """Env steps (all parallel envs) consumed by one call of the algorithm's `update`."""
        raise NotImplementedError

    @property
    def factored_masks(self) -> int:
        """Measure choices of a factored head (2^instruments), or 0 for the joint head."""
        return 2**self.num_instruments if self.measure_head == "factored" else 0

    @property
    def num_instruments(self) -> int:
        """Measure choices per step: the number of instruments, or 1 (the paper's single switch)."""
        return max(1, len(resolve_instruments(self.env_id, self.instruments)))

    @property
    def updates_per_eval(self) -> int:
        return self.eval_every // self.steps_per_update()

    @property
    def num_evals(self) -> int:
        return self.total_timesteps // self.eval_every


def stack_configs(configs: list[AgentConfig]) -> AgentConfig:
    """Stack configs that share their static fields into one config whose traced leaves have a batch axis."""
    keys = {config.static_key() for config in configs}
    if len(keys) != 1:
        raise ValueError("stack_configs: the configs differ in static fields; compile them separately")
    return jax.tree.map(lambda *xs: jnp.asarray(np.stack(xs), jnp.float32), *configs)


def unstack_config(stacked: AgentConfig, index: int) -> AgentConfig:
    """Configuration `index` of a stacked config."""
    return jax.tree.map(lambda x: x[index], stacked)
