"""Numbers published by the paper amjax replicates, in one place.

Source: C. Bellinger, A. Drozdyuk, M. Crowley and I. Tamblyn, "Balancing Information with Observation Costs in
Deep Reinforcement Learning", Proceedings of the 35th Canadian Conference on Artificial Intelligence (Canadian AI
2022). Medians over 10 trials of the best test costed reward reached during training; the environments are
CartPole with 200-step episodes (amjax's "CartPole-v0") and Acrobot ("Acrobot-v1").
"""

from __future__ import annotations

# Median best test costed reward, per (env, amjax agent name) and cost. The paper's "Dueling DQN" is amjax's "dqn".
PAPER_BEST_RETURN: dict[tuple[str, str], dict[float, float]] = {
    ("CartPole-v0", "dqn"): {0.1: 190.03, 0.2: 180.07, 0.3: 170.10},
}

# The costed reward of an agent that measures on every step of the best episodes (the paper's "always measure"
# line): CartPole 200 x (1 - cost); Acrobot "about" these values (the paper gives them rounded).
PAPER_ALWAYS_MEASURE: dict[str, dict[float, float]] = {
    "CartPole-v0": {0.1: 180.0, 0.2: 160.0, 0.3: 140.0},
    "Acrobot-v1": {0.1: -71.0, 0.2: -78.0, 0.3: -84.0},
}


def _lookup(table: dict[float, float], cost: float) -> float:
    for known, value in table.items():
        if abs(known - cost) < 1e-9:
            return value
    return float("nan")


def paper_best_return(env: str, agent: str, cost: float) -> float:
    """The paper's median best costed reward for (env, agent, cost), or NaN where it gives none."""
    return _lookup(PAPER_BEST_RETURN.get((env, agent), {}), cost)


def paper_always_measure(env: str, cost: float) -> float:
    """The paper's always-measure costed reward for (env, cost), or NaN where it gives none."""
    return _lookup(PAPER_ALWAYS_MEASURE.get(env, {}), cost)
