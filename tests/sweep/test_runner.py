"""The sweep runner and CLI: resume after a kill, no duplicate rows, atomic files, summaries, bad flags."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from amjax.agents import ALGORITHMS, config_for
from amjax.cores import cpu_description
from amjax.files import atomic_write, folder_lock
from amjax.presets import ENV_PRESETS, preset
from amjax.sweep import FolderBusyError, SweepMismatchError, SweepSpec, expand, group_runs, run_sweep
from amjax.sweep.runner import identity_differences
from amjax.sweep.storage import load_checkpoint, save_checkpoint, seed_table, summarize
from train.cli import main

TINY = SweepSpec(
    envs=("CartPole-v0",),
    agents=("ppo",),
    costs=(0.0, 0.3),
    seeds=(0, 1),
    total_timesteps=4096,
    eval_every=1024,
    eval_episodes=2,
    hyperparams={"num_envs": 4, "num_steps": 32, "learning_rate": [1e-3, 3e-4]},
)
VALUE_COLUMNS = ["eval_return", "eval_raw_return", "eval_measurements", "train_return", "loss"]


@pytest.fixture(scope="module")
def full_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("full")
    return run_sweep(TINY, out, progress=False, target_chunks=4)


def test_grid_groups_and_ids():
    runs = expand(TINY)
    assert len(runs) == 2 * 2 * 2  # costs x seeds x learning rates
    assert len({r.config_id for r in runs}) == len(runs)
    assert len(group_runs(runs)) == 1  # traced fields only: one compiled program
    assert [r.config_id for r in expand(TINY)] == [r.config_id for r in runs]  # stable across calls
    widths = SweepSpec(**{**TINY.__dict__, "hyperparams": {"hidden": [(32,), (16, 16)]}})
    assert len(group_runs(expand(widths))) == 2  # a static field compiles separately
    # One copy of each field: a run's env, cost and vanilla flag are its agent config's.
    assert all((r.env, r.cost, r.vanilla) == (r.config.env_id, float(r.config.cost), r.config.vanilla) for r in runs)
    # The last expansion is reused, keyed so that one tuple value and a list of values stay different sweeps.
    one_width = SweepSpec(**{**TINY.__dict__, "hyperparams": {"hidden": (32, 16)}})
    two_widths = SweepSpec(**{**TINY.__dict__, "hyperparams": {"hidden": [(32,), (16,)]}})
    assert len(expand(one_width)) == 4 and len(expand(two_widths)) == 8 and len(expand(one_width)) == 4
    with pytest.raises(ValueError, match="hidden"):  # [32, 16] is two values (not widths), never the tuple's runs
        expand(SweepSpec(**{**TINY.__dict__, "hyperparams": {"hidden": [32, 16]}}))


def test_vanilla_runs_take_no_measurement_options():
    """A vanilla run is not multiplied by the wrapper's options (it has none); costed runs are."""
    from amjax.analysis.results import _planned_configs

    spec = SweepSpec(
        agents=("dqn",),
        costs=(0.1,),
        seeds=(0, 1),
        vanilla=True,
        total_timesteps=2000,
        eval_every=1000,
        hyperparams={
            "instruments": "default",
            "instrument_costs": [(0.05, 0.3), (0.3, 0.05)],
            "learning_rate": [1e-3, 3e-4],
        },
    )
    runs = expand(spec)
    vanilla = [r for r in runs if r.vanilla]
    assert len(runs) == 2 * 2 * 2 + 2 * 2  # costed: prices x rates x seeds; vanilla: rates x seeds
    assert all(r.config.instruments == () and r.config.instrument_costs == () for r in vanilla)
    assert {tuple(r.hyperparams) for r in vanilla} == {("learning_rate",)}
    assert _planned_configs(spec.to_json()) == len(runs)
    one = SweepSpec(**{**spec.__dict__, "hyperparams": {"instruments": ((0, 1), (2, 3))}})
    assert _planned_configs(one.to_json()) == len(expand(one)) == 4
    for mode, options in (("random", {}), ("noisy", {"noise_std": 0.1})):  # the plain env takes no mode
        runs = expand(SweepSpec(**{**spec.__dict__, "mode": mode, "hyperparams": options}))
        assert {(r.config.mode, r.vanilla) for r in runs} == {(mode, False), ("last", True)}


def test_agent_scoped_hyperparameters():
    spec = SweepSpec(
        agents=("ppo", "dqn"),
        costs=(0.1,),
        seeds=(0,),
        total_timesteps=4096,
        eval_every=1024,
        hyperparams={"gamma": 0.95, "ppo.gamma": [0.9, 0.99], "dqn.learning_rate": 3e-4},
    )
    runs = expand(spec)
    ppo_runs = [r for r in runs if r.agent == "ppo"]
    (dqn_run,) = [r for r in runs if r.agent == "dqn"]
    assert sorted(r.config.gamma for r in ppo_runs) == [0.9, 0.99]  # the scoped list wins over the shared value
    assert [r.hyperparams for r in ppo_runs] == [{"ppo.gamma": 0.9}, {"ppo.gamma": 0.99}]
    assert dqn_run.config.gamma == 0.95 and dqn_run.config.learning_rate == 3e-4
    from amjax.analysis.results import _planned_configs

    assert _planned_configs(spec.to_json()) == len(runs) == 3
    for bad, message in (
        ({"sarsa.gamma": 0.9}, "agent"),
        ({"drqn.gamma": 0.9}, "not in this sweep's agents"),
        ({"dqn.num_steps": 8}, "belongs to none of the agents"),
    ):
        with pytest.raises(ValueError, match=message):
            expand(SweepSpec(agents=("ppo", "dqn"), hyperparams=bad))


@pytest.mark.slow
def test_full_run_tables(full_run):
    results, summary = full_run.results, full_run.summary
    assert len(results) == 8 * 4 and not results.duplicated(["config_id", "env_steps"]).any()
    assert sorted(results.env_steps.unique()) == [1024, 2048, 3072, 4096]
    assert set(results.columns) >= {"env", "agent", "cost", "seed", "learning_rate", "eval_measured_fraction"}
    for stem in ("results", "summary", "seed_summary"):
        assert (full_run.out / f"{stem}.parquet").exists() and (full_run.out / f"{stem}.csv").exists()
    meta = (full_run.out / "metadata.json").read_text()
    assert '"jax"' in meta and '"spec"' in meta
    assert json.loads(meta)["cpu"] == cpu_description() != ""  # the machine its rows are bit for bit reproducible on
    # Summary: best = max over evaluations, per configuration, recomputed by hand.
    for config_id, rows in results.groupby("config_id"):
        row = summary.set_index("config_id").loc[config_id]
        assert row.best_return == pytest.approx(rows.eval_return.max())
        at_best = rows.loc[rows.eval_return.idxmax()]
        assert row.best_measured_fraction == pytest.approx(at_best.eval_measurements / at_best.eval_length)
    assert len(full_run.table) == 4 and (full_run.table.seeds == 2).all()


@pytest.mark.slow
def test_best_policy_per_config_reproduces_its_best_score(full_run):
    import jax

    from amjax.sweep import load_sweep_policy

    summary = full_run.summary
    assert sorted(p.stem for p in (full_run.out / "policies").glob("*.msgpack")) == sorted(summary.config_id)
    for row in summary.itertuples():
        saved = load_sweep_policy(full_run.out, row.config_id)
        assert saved.info["best_return"] == pytest.approx(row.best_return, rel=1e-6)
        assert saved.info["best_env_steps"] == row.best_env_steps
        assert saved.info["trained_env_steps"] == TINY.total_timesteps
        assert saved.config.cost == pytest.approx(row.cost) and saved.info["seed"] == row.seed
        # The driver's key for the best evaluation: split(PRNGKey(seed))[1] folded with its index.
        eval_key = jax.random.fold_in(
            jax.random.split(jax.random.PRNGKey(row.seed))[1], int(row.best_env_steps) // TINY.eval_every - 1
        )
        score = saved.evaluate(eval_key, TINY.eval_episodes)
        assert score["costed_return"] == pytest.approx(row.best_return, rel=1e-4)
    with pytest.raises(FileNotFoundError, match="config_id: no saved policy 'nope'"):
        load_sweep_policy(full_run.out, "nope")


@pytest.mark.parametrize("checkpoint_every_s", [0.0, 1e9])
@pytest.mark.slow
def test_resume_after_interrupt(tmp_path, full_run, checkpoint_every_s, stop_sweep_after):
    """Interrupted after 2 of 4 chunks (with a checkpoint, or with results written past the last checkpoint),
    the rerun finishes with exactly the rows of an uninterrupted run."""
    with pytest.raises(stop_sweep_after.error):
        run_sweep(
            TINY,
            tmp_path,
            progress=False,
            target_chunks=4,
            checkpoint_every_s=checkpoint_every_s,
            on_chunk=stop_sweep_after(2),
        )
    partial = pd.read_parquet(tmp_path / "results.parquet")
    assert len(partial) == 8 * 2
    resumed = run_sweep(TINY, tmp_path, progress=False, target_chunks=4, checkpoint_every_s=checkpoint_every_s)
    assert not resumed.results.duplicated(["config_id", "env_steps"]).any()
    a = resumed.results.sort_values(["config_id", "env_steps"]).reset_index(drop=True)
    b = full_run.results.sort_values(["config_id", "env_steps"]).reset_index(drop=True)
    pd.testing.assert_frame_equal(a[["config_id", "env_steps"]], b[["config_id", "env_steps"]])
    np.testing.assert_allclose(a[VALUE_COLUMNS].to_numpy(float), b[VALUE_COLUMNS].to_numpy(float), rtol=1e-5)


@pytest.mark.slow
def test_next_batch_compiles_while_one_trains(tmp_path, monkeypatch):
    """Each batch's programs compile on a background thread while the batch before it trains, and checkpoints are
    written on a thread of their own; a failed compile stops the sweep with its error and loses nothing already
    written; a rerun does not compile finished batches."""
    import threading

    from amjax.sweep import executors, storage

    spec = SweepSpec(
        **{
            **TINY.__dict__,
            "costs": (0.3,),
            "seeds": (0,),
            "hyperparams": {"num_envs": 4, "num_steps": 32, "hidden": [(16,), (8,)]},
        }
    )
    events = []
    compile_batch = executors.compile_batch
    second_compile_began = threading.Event()

    def logged(batch, *args):
        events.append(("compile", batch.name, threading.current_thread().name))
        if sum(e[0] == "compile" for e in events) == 2:
            second_compile_began.set()
        return compile_batch(batch, *args)

    save_checkpoint = storage.save_checkpoint

    def logged_save(path, state, evals_done):
        events.append(("checkpoint", evals_done, threading.current_thread().name))
        save_checkpoint(path, state, evals_done)

    began_while_first_trains = []

    def after_chunk(results):
        if not any(e[0] == "chunk" for e in events):
            began_while_first_trains.append(second_compile_began.wait(timeout=300))
        events.append(("chunk", results.config_id.nunique()))

    # Compiling ahead pauses past half the memory-map limit (tests/sweep/test_executors.py); a test worker that ran
    # many tests may be there, and this test is about the order.
    monkeypatch.setattr(executors, "maps_past_half", lambda: False)
    monkeypatch.setattr(executors, "compile_batch", logged)
    monkeypatch.setattr(storage, "save_checkpoint", logged_save)
    full = run_sweep(
        spec,
        tmp_path / "full",
        progress=False,
        target_chunks=4,
        on_chunk=after_chunk,
    )
    # The first batch's first chunk waited in `after_chunk` (its batch still training, its thread held) until the
    # second batch's compile began: it began on its own, not when the second batch was taken.
    assert began_while_first_trains == [True]
    compiles = [e for e in events if e[0] == "compile"]
    first, second = (name for _, name, _ in compiles)
    assert first != second
    assert [e[0] for e in events if e[0] != "checkpoint"] == ["compile"] * 2 + ["chunk"] * 8
    assert all(thread == "amjax-compile-ahead" for _, _, thread in compiles)
    checkpoints = [e for e in events if e[0] == "checkpoint"]
    assert [e[1] for e in checkpoints][-1] == 4 and all(e[2].startswith("amjax-checkpoint") for e in checkpoints)
    assert len(full.summary) == 2 and full.results.env_steps.max() == spec.total_timesteps

    def second_fails(batch, *args):
        if batch.name == second:
            raise RuntimeError("compile failed")
        return compile_batch(batch, *args)

    monkeypatch.setattr(executors, "compile_batch", second_fails)
    with pytest.raises(RuntimeError, match="compile failed"):
        run_sweep(spec, tmp_path / "failed", progress=False, target_chunks=4)
    written = pd.read_parquet(tmp_path / "failed" / "results.parquet")
    assert len(written) == 4 and written.config_id.nunique() == 1  # the first batch, whole

    def no_compile(batch, *args):
        raise AssertionError(f"compiled the finished batch {batch.name}")

    monkeypatch.setattr(executors, "compile_batch", no_compile)
    again = run_sweep(spec, tmp_path / "full", progress=False, target_chunks=4)
    pd.testing.assert_frame_equal(again.summary, full.summary)


@pytest.mark.slow
def test_sigkill_then_rerun_resumes(tmp_path, tiny_sweep_flags):
    """A real SIGKILL of the command-line process at an arbitrary point; the same command then completes."""
    out = tmp_path / "run"
    command = [sys.executable, "-m", "train", "sweep", *tiny_sweep_flags(steps=8192, seeds=2), "--out", str(out)]
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).parents[2])}
    process = subprocess.Popen(command, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 240
    while not (out / "results.parquet").exists() and time.monotonic() < deadline and process.poll() is None:
        time.sleep(0.05)
    process.send_signal(signal.SIGKILL)
    process.wait()
    finished = subprocess.run(command, env=env, capture_output=True, text=True, timeout=400)
    assert finished.returncode == 0, finished.stderr
    results = pd.read_parquet(out / "results.parquet")
    assert len(results) == 2 * 8 and not results.duplicated(["config_id", "env_steps"]).any()
    assert "best costed reward" in finished.stdout
    assert not list(out.rglob(".*.partial"))  # temporary files of a write the kill cut short are cleared


@pytest.mark.slow
def test_ctrl_c_stops_with_a_message_and_the_rerun_resumes(tmp_path, tiny_sweep_flags):
    """SIGINT (Ctrl-C) once training has written rows: exit status 130, a line saying what is kept and how to
    resume, no traceback and no abort from XLA's threads; the same command then completes."""
    out = tmp_path / "run"
    command = [sys.executable, "-m", "train", "sweep", *tiny_sweep_flags(steps=32768, seeds=2), "--out", str(out)]
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).parents[2])}
    process = subprocess.Popen(command, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 480
    while not (out / "results.parquet").exists() and time.monotonic() < deadline and process.poll() is None:
        time.sleep(0.05)
    assert process.poll() is None and (out / "results.parquet").exists(), "no rows written to interrupt"
    process.send_signal(signal.SIGINT)
    _, stderr = process.communicate(timeout=240)
    assert process.returncode == 130, stderr
    assert "interrupted" in stderr and "rerun the same command to resume" in stderr
    assert "Traceback" not in stderr and "terminate called" not in stderr
    finished = subprocess.run(command, env=env, capture_output=True, text=True, timeout=400)
    assert finished.returncode == 0, finished.stderr
    results = pd.read_parquet(out / "results.parquet")
    assert len(results) == 2 * 32 and not results.duplicated(["config_id", "env_steps"]).any()


def test_ctrl_c_inside_a_garbage_collector_callback_still_stops():
    """A SIGINT whose KeyboardInterrupt Python raises inside a gc callback (jax registers one) is "ignored" by
    Python; the command must still stop with status 130 and the resume line, not train on (CI saw this once)."""
    script = """
import gc, signal, sys
import train.cli

def main(prog):
    def interrupt_during_collection(phase, info):
        if phase == "start":
            gc.callbacks.remove(interrupt_during_collection)
            signal.raise_signal(signal.SIGINT)
    gc.callbacks.append(interrupt_during_collection)
    gc.collect()
    print("trained on", flush=True)
    return 0

train.cli.main = main
sys.exit(train.cli.interruptible_main("amjax"))
"""
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).parents[2])}
    finished = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=120)
    assert finished.returncode == 130, finished.stderr
    assert "trained on" not in finished.stdout
    assert "amjax: interrupted" in finished.stderr and "rerun the same command to resume" in finished.stderr


def test_failed_write_keeps_the_old_file(tmp_path):
    path = tmp_path / "table.csv"
    path.write_text("old")

    def fail(tmp):
        Path(tmp).write_text("half")
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        atomic_write(path, fail)
    assert path.read_text() == "old" and [p.name for p in tmp_path.iterdir()] == ["table.csv"]


@pytest.mark.slow
def test_rerun_clears_partial_writes_of_a_killed_run(tmp_path, full_run):
    out = shutil.copytree(full_run.out, tmp_path / "run")
    leftovers = [out / ".results.parquet.k9x2.partial", out / "checkpoints" / ".ppo-x.msgpack.a1b2.partial"]
    for leftover in leftovers:
        leftover.write_bytes(b"half a file")
    kept = out / ".notes.txt"  # a dotfile of the user's own, not ours
    kept.write_text("mine")
    rerun = run_sweep(TINY, out, progress=False, target_chunks=4)
    assert not any(p.exists() for p in leftovers) and kept.read_text() == "mine"
    pd.testing.assert_frame_equal(rerun.table, full_run.table)


@pytest.mark.slow
def test_folder_busy_with_another_process_is_refused(tmp_path, full_run, capsys):
    out = shutil.copytree(full_run.out, tmp_path / "run")
    before = {p: p.stat().st_mtime_ns for p in out.rglob("*")}
    with folder_lock(out):  # as a second, live process would hold it
        with pytest.raises(FolderBusyError, match="out: .* another running process"):
            run_sweep(TINY, out, progress=False)
        code = main(
            [
                "sweep",
                "--agent",
                "ppo",
                "--cost",
                "0.5",
                "--seeds",
                "1",
                "--steps",
                "4096",
                "--eval-every",
                "1024",
                "--out",
                str(out),
                "--no-progress",
            ]
        )
        assert code == 2 and "another running process" in capsys.readouterr().err
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*")} == before  # nothing written
    run_sweep(TINY, out, progress=False, target_chunks=4)  # the lock is gone with its holder


@pytest.mark.slow
def test_folder_with_another_sweep_is_refused(tmp_path, full_run, capsys):
    other = SweepSpec(**{**TINY.__dict__, "costs": (0.2,)})
    before = {p: p.stat().st_mtime_ns for p in full_run.out.rglob("*")}
    with pytest.raises(SweepMismatchError, match="different sweep") as refused:
        run_sweep(other, full_run.out, progress=False)
    assert "costs: the folder has [0.0, 0.3], this sweep [0.2]" in str(refused.value)  # names what differs
    code = main(
        [
            "sweep",
            "--agent",
            "ppo",
            "--cost",
            "0.5",
            "--seeds",
            "1",
            "--steps",
            "4096",
            "--eval-every",
            "1024",
            "--out",
            str(full_run.out),
            "--no-progress",
        ]
    )
    err = capsys.readouterr().err
    assert code == 2 and "different sweep" in err and "this sweep [0.5]" in err and "total_timesteps" not in err
    assert {p: p.stat().st_mtime_ns for p in full_run.out.rglob("*")} == before  # nothing rewritten


def test_identity_differences_name_each_differing_entry_and_count_the_rest():
    stored = TINY.identity()
    assert identity_differences(stored, TINY.identity()) == []
    changed = {**stored, "seeds": [5], "hyperparams": {**stored["hyperparams"], "num_envs": 8, "gamma": 0.9}}
    assert identity_differences(stored, changed) == [
        "seeds: the folder has [0, 1], this sweep [5]",
        'hyperparams["num_envs"]: the folder has 4, this sweep 8',
        'hyperparams["gamma"]: the folder has none, this sweep 0.9',
    ]
    many = {key: "x" for key in stored}
    shown = identity_differences(stored, many, limit=3)
    assert len(shown) == 5 and shown[3] == f"and {len(stored) - 3} more"  # the env_defaults line after the count
    assert "amjax.presets" in shown[4]


@pytest.mark.slow
def test_a_preset_added_for_another_agent_leaves_a_folder_resumable(full_run, monkeypatch):
    """A folder is identified by the presets of its own agents: a CartPole preset added for Dueling DQN after a PPO
    sweep was written leaves it resumable; one added for PPO makes it another sweep, refused before any write."""
    before = {p: p.stat().st_mtime_ns for p in full_run.out.rglob("*")}
    cartpole = dict(ENV_PRESETS.get("CartPole-v0", {}))
    monkeypatch.setitem(ENV_PRESETS, "CartPole-v0", {**cartpole, "dqn.n_step": 5})
    assert TINY.to_json()["env_defaults"]["CartPole-v0"]["dqn.n_step"] == 5  # stored in full, as before
    assert "dqn.n_step" not in TINY.identity()["env_defaults"].get("CartPole-v0", {})
    run_sweep(TINY, full_run.out, progress=False)  # finished already: nothing to train
    monkeypatch.setitem(ENV_PRESETS, "CartPole-v0", {**cartpole, "ppo.ent_coef": 0.02})
    with pytest.raises(SweepMismatchError, match="different sweep") as refused:
        run_sweep(TINY, full_run.out, progress=False)
    assert 'env_defaults["CartPole-v0"]["ppo.ent_coef"]: the folder has none, this sweep 0.02' in str(refused.value)
    assert "amjax.presets" in str(refused.value)
    assert {p for p in full_run.out.rglob("*")} == set(before)


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--env", "NoSuchEnv-v9"], "unknown environment"),
        (["--agent", "sac"], "unknown agent"),
        (["--cost", "-0.1"], "cost"),
        (["--cost", "nan"], "cost"),
        (["--seeds", "0"], "--seeds"),
        (["--set", "total_timesteps=1000,2000"], "total_timesteps"),
        (["--set", "learning_rate=-1"], "learning_rate"),
        (["--set", "no_such_field=3"], "no_such_field"),
        (["--steps", "0"], "--steps"),
        (["--eval-every", "-5"], "--eval-every"),
        (["--max-batch", "0"], "max-batch"),
    ],
)
def test_bad_flags_exit_2_without_output(tmp_path, capsys, flags, message):
    out = tmp_path / "never"
    with pytest.raises(SystemExit) as exit_info:
        main(["sweep", "--agent", "ppo", "--out", str(out), *flags])
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_checkpoint_roundtrip_and_corruption(tmp_path):
    state = {"a": np.arange(6, dtype=np.float32).reshape(2, 3), "b": (np.int32(4), np.ones(2, bool))}
    save_checkpoint(tmp_path / "c.msgpack", state, evals_done=3)
    restored, evals_done = load_checkpoint(tmp_path / "c.msgpack", state)
    assert evals_done == 3
    np.testing.assert_array_equal(restored["a"], state["a"])
    with pytest.raises(ValueError, match="does not match"):
        load_checkpoint(tmp_path / "c.msgpack", {"a": np.zeros((3, 3), np.float32), "b": state["b"]})
    (tmp_path / "c.msgpack").write_bytes(b"\x00garbage")
    with pytest.raises(ValueError, match="unreadable"):
        load_checkpoint(tmp_path / "c.msgpack", state)


def test_a_checkpoint_whose_step_counters_differ_is_refused(tmp_path):
    """The chunk program takes a batch's step counters from its first configuration (`batching.take_shared`), so a
    checkpoint whose configurations disagree on one is refused, not resumed from the wrong step."""
    from flax import struct

    from amjax.batching import shared_field

    @struct.dataclass
    class State:
        params: np.ndarray
        env_steps: np.ndarray = shared_field()

    good = {"algo": State(np.ones((3, 2), np.float32), np.full(3, 40, np.int32))}
    save_checkpoint(tmp_path / "c.msgpack", good, evals_done=2)
    restored, _ = load_checkpoint(tmp_path / "c.msgpack", good)
    np.testing.assert_array_equal(restored["algo"].env_steps, good["algo"].env_steps)
    bad = {"algo": State(good["algo"].params, np.array([40, 40, 36], np.int32))}
    save_checkpoint(tmp_path / "c.msgpack", bad, evals_done=2)
    with pytest.raises(ValueError, match=r"differ between its configurations \(\['algo'\]\.env_steps\)"):
        load_checkpoint(tmp_path / "c.msgpack", good)


def test_summaries_by_hand():
    rows = pd.DataFrame(
        {
            "config_id": ["a"] * 3 + ["b"] * 3 + ["c"] * 3,
            "env": "E",
            "agent": "dqn",
            "vanilla": False,
            "cost": 0.1,
            "seed": [0] * 3 + [1] * 3 + [2] * 3,
            "env_steps": [1, 2, 3] * 3,
            "eval_return": [10.0, 30.0, 20.0, 5.0, 50.0, 40.0, 1.0, 2.0, 3.0],
            "eval_raw_return": [11.0, 33.0, 22.0, 6.0, 60.0, 44.0, 1.0, 2.0, 3.0],
            "eval_length": [100.0] * 9,
            "eval_measurements": [10.0, 50.0, 20.0, 100.0, 25.0, 60.0, 100.0, 100.0, 100.0],
            "diverged": [False] * 4 + [True, True] + [False] * 3,  # b diverged at step 2: its 50 doesn't count
        }
    )
    summary = summarize(rows, []).set_index("config_id")
    assert summary.loc["a"].best_return == 30.0 and summary.loc["a"].best_measured_fraction == 0.5
    assert summary.loc["a"].measurement_reduction == pytest.approx(0.5)
    assert summary.loc["b"].best_return == 5.0 and summary.loc["b"].diverged
    assert summary.loc["c"].final_return == 3.0
    table = seed_table(summary.reset_index(), [])
    assert table.best_return_median[0] == 5.0  # median of 30, 5, 3
    assert table.best_return_q25[0] == pytest.approx(4.0) and table.best_return_q75[0] == pytest.approx(17.5)
    assert table.diverged[0] == 1


@pytest.mark.slow
def test_cli_accepts_any_budget_and_records_the_rounding(tmp_path, capsys):
    """Like SB3 and CleanRL, any --steps / --eval-every: rounded to whole updates (here 4 envs x 32 steps = 128)
    and whole evaluation periods, said in one line and kept in metadata.json."""
    import json

    out = tmp_path / "run"
    code = main(
        [
            "sweep",
            "--agent",
            "ppo",
            "--cost",
            "0.1",
            "--seeds",
            "1",
            "--steps",
            "1000",
            "--eval-every",
            "300",
            "--eval-episodes",
            "2",
            "--set",
            "num_envs=4",
            "--set",
            "num_steps=32",
            "--set",
            "rescore_episodes=2",
            "--out",
            str(out),
            "--no-progress",
        ]
    )
    assert code == 0
    assert "steps 1,000 and eval-every 300 rounded to 1,024 and 256" in capsys.readouterr().out
    meta = json.loads((out / "metadata.json").read_text())
    assert meta["requested_schedule"] == {"total_timesteps": 1000, "eval_every": 300}
    assert (meta["spec"]["total_timesteps"], meta["spec"]["eval_every"]) == (1024, 256)
    assert sorted(pd.read_parquet(out / "results.parquet").env_steps) == [256, 512, 768, 1024]
    with pytest.raises(ValueError, match="nearest valid values: eval_every=256, total_timesteps=1024"):
        expand(
            SweepSpec(
                agents=("ppo",), total_timesteps=1000, eval_every=300, hyperparams={"num_envs": 4, "num_steps": 32}
            )
        )


def test_env_defaults_apply_per_env_and_flags_override_them():
    spec = SweepSpec(
        envs=("CartPole-v0", "Acrobot-v1"),
        agents=("ppo", "dqn"),
        costs=(0.1,),
        seeds=(0,),
        total_timesteps=20480,
        eval_every=10240,
        hyperparams={"dqn.gamma": 0.9},
        env_defaults={"Acrobot-v1": {"ppo.ent_coef": 0.0, "gamma": 0.95}},
    )
    configs = {(r.env, r.agent): r for r in expand(spec)}
    assert configs["Acrobot-v1", "ppo"].config.ent_coef == 0.0 and configs["Acrobot-v1", "ppo"].config.gamma == 0.95
    assert configs["CartPole-v0", "ppo"].config.ent_coef == 0.01 and configs["CartPole-v0", "ppo"].config.gamma == 0.99
    assert configs["Acrobot-v1", "dqn"].config.gamma == 0.9  # the sweep's own value wins over the env's default
    assert configs["Acrobot-v1", "ppo"].hyperparams == {}  # defaults are not swept columns
    for bad in ({"nope": 1}, {"gamma": [0.9, 0.99]}, {"total_timesteps": 10}):
        with pytest.raises(ValueError, match="env_defaults"):
            expand(SweepSpec(env_defaults={"Acrobot-v1": bad}))


def test_cli_sweep_starts_each_env_from_its_tuned_defaults():
    from train.cli import build_parser, spec_from_args

    args = build_parser().parse_args(
        [
            "sweep",
            "--env",
            "CartPole-v0",
            "Acrobot-v1",
            "--agent",
            "ppo",
            "dqn",
            "--set",
            "ppo.ent_coef=0.05",
            "--out",
            "x",
        ]
    )
    configs = {(r.env, r.agent): r.config for r in expand(spec_from_args(args))}
    assert configs["Acrobot-v1", "ppo"].reward_scale == 0.1  # amjax.presets's Acrobot PPO
    assert configs["Acrobot-v1", "ppo"].ent_coef == pytest.approx(0.05)  # --set wins
    assert configs["CartPole-v0", "ppo"].reward_scale == 1.0
    assert (configs["Acrobot-v1", "dqn"].hidden, configs["Acrobot-v1", "dqn"].n_step) == ((128, 128), 3)  # ACROBOT_DQN
    assert configs["Acrobot-v1", "ppo"].hidden == (128, 128) and configs["CartPole-v0", "ppo"].hidden == (64, 64)
    acrobot_ppo, cartpole_ppo = configs["Acrobot-v1", "ppo"], configs["CartPole-v0", "ppo"]
    assert (acrobot_ppo.update_epochs, acrobot_ppo.num_minibatches) == (10, 8)  # ACROBOT_PPO, runs 8-9
    assert acrobot_ppo.clip_value is False and cartpole_ppo.clip_value is True  # ACROBOT_PPO, run 11
    assert (cartpole_ppo.update_epochs, cartpole_ppo.num_minibatches) == (4, 4)
    assert (configs["CartPole-v0", "dqn"].hidden, configs["CartPole-v0", "dqn"].n_step) == ((64, 64), 10)
    args = build_parser().parse_args(
        ["sweep", "--env", "Acrobot-v1", "--agent", "ppo", "--no-env-defaults", "--out", "x"]
    )
    assert expand(spec_from_args(args))[0].config.reward_scale == 1.0


def test_cli_set_reads_true_and_false_in_any_case():
    """`--set` takes booleans as Python writes them and as YAML and JSON do (true, FALSE), alone and in lists."""
    from train.cli import build_parser, spec_from_args

    flags = ["sweep", "--agent", "pqn", "--seeds", "1", "--out", "x", "--set", "pqn.dueling=true,False"]
    args = build_parser().parse_args([*flags, "--set", "pqn.layer_norm=FALSE", "--set", "pqn.activation=tanh"])
    configs = [r.config for r in expand(spec_from_args(args))]
    assert sorted({c.dueling for c in configs}) == [False, True]
    assert all(c.layer_norm is False and c.activation == "tanh" for c in configs)


@pytest.mark.parametrize("env", sorted(ENV_PRESETS))
def test_the_cli_and_the_library_build_the_same_configs(env):
    """One source of defaults: for every env with presets and every agent, the command line, `SweepSpec` from
    Python and `config_for` build the same config; each one's opt-out gives the agent's own defaults."""
    from train.cli import build_parser, spec_from_args

    agents = sorted({key.partition(".")[0] for key in ENV_PRESETS[env]})
    schedule = {"total_timesteps": 32768, "eval_every": 16384}
    flags = [
        "sweep",
        "--env",
        env,
        "--agent",
        *agents,
        "--cost",
        "0.2",
        "--seeds",
        "1",
        "--steps",
        "32768",
        "--eval-every",
        "16384",
        "--out",
        "x",
    ]
    cli = {r.agent: r.config for r in expand(spec_from_args(build_parser().parse_args(flags)))}
    library = {
        r.agent: r.config
        for r in expand(SweepSpec(envs=(env,), agents=tuple(agents), costs=(0.2,), seeds=(0,), **schedule))
    }
    for agent in agents:
        alone = config_for(env, agent, cost=0.2, **schedule)
        assert cli[agent] == library[agent] == alone, agent
        assert preset(env, agent) and all(getattr(alone, k) == v for k, v in preset(env, agent).items())
        plain = config_for(env, agent, presets=False, cost=0.2, **schedule)
        assert plain == ALGORITHMS[agent].config_type(env_id=env, cost=0.2, **schedule) != alone
    off = spec_from_args(build_parser().parse_args([*flags, "--no-env-defaults"]))
    opted_out = {r.agent: r.config for r in expand(off)}
    assert opted_out == {
        r.agent: r.config
        for r in expand(
            SweepSpec(envs=(env,), agents=tuple(agents), costs=(0.2,), seeds=(0,), env_defaults={}, **schedule)
        )
    }
    assert all(opted_out[a] == config_for(env, a, presets=False, cost=0.2, **schedule) for a in agents)


def test_a_python_spec_stores_the_presets_it_used():
    """`env_defaults=None` is stored resolved, so a folder says which presets its configurations started from and
    a command-line sweep of the same grid resumes it."""
    spec = SweepSpec(envs=("CartPole-v0", "Acrobot-v1"), agents=("ppo",))
    stored = spec.to_json()["env_defaults"]
    presets = {env: ENV_PRESETS[env] for env in ("CartPole-v0", "Acrobot-v1")}
    assert stored == json.loads(json.dumps(presets, default=list))
    ppo_only = {"Acrobot-v1": {k: v for k, v in ENV_PRESETS["Acrobot-v1"].items() if k.startswith("ppo.")}}
    assert spec.identity()["env_defaults"] == json.loads(json.dumps(ppo_only, default=list))  # CartPole's is PQN's
    assert SweepSpec.from_json(spec.to_json()).to_json() == spec.to_json()
    assert SweepSpec(envs=("Acrobot-v1",), env_defaults={}).to_json()["env_defaults"] == {}
