"""The bad-input corpus: every command and the public entry points given bad values. Each case must end with a clear
message naming the argument (command line: exit status 2 and no traceback), before anything is compiled or written,
and lose nothing already written."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import submitit  # noqa: F401 (imported here, its log handlers bind the real stderr rather than a test's capture)

import amjax
from amjax.agents import DQNConfig, DRQNConfig, PolicyFileError, PPOConfig, PPORNNConfig, load_policy
from amjax.analysis import NotASweepError, load_results
from amjax.sweep import SweepMismatchError, SweepSpec, SweepTooLargeError, expand, run_sweep
from amjax.sweep.storage import UnreadableFileError
from train.cli import main

RESCORE_2 = ("--set", "rescore_episodes=2")  # with tiny_sweep_flags (conftest): a small command-line sweep

# (flags after `sweep --agent ppo`, a piece of the message): values a user can mistype.
SWEEP_CASES = [
    (["--cost", "nan"], "cost: got nan"),
    (["--cost", "inf"], "cost: got inf"),
    (["--cost", "-0.1"], "cost: got -0.1"),
    (["--cost", "abc"], "argument --cost: invalid float value"),
    (["--cost"], "argument --cost: expected at least one argument"),
    (["--env"], "argument --env: expected at least one argument"),
    (["--env", ""], "--env: unknown environment ''"),
    (["--env", "CartPole-v9"], "--env: unknown environment 'CartPole-v9'"),
    (["--agent", "sac"], "--agent: unknown agent 'sac'"),
    (["--mode", "sometimes"], "argument --mode: invalid choice"),
    (["--seeds", "0"], "--seeds: got 0"),
    (["--seeds", "-3"], "--seeds: got -3"),
    (["--seeds", "1.5"], "argument --seeds: invalid int value"),
    (["--seeds", "1000000000000"], "--seeds: got 1000000000000"),
    (["--seed-list", "-1"], "seed: got -1"),
    (["--seed-list", "4294967296"], "seed: got 4294967296"),
    (["--seed-list", "3", "3"], "seeds: repeated values"),
    (["--seeds", "2", "--seed-list", "1"], "--seeds and --seed-list"),
    (["--steps", "0"], "--steps: got 0"),
    (["--steps", "-5"], "--steps: got -5"),
    (["--steps", "1e6"], "argument --steps: invalid int value"),
    (["--steps", "100000000000000"], "total_timesteps: got"),
    (["--eval-every", "0"], "--eval-every: got 0"),
    (["--eval-episodes", "0"], "eval_episodes: got 0"),
    (["--eval-episodes", "1000000000"], "eval_episodes: got 1000000000"),
    (["--max-batch", "0"], "--max-batch: got 0"),
    (["--max-batch", "-1"], "--max-batch: got -1"),
    (["--set", "learning_rate=nan"], "learning_rate: got 'nan'"),
    (["--set", "learning_rate=inf"], "learning_rate: got 'inf'"),
    (["--set", "learning_rate=-1"], "learning_rate: got -1"),
    (["--set", "learning_rate=abc"], "learning_rate: expected a real number"),
    (["--set", "learning_rate=[]"], "learning_rate: an empty list"),
    (["--set", "gamma=1.5"], "gamma: got 1.5"),
    (["--set", "num_envs=0"], "num_envs: got 0"),
    (["--set", "num_envs=1.5"], "num_envs: got 1.5"),
    (["--set", "num_envs=abc"], "num_envs: got 'abc'"),
    (["--set", "num_envs=1000000000"], "total_timesteps: got"),
    (["--set", "hidden=(0,)"], "hidden: got (0,)"),
    (["--set", "hidden=(64,-1)"], "hidden: got (64, -1)"),
    (["--set", "rescore_episodes=0"], "rescore_episodes: got 0"),
    (["--set", "train_group=-1"], "train_group: got -1; allowed values: integers >= 0"),
    # Lists of bare words are split, and the bad word is named.
    (["--set", "activation=relu,swish"], "activation: got 'swish'; allowed values: 'tanh', 'relu', 'elu'"),
    (["--set", "eval_policy=stochastic,sample"], "eval_policy: got 'sample'"),
    (["--set", "no_such_field=3"], "no_such_field"),
    (["--set", "total_timesteps=1000"], "total_timesteps is set for the whole sweep"),
    (["--set", "cost=0.5"], "cost is a grid axis"),
    (["--set", "dqn.gamma=0.9"], "agent 'dqn' is not in this sweep's agents"),
    (["--set", "extra_obs=('since',)"], "extra_obs: got 'since'"),
    (["--set", "extra_obs=since_measured"], "extra_obs: got 'since_measured'"),
    (["--set", "budget=5"], "budget: set budgeted=True"),
    (["--set", "budgeted=True", "--set", "budget=-1"], "budget: got -1"),
    (["--set", "budgeted=1"], "budgeted: got 1"),
    (["--set", "budgeted=True", "--set", "budget=2.5"], "budget: got 2.5; allowed values: whole numbers"),
    (["--mode", "noisy"], "noise_std: mode 'noisy' needs noise_std"),
    (["--mode", "random", "--set", "noise_std=0.1"], "noise_std: only used with mode 'noisy'"),
    (["--set", "instruments=((0,1),(2,))"], "instruments: ((0, 1), (2,)) must hold each observation index"),
    (["--set", "instruments=cart"], "instruments: got 'cart'"),
    (["--set", "instruments=default", "--set", "instrument_costs=(0.1,)"], "instrument_costs: got 1 values"),
    (["--set", "instrument_costs=(0.1,0.2)"], "set instruments first"),
    (["--set", "measure_head=split"], "measure_head: got 'split'"),
    (["--set", "reward_timing=later"], "reward_timing: got 'later'"),
    (["--set", "=3"], "--set: expected NAME=VALUE"),
    (["--set", "gamma"], "--set: expected NAME=VALUE"),
    (["--cluster", "local:0"], "--cluster: got 'local:0'; allowed values: local:N"),
    (["--cluster", "ray"], "--cluster: got 'ray'"),
    (["--cluster", "slurm:"], "--cluster: got 'slurm:'"),
    (["--cluster-option", "time=60"], "--cluster-option: give --cluster too"),
    (["--cluster", "local:2", "--cluster-option", "=3"], "--cluster-option: got '=3'"),
    (["--cluster", "local:2", "--cluster-option", "account=lab"], "--cluster-option: 'account' is not a parameter"),
    (["--cluster", "slurm:gpu"], "--cluster: slurm:gpu needs Slurm's sbatch and srun on PATH"),
    (["--cluster", "local:2", "--cluster-option", "setup=module load x"], "--cluster-option: setup must be a list"),
]


def _run(argv, capsys) -> tuple[int, str]:
    try:
        code = main(argv)
    except SystemExit as exit_info:
        code = exit_info.code
    err = capsys.readouterr().err
    return code, err


@pytest.mark.parametrize(("flags", "message"), SWEEP_CASES, ids=[" ".join(c[0]) or "empty" for c in SWEEP_CASES])
def test_sweep_flag_corpus(tmp_path, capsys, flags, message):
    out = tmp_path / "never"
    code, err = _run(["sweep", "--agent", "ppo", "--out", str(out), *flags], capsys)
    assert code == 2 and message in err and "Traceback" not in err, err
    assert not out.exists()


COMMAND_CASES = [
    ("replicate", ["--seeds", "0"], "--seeds: got 0"),
    ("replicate", ["--env", "Pong-v0"], "--env: no replication budget for Pong-v0"),
    ("replicate", ["--agent", "sarsa"], "sarsa"),
    ("replicate", ["--max-batch", "0"], "--max-batch: got 0"),
    ("replicate", ["--seeds", "x"], "argument --seeds: invalid int value"),
    ("replicate", ["--cluster", "local:0"], "--cluster: got 'local:0'"),
    ("pareto", ["--seeds", "0"], "--seeds: got 0"),
    ("pareto", ["--cost-high", "0"], "--cost-high: got 0"),
    ("pareto", ["--grid-step", "0"], "--grid-step: got 0"),
    ("pareto", ["--grid-step", "0.9"], "--grid-step: got 0.9"),
    ("pareto", ["--specialist-costs", "-0.1"], "--specialist-costs: got -0.1"),
    ("pareto", ["--steps", "0"], "--steps: got 0"),
    ("pareto", ["--agent", "sarsa"], "sarsa"),
    (
        "pareto",
        ["--cost-high", "0.2", "--specialist-costs", "0.1", "0.3"],
        "--specialist-costs: got 0.3, above --cost-high 0.2",
    ),
    ("pareto", ["--seeds", "2", "--seed-list", "3", "4"], "--seeds and --seed-list: give one of them"),
    ("pareto", ["--seed-list", "-1"], "seed: got -1"),
]


@pytest.mark.parametrize(
    ("command", "flags", "message"), COMMAND_CASES, ids=[f"{c[0]} {' '.join(c[1])}" for c in COMMAND_CASES]
)
def test_replicate_and_pareto_flag_corpus(tmp_path, capsys, command, flags, message):
    code, err = _run([command, "--out", str(tmp_path / "never"), *flags], capsys)
    assert code == 2 and message in err and "Traceback" not in err, err
    assert not (tmp_path / "never").exists()


def test_out_that_is_not_a_folder(tmp_path, capsys, tiny_sweep_flags):
    afile = tmp_path / "afile"
    afile.write_text("mine")
    for out, message in ((afile, "is a file; give a folder"), (afile / "sub", "cannot create the folder")):
        code, err = _run(["sweep", *tiny_sweep_flags(extra=RESCORE_2), "--out", str(out)], capsys)
        assert code == 2 and "out: " in err and str(out) in err and message in err and "Traceback" not in err
    assert afile.read_text() == "mine"


def test_foreign_folder_is_refused_untouched(tmp_path, capsys, tiny_sweep_flags):
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "metadata.json").write_text("{not json")
    code, err = _run(["sweep", *tiny_sweep_flags(extra=RESCORE_2), "--out", str(foreign)], capsys)
    assert code == 2 and "is not a sweep's metadata" in err
    assert [p.name for p in foreign.iterdir()] == ["metadata.json"]
    code, err = _run(["report", str(foreign)], capsys)
    assert code == 2 and "metadata.json: unreadable" in err and "Traceback" not in err


@pytest.fixture(scope="module")
def finished(tmp_path_factory, tiny_sweep_flags) -> Path:
    out = tmp_path_factory.mktemp("bad") / "run"
    assert main(["sweep", *tiny_sweep_flags(extra=RESCORE_2), "--out", str(out)]) == 0
    return out


def test_truncated_results_are_refused_and_kept(finished, tmp_path, capsys, tiny_sweep_flags):
    out = shutil.copytree(finished, tmp_path / "run")
    parquet = out / "results.parquet"
    parquet.write_bytes(parquet.read_bytes()[:40])
    before = parquet.read_bytes()
    code, err = _run(["sweep", *tiny_sweep_flags(extra=RESCORE_2), "--out", str(out)], capsys)
    assert code == 2 and "results.parquet is unreadable" in err and "Traceback" not in err
    assert parquet.read_bytes() == before  # nothing overwritten
    code, err = _run(["report", str(out)], capsys)
    assert code == 2 and "results.parquet is unreadable" in err
    with pytest.raises(NotASweepError, match="unreadable"):
        load_results(out)


def test_corrupt_checkpoint_and_policy(finished, tmp_path, capsys, tiny_sweep_flags):
    out = shutil.copytree(finished, tmp_path / "run")
    (checkpoint,) = (out / "checkpoints").glob("*.msgpack")
    checkpoint.write_bytes(b"\x00garbage")
    (out / "results.parquet").unlink()  # so the rerun has a batch to resume from the checkpoint
    code, err = _run(["sweep", *tiny_sweep_flags(extra=RESCORE_2), "--out", str(out)], capsys)
    assert code == 2 and "is unreadable" in err and "delete it" in err and "Traceback" not in err
    (policy,) = (out / "policies").glob("*.msgpack")
    policy.write_bytes(policy.read_bytes()[:100])
    with pytest.raises(PolicyFileError):
        load_policy(policy)


def test_python_api_errors_name_the_argument():
    with pytest.raises(ValueError, match="eval_every=300 must be a multiple .* nearest valid values"):
        PPOConfig(total_timesteps=1000, eval_every=300).validate()
    with pytest.raises(ValueError, match="hidden: got"):
        DQNConfig(hidden=(0,)).validate()
    with pytest.raises(ValueError, match="the grid has 2,000,000 configurations"):
        expand(SweepSpec(agents=("ppo",), costs=(0.1,), seeds=tuple(range(2_000_000))))
    with pytest.raises(ValueError, match="cost: got -1"):
        expand(SweepSpec(agents=("ppo",), costs=(-1.0,)))


def test_a_batch_too_large_for_memory_is_refused_before_writing(tmp_path):
    spec = SweepSpec(
        agents=("dqn",),
        costs=(0.1,),
        seeds=(0, 1),
        total_timesteps=4096,
        eval_every=1024,
        hyperparams={"buffer_size": 4_000_000_000},
    )
    with pytest.raises(SweepTooLargeError, match="GiB .* lower --max-batch"):
        run_sweep(spec, tmp_path / "never", progress=False)
    assert not (tmp_path / "never").exists()
    with pytest.raises(SweepMismatchError, match="is a file"):
        (tmp_path / "f").write_text("x")
        run_sweep(SweepSpec(agents=("ppo",), seeds=(0,)), tmp_path / "f", progress=False)
    assert issubclass(UnreadableFileError, ValueError)


SCHEDULE = {"total_timesteps": 8192, "eval_every": 8192}  # valid for every agent's defaults
# (amjax.make's arguments, an agent config's fields, the message's start): one shared check refuses both the same way.
MEASURE_SETUP_CASES = [
    ({"mode": "last", "noise_std": 0.1}, {"mode": "last", "noise_std": 0.1}, "noise_std: only used with mode 'noisy'"),
    ({"mode": "random", "noise_std": 0.1}, {"mode": "random", "noise_std": 0.1}, "noise_std: only used"),
    ({"mode": "noisy", "noise_std": 0.0}, {"mode": "noisy"}, "noise_std: mode 'noisy' needs noise_std"),
    ({"mode": "noisy"}, {"mode": "noisy", "noise_std": 0.0}, "noise_std: mode 'noisy' needs noise_std"),
    (
        {"vanilla": True, "mode": "noisy", "noise_std": 0.1},
        {"vanilla": True, "mode": "noisy", "noise_std": 0.1},
        "vanilla: a vanilla run",
    ),
    ({"vanilla": True, "mode": "random"}, {"vanilla": True, "mode": "random"}, "vanilla: a vanilla run"),
    (
        {"vanilla": True, "reward_timing": "on_measure"},
        {"vanilla": True, "reward_timing": "on_measure"},
        "vanilla: a vanilla run",
    ),
    ({"budget": 2.5}, {"budgeted": True, "budget": 2.5}, "budget: got 2.5; allowed values: whole numbers"),
    ({"budget": [1.0, 0.5]}, {"budgeted": True, "budget": 0.5}, "budget: got"),
]


@pytest.mark.parametrize(
    ("make_kwargs", "fields", "message"), MEASURE_SETUP_CASES, ids=[str(c[1]) for c in MEASURE_SETUP_CASES]
)
def test_make_and_agent_configs_refuse_the_same_measure_setups(make_kwargs, fields, message):
    """`amjax.make` and every agent config (hence every sweep) refuse the same settings, before compiling."""
    with pytest.raises(ValueError) as from_make:
        amjax.make("CartPole-v0", **make_kwargs)
    assert str(from_make.value).startswith(message), from_make.value
    for config_type in (PPOConfig, DQNConfig, DRQNConfig, PPORNNConfig):
        with pytest.raises(ValueError) as from_config:
            config_type(**SCHEDULE, **fields).validate()
        assert str(from_config.value).startswith(message), from_config.value
        if make_kwargs == fields:  # the same settings: the same words
            assert str(from_config.value) == str(from_make.value)


def test_the_measure_setups_both_entry_points_accept():
    """What the shared check lets through: a config's noise_std 0 is "unset" (make's None), integral budgets."""
    for make_kwargs, fields in (
        ({"mode": "noisy", "noise_std": 0.1}, {"mode": "noisy", "noise_std": 0.1}),
        ({"mode": "last"}, {"mode": "last", "noise_std": 0.0}),
        ({"mode": "random"}, {"mode": "random"}),
        ({"budget": 3.0}, {"budgeted": True, "budget": 3.0}),
        ({"vanilla": True}, {"vanilla": True}),
    ):
        amjax.make("CartPole-v0", **make_kwargs)
        for config_type in (PPOConfig, DQNConfig, DRQNConfig, PPORNNConfig):
            config_type(**SCHEDULE, **fields).validate()
