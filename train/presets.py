"""Named sweeps. `demo` is the README's quick start; `paper` is the grid of Bellinger et al. (2022)."""

from __future__ import annotations

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
