"""The algorithm registry: every trainer by name, and the lookups by name and by config type."""

from __future__ import annotations

from amjax.agents.config import AgentConfig
from amjax.agents.dqn import DQN
from amjax.agents.drqn import DRQN
from amjax.agents.ppo import PPO
from amjax.agents.ppo_rnn import PPO_RNN
from amjax.agents.training import Algorithm

ALGORITHMS: dict[str, Algorithm] = {algo.name: algo for algo in (PPO, DQN, DRQN, PPO_RNN)}


def algorithm(agent: str) -> Algorithm:
    """The registered algorithm named `agent`; ValueError listing the names otherwise."""
    if agent not in ALGORITHMS:
        raise ValueError(f"agent: unknown agent {agent!r}; allowed values: {', '.join(sorted(ALGORITHMS))}")
    return ALGORITHMS[agent]


def agent_of(config: AgentConfig) -> str:
    """The registered name of the algorithm whose config type `config` is (exactly)."""
    for name, algo in ALGORITHMS.items():
        if type(config) is algo.config_type:
            return name
    raise TypeError(f"config: no registered algorithm uses {type(config).__name__}")


__all__ = ["ALGORITHMS", "agent_of", "algorithm"]
