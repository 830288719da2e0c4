"""`python -m train replicate`: one resumable sweep per environment, reports, an index with wall times."""

from __future__ import annotations

import json

import pandas as pd
import pytest

from amjax.files import folder_lock
from train import presets
from train.cli import main


def test_replication_grid_is_the_papers():
    specs = presets.replicate_specs()
    assert list(specs) == ["CartPole-v0", "Acrobot-v1", "LunarLander-v3"]
    for env, spec in specs.items():
        assert spec.envs == (env,) and spec.agents == ("dqn", "ppo", "drqn") and spec.vanilla
        assert spec.costs == (0.0, 0.1, 0.2, 0.3) and spec.seeds == tuple(range(10))
    from amjax.sweep.grid import expand

    assert sum(len(expand(spec)) for spec in specs.values()) == 3 * 5 * 3 * 10
    # LunarLander's PPO runs use the tuned settings, its DQN runs four envs at the default replay ratio with scaled
    # rewards (agent-scoped: DRQN keeps its defaults).
    lunar = {r.agent: r.config for r in expand(specs["LunarLander-v3"])}
    assert lunar["ppo"].num_envs == 16 and lunar["ppo"].gamma == pytest.approx(0.999)
    assert lunar["ppo"].eval_policy == "greedy_control"  # a costed run's greedy policy crashes (docs/eval_policy.md)
    assert lunar["dqn"].gamma == pytest.approx(0.99) and lunar["dqn"].steps_per_update() == 4
    assert (lunar["dqn"].num_envs, lunar["dqn"].train_freq, lunar["drqn"].train_freq) == (4, 1, 8)
    # scaled rewards: DQN's and PPO's presets (PPO's critic, docs/lunar_lander.md), not DRQN
    assert (lunar["dqn"].reward_scale, lunar["ppo"].reward_scale, lunar["drqn"].reward_scale) == (0.1, 0.01, 1.0)
    assert presets.replicate_specs(("LunarLander-v3",), ("drqn",))["LunarLander-v3"].hyperparams == {}


def test_default_grid_is_the_papers_and_extended_adds_the_recurrent_agents():
    from amjax.sweep.grid import expand
    from train.replicate import replicate_grid

    envs = tuple(presets.REPLICATE_BUDGETS)
    paper = replicate_grid(envs)
    assert {env: spec.agents for env, spec in paper.items()} == {
        "CartPole-v0": ("dqn", "ppo", "drqn"),
        "Acrobot-v1": ("dqn", "ppo"),
        "LunarLander-v3": ("dqn", "ppo"),
    }
    assert sum(len(expand(spec)) for spec in paper.values()) == (3 + 2 + 2) * 5 * 10 == 350
    extended = replicate_grid(envs, extended=True)
    assert all(spec.agents == ("dqn", "ppo", "drqn", "ppo-rnn", "pqn", "pqn-rnn") for spec in extended.values())
    assert sum(len(expand(spec)) for spec in extended.values()) == 3 * 6 * 5 * 10 == 900
    # PQN's LunarLander-v3 preset (gamma 0.995, docs/pqn.md), not recurrent PQN's nor on other envs
    configs = {(r.env, r.agent): r.config for spec in extended.values() for r in expand(spec)}
    gammas = {key: config.gamma for key, config in configs.items()}
    assert gammas["LunarLander-v3", "pqn"] == pytest.approx(0.995)
    assert gammas["LunarLander-v3", "pqn-rnn"] == gammas["Acrobot-v1", "pqn"] == pytest.approx(0.99)
    # PQN's CartPole-v0 preset (a 64x64 network), not recurrent PQN's nor on other envs
    widths = {key: tuple(config.hidden) for key, config in configs.items()}
    assert widths["CartPole-v0", "pqn"] == (64, 64) and widths["CartPole-v0", "pqn-rnn"] == (64,)
    assert widths["Acrobot-v1", "pqn"] == widths["LunarLander-v3", "pqn"] == (128, 128)
    assert replicate_grid(("Acrobot-v1",), ("drqn",))["Acrobot-v1"].agents == ("drqn",)
    # DRQN's Acrobot-v1 preset (rewards x 0.1, docs/acrobot.md run 14), not on other envs
    scales = {key: config.reward_scale for key, config in configs.items()}
    assert scales["Acrobot-v1", "drqn"] == pytest.approx(0.1)
    assert scales["CartPole-v0", "drqn"] == scales["LunarLander-v3", "drqn"] == 1.0
    # recurrent PPO's LunarLander-v3 preset (rewards x 0.01, the stochastic test policy; docs/lunar_lander.md)
    lander = configs["LunarLander-v3", "ppo-rnn"]
    assert (lander.reward_scale, lander.eval_policy) == (pytest.approx(0.01), "stochastic")
    # recurrent PPO's Acrobot-v1 preset (PPO's fixes and a measure prior of 0.9; docs/acrobot.md run 15)
    acrobot = configs["Acrobot-v1", "ppo-rnn"]
    assert (acrobot.reward_scale, acrobot.update_epochs, acrobot.clip_value) == (pytest.approx(0.1), 10, False)
    assert (acrobot.ent_coef, acrobot.measure_prior) == (0.0, pytest.approx(0.9))
    assert (configs["CartPole-v0", "ppo-rnn"].reward_scale, configs["CartPole-v0", "ppo-rnn"].eval_policy) == (
        1.0,
        "greedy",
    )


@pytest.mark.slow
def test_replicate_runs_reports_and_resumes(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(presets.QUICK_BUDGETS, "CartPole-v0", (2048, 1024))
    args = [
        "replicate",
        "--quick",
        "--env",
        "CartPole-v0",
        "--agent",
        "ppo",
        "--seeds",
        "1",
        "--out",
        str(tmp_path),
        "--no-progress",
    ]
    assert main(args) == 0
    index = (tmp_path / "report.md").read_text()
    assert "## CartPole-v0" in index and "| CartPole-v0 | ppo | vanilla |" in index
    assert (tmp_path / "CartPole-v0" / "report" / "report.md").exists()
    assert (tmp_path / "CartPole-v0" / "report" / "figures" / "maps_CartPole-v0_ppo.png").exists()
    table = pd.read_csv(tmp_path / "paper_table.csv")
    assert len(table) == 5  # vanilla + 4 costs
    first = json.loads((tmp_path / "wall_times.json").read_text())["CartPole-v0"]
    results = pd.read_parquet(tmp_path / "CartPole-v0" / "results.parquet")
    assert len(results) == 5 * 2  # configurations x evaluations
    # A rerun finds everything done: no new rows, the wall time only grows.
    assert main(args) == 0
    pd.testing.assert_frame_equal(pd.read_parquet(tmp_path / "CartPole-v0" / "results.parquet"), results)
    again = json.loads((tmp_path / "wall_times.json").read_text())["CartPole-v0"]
    assert again >= first
    assert json.loads((tmp_path / "CartPole-v0" / "wall_time.json").read_text()) == {"seconds": again, "invocations": 2}


@pytest.mark.slow
def test_next_environment_compiles_while_one_trains(tmp_path, monkeypatch):
    """One compile queue across the environments: the next environment's batches compile on the background thread
    (in training order) before this one's report, and a rerun of the finished grid compiles nothing."""
    import threading

    import amjax.analysis
    from amjax.sweep import executors

    for env in ("CartPole-v0", "Acrobot-v1"):
        monkeypatch.setitem(presets.QUICK_BUDGETS, env, (2048, 1024))
    events = []
    compile_batch, write_report = executors.compile_batch, amjax.analysis.write_report

    next_env_compile_began = threading.Event()

    def logged_compile(batch, *args):
        events.append(("compile", batch.runs[0].env, batch.name, threading.current_thread().name))
        if batch.runs[0].env == "Acrobot-v1":
            next_env_compile_began.set()
        return compile_batch(batch, *args)

    def logged_report(folder, **kwargs):
        if folder.name == "CartPole-v0":  # CartPole trained; waits (held) for Acrobot's compile to begin on its own
            began_before_report.append(next_env_compile_began.wait(timeout=300))
        events.append(("report", folder.name))
        return write_report(folder, **kwargs)

    began_before_report = []
    # Compiling ahead pauses past half the memory-map limit; a test worker that ran many tests may be there.
    monkeypatch.setattr(executors, "maps_past_half", lambda: False)
    monkeypatch.setattr(executors, "compile_batch", logged_compile)
    monkeypatch.setattr(amjax.analysis, "write_report", logged_report)
    args = [
        "replicate",
        "--quick",
        "--env",
        "CartPole-v0",
        "Acrobot-v1",
        "--agent",
        "ppo",
        "--seeds",
        "1",
        "--out",
        str(tmp_path),
        "--no-progress",
        "--no-maps",
    ]
    assert main(args) == 0
    compiles = [e for e in events if e[0] == "compile"]
    assert [e[1] for e in compiles] == ["CartPole-v0"] * 2 + ["Acrobot-v1"] * 2  # vanilla and costed PPO each
    assert len({e[2] for e in compiles}) == 4 and {e[3] for e in compiles} == {"amjax-compile-ahead"}
    assert began_before_report == [True] and events.index(compiles[2]) < events.index(("report", "CartPole-v0"))
    assert events[-1] == ("report", "Acrobot-v1")
    assert pd.read_csv(tmp_path / "paper_table.csv").env.tolist() == ["CartPole-v0"] * 5 + ["Acrobot-v1"] * 5
    events.clear()
    assert main(args) == 0
    assert events == [("report", "CartPole-v0"), ("report", "Acrobot-v1")]


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--env", "Pong-v0"], "--env: no replication budget for Pong-v0"),
        (["--seeds", "0"], "--seeds: got 0"),
        (["--agent", "sarsa"], "sarsa"),
        (["--max-batch", "0"], "--max-batch: got 0"),
    ],
)
def test_bad_flags_exit_2_without_output(tmp_path, capsys, flags, message):
    with pytest.raises(SystemExit) as exit_info:
        main(["replicate", "--out", str(tmp_path / "out"), *flags])
    assert exit_info.value.code == 2 and message in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_folder_in_use_is_refused(tmp_path, capsys):
    out = tmp_path / "rep"
    with folder_lock(out):  # as a second, live replicate process would hold it
        code = main(
            [
                "replicate",
                "--quick",
                "--env",
                "CartPole-v0",
                "--agent",
                "dqn",
                "--out",
                str(out),
                "--no-progress",
                "--no-maps",
            ]
        )
    assert code == 2 and "another running process" in capsys.readouterr().err
    assert [p.name for p in out.iterdir()] == [".lock"]  # nothing written
