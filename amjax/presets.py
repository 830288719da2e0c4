"""Each environment's tuned hyperparameters per agent: the one source of defaults.

Every entry point starts an environment's configurations from these unless told otherwise: the commands (`amjax
sweep`, `replicate`, `pareto`; `--no-env-defaults` turns them off), `SweepSpec` / `run_sweep` (`env_defaults=None`,
the default; `env_defaults={}` turns them off), and one agent config built from Python
(`amjax.agents.config_for(env_id, agent, **overrides)`; `presets=False` turns them off). A value the user sets
always wins. An agent without an entry for an environment (`ENV_PRESETS` below) uses its config's own defaults,
which were tuned on CartPole. The runs behind each value are cited beside it. A sweep folder
is identified by the presets of its own agents only (`SweepSpec.identity`), so a preset added for one agent leaves
the folders of the others resumable.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

# PPO on LunarLander: the RL Baselines3 Zoo's tuned LunarLander-v2 entry (hyperparams/ppo.yml in
# DLR-RM/rl-baselines3-zoo: n_envs 16, n_timesteps 1e6, n_steps 1024, batch_size 64, gae_lambda 0.98, gamma 0.999,
# n_epochs 4, ent_coef 0.01) with SB3's PPO defaults for the rest (learning_rate 3e-4 constant, clip_range 0.2,
# vf_coef 0.5, max_grad_norm 0.5, separate 64x64 tanh actor and critic); batch_size 64 -> 16 * 1024 / 64 = 256
# minibatches. With it amjax's PPO, trained in the JAX port, scores 236.5 in Gymnasium's LunarLander-v3
# (experiments/lunar_lander_transfer.py). Test policy "greedy_control" (docs/eval_policy.md): the greedy policy of a
# costed run crashes (a memoryless argmax repeats itself on a stale observation); the most probable control with the
# policy's own measuring draws scored 143 / 87 / 29 re-scored at costs 0.1 / 0.2 / 0.3 on tuning seeds (greedy:
# -311 to -658), the whole stochastic policy 87 / 83 / 80. A vanilla run is greedy either way. The initial policy
# measures with probability 0.9 (`measure_prior`): from the uniform policy's 0.5 PPO kept measuring on about half
# the steps even at cost 0 (re-scored 127 there on the tuning seeds, 193 with 0.9; docs/eval_policy.md). Rewards
# scaled by 0.01: returns of -200 to +300 at gamma 0.999 left the clipped critic (0.2 per update) far behind, and
# the costed lander learned to hover; scaled, PPO's median best rose from 217 / 193 / 179 to 285 / 269 / 245 at
# costs 0 / 0.1 / 0.3 on the tuning seeds (docs/lunar_lander.md, "PPO's critic").
LUNAR_LANDER_PPO: dict[str, object] = {
    "num_envs": 16,
    "num_steps": 1024,
    "num_minibatches": 256,
    "update_epochs": 4,
    "hidden": (64, 64),
    "activation": "tanh",
    "anneal_lr": False,
    "learning_rate": 3e-4,
    "gamma": 0.999,
    "gae_lambda": 0.98,
    "clip_eps": 0.2,
    "ent_coef": 0.01,
    "vf_coef": 0.5,
    "max_grad_norm": 0.5,
    "eval_policy": "greedy_control",
    "measure_prior": 0.9,
    "reward_scale": 0.01,
}
# PPO on Acrobot-v1 (tuning runs in docs/acrobot.md): Acrobot pays -1 per step, so returns are about -60 to -500
# and PPO's value clipping (clip_eps = 0.2 in reward units per update) keeps the critic far behind them; the
# advantages are then the next few steps' rewards, where the one visible effect of a measurement is its cost, and
# under a cost of 0.2 or more PPO stops measuring and never reaches the goal. Scaled rewards keep the critic close.
# A 128x128 torso (run 7 there) controls the swing-up better than 64x64 at every cost, and 10 epochs of 8
# minibatches per rollout (runs 8-9; 2.5x the gradient work of 4 x 4) far better than 4 x 4, vanilla included. With
# that many steps a clipped critic lags the policy again: 12 of 90 costed runs collapsed; unclipped, 0 of 30 (run 11).
ACROBOT_PPO: dict[str, object] = {
    "reward_scale": 0.1,
    "ent_coef": 0.0,
    "hidden": (128, 128),
    "update_epochs": 10,
    "num_minibatches": 8,
    "clip_value": False,
}
# Dueling DQN on Acrobot-v1 (tuning runs 5-6 in docs/acrobot.md): a wider torso and 3-step returns control the
# swing-up from stale views better than the CartPole defaults (64x64, 10-step returns). 128x128, not 256x256: the
# wider one scored within these runs' noise of it and trains about 4x slower on CPU (the torso's matmuls bound it).
ACROBOT_DQN: dict[str, object] = {
    "hidden": (128, 128),
    "n_step": 3,
    "train_group": 5,  # 5 configurations at a time under vmap: about 9% faster than 20 (docs/recurrent.md)
}
# DRQN on Acrobot-v1 (run 14 in docs/acrobot.md): rewards scaled by 0.1, as PPO's above. Unscaled, returns down to
# -500 put the TD errors far past the Huber threshold and DRQN stopped measuring (and never reached the goal) on 3
# and 5 of the grid's 10 seeds at costs 0.2 and 0.3. Scaled, on those seeds at the grid's budget: 0 of 40 costed runs
# collapsed, median best -88.8 / -95.8 / -103.1 / -106.3 at costs 0 / 0.1 / 0.2 / 0.3, against -79.1 / -89.3 /
# -98.7 / -314.8 unscaled (a screen on seeds 100-107: 0 of 32 against 26 of 32).
ACROBOT_DRQN: dict[str, object] = {
    "reward_scale": 0.1,
}
# Recurrent PPO on Acrobot-v1 (run 15 in docs/acrobot.md): PPO's preset above plus a measure head that starts at 0.9.
# With CartPole's defaults it stopped measuring and never reached the goal on 26 of 30 costed runs; rewards x 0.1
# alone were not enough (screen 1), 10 epochs and the prior of 0.9 each lifted cost 0.3 most (screen 2). On the
# grid's seeds 0-9 and budget: 0 of 40 costed runs collapse, re-scored medians -79.3 / -85.0 / -92.9 / -101.8 at costs
# 0 / 0.1 / 0.2 / 0.3, within 3.2 of Dueling DQN's preset, behind PPO's.
ACROBOT_PPO_RNN: dict[str, object] = {
    "reward_scale": 0.1,
    "ent_coef": 0.0,
    "update_epochs": 10,
    "clip_value": False,
    "measure_prior": 0.9,
}
# Dueling DQN on LunarLander-v3: four envs per configuration, a gradient step after each step of all four (still 64
# samples per 4 env steps: the replay ratio, exploration schedule, target interval and budget are the defaults').
# The port steps 4 envs nearly as fast as one (a single env is where it is slowest per step), so an update of the
# replicate's 20 configurations per core costs 2.14 ms instead of 2.87 (1.34x; benchmarks/dqn_update_split.py
# --layouts, docs/lunar_lander.md). Rewards scaled by 0.1 (returns of -100 to +300 otherwise put most TD errors past
# the Huber loss's threshold of 1): ahead at costs 0.2 and 0.3 and on vanilla in a 3-seed tuning run, checked on the
# grid's seeds (docs/lunar_lander.md, "Dueling DQN with scaled rewards").
LUNAR_LANDER_DQN: dict[str, object] = {
    "num_envs": 4,
    "train_freq": 1,
    "reward_scale": 0.1,
}
# Recurrent PPO on LunarLander-v3 (screens on seeds 100-102 at a quarter of the budget, docs/lunar_lander.md,
# "Recurrent PPO"): with CartPole's defaults it never learns to land (training episodes -60 to -132 raw); rewards x
# 0.01 (PPO's critic fix above) make the policy as trained land, and the "stochastic" test policy keeps that: median
# re-scored 158.0 / 165.2 at costs 0.1 / 0.3, every seed above 108, where "greedy_control" (PPO's choice) re-scored
# 133.5 / -105.1 and "greedy" crashed (-695 at cost 0.3).
LUNAR_LANDER_PPO_RNN: dict[str, object] = {
    "reward_scale": 0.01,
    "eval_policy": "stochastic",
}
# PQN on CartPole-v0: a 64x64 torso (Dueling DQN's width there) instead of PQN's 128x128. On seeds 100-104 at the
# grid's budget it scored within 0.3 of 128x128 at costs 0.1 / 0.2 / 0.3 (4 epochs; 2 epochs lost up to 0.8
# re-scored), on the grid's seeds 0-9 189.5 / 180.0 / 170.0 (re-scored 189.6 / 180.0 / 169.9) against Dueling DQN's
# 189.4 / 180.0 / 169.9 (re-scored 189.3 / 179.5 / 169.9), and it trains about 3x faster than 128x128
# (benchmarks/pqn_speed.py; docs/pqn.md, "A 64x64 network on CartPole-v0").
CARTPOLE_PQN: dict[str, object] = {
    "hidden": (64, 64),
}
# PQN on LunarLander-v3: gamma 0.995 (from 0.99). A 3-seed screen of learning rate 3e-4 / 1e-3 x gamma 0.99 / 0.995
# at costs 0.1 and 0.3 (seeds 100-102) re-scored best at 1e-3 and 0.995; on the grid's seeds 0-9 it re-scores 251.8
# / 241.8 / 231.3 at costs 0.1 / 0.2 / 0.3, against 234.9 / 219.8 / 216.6 at 0.99 (docs/pqn.md, "LunarLander-v3").
LUNAR_LANDER_PQN: dict[str, object] = {
    "gamma": 0.995,
}

# PPO on gymnax's Pendulum-v1 (Box control; the Gaussian + Bernoulli head of amjax/agents/policies.py). Pendulum
# pays -16 to 0 per step over 200 steps; as on Acrobot, unscaled rewards leave the critic behind. Chosen from a
# 3-seed sweep of learning rate 1e-3 / 3e-4 x gamma 0.9 / 0.95 / 0.99 x reward scale 1 / 0.1 at 491,520 steps
# (docs/continuous.md): 10 epochs of 32 minibatches over 8 x 256 steps, gamma 0.95, no entropy bonus.
PENDULUM_PPO: dict[str, object] = {
    "num_envs": 8,
    "num_steps": 256,
    "update_epochs": 10,
    "num_minibatches": 32,
    "reward_scale": 0.1,
    "ent_coef": 0.0,
    "gamma": 0.95,
    "learning_rate": 3e-4,
}


def scoped(agent: str, values: dict[str, object]) -> dict[str, object]:
    """`values` as hyperparameters of `agent` only ("agent.field": value)."""
    return {f"{agent}.{name}": value for name, value in values.items()}


# Per-environment hyperparameters on top of each agent's defaults ("agent.field": value).
ENV_PRESETS: dict[str, dict[str, object]] = {
    "CartPole-v0": scoped("pqn", CARTPOLE_PQN),
    "Acrobot-v1": scoped("ppo", ACROBOT_PPO)
    | scoped("dqn", ACROBOT_DQN)
    | scoped("drqn", ACROBOT_DRQN)
    | scoped("ppo-rnn", ACROBOT_PPO_RNN),
    "LunarLander-v3": scoped("ppo", LUNAR_LANDER_PPO)
    | scoped("dqn", LUNAR_LANDER_DQN)
    | scoped("ppo-rnn", LUNAR_LANDER_PPO_RNN)
    | scoped("pqn", LUNAR_LANDER_PQN),
    "Pendulum-v1": scoped("ppo", PENDULUM_PPO),
}


def for_agents(values: Mapping[str, Any], agents: Sequence[str]) -> dict[str, Any]:
    """`values` ("field" or "agent.field": value) restricted to `agents`: keys scoped to another agent dropped."""
    return {key: value for key, value in values.items() if "." not in key or key.partition(".")[0] in agents}


def env_hyperparams(env: str, agents: tuple[str, ...]) -> dict[str, object]:
    """`ENV_PRESETS[env]` restricted to `agents` (keys scoped to another agent dropped)."""
    return for_agents(ENV_PRESETS.get(env, {}), agents)


def preset(env_id: str, agent: str) -> dict[str, object]:
    """The tuned field values of `agent` on `env_id` (unscoped names; {} where there are none)."""
    prefix = f"{agent}."
    return {
        key.removeprefix(prefix): value for key, value in ENV_PRESETS.get(env_id, {}).items() if key.startswith(prefix)
    }


__all__ = [
    "ACROBOT_DQN",
    "ACROBOT_DRQN",
    "ACROBOT_PPO",
    "ACROBOT_PPO_RNN",
    "CARTPOLE_PQN",
    "ENV_PRESETS",
    "LUNAR_LANDER_DQN",
    "LUNAR_LANDER_PPO",
    "LUNAR_LANDER_PPO_RNN",
    "LUNAR_LANDER_PQN",
    "PENDULUM_PPO",
    "env_hyperparams",
    "for_agents",
    "preset",
    "scoped",
]
