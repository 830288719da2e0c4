"""Learning tests: with the default hyperparameters each agent solves CartPole-v0, and under a measurement cost
its best policy (the paper's metric, and the policy a sweep saves) keeps the pole up while measuring less. Each
agent trains 3 seeds x 2 costs as one vmapped program.

At cost 0.2 the test looks at the best evaluation, not the last: PPO's final policy at this budget collapses now and
then after having solved the task (over 24 seeds, before and after the throughput work: median final raw return
185.7 / 198.6, every run's best evaluation >= 181 / 184), so a 3-seed median of final returns passes or fails by
seed luck. At cost 0 the final policy must still be solved.

On Acrobot-v1 (-1 per step) PPO with unscaled rewards stopped measuring within 60k steps at cost 0.3 and never
reached the goal again; with Acrobot's preset hyperparameters it keeps measuring and reaches it
(docs/acrobot.md). On LunarLander-v3 its unscaled critic lagged the returns and the costed lander hovered
(docs/lunar_lander.md)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from amjax.agents import (
    DQN,
    DRQN,
    PPO,
    PPO_RNN,
    PQN,
    PQN_RNN,
    DQNConfig,
    DRQNConfig,
    PPOConfig,
    PPORNNConfig,
    PQNConfig,
    PQNRNNConfig,
    init_run,
    run_evals,
    stack_configs,
)
from amjax.presets import preset

SEEDS = (0, 1, 2)
COSTS = (0.0, 0.2)
BUDGETS = {
    "ppo": (PPO, PPOConfig(total_timesteps=204_800, eval_every=20_480)),
    # about 60 s of CPU time on 2 cores (about 20 s compiling, 33 s training the 6 configurations)
    "dqn": (DQN, DQNConfig(total_timesteps=150_000, eval_every=10_000)),
    "pqn": (PQN, PQNConfig(total_timesteps=102_400, eval_every=10_240)),
    "pqn-rnn": (PQN_RNN, PQNRNNConfig(total_timesteps=102_400, eval_every=10_240)),
}


def train_rows(algo, configs: list, seeds: list[int]):
    """Train `configs` (one per seed in `seeds`) as one vmapped program; their `EvalRow`s [configs, evals]."""
    stacked = stack_configs(configs)
    keys = jnp.stack([jax.random.PRNGKey(s) for s in seeds])
    states = jax.jit(jax.vmap(lambda c, k: init_run(algo, c, k)))(stacked, keys)
    _, rows = jax.jit(jax.vmap(lambda c, s: run_evals(algo, c, s, c.num_evals)))(stacked, states)
    return rows


def at_best_evaluation(rows, *values):
    """Each configuration's `values` (arrays [configs, evals]) at its best test costed return (the paper's metric,
    and the policy a sweep saves)."""
    best = np.argmax(np.asarray(rows.test.costed_return), axis=1)
    return [np.asarray(value)[np.arange(len(best)), best] for value in values]


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(BUDGETS))
def test_solves_cartpole_and_measures_less_under_cost(name):
    algo, base = BUDGETS[name]
    rows = train_rows(algo, [base.replace(cost=c) for c in COSTS for _ in SEEDS], [s for _ in COSTS for s in SEEDS])
    shape = (len(COSTS), len(SEEDS))
    raw = np.asarray(rows.test.raw_return)
    best_raw, best_measured = (v.reshape(shape) for v in at_best_evaluation(rows, raw, rows.test.measured_fraction))
    final_raw = raw[:, -1].reshape(shape)
    message = (
        f"final raw returns {final_raw.tolist()}; at the best evaluation: raw {best_raw.tolist()}, "
        f"measured fractions {best_measured.round(3).tolist()}"
    )
    assert np.median(final_raw[0]) >= 195, message  # cost 0: solved, and still solved at the end
    assert np.median(best_raw[1]) >= 195, message  # cost 0.2: the best policy keeps the pole up ...
    assert np.median(best_measured[1]) < 0.9, message  # ... while skipping measurements


@pytest.mark.slow
def test_drqn_skips_measurements_at_the_default_budget():
    """Issue 55's guard: at the budget a user's first sweep uses (`SweepSpec`'s 102,400 steps, an evaluation every
    10,240), DRQN at cost 0.3 learns to skip several measurements in a row. A memoryless agent can do no better than
    measure every other step (costed return 200 - 0.3 x 100 = 170; Dueling DQN's median best is 169-170 on every
    seed set tried), so the median best evaluation must clear 175 while measuring on under 40% of steps. With the
    earlier default learning rate (2e-3) 4 of 10 seeds never learnt to skip at this budget (docs/research/
    drqn_default_budget.md): a speed change that costs the skipping policy fails here. (It catches a full loss: on
    these seeds 2e-3 itself passes narrowly, 176.9 at 38.5%; section 9 there.)"""
    config = DRQNConfig(total_timesteps=102_400, eval_every=10_240, cost=0.3)
    rows = train_rows(DRQN, [config] * len(SEEDS), list(SEEDS))
    best_costed, best_measured = at_best_evaluation(rows, rows.test.costed_return, rows.test.measured_fraction)
    message = f"best costed returns {best_costed.round(1).tolist()}, measured there {best_measured.round(3).tolist()}"
    assert np.median(best_costed) >= 175, message
    assert np.median(best_measured) < 0.4, message


def assert_keeps_measuring_and_reaches_goal(rows, min_measured: float, max_collapsed: int = 0) -> None:
    """On Acrobot-v1: the training episodes of the last evaluation period measure on more than `min_measured` of
    their steps on every seed but at most `max_collapsed`, and their median length is under 250 steps (unsolved
    episodes stop at 500)."""
    measured = np.asarray(rows.train.measured_fraction)[:, -1]
    length = np.asarray(rows.train.length)[:, -1]
    message = f"training episodes' measured fractions {measured.round(3).tolist()}, lengths {length.round(1).tolist()}"
    assert np.sum(measured <= min_measured) <= max_collapsed, message  # (almost) no seed stops measuring ...
    assert np.median(length) < 250, message  # ... and they reach the goal


@pytest.mark.slow
def test_ppo_keeps_measuring_on_acrobot_under_cost():
    """The collapse this catches: PPO's training episodes measuring on ~2-7% of steps and lasting all 500 steps, by
    40k steps. With the old defaults (unscaled rewards) it fails on every seed tried; with Acrobot's preset but a
    clipped critic, 3 of these 12 seeds collapse (measured 0.06 / 0.07 / 0.04 in steps 20k-41k; the lowest
    unclipped seed measures 0.20). One seed may: the preset itself collapsed on seed 11 (0.015, 500 steps) on a 2-core
    AMD EPYC with AVX-512, whose float rounding differs, while the other 11 measured on 31-58% of steps; there the
    clipped critic collapses on 2 of the 12 (0.039 / 0.070), still caught."""
    seeds = list(range(12))
    config = PPOConfig(
        env_id="Acrobot-v1", cost=0.3, total_timesteps=40_960, eval_every=20_480, **preset("Acrobot-v1", "ppo")
    )
    rows = train_rows(PPO, [config] * len(seeds), seeds)
    assert_keeps_measuring_and_reaches_goal(rows, min_measured=0.1, max_collapsed=1)  # the last 20,480 steps


@pytest.mark.slow
def test_recurrent_ppo_keeps_measuring_on_acrobot_under_cost():
    """The same collapse for recurrent PPO (docs/acrobot.md, run 15): with CartPole's defaults its training episodes
    measured on 3-7% of steps and lasted 456-500 steps by 40,960 steps at cost 0.3 on every tuning seed (100-103);
    with its Acrobot preset they measured on 61-78% and lasted 92-94. On this test's seeds: defaults 5-8% and 491-500
    steps, the preset 69-92% and 93-99 steps."""
    config = PPORNNConfig(
        env_id="Acrobot-v1", cost=0.3, total_timesteps=40_960, eval_every=20_480, **preset("Acrobot-v1", "ppo-rnn")
    )
    seeds = list(range(6))
    rows = train_rows(PPO_RNN, [config] * len(seeds), seeds)
    assert_keeps_measuring_and_reaches_goal(rows, min_measured=0.2)  # the last 20,480 steps' episodes


@pytest.mark.slow
def test_ppo_lands_under_cost_on_lunar_lander():
    """The critic lag this catches (docs/lunar_lander.md, "PPO's critic"): with unscaled rewards (returns of -200 to
    +300 at gamma 0.999) value clipping lets PPO's critic move 0.2 per update, and at cost 0.3 the lander learns to
    hover, paying for measurements through long episodes: the costed returns of the training episodes that ended in
    steps 196-262k were -52 / -107 / -112 on the tuning seeds 100-102, against -17 / -32 / -22 with the preset's
    scaled rewards. 16 updates of the preset (its schedules do not depend on the budget)."""
    config = PPOConfig(
        env_id="LunarLander-v3", cost=0.3, total_timesteps=262_144, eval_every=65_536, **preset("LunarLander-v3", "ppo")
    )
    rows = train_rows(PPO, [config] * len(SEEDS), list(SEEDS))
    costed = np.asarray(rows.train.costed_return)[:, -1]  # the episodes that ended in the last 65,536 steps
    length = np.asarray(rows.train.length)[:, -1]
    message = f"training episodes' costed returns {costed.round(1).tolist()}, lengths {length.round(1).tolist()}"
    assert np.median(costed) > -50, message


@pytest.mark.slow
def test_ppo_swings_up_pendulum():
    """Box control: PPO's Gaussian head with Pendulum-v1's preset (vanilla) swings the pendulum up and holds it.
    Gymnasium-style returns: about -1,200 for a random policy, -150 for a good one (episodes of 200 steps)."""
    config = PPOConfig(
        env_id="Pendulum-v1", vanilla=True, total_timesteps=204_800, eval_every=20_480, **preset("Pendulum-v1", "ppo")
    )
    rows = train_rows(PPO, [config] * len(SEEDS), list(SEEDS))
    best = np.asarray(rows.test.raw_return).max(axis=1)
    assert np.median(best) >= -200, f"best test returns per seed {best.round(1).tolist()}"


@pytest.mark.slow
def test_ppo_balances_brax_inverted_pendulum():
    """brax (the optional extra): PPO's Gaussian head with the default hyperparameters (vanilla) balances brax's
    inverted_pendulum: 1 per step while the pole is within 0.2 rad of upright, 1,000-step episodes; the first
    evaluations, after 10,240 steps, last about 50 to 70 steps. At 122,880 steps the outcome hung on the machine's
    float rounding (seeds 0-2 passed on a 2-core Intel Xeon, scored 897 / 1000 / 632 on a 2-core AMD EPYC); at
    204,800 steps seeds 0-5 all reach 1,000 on the AMD EPYC (87 s for the 6)."""
    pytest.importorskip("brax")
    config = PPOConfig(
        env_id="brax:inverted_pendulum", vanilla=True, total_timesteps=204_800, eval_every=10_240, eval_episodes=5
    )
    rows = train_rows(PPO, [config] * len(SEEDS), list(SEEDS))
    best = np.asarray(rows.test.raw_return).max(axis=1)
    assert np.median(best) >= 950, f"best test returns per seed {best.round(1).tolist()}"


@pytest.mark.slow
def test_a_single_cost_range_trains_like_the_fixed_cost():
    """A conditioned run whose range is the single cost 0.2 trains, in distribution over 24 seeds, like an ordinary
    run at 0.2 (two-sided Mann-Whitney U on each seed's mean test costed return and measured fraction over its
    evaluations, p > 0.001): the conditioned network only sees one more, constant, input. The same test tells the
    ordinary run from a conditioned one charged 0.6 (p < 0.001), so it has the power to catch a wrong charge."""
    from scipy.stats import mannwhitneyu

    seeds = list(range(100, 124))
    base = PPOConfig(total_timesteps=40_960, eval_every=10_240)
    conditioned = base.replace(cost_conditioned=True)

    def per_seed(config):
        rows = train_rows(PPO, [config] * len(seeds), seeds)
        return (np.asarray(rows.test.costed_return).mean(axis=1), np.asarray(rows.test.measured_fraction).mean(axis=1))

    ordinary = per_seed(base.replace(cost=0.2))
    single = per_seed(conditioned.replace(cost_low=0.2, cost_high=0.2))
    dearer = per_seed(conditioned.replace(cost_low=0.6, cost_high=0.6))
    for name, a, b in zip(("costed return", "measured fraction"), ordinary, single, strict=True):
        p = mannwhitneyu(a, b).pvalue
        assert p > 1e-3, f"{name}: ordinary {np.median(a):.3f} vs single-cost range {np.median(b):.3f}, p = {p:.2g}"
    p = mannwhitneyu(ordinary[0], dearer[0]).pvalue
    assert p < 1e-3, f"cost 0.2 vs a 0.6 range: medians {np.median(ordinary[0]):.1f} / {np.median(dearer[0]):.1f}"


@pytest.mark.slow
def test_dqn_cnn_catches_on_an_image():
    """An image observation: Dueling DQN picks the MinAtar CNN for bsuite's Catch ([10, 5] board + the flag channel;
    +1 for a catch, -1 for a miss, 9 steps an episode; a random policy scores about -0.6) and catches the ball
    under cost 0.01 within 30,720 steps (in `amjax sweep`, seeds 0-2 re-scored 0.99 / 0.97 / 0.94 on 50 fresh
    episodes, measuring on 10% / 39% / 69% of their steps)."""
    config = DQNConfig(env_id="Catch-bsuite", cost=0.01, total_timesteps=30_720, eval_every=10_240, eval_episodes=20)
    rows = train_rows(DQN, [config] * len(SEEDS), list(SEEDS))
    best, measured = at_best_evaluation(rows, rows.test.costed_return, rows.test.measured_fraction)
    message = f"best test costed returns {best.round(2).tolist()}, measured fractions {measured.round(3).tolist()}"
    assert np.median(best) >= 0.8, message
    assert np.median(measured) < 0.7, message  # the ball falls straight down: one look is enough
