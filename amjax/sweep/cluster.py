"""Sweeps on a cluster through submitit: the same batches as a local sweep, each run as a job on a worker.

The driver (`run_sweep(..., cluster=...)`) plans the batches as a local sweep does and submits each unfinished one
as a job: a Slurm job on a whole node (`slurm:PARTITION[:JOBS]`), or a local subprocess (`local:N`, for trying it
on one machine and for the tests). A worker re-plans the sweep from its JSON spec, trains its batch into
`out/parts/<batch>/` with the local runner's own code (results, re-scoring, checkpoints, policies, all written
atomically) on every core it has, and the driver folds each finished part into `out/` exactly as a local sweep
writes it. So results are the same row for row whatever the number of workers, and a sweep may resume locally
after a cluster run and vice versa (unfinished parts are folded back when the folder is opened).

Faults: a worker that dies (SIGKILL, a lost node) makes its job fail; the driver submits the batch again (at most
`MAX_ATTEMPTS` times), and the new worker resumes from the part's last checkpoint. A killed driver resumes as a
local sweep does; a worker it left running keeps the part's lock, and the new worker for that batch waits for it.
Shared: `out` must be on a filesystem that the driver and every worker see (a cluster's shared home or scratch);
nothing is shipped back through the engine but a small dict saying where the batch ran.
"""

from __future__ import annotations

import contextlib
import importlib.util
import os
import re
import shlex
import shutil
import socket
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd

from amjax.files import FolderBusyError, atomic_write, folder_lock, remove_partial_writes
from amjax.sweep import storage

CLUSTER_TARGETS = ("local:N (N worker processes on this machine) or slurm:PARTITION[:JOBS] (Slurm jobs on "
                   "PARTITION, a whole node each, at most JOBS at once; default 64)")
POLL_S = 1.0
MAX_ATTEMPTS = 3  # submissions of one batch before the sweep stops with an error
SLURM_JOBS = 64
LOGS = "cluster_logs"  # the jobs' logs, under `out`
COMPILE_CACHE = "compile_cache"  # the workers' shared JAX compilation cache, under `out`


@dataclass(frozen=True)
class ClusterTarget:
    kind: str  # "local" or "slurm"
    workers: int  # local: worker processes; slurm: jobs running at once
    partition: str | None = None


def parse_cluster(target: str) -> ClusterTarget:
    """`local:N` or `slurm:PARTITION[:JOBS]`; ValueError naming `cluster` and the allowed values otherwise."""
    match = re.fullmatch(r"local:(\d+)|slurm:([\w.-]+)(?::(\d+))?", str(target))
    count = match and int(match.group(1) or match.group(3) or SLURM_JOBS)
    if not match or count < 1:
        raise ValueError(f"cluster: got {target!r}; allowed values: {CLUSTER_TARGETS}")
    if match.group(1) is not None:
        return ClusterTarget("local", count)
    return ClusterTarget("slurm", count, match.group(2))


def check_engine() -> None:
    """ImportError naming the extra to install when submitit is missing (raised before anything is written)."""
    if importlib.util.find_spec("submitit") is None:
        raise ImportError("cluster: sweeps on a cluster need submitit: pip install 'amjax-rl[cluster]'")


LOCAL_PARAMETERS = ("setup", "signal_delay_s", "stderr_to_stdout", "timeout_min")  # what LocalExecutor reads


def check_parameters(target: ClusterTarget, parameters: Mapping[str, Any] | None) -> None:
    """ValueError naming `cluster_parameters` for a name the target's submitit executor does not take (submitit's
    LocalExecutor would ignore it silently; its Slurm executor would refuse it only once the sweep started)."""
    import submitit

    if target.kind == "local":
        allowed = set(LOCAL_PARAMETERS)
    else:  # submitit's own list (the sbatch options it writes, and their executor-neutral aliases)
        allowed = submitit.SlurmExecutor._valid_parameters() | set(submitit.SlurmExecutor._equivalence_dict())
    for name in parameters or {}:
        if name not in allowed:
            raise ValueError(f"cluster_parameters: {name!r} is not a parameter of submitit's {target.kind} executor; "
                             f"allowed values: {', '.join(sorted(allowed))}")


def make_executor(target: ClusterTarget, folder: Path, devices: int,
                  parameters: Mapping[str, Any] | None = None) -> Any:
    """A submitit executor for `target` whose workers have `devices` JAX CPU devices, its job logs in `folder`;
    `parameters` go to `update_parameters` (e.g. `{"account": "lab", "time": 600, "setup": ["module load
    python"]}` for Slurm)."""
    import submitit

    parameters = dict(parameters or {})
    if target.kind == "local":
        executor = submitit.LocalExecutor(folder=folder)
        executor.update_parameters(timeout_min=7 * 24 * 60)
    else:
        executor = submitit.SlurmExecutor(folder=folder)
        # A whole node per job: its cores run the worker's devices (and XLA's threads within each).
        executor.update_parameters(partition=target.partition, exclusive=True, nodes=1, ntasks_per_node=1,
                                   time=24 * 60, job_name="amjax-sweep")
    # The worker splits a batch over as many devices as the driver planned for: the same per-device shapes, so
    # the same numbers bit for bit (XLA's float rounding can depend on a shard's size). Set before the worker's
    # Python starts: the job imports amjax, whose agents start JAX, before the job function runs. Workers also
    # share one persistent compilation cache in `out`, so a program compiles once, not once per batch of its
    # group or retry (a cache the user set is kept).
    cache = shlex.quote(str(Path(folder).parent / COMPILE_CACHE))
    setup = [f"export JAX_NUM_CPU_DEVICES={int(devices)}",
             f"export JAX_COMPILATION_CACHE_DIR=${{JAX_COMPILATION_CACHE_DIR:-{cache}}}", *parameters.pop("setup", ())]
    executor.update_parameters(setup=setup, **parameters)
    return executor


def part_folder(out: Path, batch_name: str) -> Path:
    return Path(out) / "parts" / batch_name


def _is_done(rescored: pd.DataFrame | None, config_ids: Sequence[str]) -> bool:
    return rescored is not None and set(config_ids) <= set(rescored.config_id)


def _newer(path: Path, than: Path) -> bool:
    return path.exists() and (not than.exists() or path.stat().st_mtime > than.stat().st_mtime)


def _copy_checkpoint(out: Path, part: Path, batch_name: str, config_ids: Sequence[str]) -> None:
    """Start a part from `out`'s checkpoint of the batch (and its rows) when that is the newer one: a sweep that
    ran locally for a while resumes on the cluster where it stopped."""
    source = out / "checkpoints" / f"{batch_name}.msgpack"
    target = part / "checkpoints" / f"{batch_name}.msgpack"
    if not _newer(source, target):
        return
    atomic_write(target, lambda tmp: shutil.copyfile(source, tmp))
    rows = storage.read_table(out / "results")
    if rows is not None and rows.config_id.isin(config_ids).any():
        storage.write_table(part / "results",
                            storage.merge_rows(storage.read_table(part / "results"),
                                               rows[rows.config_id.isin(config_ids)]))


def train_part(spec_json: dict[str, Any], out: str, batch_name: str, max_batch: int,
               options: dict[str, Any]) -> dict[str, Any]:
    """A worker's job: train batch `batch_name` of the sweep `spec_json` into its part folder, split over the
    worker's devices (`make_executor` sets how many) and resuming from the part's checkpoint. Returns where it
    ran."""
    from tqdm.auto import tqdm

    from amjax.sweep import runner
    from amjax.sweep.batches import plan_batches
    from amjax.sweep.devices import sweep_devices
    from amjax.sweep.grid import SweepSpec, expand

    spec = SweepSpec.from_json(spec_json)
    runs = expand(spec)
    devices = tuple(sweep_devices())
    batch = next(b for b in plan_batches(runs, max_batch, len(devices)) if b.name == batch_name)
    config_ids = [r.config_id for r in batch.runs]
    out_path, part = Path(out), part_folder(Path(out), batch_name)
    info = {"batch": batch_name, "node": socket.gethostname(), "pid": os.getpid(), "devices": len(devices)}
    with folder_lock(part, wait=True):  # a worker left by a killed driver finishes first
        remove_partial_writes(part)
        if _is_done(storage.read_table(out_path / "rescored"), config_ids):  # merged already
            return {**info, "seconds": 0.0}
        storage.write_json(part / "worker.json", info)
        _copy_checkpoint(out_path, part, batch_name, config_ids)
        start = time.monotonic()
        hyper_columns = sorted({k for r in runs for k in r.hyperparams})
        with tqdm(disable=True) as bar:
            runner._train_batch(
                batch, part, storage.read_table(part / "results"), hyper_columns, bar, devices=devices,
                wall_time=storage.WallTime(part / "wall_time.json"), rescored=storage.read_table(part / "rescored"),
                loggers=(), on_chunk=None, **options)
    return {**info, "seconds": round(time.monotonic() - start, 1)}


def merge_part(out: Path, batch_name: str, results: pd.DataFrame | None,
               rescored: pd.DataFrame | None) -> tuple[pd.DataFrame | None, pd.DataFrame | None, pd.DataFrame | None]:
    """Fold the part of `batch_name` into `out` (rows keyed, never duplicated; its checkpoint and policies where
    they are newer), then remove it. Returns results, rescored and the part's rows (None if it had none).
    Raises FolderBusyError if a worker still holds the part."""
    part = part_folder(out, batch_name)
    with folder_lock(part, argument=f"parts/{batch_name}"):
        rows = storage.read_table(part / "results")
        if rows is not None:
            results = storage.merge_rows(results, rows)
            storage.write_table(out / "results", results)
        part_rescored = storage.read_table(part / "rescored")
        if part_rescored is not None:
            rescored = storage.merge_by_config(rescored, part_rescored)
            storage.write_table(out / "rescored", rescored)
        for sub in ("checkpoints", "policies"):
            for path in sorted((part / sub).glob("*.msgpack")):
                if _newer(path, out / sub / path.name):
                    (out / sub).mkdir(exist_ok=True)
                    os.replace(path, out / sub / path.name)
        shutil.rmtree(part)
    with contextlib.suppress(OSError):  # the last part: no empty parts/ left behind
        part.parent.rmdir()
    return results, rescored, rows


def merge_parts(out: Path, results: pd.DataFrame | None,
                rescored: pd.DataFrame | None) -> tuple[pd.DataFrame | None, pd.DataFrame | None]:
    """Fold every part that no worker holds into `out` (a cluster run that was stopped); the local runner and the
    driver call this when they open a folder."""
    for part in sorted((Path(out) / "parts").glob("*/")):
        with contextlib.suppress(FolderBusyError):  # its worker still runs: its next job waits for it
            results, rescored, _ = merge_part(out, part.name, results, rescored)
    remove_job_pickles(out)
    return results, rescored


def _delete_job_files(job: Any) -> None:
    """submitit's pickled call and result of a finished job (its .out / .err logs stay): no pickle is left in
    `out`, which users share."""
    for path in Path(job.paths.folder).glob(f"{job.job_id}_*.pkl"):
        path.unlink(missing_ok=True)


def remove_job_pickles(out: Path) -> None:
    """The pickled calls and results of jobs whose driver was killed (no driver runs: the caller holds `out`)."""
    for path in (Path(out) / LOGS).glob("*.pkl"):
        path.unlink(missing_ok=True)


def drive(spec: Any, out: Path, batches: Sequence[Any], results: pd.DataFrame | None,
          rescored: pd.DataFrame | None, target: ClusterTarget, max_batch: int, num_devices: int,
          options: dict[str, Any], bar: Any, *, parameters: Mapping[str, Any] | None = None,
          record: Callable[[str, dict[str, Any]], None],
          on_rows: Callable[[pd.DataFrame, pd.DataFrame], None]) -> tuple[pd.DataFrame | None, pd.DataFrame | None]:
    """Run every unfinished batch on the cluster, at most `target.workers` at once, each worker on `num_devices`
    devices (the driver's: `batches` were planned for them); fold each finished part into
    `out`, call `on_rows(new_rows, results)` and `record(batch, where_it_ran)`. A failed job is submitted again
    (the worker resumes from the part's checkpoint); Ctrl-C cancels the running jobs."""
    queue = [b for b in batches if not _is_done(rescored, [r.config_id for r in b.runs])]
    bar.update(sum(len(b.runs) for b in batches if b not in queue) * spec.total_timesteps)
    executor = make_executor(target, out / LOGS, num_devices, parameters)
    running: dict[str, tuple[Any, Any]] = {}
    attempts: dict[str, int] = {}
    counted: dict[str, int] = {}
    try:
        while queue or running:
            while queue and len(running) < target.workers:
                batch = queue.pop(0)
                attempts[batch.name] = attempts.get(batch.name, 0) + 1
                job = executor.submit(train_part, spec.to_json(), str(out), batch.name, max_batch, options)
                running[batch.name] = (batch, job)
            bar.set_description(f"sweep on {target.kind}: {len(running)} batches running, {len(queue)} queued")
            time.sleep(POLL_S)
            for name, (batch, job) in list(running.items()):
                part_rows = storage.read_table(part_folder(out, name) / "results")
                seen = 0 if part_rows is None else len(part_rows)
                bar.update(max(0, seen - counted.get(name, 0)) * spec.eval_every)
                counted[name] = max(seen, counted.get(name, 0))
                if not job.done():
                    continue
                del running[name]
                try:
                    info = job.result()
                except Exception as error:  # the worker died or raised: submit the batch again
                    _delete_job_files(job)
                    if attempts[name] >= MAX_ATTEMPTS:
                        raise RuntimeError(f"cluster: batch {name} failed {attempts[name]} times; last error: "
                                           f"{error} (job logs in {out / LOGS})") from None
                    queue.insert(0, batch)
                    continue
                try:
                    results, rescored, rows = merge_part(out, name, results, rescored)
                except FolderBusyError:  # a worker of an earlier driver took the part after this job: wait
                    queue.append(batch)
                    continue
                total_rows = len(batch.runs) * batch.runs[0].config.num_evals
                bar.update((total_rows - counted[name]) * spec.eval_every)
                counted[name] = total_rows
                record(name, {**info, "job_id": str(job.job_id), "attempts": attempts[name]})
                _delete_job_files(job)
                if rows is not None:
                    on_rows(rows, results)
    except BaseException:
        for _, job in running.values():
            job.cancel(check=False)
        raise
    return results, rescored
