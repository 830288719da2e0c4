"""The algorithm registry: every trainer by name, the lookups by name and by config type, and `config_for` (an agent's
config for an env, from the env's tuned presets)."""

from __future__ import annotations

from typing import Any

from amjax.agents.config import AgentConfig
from amjax.agents.dqn import DQN
from amjax.agents.drqn import DRQN
from amjax.agents.ppo import PPO
from amjax.agents.ppo_rnn import PPO_RNN
from amjax.agents.pqn import PQN
from amjax.agents.pqn_rnn import PQN_RNN
from amjax.agents.training import Algorithm
from amjax.presets import preset

ALGORITHMS: dict[str, Algorithm] = {algo.name: algo for algo in (PPO, DQN, DRQN, PPO_RNN, PQN, PQN_RNN)}
# What each agent is, in the words every listing of the agents uses (the commands' help, the docs).
DESCRIPTIONS: dict[str, str] = {
    "ppo": "PPO",
    "dqn": "Dueling Double DQN with n-step returns",
    "drqn": "recurrent Dueling Double DQN, R2D2-style sequence replay",
    "ppo-rnn": "recurrent PPO",
    "pqn": "PQN, parallelised Q-learning with Q(lambda) targets and LayerNorm",
    "pqn-rnn": "recurrent PQN",
}


def agent_list() -> str:
    """Every agent id with what it is, e.g. "ppo (PPO), dqn (Dueling Double DQN with n-step returns), ..."."""
    return ", ".join(f"{name} ({DESCRIPTIONS[name]})" for name in ALGORITHMS)


def algorithm(agent: str) -> Algorithm:
    """The registered algorithm named `agent`; ValueError listing the names otherwise."""
    if agent not in ALGORITHMS:
        raise ValueError(f"agent: unknown agent {agent!r}; allowed values: {agent_list()}")
    return ALGORITHMS[agent]


def config_for(env_id: str, agent: str, *, presets: bool = True, **fields: Any) -> AgentConfig:
    """`agent`'s config for `env_id`: the env's tuned presets for that agent (`amjax.presets`, as every command and
    `SweepSpec` applies them; `presets=False` for none), then `fields` on top, e.g.
    `config_for("Acrobot-v1", "ppo", cost=0.2, total_timesteps=491_520)`. The config constructors themselves
    (`PPOConfig(env_id=...)`) never apply presets."""
    config_type = algorithm(agent).config_type
    values = preset(env_id, agent) if presets else {}
    return config_type(env_id=env_id, **{**values, **fields})


def agent_of(config: AgentConfig) -> str:
    """The registered name of the algorithm whose config type `config` is (exactly)."""
    for name, algo in ALGORITHMS.items():
        if type(config) is algo.config_type:
            return name
    raise TypeError(f"config: no registered algorithm uses {type(config).__name__}")


__all__ = ["ALGORITHMS", "DESCRIPTIONS", "agent_list", "agent_of", "algorithm", "config_for"]
