"""Sweeps on a cluster (`amjax.sweep.cluster`) with a real local submitit cluster: worker processes that train the
batches, one of them SIGKILLed mid-batch; the same rows as the local runner; either runner resuming the other."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import jax
import numpy as np
import pandas as pd
import pytest

from amjax.files import folder_lock
from amjax.sweep import SweepSpec, run_sweep
from amjax.sweep.cluster import (
    ClusterTarget,
    check_parameters,
    make_executor,
    merge_parts,
    parse_cluster,
    starting_workers,
)
from amjax.sweep.storage import checkpoint_evals, read_table, save_checkpoint, write_table

SPEC = SweepSpec(
    envs=("CartPole-v0",),
    agents=("ppo", "dqn"),
    costs=(0.0, 0.2),
    seeds=(0, 1),
    total_timesteps=8192,
    eval_every=1024,
    eval_episodes=2,
    hyperparams={"ppo.num_envs": 4, "ppo.num_steps": 32, "rescore_episodes": 4},
)
KEY = ["config_id", "env_steps"]
VALUE_COLUMNS = ["eval_return", "eval_raw_return", "eval_measurements", "train_return", "loss"]
RESCORED_COLUMNS = ["best_policy_return", "best_policy_raw_return", "best_policy_measured_fraction"]


def _part_rows(out: Path, agent: str) -> int:
    """Rows written so far in `agent`'s parts, read as the driver reads them (`read_table`: one open file, never
    torn by a worker's atomic replace)."""
    tables = (read_table(p.with_suffix("")) for p in (out / "parts").glob(f"{agent}-*/results.parquet"))
    return sum(len(table) for table in tables if table is not None)


def _assert_same_results(out: Path, local) -> None:
    """`out` holds exactly the local run's rows, re-scores and policies, with nothing left of the cluster's parts
    or of submitit's pickled calls."""
    results = pd.read_parquet(out / "results.parquet")
    assert not results.duplicated(KEY).any()
    a = results.sort_values(KEY).reset_index(drop=True)
    b = local.results.sort_values(KEY).reset_index(drop=True)
    pd.testing.assert_frame_equal(a[KEY], b[KEY])
    np.testing.assert_allclose(a[VALUE_COLUMNS].to_numpy(float), b[VALUE_COLUMNS].to_numpy(float), rtol=1e-5)
    summary = pd.read_parquet(out / "summary.parquet").sort_values("config_id").reset_index(drop=True)
    expected = local.summary.sort_values("config_id").reset_index(drop=True)
    np.testing.assert_allclose(
        summary[RESCORED_COLUMNS].to_numpy(float), expected[RESCORED_COLUMNS].to_numpy(float), rtol=1e-5
    )
    assert not (out / "parts").exists()
    assert not list(out.rglob("*.pkl"))
    policies = sorted(p.name for p in (out / "policies").iterdir())
    assert policies == sorted(f"{c}.msgpack" for c in local.summary.config_id)


@pytest.mark.slow
def test_cluster_and_local_runs_resume_each_other_through_kills(tmp_path, stop_sweep_after):
    """One sweep folder through every hand-over, each stop a hard one:
    1. the local runner, stopped after 2 chunks of the PPO batch;
    2. `local:2` resumes it (PPO from the local checkpoint); once DQN has begun, the driver and its workers are
       SIGKILLed;
    3. the local runner folds the unfinished parts back and is stopped again after a chunk;
    4. `local:2` finishes, its DQN worker SIGKILLed mid-batch: the driver submits the batch again and the new
       worker resumes from the part's checkpoint.
    The rows, re-scores and policies equal an uninterrupted local run's."""
    out = tmp_path / "run"
    with pytest.raises(stop_sweep_after.error):
        run_sweep(SPEC, out, progress=False, target_chunks=8, checkpoint_every_s=0, on_chunk=stop_sweep_after(2))
    local_rows = len(pd.read_parquet(out / "results.parquet"))

    driver = (
        f"from amjax.sweep import SweepSpec, run_sweep; spec = SweepSpec.from_json({SPEC.to_json()!r}); "
        f"run_sweep(spec, {str(out)!r}, progress=False, target_chunks=8, checkpoint_every_s=0, "
        "cluster='local:2')"
    )
    # The driver (and so its workers) on this process's device count, as every other run of the chain: across
    # counts, results agree only to float rounding, which training can amplify past the comparison's tolerance.
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).parents[2]), "JAX_NUM_CPU_DEVICES": str(jax.device_count())}
    process = subprocess.Popen(
        [sys.executable, "-c", driver],
        env=env,
        start_new_session=True,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    deadline = time.monotonic() + 300
    try:  # once the DQN batch has begun (the PPO batch went on from the local checkpoint)
        while not _part_rows(out, "dqn"):
            assert process.poll() is None, "the cluster run ended before it could be killed"
            assert time.monotonic() < deadline
            time.sleep(0.05)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(process.pid, signal.SIGKILL)  # the driver and its workers, as a lost login session would
    process.wait()
    for part in (out / "parts").glob("*/"):  # a SIGKILLed worker drops its part's lock as it exits, a moment later
        with folder_lock(part, wait=True):
            pass

    with pytest.raises(stop_sweep_after.error):
        run_sweep(SPEC, out, progress=False, target_chunks=8, checkpoint_every_s=0, on_chunk=stop_sweep_after(1))
    assert not (out / "parts").exists()
    assert len(pd.read_parquet(out / "results.parquet")) > local_rows

    killed, errors = [], []
    dqn_rows = len(SPEC.costs) * len(SPEC.seeds) * (SPEC.total_timesteps // SPEC.eval_every)  # its one batch's

    def kill_the_dqn_worker():
        seen, deadline = None, time.monotonic() + 600  # its own: the steps above took part of theirs
        try:
            while time.monotonic() < deadline and not killed:
                for part in (out / "parts").glob("dqn-*"):
                    table = read_table(part / "results")  # one open file: never torn by the worker's replace
                    if (part / "worker.json").exists() and table is not None:
                        rows = len(table)
                        seen = rows if seen is None else seen
                        if seen < rows < dqn_rows:  # a chunk trained by this worker, and more to come
                            killed.append(json.loads((part / "worker.json").read_text())["pid"])
                            os.kill(killed[0], signal.SIGKILL)
                time.sleep(0.05)
        except BaseException as error:  # raised in the test's thread below
            errors.append(error)

    threading.Thread(target=kill_the_dqn_worker, daemon=True).start()
    result = run_sweep(SPEC, out, progress=False, target_chunks=8, checkpoint_every_s=0, cluster="local:2")
    if errors:
        raise errors[0]
    assert killed
    reference = run_sweep(SPEC, tmp_path / "local", progress=False, target_chunks=8)
    _assert_same_results(out, reference)
    assert len(result.summary) == len(reference.summary)
    ran = json.loads((out / "metadata.json").read_text())["cluster_batches"]
    assert [info["attempts"] for name, info in ran.items() if name.startswith("dqn")] == [2]
    assert {info["node"] for info in ran.values()} == {socket.gethostname()}
    assert killed[0] not in {info["pid"] for info in ran.values()}  # the second worker finished the batch


@pytest.fixture
def slurm_commands(tmp_path, monkeypatch):
    """Stand-ins for Slurm's sbatch and srun on PATH (submitit needs srun to build a Slurm executor)."""
    folder = tmp_path / "bin"
    folder.mkdir()
    for name in ("sbatch", "srun"):
        (folder / name).write_text("#!/bin/sh\nexit 1\n")
        (folder / name).chmod(0o755)
    monkeypatch.setenv("PATH", f"{folder}{os.pathsep}{os.environ['PATH']}")


def test_targets_and_parameters_are_checked_before_anything_is_written(tmp_path, monkeypatch):
    assert parse_cluster("local:3") == ClusterTarget("local", 3)
    assert parse_cluster("slurm:gpu-a100") == ClusterTarget("slurm", 64, "gpu-a100")
    assert parse_cluster("slurm:cpu:8") == ClusterTarget("slurm", 8, "cpu")
    never = tmp_path / "never"
    for bad in ("local", "local:0", "local:-1", "slurm:", "ray:4", "slurm:cpu:0"):
        with pytest.raises(ValueError, match=f"cluster: got '{bad}'; allowed values: local:N"):
            run_sweep(SPEC, never, cluster=bad)
    for parameters, message in (
        ({"account": "lab"}, "'account' is not a parameter of submitit's local executor"),
        ({"setup": "module load x"}, "setup must be a list of shell lines"),
    ):
        with pytest.raises(ValueError, match=message):
            run_sweep(SPEC, never, cluster="local:2", cluster_parameters=parameters)
    monkeypatch.setenv("PATH", str(tmp_path / "empty"))  # no Slurm here
    with pytest.raises(ValueError, match="slurm:cpu needs Slurm's sbatch and srun on PATH"):
        run_sweep(SPEC, never, cluster="slurm:cpu")
    assert not never.exists()


def test_slurm_jobs_take_a_whole_node_and_the_drivers_device_count(tmp_path, slurm_commands):
    """The sbatch script submitit would send, and the names Slurm's executor takes (checked before submitting)."""
    check_parameters(ClusterTarget("slurm", 4, "cpu"), {"account": "lab", "time": 600, "mem": "64G"})
    with pytest.raises(ValueError, match="'timeout_min' is not a parameter of submitit's slurm executor"):
        check_parameters(ClusterTarget("slurm", 4, "cpu"), {"timeout_min": 600})  # sbatch's name is `time`
    executor = make_executor(
        parse_cluster("slurm:cpu:8"), tmp_path / "logs", 64, {"account": "lab", "setup": ["source ~/venv/bin/activate"]}
    )
    script = executor._make_submission_file_text("python -m submitit.core._submit", "uid")
    for line in (
        "#SBATCH --partition=cpu",
        "#SBATCH --exclusive",
        "#SBATCH --nodes=1",
        "#SBATCH --account=lab",
        "export JAX_NUM_CPU_DEVICES=64",
        "source ~/venv/bin/activate",
    ):
        assert line in script, script


@pytest.mark.parametrize("driver_sigint", ["default", "ignored"])
def test_a_cancelled_local_job_stops_its_worker(tmp_path, driver_sigint):
    """Ctrl-C or an error in the driver cancels its jobs: a local job's process really ends, also when the driver
    itself ignores SIGINT (a background job of a shell script), which its children would inherit."""
    handler = signal.SIG_IGN if driver_sigint == "ignored" else signal.default_int_handler
    previous = signal.signal(signal.SIGINT, handler)
    try:
        executor = make_executor(parse_cluster("local:1"), tmp_path / "logs", 1)
        with starting_workers({}):
            job = executor.submit(time.sleep, 120)
        assert signal.getsignal(signal.SIGINT) is handler  # the driver's own handling is given back
    finally:
        signal.signal(signal.SIGINT, previous)
    deadline = time.monotonic() + 60
    time.sleep(1.0)  # the job's Python is up
    job.cancel(check=False)
    while not job.done() and time.monotonic() < deadline:
        time.sleep(0.1)
    assert job.done() and time.monotonic() < deadline


def _fake_part(out: Path, batch: str, evals: int, rows: int, finished: bool) -> None:
    part = out / "parts" / batch
    save_checkpoint(part / "checkpoints" / f"{batch}.msgpack", {"w": np.zeros(3)}, evals)
    table = pd.DataFrame(
        {
            "config_id": ["c0"] * rows,
            "env_steps": np.arange(1, rows + 1) * 1024,
            "eval_return": np.full(rows, float(evals)),
        }
    )
    write_table(part / "results", table)
    if finished:
        write_table(part / "rescored", pd.DataFrame({"config_id": ["c0"], "best_policy_return": [1.0]}))


def test_a_part_is_taken_only_when_it_is_ahead(tmp_path):
    """A part left by a killed driver's worker: folded in when it is further on than `out`'s checkpoint, dropped
    (without touching `out`) when it fell behind or its batch has finished in `out` meanwhile."""
    out = tmp_path / "out"
    save_checkpoint(out / "checkpoints" / "b.msgpack", {"w": np.ones(3)}, 4)
    _fake_part(out, "b", evals=2, rows=2, finished=False)  # behind out's checkpoint
    results, rescored = merge_parts(out, None, None)
    assert results is None and rescored is None and not (out / "parts").exists()
    assert checkpoint_evals(out / "checkpoints" / "b.msgpack") == 4
    _fake_part(out, "b", evals=6, rows=6, finished=False)  # ahead
    results, rescored = merge_parts(out, None, None)
    assert len(results) == 6 and rescored is None and checkpoint_evals(out / "checkpoints" / "b.msgpack") == 6
    _fake_part(out, "b", evals=8, rows=8, finished=True)  # finished
    results, rescored = merge_parts(out, results, None)
    assert len(results) == 8 and list(rescored.config_id) == ["c0"]
    _fake_part(out, "b", evals=3, rows=3, finished=True)  # a straggler of a batch finished in `out`
    results, rescored = merge_parts(out, results, rescored)
    assert len(results) == 8 and results.eval_return.max() == 8 and not (out / "parts").exists()


def test_a_part_read_while_its_worker_replaces_it_is_never_torn(tmp_path):
    """The driver reads each part's results for the progress bar while the worker rewrites them (atomically):
    every read gives a whole table, the old or the new one (given a path, pyarrow opened the file twice and
    a replace in between failed the read, and with it the sweep)."""
    stem = tmp_path / "results"
    stop = threading.Event()

    writes = []

    def worker() -> None:
        rows = 10
        while not stop.is_set():
            rows = rows + 37 if rows < 3000 else 10
            write_table(
                stem,
                pd.DataFrame({"config_id": ["c0"] * rows, "env_steps": np.arange(rows), "eval_return": np.zeros(rows)}),
            )
            writes.append(rows)

    writer = threading.Thread(target=worker)
    writer.start()
    reads, deadline = 0, time.monotonic() + 60  # the counts below, not a speed: a loaded machine only takes longer
    try:
        while (reads < 200 or len(writes) < 50) and time.monotonic() < deadline:
            table = read_table(stem)
            assert table is None or (len(table) - 10) % 37 == 0
            reads += 1
    finally:
        stop.set()
        writer.join()
    assert reads >= 200 and len(writes) >= 50
