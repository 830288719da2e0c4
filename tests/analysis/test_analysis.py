"""amjax.analysis: figures on a real (tiny) sweep, the paper table by hand, measurement maps vs a hand loop, the
report and its command line."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import pytest  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

import amjax  # noqa: E402
from amjax import analysis  # noqa: E402
from amjax.agents import ppo  # noqa: E402
from amjax.agents.rollout import fast_key  # noqa: E402
from amjax.sweep import SweepSpec, run_sweep  # noqa: E402
from train import report as report_cli  # noqa: E402

TINY = SweepSpec(
    envs=("CartPole-v0",),
    agents=("ppo",),
    costs=(0.0, 0.2),
    seeds=(0, 1),
    total_timesteps=4096,
    eval_every=1024,
    eval_episodes=2,
    vanilla=True,
    hyperparams={"num_envs": 4, "num_steps": 32},
)


@pytest.fixture(scope="module")
def sweep_dir(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("sweep")
    run_sweep(TINY, out, progress=False)
    return out


@pytest.fixture(scope="module")
def data(sweep_dir) -> analysis.SweepData:
    return analysis.load_results(sweep_dir)


def _partial_copy(src: Path, dst: Path, keep) -> Path:
    """A sweep folder holding only the result rows `keep(results)` selects (as a partly finished sweep)."""
    dst.mkdir()
    shutil.copy(src / "metadata.json", dst / "metadata.json")
    results = pd.read_parquet(src / "results.parquet")
    results[keep(results)].to_parquet(dst / "results.parquet", index=False)
    return dst


def _nonempty_image(path: Path) -> None:
    assert path.exists() and path.stat().st_size > 1000, path


# -- loading -----------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_load_results(data, sweep_dir):
    results, summary, metadata = data
    assert len(results) == 6 * 4  # (2 costs + vanilla) x 2 seeds, 4 evaluations each
    assert len(summary) == 6 and metadata["spec"] == TINY.to_json()
    stored = pd.read_parquet(sweep_dir / "summary.parquet").set_index("config_id").sort_index()
    ours = summary.set_index("config_id").sort_index()
    np.testing.assert_allclose(ours.best_return, stored.best_return)
    assert analysis.load_results(sweep_dir).results.equals(results)


@pytest.mark.slow
def test_load_results_errors(tmp_path, sweep_dir):
    with pytest.raises(analysis.NotASweepError, match="no such folder"):
        analysis.load_results(tmp_path / "missing")
    with pytest.raises(analysis.NotASweepError, match="not a sweep folder"):
        analysis.load_results(tmp_path)
    started = tmp_path / "started"
    started.mkdir()
    shutil.copy(sweep_dir / "metadata.json", started / "metadata.json")
    with pytest.raises(analysis.NotASweepError, match="no results yet"):
        analysis.load_results(started)


# -- figures on the real sweep --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "name, draw",
    [
        ("curves", lambda d: analysis.learning_curves(d.results)),
        ("curves_raw", lambda d: analysis.learning_curves(d.results, raw=True, bound="episodes")),
        ("vanilla", lambda d: analysis.vanilla_vs_cost0(d.results)),
        ("costs", lambda d: analysis.cost_analysis(d.summary, d.results)),
        ("bars", lambda d: analysis.agent_comparison(d.summary, d.results)),
    ],
)
def test_plots_write_images(data, tmp_path, name, draw):
    fig = draw(data)
    assert isinstance(fig, Figure) and fig.axes
    for suffix in (".png", ".svg"):
        analysis.save_figure(fig, tmp_path / f"{name}{suffix}")
        _nonempty_image(tmp_path / f"{name}{suffix}")


def test_plot_path_argument_and_bound(data, tmp_path):
    fig = analysis.learning_curves(data.results, path=tmp_path / "c.png")
    _nonempty_image(tmp_path / "c.png")
    # The dotted bound at cost 0.2 is the best observed test episodes, always measured.
    rows = data.results
    expected = (rows.eval_raw_return - 0.2 * rows.eval_length).max()
    levels = [line.get_ydata()[0] for line in fig.axes[0].lines if line.get_linestyle() == ":"]
    assert levels == pytest.approx([expected])


def test_vanilla_figure_needs_vanilla_runs(data):
    with pytest.raises(ValueError, match="vanilla"):
        analysis.vanilla_vs_cost0(data.results[~data.results.vanilla])
    with pytest.raises(ValueError, match="no results"):
        analysis.learning_curves(data.results, envs=["Acrobot-v1"])


# -- tables by hand ---------------------------------------------------------------------------------------------


def _hand_tables() -> tuple[pd.DataFrame, pd.DataFrame]:
    summary = pd.DataFrame(
        {
            "config_id": list("abcdefg"),
            "env": ["CartPole-v0"] * 4 + ["Acrobot-v1"] * 2 + ["CartPole-v0"],
            "agent": ["dqn"] * 4 + ["ppo"] * 2 + ["dqn"],
            "vanilla": [False] * 6 + [True],
            "cost": [0.1] * 4 + [0.2] * 2 + [0.0],
            "seed": [0, 1, 2, 3, 0, 1, 0],
            "best_return": [170.0, 186.0, 194.0, 200.0, -90.0, -80.0, 200.0],
            "best_measured_fraction": [0.4, 0.5, 0.6, 0.7, 0.9, 1.0, 1.0],
            "diverged": [False, False, False, True, False, False, False],
        }
    )
    results = pd.DataFrame(
        {
            "env": ["CartPole-v0", "CartPole-v0", "CartPole-v0", "Acrobot-v1", "Acrobot-v1", "Acrobot-v1"],
            "cost": [0.1, 0.1, 0.1, 0.2, 0.2, 0.2],
            "eval_raw_return": [200.0, 150.0, 500.0, -63.0, -100.0, np.nan],
            "eval_length": [200.0, 150.0, 500.0, 64.0, 100.0, np.nan],
            "diverged": [False, False, True, False, False, False],  # a diverged point never sets the bound
        }
    )
    return summary, results


def test_paper_table_by_hand():
    summary, results = _hand_tables()
    table = analysis.paper_table(summary, results).set_index(["env", "agent", "vanilla", "cost"])
    cart = table.loc[("CartPole-v0", "dqn", False, 0.1)]
    assert cart.seeds == 4 and cart.diverged == 1
    # best returns 170, 186, 194, 200: median 190, quartiles by linear interpolation 182 and 195.5
    assert (cart.best_return, cart.best_return_q25, cart.best_return_q75) == pytest.approx((190.0, 182.0, 195.5))
    assert (cart.measured_fraction, cart.measurement_reduction) == pytest.approx((0.55, 0.45))
    assert cart.always_measure == pytest.approx(200 - 0.1 * 200)  # 180, not 150 - 15 nor the diverged 450
    assert cart.gain_vs_always_measure == pytest.approx(10.0)
    assert (cart.paper_best_return, cart.paper_always_measure) == (190.03, 180.0)
    acro = table.loc[("Acrobot-v1", "ppo", False, 0.2)]
    assert acro.best_return == pytest.approx(-85.0)
    assert acro.always_measure == pytest.approx(-63 - 0.2 * 64)
    assert np.isnan(acro.paper_best_return) and acro.paper_always_measure == -78.0
    vanilla = table.loc[("CartPole-v0", "dqn", True, 0.0)]
    assert vanilla.best_return == 200.0 and np.isnan(vanilla.always_measure) and np.isnan(vanilla.paper_best_return)
    assert np.isnan(analysis.paper_table(summary).always_measure).all()  # no results: no bound from data


def test_seed_spread_by_hand():
    summary, _ = _hand_tables()
    spread = analysis.seed_spread(summary.assign(best_policy_return=summary.best_return - 1.0))
    cart = spread.set_index(["env", "agent", "vanilla", "cost"]).loc[("CartPole-v0", "dqn", False, 0.1)]
    best = np.array([170.0, 186.0, 194.0, 200.0])
    assert cart.seeds == 4
    assert (cart.best_return_mean, cart.best_return_min, cart.best_return_max) == (187.5, 170.0, 200.0)
    assert cart.best_return_sd == pytest.approx(np.std(best, ddof=1))  # the sample sd, over seeds
    assert cart.rescored_return_mean == 186.5 and cart.rescored_return_sd == pytest.approx(cart.best_return_sd)
    one = spread.set_index(["env", "agent", "vanilla", "cost"]).loc[("CartPole-v0", "dqn", True, 0.0)]
    assert one.seeds == 1 and one.best_return_mean == 200.0 and np.isnan(one.best_return_sd)
    assert analysis.seed_spread(summary).rescored_return_mean.isna().all()  # not re-scored: NaN, not an error


def test_paper_table_on_sweep_and_markdown(data):
    table = analysis.paper_table(data.summary, data.results)
    assert len(table) == 3 and set(table.seeds) == {2}
    text = analysis.to_markdown(table)
    assert text.count("\n") == len(table) + 1 and "CartPole-v0" in text and "nan" not in text


def test_best_hyperparams_picks_the_best_median():
    summary = pd.DataFrame(
        {
            "env": ["E"] * 4,
            "agent": ["ppo"] * 4,
            "vanilla": [False] * 4,
            "cost": [0.1] * 4,
            "seed": [0, 1, 0, 1],
            "learning_rate": [1e-3, 1e-3, 3e-4, 3e-4],
            "env_steps": [4096] * 4,
            "best_return": [10.0, 20.0, 30.0, 5.0],  # medians 15 and 17.5
        }
    )
    chosen = analysis.best_hyperparams(summary)
    assert list(chosen.learning_rate) == [3e-4, 3e-4]
    assert (
        analysis.to_markdown(analysis.paper_table(summary.assign(best_measured_fraction=0.5, diverged=False))).count(
            "| 0.0003 |"
        )
        == 1
    )  # the table keeps every combination
    assert analysis.best_hyperparams(summary.drop(columns="learning_rate")).equals(
        summary.drop(columns="learning_rate")
    )


# -- measurement maps ------------------------------------------------------------------------------------------

NUM_EPISODES, MAX_STEPS = 3, 40


def _alternating_policy(num_controls: int, num_envs: int):
    """Push right; measure on the even steps of each episode (a step counter in the carry, reset on `first`)."""

    def act(batch, count, key):
        count = jnp.where(batch.first, 0, count)
        return 1 + num_controls * (count % 2 == 0), count + 1, None

    return act, jnp.zeros(num_envs, jnp.int32)


def _always_policy(num_controls: int):
    def act(batch, carry, key):
        return jnp.full(batch.obs.shape[0], 1 + num_controls), carry, None

    return act, None


def _by_hand(env, params, key, measure_at) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Step each episode in a Python loop with the recorder's keys; returns measured, active, costed returns."""
    reset_key, run_key = jax.random.split(fast_key(key))
    reset_keys = jax.random.split(reset_key, NUM_EPISODES)
    env_keys = [jax.random.split(k)[1] for k in jax.random.split(run_key, MAX_STEPS)]
    measured = np.zeros((NUM_EPISODES, MAX_STEPS), bool)
    active = np.zeros((NUM_EPISODES, MAX_STEPS), bool)
    returns = np.zeros(NUM_EPISODES)
    for i in range(NUM_EPISODES):
        _, state = env.reset(reset_keys[i], params)
        for t in range(MAX_STEPS):
            action = 1 + env.num_controls * int(measure_at(t))
            _, state, reward, terminated, truncated, info = env.step(
                jax.random.split(env_keys[t], NUM_EPISODES)[i], state, action, params
            )
            active[i, t], measured[i, t] = True, bool(info["measured"])
            returns[i] += float(reward)
            if terminated or truncated:
                break
    return measured, active, returns


@pytest.mark.parametrize("pattern", ["always", "alternating"])
def test_record_measurements_matches_hand_loop(pattern):
    env, params = amjax.make("CartPole-v0", cost=0.25)
    key = jax.random.key(3)
    if pattern == "always":
        policy, measure_at = _always_policy(env.num_controls), lambda t: True
    else:
        policy, measure_at = _alternating_policy(env.num_controls, NUM_EPISODES), lambda t: t % 2 == 0
    mmap = analysis.record_measurements(env, params, policy, key, NUM_EPISODES, MAX_STEPS)
    measured, active, returns = _by_hand(env, params, key, measure_at)
    np.testing.assert_array_equal(mmap.active, active)
    np.testing.assert_array_equal(mmap.measured, measured)
    np.testing.assert_allclose(mmap.costed_return, returns, rtol=1e-5)
    assert active[:, 0].all() and not active.all()  # pushing right ends every episode within 40 steps
    if pattern == "always":
        np.testing.assert_array_equal(mmap.measured, mmap.active)
        assert mmap.measured_fraction == 1.0
    else:
        steps = np.arange(MAX_STEPS)[None, :]
        np.testing.assert_array_equal(mmap.measured, mmap.active & (steps % 2 == 0))
    np.testing.assert_allclose(mmap.raw_return - 0.25 * mmap.measured.sum(1), mmap.costed_return, rtol=1e-5)
    grid = mmap.grid()
    assert set(np.unique(grid)) <= {0, 1, 2} and (grid[~mmap.active] == 2).all()


def test_record_agent_and_plot(tmp_path):
    config = ppo.PPOConfig(env_id="CartPole-v0", cost=0.2, num_envs=4, num_steps=32, hidden=(16,))
    setup = ppo.PPO.setup(config)
    params = ppo.init(config, setup, jax.random.key(0)).params  # an untrained policy is enough to test the plumbing
    key = jax.random.key(1)
    mmap = analysis.record_agent(config, params, key, num_episodes=4)
    max_steps = setup.max_steps
    by_policy = analysis.record_measurements(setup.env, setup.env_params, ppo.greedy(config, setup, params, 4), key, 4)
    assert mmap.measured.shape == (4, max_steps) == (4, 200)
    np.testing.assert_array_equal(mmap.measured, by_policy.measured)
    np.testing.assert_array_equal(mmap.active, by_policy.active)
    fig = analysis.plot_measurement_map(
        {"cost 0.2": mmap, "again": by_policy}, title="untrained", path=tmp_path / "map.png"
    )
    assert len(fig.axes) == 2
    _nonempty_image(tmp_path / "map.png")
    analysis.save_figure(analysis.plot_measurement_map(mmap), tmp_path / "single.svg")
    _nonempty_image(tmp_path / "single.svg")


def test_record_agent_sizes_a_recurrent_carry():
    from amjax.agents import ALGORITHMS

    if "drqn" not in ALGORITHMS:
        pytest.skip("no recurrent agent registered")
    algo = ALGORITHMS["drqn"]
    config = algo.config_type(env_id="CartPole-v0", cost=0.2)
    assert config.eval_episodes != 3  # the carry is resized to the recorded episodes
    mmap = analysis.record_agent(
        config, algo.params(algo.init(config, algo.setup(config), jax.random.key(0))), jax.random.key(1), num_episodes=3
    )
    assert mmap.measured.shape == (3, 200) and mmap.active[:, 0].all()


def test_agent_config_from_metadata(data):
    config = analysis.agent_config(data.metadata, "ppo", cost=0.3)
    assert (config.num_envs, config.num_steps, config.total_timesteps, config.cost) == (4, 32, 4096, 0.3)
    assert not config.vanilla and config.env_id == "CartPole-v0"
    legacy = {"spec": data.metadata["spec"]}  # a folder written before the runner stored agent configs
    assert analysis.agent_config(legacy, "ppo", cost=0.3) == config
    with pytest.raises(ValueError, match="unknown agent"):
        analysis.agent_config(data.metadata, "a2c")


# -- report --------------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_write_report(sweep_dir, tmp_path):
    report = analysis.write_report(sweep_dir, tmp_path / "report", formats=("png", "svg"))
    text = report.read_text()
    assert "Status: finished" in text and "| CartPole-v0 | ppo | cost 0.2 |" in text and "Not drawn" not in text
    for name in ("learning_curves", "learning_curves_raw", "vanilla_vs_cost0", "cost_analysis", "agent_comparison"):
        assert f"figures/{name}.png" in text
        _nonempty_image(report.parent / "figures" / f"{name}.png")
        _nonempty_image(report.parent / "figures" / f"{name}.svg")
    assert len(pd.read_csv(report.parent / "paper_table.csv")) == 3
    assert "## Spread over seeds" in text and "| best sd |" in text  # beside the medians, one row per setting
    # Measurement maps of the saved best policies: one figure per env x agent, one panel per cost.
    assert "figures/maps_CartPole-v0_ppo.png" in text and "cost 0.2: seed" in text
    _nonempty_image(report.parent / "figures" / "maps_CartPole-v0_ppo.png")
    assert "Not drawn (maps=False" in analysis.write_report(sweep_dir, tmp_path / "nomaps", maps=False).read_text()


@pytest.mark.slow
def test_report_on_partial_sweep(sweep_dir, tmp_path):
    # No vanilla, one cost, one seed, half the evaluations: as a sweep interrupted early.
    partial = _partial_copy(
        sweep_dir,
        tmp_path / "partial",
        lambda r: ~r.vanilla & (r.cost == 0.2) & (r.seed == 0) & (r.env_steps <= 2048),
    )
    report = analysis.write_report(partial)
    text = report.read_text()
    assert report == partial / "report" / "report.md"
    assert "partial" in text and "1 of 6 configurations" in text and "2 of 24 evaluation points" in text
    assert "Not drawn: vanilla_vs_cost0" in text
    assert "No saved policies in this sweep folder" in text  # the copy holds results only
    _nonempty_image(partial / "report" / "figures" / "learning_curves.png")


@pytest.mark.slow
def test_report_command(sweep_dir, tmp_path, capsys):
    assert report_cli.main([str(sweep_dir), "--out", str(tmp_path / "r")]) == 0
    assert (tmp_path / "r" / "report.md").exists()
    assert report_cli.main([str(tmp_path / "missing")]) == 2
    assert "no such folder" in capsys.readouterr().err
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "metadata.json").write_text(json.dumps({"something": 1}))
    assert report_cli.main([str(tmp_path / "other")]) == 2
    assert "not a sweep's metadata" in capsys.readouterr().err
    assert not (tmp_path / "other" / "report").exists()
