"""What one compiled program builds once from an agent config: the environment and the network (as PureJaxRL's
`make_train` does), passed to the algorithm's functions instead of rebuilt inside each of them.

The config describes a run; `training_env` and `Algorithm.setup` turn its static fields into Python objects (env,
network) and put its traced cost and noise straight into the env params."""

from __future__ import annotations

from typing import Any

from flax import linen as nn
from flax import struct

from amjax.wrappers.episode_stats import EpisodeStats


def training_env(config: Any) -> tuple[Any, Any, int]:
    """The env a config trains and evaluates on (with episode statistics), its params (the config's cost and
    noise, traced or not) and its episode step limit: the config's `MeasureSpec` fields, unchecked (the config's
    `validate` checked them)."""
    env, env_params = config.wrap_env(config.env_id)
    max_steps = int(env_params.max_steps_in_episode)
    return EpisodeStats(env), config.measure_params(env, env_params), max_steps


@struct.dataclass
class Setup:
    """The env and network of one compiled program (static objects) and the env params (a pytree of traced
    leaves)."""

    env: Any = struct.field(pytree_node=False)
    env_params: Any
    max_steps: int = struct.field(pytree_node=False)
    network: nn.Module = struct.field(pytree_node=False)

    @property
    def num_actions(self) -> int:
        return self.env.action_space(self.env_params).n
