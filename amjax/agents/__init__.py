"""Agents: networks, shared rollout / replay / evaluation, and one file per algorithm."""

from amjax.agents.config import AgentConfig, stack_configs, unstack_config
from amjax.agents.dqn import DQN, DQNConfig
from amjax.agents.drqn import DRQN, DRQNConfig
from amjax.agents.ppo import PPO, PPOConfig
from amjax.agents.ppo_rnn import PPO_RNN, PPORNNConfig
from amjax.agents.pqn import PQN, PQNConfig
from amjax.agents.pqn_rnn import PQN_RNN, PQNRNNConfig
from amjax.agents.registry import ALGORITHMS, agent_of, algorithm, config_for
from amjax.agents.saved import PolicyFileError, SavedPolicy, load_policy, save_policy
from amjax.agents.setup import Setup, training_env
from amjax.agents.training import (
    Algorithm,
    EvalRow,
    FinishedEpisodes,
    RunState,
    evaluate,
    evaluate_greedy,
    init_run,
    rescore,
    run_evals,
)

__all__ = [
    "ALGORITHMS",
    "DQN",
    "DRQN",
    "PPO",
    "PPO_RNN",
    "PQN",
    "PQN_RNN",
    "AgentConfig",
    "Algorithm",
    "DQNConfig",
    "DRQNConfig",
    "EvalRow",
    "FinishedEpisodes",
    "PPOConfig",
    "PPORNNConfig",
    "PQNConfig",
    "PQNRNNConfig",
    "PolicyFileError",
    "RunState",
    "SavedPolicy",
    "Setup",
    "agent_of",
    "algorithm",
    "config_for",
    "evaluate",
    "evaluate_greedy",
    "init_run",
    "load_policy",
    "rescore",
    "run_evals",
    "save_policy",
    "stack_configs",
    "training_env",
    "unstack_config",
]
