"""Learning tests: with the default hyperparameters each agent solves CartPole-v0, and under a measurement cost
it keeps the pole up while measuring less. Each agent trains 3 seeds x 2 costs as one vmapped program."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from amjax.agents import DQN, PPO, DQNConfig, PPOConfig, init_run, run_evals, stack_configs

SEEDS = (0, 1, 2)
COSTS = (0.0, 0.2)
BUDGETS = {
    "ppo": (PPO, PPOConfig(total_timesteps=204_800, eval_every=20_480)),
    # about 60 s of CPU time on 2 cores (about 20 s compiling, 33 s training the 6 configurations)
    "dqn": (DQN, DQNConfig(total_timesteps=150_000, eval_every=10_000)),
}


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(BUDGETS))
def test_solves_cartpole_and_measures_less_under_cost(name):
    algo, base = BUDGETS[name]
    configs = stack_configs([base.replace(cost=c) for c in COSTS for _ in SEEDS])
    keys = jnp.stack([jax.random.PRNGKey(s) for _ in COSTS for s in SEEDS])
    states = jax.jit(lambda cs, ks: jax.lax.map(lambda ck: init_run(algo, *ck), (cs, ks)))(configs, keys)
    _, rows = jax.jit(jax.vmap(lambda c, s: run_evals(algo, c, s, c.num_evals)))(configs, states)
    final_raw = np.asarray(rows.eval_raw_return)[:, -1].reshape(len(COSTS), len(SEEDS))
    final_measured = np.asarray(rows.eval_measurements / rows.eval_length)[:, -1].reshape(len(COSTS), len(SEEDS))
    message = f"final raw returns {final_raw.tolist()}, measured fractions {final_measured.round(3).tolist()}"
    assert np.median(final_raw[0]) >= 195, message  # cost 0: solved
    assert np.median(final_raw[1]) >= 195, message  # cost 0.2: still solved ...
    assert np.median(final_measured[1]) < 0.9, message  # ... while skipping measurements
