"""The unbiased score beside the paper's: each configuration's best policy re-scored on fresh test episodes;
paired seeds across costs and agents; seeds limited to 32 bits."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest

from amjax.agents import ALGORITHMS, init_run, rescore, run_evals, training, training_env
from amjax.agents.rollout import fast_key, reset_envs
from amjax.agents.training import RESCORE_STREAM
from amjax.sweep import SweepSpec, expand, load_sweep_policy, run_sweep
from train.cli import main

SPEC = SweepSpec(
    envs=("CartPole-v0",),
    agents=("ppo",),
    costs=(0.0, 0.3),
    seeds=(0, 1),
    total_timesteps=4096,
    eval_every=1024,
    eval_episodes=2,
    hyperparams={"num_envs": 4, "num_steps": 32, "rescore_episodes": 16},
)


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    return run_sweep(SPEC, tmp_path_factory.mktemp("rescore"), progress=False, target_chunks=2)


@pytest.mark.slow
def test_summary_and_policies_carry_the_rescored_figures(sweep):
    summary = sweep.summary.set_index("config_id")
    assert np.isfinite(summary.best_policy_return).all() and (summary.best_policy_episodes == 16).all()
    assert ((summary.best_policy_measured_fraction >= 0) & (summary.best_policy_measured_fraction <= 1)).all()
    # cost 0: costed and raw returns agree; cost 0.3: the costed return is the raw one less 0.3 per measurement
    free = summary[summary.cost == 0]
    np.testing.assert_allclose(free.best_policy_return, free.best_policy_raw_return, rtol=1e-6)
    # CartPole pays 1 a step, so the raw return is the episode length and the measurements per episode are the
    # measured fraction times it (means over the same episodes).
    paid = summary[summary.cost == 0.3]
    assert len(paid) == 2 and (paid.best_policy_measured_fraction > 0).all()  # the cost was charged
    measurements = paid.best_policy_measured_fraction * paid.best_policy_raw_return
    np.testing.assert_allclose(paid.best_policy_return, paid.best_policy_raw_return - 0.3 * measurements, rtol=1e-5)
    stored = pd.read_parquet(sweep.out / "rescored.parquet").set_index("config_id")
    assert sorted(stored.index) == sorted(summary.index)
    for config_id, row in summary.iterrows():
        info = load_sweep_policy(sweep.out, config_id).info
        assert info["best_policy_return"] == pytest.approx(row.best_policy_return, rel=1e-6)
    table = sweep.table
    assert np.isfinite(table.best_policy_return_median).all()
    assert "best_policy_return_median" in pd.read_csv(sweep.out / "seed_summary.csv").columns


@pytest.mark.slow
def test_sweep_rescore_equals_the_run_alone(sweep):
    """Config i re-scored inside the sweep == the same config trained alone and re-scored."""
    summary = sweep.summary.set_index("config_id")
    for run in expand(SPEC)[:2]:
        algo = ALGORITHMS[run.agent]
        state, _ = jax.jit(lambda c, k, a=algo: run_evals(a, c, init_run(a, c, k), c.num_evals))(
            run.config, jax.random.PRNGKey(run.seed)
        )
        alone = rescore(algo, run.config, state)
        assert float(alone.costed_return) == pytest.approx(summary.loc[run.config_id].best_policy_return, rel=1e-5)


def test_rescoring_episodes_are_not_the_selection_episodes():
    (run,) = expand(SweepSpec(agents=("ppo",), costs=(0.1,), seeds=(3,), total_timesteps=4096, eval_every=1024))
    state = init_run(ALGORITHMS["ppo"], run.config, jax.random.PRNGKey(run.seed))
    env, params, _ = training_env(run.config)

    def first_observations(key):  # what `evaluate` starts its episodes from (its docstring's key rule)
        reset_key, _ = jax.random.split(fast_key(key))
        return np.asarray(reset_envs(env, params, reset_key, 100).obs)

    fresh = first_observations(jax.random.fold_in(state.key, jnp.uint32(RESCORE_STREAM)))
    for i in range(run.config.num_evals):
        selection = first_observations(jax.random.fold_in(state.key, i))
        assert not (fresh[:, None, :] == selection[None, :, :]).all(-1).any(), f"evaluation {i} shares an episode"


def test_seeds_are_paired_across_costs_and_agents():
    spec = SweepSpec(agents=("ppo", "dqn"), costs=(0.1, 0.3), seeds=(0, 1), total_timesteps=4096, eval_every=1024)
    states = {
        (r.agent, r.cost, r.seed): init_run(ALGORITHMS[r.agent], r.config, jax.random.PRNGKey(r.seed))
        for r in expand(spec)
    }

    def same(a, b):
        return all(
            np.array_equal(np.asarray(x, float), np.asarray(y, float), equal_nan=True)
            for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True)
        )

    for agent in ("ppo", "dqn"):
        low, high, other_seed = states[agent, 0.1, 0], states[agent, 0.3, 0], states[agent, 0.1, 1]
        assert same(low.best_params, high.best_params)  # the same network initialisation
        assert same(low.algo.envs.obs, high.algo.envs.obs)  # the same env resets (and DQN warm-up actions)
        assert not same(low.best_params, other_seed.best_params)
        assert not same(low.algo.envs.obs, other_seed.algo.envs.obs)
    # every agent of one seed is evaluated (and re-scored) on the same episodes
    assert np.array_equal(states["ppo", 0.1, 0].key, states["dqn", 0.3, 0].key)
    assert not np.array_equal(states["ppo", 0.1, 0].key, states["ppo", 0.1, 1].key)


def test_seeds_beyond_32_bits_are_refused(tmp_path, capsys):
    expand(SweepSpec(agents=("ppo",), seeds=(2**32 - 1,)))  # the largest allowed
    with pytest.raises(ValueError, match=r"seed: got 4294967296; allowed values: integers in \[0, 4294967295\]"):
        expand(SweepSpec(agents=("ppo",), seeds=(2**32,)))
    with pytest.raises(SystemExit) as exit_info:
        main(["sweep", "--agent", "ppo", "--seed-list", str(2**32 + 5), "--out", str(tmp_path / "never")])
    assert exit_info.value.code == 2 and "seed: got 4294967301" in capsys.readouterr().err
    assert not (tmp_path / "never").exists()


@pytest.mark.parametrize("agent", sorted(ALGORITHMS))
def test_every_agent_rescores_with_more_episodes_than_it_evaluates(agent, monkeypatch):
    """Recurrent agents size their carry by the episode count: re-scoring (100) must not reuse eval_episodes (2)."""
    spec = SweepSpec(
        agents=(agent,),
        costs=(0.2,),
        seeds=(0,),
        total_timesteps=8192,
        eval_every=8192,
        eval_episodes=2,
        hyperparams={"rescore_episodes": 5},
    )
    (run,) = expand(spec)
    algo = ALGORITHMS[agent]
    state = init_run(algo, run.config, jax.random.PRNGKey(0))
    scores = jax.jit(lambda c, s: rescore(algo, c, s))(run.config, state)
    assert np.isfinite(float(scores.costed_return)) and 0.0 <= float(scores.measured_fraction) <= 1.0
    # The episodes it ran, counted: rescore again outside jit, recording what its `evaluate` was asked for and what
    # finished (the same means as the compiled run).
    counted, real_evaluate = [], training.evaluate

    def counting_evaluate(*args):
        finished = real_evaluate(*args)
        counted.append((args[-1], float(finished.count)))
        return finished

    monkeypatch.setattr(training, "evaluate", counting_evaluate)
    again = rescore(algo, run.config, state)
    assert counted == [(5, 5.0)]  # 5 re-scoring episodes (not eval_episodes' 2), each run to its end
    assert float(again.costed_return) == pytest.approx(float(scores.costed_return), rel=1e-5)
