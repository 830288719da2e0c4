"""Optional logging: one TensorBoard / W&B run per configuration, holding exactly the results table's values."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from amjax.sweep import SweepSpec, run_sweep
from amjax.sweep.loggers import TensorBoardLogger, WandbLogger
from train.cli import main

TINY = SweepSpec(
    envs=("CartPole-v0",),
    agents=("ppo",),
    costs=(0.0, 0.3),
    seeds=(0, 1),
    total_timesteps=2048,
    eval_every=1024,
    eval_episodes=2,
    hyperparams={"num_envs": 4, "num_steps": 32},
)


class FakeRun:
    def __init__(self, **kwargs):
        self.kwargs, self.logged, self.finished = kwargs, [], False

    def log(self, values, step):
        self.logged.append((step, values))

    def finish(self):
        self.finished = True


class FakeWandb:
    def __init__(self):
        self.runs = []

    def init(self, **kwargs):
        self.runs.append(FakeRun(**kwargs))
        return self.runs[-1]


def _tensorboard_scalars(run_dir: Path) -> dict[str, dict[int, float]]:
    """Scalars of a tensorboardX run folder, read from its TFRecord event files."""
    from tensorboardX.proto.event_pb2 import Event

    scalars: dict[str, dict[int, float]] = {}
    for path in sorted(run_dir.glob("events.out.tfevents.*")):
        data = path.read_bytes()
        offset = 0
        while offset < len(data):
            (length,) = struct.unpack("<Q", data[offset : offset + 8])
            event = Event.FromString(data[offset + 12 : offset + 12 + length])
            offset += 12 + length + 4
            for value in event.summary.value:
                if value.HasField("simple_value"):
                    scalars.setdefault(value.tag, {})[event.step] = value.simple_value
    return scalars


@pytest.fixture(scope="module")
def logged(tmp_path_factory):
    out = tmp_path_factory.mktemp("logged")
    fake = FakeWandb()
    loggers = [
        TensorBoardLogger(out / "tensorboard"),
        WandbLogger("amjax-test", out, wandb_module=fake),
        WandbLogger("amjax-test", out / "real", mode="offline"),
    ]
    result = run_sweep(TINY, out, progress=False, target_chunks=2, loggers=loggers)
    return out, result.results, fake


@pytest.mark.slow
def test_tensorboard_one_run_per_config_with_the_results_values(logged):
    out, results, _ = logged
    assert sorted(p.name for p in (out / "tensorboard").iterdir()) == sorted(results.config_id.unique())
    for config_id, rows in results.groupby("config_id"):
        scalars = _tensorboard_scalars(out / "tensorboard" / config_id)
        assert scalars["eval/return"] == pytest.approx(dict(zip(rows.env_steps, rows.eval_return, strict=True)))
        assert scalars["eval/measured_fraction"] == pytest.approx(
            dict(zip(rows.env_steps, rows.eval_measured_fraction, strict=True))
        )
        assert set(scalars["diverged"].values()) == {0.0}


def test_wandb_one_run_per_config_closed_at_the_end(logged):
    _, results, fake = logged
    assert sorted(run.kwargs["id"] for run in fake.runs) == sorted(results.config_id.unique())
    for run in fake.runs:
        assert run.finished and run.kwargs["mode"] == "offline" and run.kwargs["group"] == "CartPole-v0-ppo"
        rows = results[results.config_id == run.kwargs["id"]]
        assert run.kwargs["config"]["cost"] == rows.cost.iloc[0] and run.kwargs["config"]["seed"] == rows.seed.iloc[0]
        assert [step for step, _ in run.logged] == list(rows.env_steps)
        np.testing.assert_allclose([v["eval/return"] for _, v in run.logged], rows.eval_return)


def test_wandb_offline_needs_no_network(logged):
    out, results, _ = logged
    pytest.importorskip("wandb")
    runs = sorted((out / "real" / "wandb").glob("offline-run-*"))
    assert sorted(p.name.rsplit("-", 1)[1] for p in runs) == sorted(results.config_id.unique())
    assert all(next(p.glob("run-*.wandb")).stat().st_size > 0 for p in runs)


@pytest.mark.slow
def test_cli_tensorboard_flag_and_bad_mode(tmp_path, capsys, tiny_sweep_flags):
    args = ["sweep", *tiny_sweep_flags(steps=1024, extra=("--tensorboard",)), "--out", str(tmp_path / "run")]
    assert main(args) == 0
    results = pd.read_parquet(tmp_path / "run" / "results.parquet")
    (run_dir,) = (tmp_path / "run" / "tensorboard").iterdir()
    assert run_dir.name == results.config_id.iloc[0] and _tensorboard_scalars(run_dir)["eval/return"]
    with pytest.raises(SystemExit) as exit_info:
        main([*args[:-1], str(tmp_path / "other"), "--wandb", "p", "--wandb-mode", "cloud"])
    assert exit_info.value.code == 2 and "--wandb-mode" in capsys.readouterr().err
    assert not (tmp_path / "other").exists()
    with pytest.raises(ValueError, match="mode: .*'cloud'"):
        WandbLogger("p", tmp_path, mode="cloud", wandb_module=FakeWandb())
