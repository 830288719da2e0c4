"""Named sweeps. `demo` is the README's quick start; `paper` is the grid of Bellinger et al. (2022);
`replicate_specs` is the whole replication (`python -m train replicate`): one sweep per environment. Each
environment's tuned hyperparameters are the library's (`amjax.presets`)."""

from __future__ import annotations

import dataclasses

from amjax.presets import env_hyperparams
from amjax.sweep import SweepSpec

PRESETS: dict[str, SweepSpec] = {
    # A few minutes on 2 CPU cores: both agents, the paper's costs, 3 seeds on CartPole-v0.
    "demo": SweepSpec(
        envs=("CartPole-v0",),
        agents=("ppo", "dqn"),
        costs=(0.0, 0.1, 0.2, 0.3),
        seeds=(0, 1, 2),
        total_timesteps=153_600,
        eval_every=10_240,
    ),
    # Bellinger et al. (2022): CartPole (200 steps) and Acrobot, costs 0-0.3 plus vanilla, 10 trials.
    "paper": SweepSpec(
        envs=("CartPole-v0", "Acrobot-v1"),
        agents=("dqn", "ppo"),
        costs=(0.0, 0.1, 0.2, 0.3),
        seeds=tuple(range(10)),
        total_timesteps=491_520,
        eval_every=20_480,
        vanilla=True,
    ),
}

# The replication grid: the paper's three environments x costs 0-0.3 plus vanilla x its three agents x 10 seeds.
# Budgets are per environment (env steps per configuration, steps between evaluations): each environment is its
# own sweep, in its own folder. Every budget is a multiple of every agent's env steps per update (PPO 1,024,
# DQN 4, DRQN 32, PQN 512) so all agents share the evaluation points.
REPLICATE_AGENTS = ("dqn", "ppo", "drqn")
REPLICATE_BUDGETS: dict[str, tuple[int, int]] = {
    # CartPole: DQN and PPO reach the paper's medians within 153,600 steps (the demo), so does DRQN (beating DQN).
    "CartPole-v0": (153_600, 10_240),
    "Acrobot-v1": (491_520, 20_480),
    "LunarLander-v3": (1_048_576, 65_536),  # whole updates of amjax.presets.LUNAR_LANDER_PPO (16 x 1,024 steps)
}
# A smoke version of the same grid (2 seeds, 1/12 to 1/16 of the budget) for trying the command end to end.
QUICK_BUDGETS: dict[str, tuple[int, int]] = {
    "CartPole-v0": (40_960, 10_240),
    "Acrobot-v1": (40_960, 10_240),
    "LunarLander-v3": (65_536, 32_768),
}


def replicate_specs(
    envs: tuple[str, ...] = tuple(REPLICATE_BUDGETS),
    agents: tuple[str, ...] = REPLICATE_AGENTS,
    seeds: int = 10,
    quick: bool = False,
) -> dict[str, SweepSpec]:
    """One sweep per environment of the replication grid (`quick`: the smoke budgets)."""
    budgets = QUICK_BUDGETS if quick else REPLICATE_BUDGETS
    unknown = [env for env in envs if env not in budgets]
    if unknown:
        raise ValueError(f"--env: no replication budget for {', '.join(unknown)}; allowed values: {', '.join(budgets)}")
    base = SweepSpec(costs=(0.0, 0.1, 0.2, 0.3), vanilla=True)
    return {
        env: dataclasses.replace(
            base,
            envs=(env,),
            agents=tuple(agents),
            seeds=tuple(range(seeds)),
            total_timesteps=budgets[env][0],
            eval_every=budgets[env][1],
            # The presets as the sweep's own values (as since the grid's first run: folders keep resuming), so
            # none come again through `env_defaults`.
            hyperparams=env_hyperparams(env, tuple(agents)),
            env_defaults={},
        )
        for env in envs
    }
