"""Sweeps on a cluster through submitit: the same batches as a local sweep, each run as a job on a worker.

The driver (`run_sweep(spec, out, ClusterExecutor(...))`, or `amjax sweep --cluster ...`) plans the batches as a
local sweep does and submits each unfinished one as a job: a Slurm job on a whole node (`slurm:PARTITION[:JOBS]`), or
a local subprocess (`local:N`, for trying it on one machine and for the tests). A worker re-plans the sweep from
its JSON spec, trains its batch into `out/parts/<batch>/` with the local executor's own code
(`amjax.sweep.batch_run`: results, re-scoring, checkpoints, policies, all written
atomically) on as many JAX devices as the driver has, and the driver folds each finished part into `out/` exactly
as a local sweep writes it. So results are the same row for row (values equal to float rounding) whatever the
number of workers, and a sweep may resume locally after a cluster run and vice versa (parts ahead of `out` are
folded back when the folder is opened).

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
import signal
import socket
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd

from amjax.files import FolderBusyError, atomic_write, commit, folder_lock, remove_partial_writes, use_compile_cache
from amjax.sweep import storage
from amjax.sweep.devices import sweep_devices

CLUSTER_TARGETS = (
    "local:N (N worker processes on this machine) or slurm:PARTITION[:JOBS] (Slurm jobs on "
    "PARTITION, a whole node each, at most JOBS at once; default 64)"
)
POLL_S = 1.0
MAX_ATTEMPTS = 3  # submissions of one batch before the sweep stops with an error
SLURM_JOBS = 64
LOGS = "cluster_logs"  # the jobs' logs, under `out`
PARTS = "parts"  # the workers' folders, under `out`
STALE_S = 900  # a job Slurm reports as PREEMPTED or UNKNOWN this long is cancelled and its batch run again


class ClusterError(RuntimeError):
    """A batch could not be run on the cluster (submission refused, or its job failed every attempt)."""


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


LOCAL_PARAMETERS = ("signal_delay_s", "stderr_to_stdout", "timeout_min")  # what LocalExecutor reads (bar setup)


def check_parameters(target: ClusterTarget, parameters: Mapping[str, Any] | None) -> None:
    """ValueError naming `cluster_parameters` for a name the target's submitit executor does not take (submitit's
    LocalExecutor would ignore it silently; its Slurm executor would refuse it only once the sweep started), or a
    `setup` that is not a list of shell lines; for Slurm, also that its commands are here."""
    import submitit

    setup = (parameters or {}).get("setup", [])
    if not isinstance(setup, list | tuple) or not all(isinstance(line, str) for line in setup):
        raise ValueError(
            f'cluster_parameters: setup must be a list of shell lines, e.g. ["module load python"]; got {setup!r}'
        )
    if target.kind == "slurm" and not (shutil.which("sbatch") and shutil.which("srun")):
        raise ValueError(
            f"cluster: {target.kind}:{target.partition} needs Slurm's sbatch and srun on PATH; run the "
            "command on a node of the cluster (a login node), or use local:N here"
        )
    # Slurm: submitit's own list, the sbatch options it writes.
    allowed = set(LOCAL_PARAMETERS) if target.kind == "local" else submitit.SlurmExecutor._valid_parameters()
    for name in parameters or {}:
        if name not in allowed:
            raise ValueError(
                f"cluster_parameters: {name!r} is not a parameter of submitit's {target.kind} executor; "
                f"allowed values: {', '.join(sorted(allowed))}"
            )


def make_executor(
    target: ClusterTarget, folder: Path, devices: int, parameters: Mapping[str, Any] | None = None
) -> Any:
    """A submitit executor for `target` whose workers have `devices` JAX CPU devices, its job logs in `folder`;
    `parameters` go to `update_parameters` (e.g. `{"account": "lab", "time": 600, "setup": ["module load
    python"]}` for Slurm)."""
    import submitit

    parameters = dict(parameters or {})
    if target.kind == "local":
        executor = submitit.LocalExecutor(folder=folder)
        executor.update_parameters(timeout_min=7 * 24 * 60, **parameters)
        return executor  # `worker_environment` is set around each submission instead of shell lines
    executor = submitit.SlurmExecutor(folder=folder)
    # A whole node per job: its cores run the worker's devices (and XLA's threads within each).
    executor.update_parameters(
        partition=target.partition, exclusive=True, nodes=1, ntasks_per_node=1, time=24 * 60, job_name="amjax-sweep"
    )
    exports = [
        f"export {name}=${{{name}:-{shlex.quote(value)}}}"
        if name == "JAX_COMPILATION_CACHE_DIR"
        else f"export {name}={shlex.quote(value)}"
        for name, value in worker_environment(devices).items()
    ]
    executor.update_parameters(setup=[*exports, *parameters.pop("setup", ())], **parameters)
    return executor


def worker_environment(devices: int) -> dict[str, str]:
    """What a worker's Python must find set when it starts (the job imports amjax, whose agents start JAX, before
    the job function runs):
    - JAX_NUM_CPU_DEVICES: as many devices as the driver planned the batches for, so the same per-device shapes
      as the local run's programs (XLA's float rounding can depend on a shard's size);
    - JAX_COMPILATION_CACHE_DIR, if the user set one. Otherwise each worker keeps its programs in
      `out/compile_cache/<its backend and CPU>` (`train_part` calls `use_compile_cache`), shared by every worker of
      that kind of machine: a program compiles once, not once per batch of its group or retry, and never loads on a
      CPU of another vector extension."""
    variables = {"JAX_NUM_CPU_DEVICES": str(int(devices))}
    if os.environ.get("JAX_COMPILATION_CACHE_DIR"):
        variables["JAX_COMPILATION_CACHE_DIR"] = os.environ["JAX_COMPILATION_CACHE_DIR"]
    return variables


@contextlib.contextmanager
def starting_workers(variables: Mapping[str, str]) -> Iterator[None]:
    """For the block: `variables` set in os.environ (a local job's processes copy it when they start), and SIGINT
    not ignored. A process started with SIGINT ignored, such as a background job of a shell script, passes that on
    to its children, and submitit cancels a local job with SIGINT: its worker would never stop. A handler that does
    nothing is reset to the default in a child, while the driver still ignores Ctrl-C as it was told to."""
    before = {name: os.environ.get(name) for name in variables}
    os.environ.update(variables)
    ignored = (
        threading.current_thread() is threading.main_thread() and signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    )
    if ignored:
        signal.signal(signal.SIGINT, lambda *_: None)
    try:
        yield
    finally:
        if ignored:
            signal.signal(signal.SIGINT, signal.SIG_IGN)
        for name, value in before.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def part_folder(out: Path, batch_name: str) -> Path:
    return Path(out) / PARTS / batch_name


def _copy_checkpoint(out: Path, part: Path, batch_name: str, config_ids: Sequence[str]) -> None:
    """Start a part from `out`'s checkpoint of the batch (and its rows) when that is further on: a sweep that ran
    locally for a while resumes on the cluster where it stopped."""
    source = storage.checkpoint_path(out, batch_name)
    target = storage.checkpoint_path(part, batch_name)
    if storage.checkpoint_evals(source) <= storage.checkpoint_evals(target):
        return
    atomic_write(target, lambda tmp: shutil.copyfile(source, tmp))
    rows = storage.read_table(out / "results")
    if rows is not None and rows.config_id.isin(config_ids).any():
        storage.write_table(
            part / "results",
            storage.merge_rows(storage.read_table(part / "results"), rows[rows.config_id.isin(config_ids)]),
        )


def train_part(
    spec_json: dict[str, Any], out: str, batch_name: str, max_batch: int, options: dict[str, Any]
) -> dict[str, Any]:
    """A worker's job: train batch `batch_name` of the sweep `spec_json` into its part folder, split over the
    worker's devices (`make_executor` sets how many) and resuming from the part's checkpoint. Returns where it
    ran."""
    from tqdm.auto import tqdm

    from amjax.sweep.batch_run import train_batch
    from amjax.sweep.batches import plan_batches, release_programs
    from amjax.sweep.devices import sweep_devices
    from amjax.sweep.grid import SweepSpec, expand

    use_compile_cache(out)
    spec = SweepSpec.from_json(spec_json)
    runs = expand(spec)
    devices = tuple(sweep_devices())
    batch = next(b for b in plan_batches(runs, max_batch, len(devices)) if b.name == batch_name)
    config_ids = [r.config_id for r in batch.runs]
    out_path, part = Path(out), part_folder(Path(out), batch_name)
    info = {"batch": batch_name, "node": socket.gethostname(), "pid": os.getpid(), "devices": len(devices)}
    with folder_lock(part, wait=True):  # a worker left by a killed driver finishes first
        remove_partial_writes(part)
        if storage.batch_complete(
            out_path,
            batch_name,
            storage.read_table(out_path / "results"),
            storage.read_table(out_path / "rescored"),
            options["save_policies"],
        ):
            return {**info, "seconds": 0.0}  # merged already
        storage.write_json(part / "worker.json", info)
        _copy_checkpoint(out_path, part, batch_name, config_ids)
        start = time.monotonic()
        hyper_columns = sorted({k for r in runs for k in r.hyperparams})
        with tqdm(disable=True) as bar:
            train_batch(
                batch,
                part,
                storage.read_table(part / "results"),
                hyper_columns,
                bar,
                devices=devices,
                wall_time=storage.WallTime(part / "wall_time.json"),
                rescored=storage.read_table(part / "rescored"),
                loggers=(),
                on_chunk=None,
                **options,
            )
        release_programs()  # a worker trains its group's batches one after another
    return {**info, "seconds": round(time.monotonic() - start, 1)}


def merge_part(
    out: Path, batch_name: str, results: pd.DataFrame | None, rescored: pd.DataFrame | None, policies: bool = True
) -> tuple[pd.DataFrame | None, pd.DataFrame | None, pd.DataFrame | None]:
    """Fold the part of `batch_name` into `out`, then remove it; returns results, rescored and the rows taken from
    the part (None if none). A part is taken when it is ahead of `out`: finished (its commit marker), or
    checkpointed further than `out`'s checkpoint of the batch; and not when `out` holds the batch finished already
    (a worker of a killed driver that fell behind, or a part merged before a kill). `policies`: whether the sweep
    keeps policies (what "finished" includes).

    Crash consistency: rows and re-scores are merged first (keyed: merging twice changes nothing), then the
    checkpoint and policies are moved, then the batch's marker is written in `out`, and only then is the part
    removed. A driver killed at any point leaves a part that is still ahead, or `out` with the batch committed, so
    the next merge completes it; no file is ever only in a part that is being removed.
    Raises FolderBusyError if a worker still holds the part."""
    part = part_folder(out, batch_name)
    checkpoint = storage.checkpoint_path(Path(), batch_name)
    with folder_lock(part, argument=f"parts/{batch_name}"):
        rows = storage.read_table(part / "results")
        marker = storage.read_marker(part, batch_name)
        ahead = marker is not None or (
            storage.checkpoint_evals(part / checkpoint) > storage.checkpoint_evals(out / checkpoint)
        )
        if rows is None or not ahead or storage.batch_complete(out, batch_name, results, rescored, policies):
            rows = None
        else:
            results = storage.merge_rows(results, rows)
            storage.write_table(out / "results", results)
            part_rescored = storage.read_table(part / "rescored")
            if part_rescored is not None:
                rescored = storage.merge_by_config(rescored, part_rescored)
                storage.write_table(out / "rescored", rescored)
            for path in [part / checkpoint, *sorted((part / "policies").glob("*.msgpack"))]:
                if path.exists():
                    target = out / path.relative_to(part)
                    target.parent.mkdir(exist_ok=True)
                    commit(path, target)
            if marker is not None and storage.marker_files_present(out, marker, results, rescored, policies):
                storage.write_marker(out, marker)
        shutil.rmtree(part)
    with contextlib.suppress(OSError):  # the last part: no empty parts/ left behind
        part.parent.rmdir()
    return results, rescored, rows


def merge_parts(
    out: Path, results: pd.DataFrame | None, rescored: pd.DataFrame | None, policies: bool = True
) -> tuple[pd.DataFrame | None, pd.DataFrame | None]:
    """Fold every part that no worker holds into `out` (a cluster run that was stopped); the local runner and the
    driver call this when they open a folder."""
    for part in sorted((Path(out) / PARTS).glob("*/")):
        with contextlib.suppress(FolderBusyError):  # its worker still runs: its next job waits for it
            results, rescored, _ = merge_part(out, part.name, results, rescored, policies)
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


def drive(
    spec: Any,
    out: Path,
    batches: Sequence[Any],
    results: pd.DataFrame | None,
    rescored: pd.DataFrame | None,
    target: ClusterTarget,
    max_batch: int,
    num_devices: int,
    options: dict[str, Any],
    bar: Any,
    *,
    parameters: Mapping[str, Any] | None = None,
    record: Callable[[str, dict[str, Any]], None],
    on_rows: Callable[[pd.DataFrame, pd.DataFrame], None],
) -> tuple[pd.DataFrame | None, pd.DataFrame | None]:
    """Run `batches` (those not finished in `out`) on the cluster, at most `target.workers` at once, each worker on
    `num_devices` devices (the driver's: `batches` were planned for them); fold each finished part into `out`,
    call `on_rows(new_rows, results)` and `record(batch, where_it_ran)`. A failed job is submitted again (the
    worker resumes from the part's checkpoint); Ctrl-C cancels the running jobs."""
    queue = list(batches)
    policies = options["save_policies"]
    executor = make_executor(target, out / LOGS, num_devices, parameters)
    running: dict[str, tuple[Any, Any]] = {}
    attempts: dict[str, int] = {}
    counted: dict[str, int] = {}
    stale_since: dict[str, float] = {}

    def run_again(batch: Any, job: Any, error: Any) -> None:
        """The job failed (or hung): its batch goes back to the queue, up to MAX_ATTEMPTS submissions."""
        _delete_job_files(job)
        if attempts[batch.name] >= MAX_ATTEMPTS:
            raise ClusterError(
                f"cluster: batch {batch.name} failed {attempts[batch.name]} times; last error: "
                f"{error} (job logs in {out / LOGS})"
            )
        queue.insert(0, batch)

    try:
        while queue or running:
            while queue and len(running) < target.workers:
                batch = queue.pop(0)
                attempts[batch.name] = attempts.get(batch.name, 0) + 1
                try:
                    with starting_workers(worker_environment(num_devices)):
                        job = executor.submit(train_part, spec.to_json(), str(out), batch.name, max_batch, options)
                except Exception as error:  # e.g. sbatch refused the job (partition, account, time limit)
                    raise ClusterError(f"cluster: submitting batch {batch.name} failed: {error}") from None
                running[batch.name] = (batch, job)
            bar.set_description(f"sweep on {target.kind}: {len(running)} batches running, {len(queue)} queued")
            time.sleep(POLL_S)
            for name, (batch, job) in list(running.items()):
                part_rows = storage.read_table(part_folder(out, name) / "results")
                seen = 0 if part_rows is None else len(part_rows)
                bar.update(max(0, seen - counted.get(name, 0)) * spec.eval_every)
                counted[name] = max(seen, counted.get(name, 0))
                if not job.done():
                    # Slurm may leave a preempted (not requeued) or lost job in a state submitit never calls done.
                    if target.kind == "slurm" and job.state in ("PREEMPTED", "UNKNOWN"):
                        if time.monotonic() - stale_since.setdefault(name, time.monotonic()) > STALE_S:
                            job.cancel(check=False)
                            del running[name]
                            run_again(batch, job, f"Slurm reported the job {job.state} for {STALE_S} s")
                    else:
                        stale_since.pop(name, None)
                    continue
                del running[name]
                try:
                    info = job.result()
                except Exception as error:  # the worker died or raised: submit the batch again
                    run_again(batch, job, error)
                    continue
                try:
                    results, rescored, rows = merge_part(out, name, results, rescored, policies)
                except FolderBusyError:  # a worker of an earlier driver took the part after this job: wait
                    attempts[name] -= 1  # not a failure
                    _delete_job_files(job)
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


class ClusterExecutor:
    """Runs the batches as submitit jobs (`drive`): `target` "local:N" (N worker processes here) or
    "slurm:PARTITION[:JOBS]" (a whole node per job, at most JOBS at once). The sweep's folder must be on a
    filesystem the workers share. Each worker splits its batch over as many JAX devices as `devices` holds (the
    driver's, by default), so its programs are the local run's; results are a local run's, and either may resume
    the other (docs/cluster.md).

    Args:
      target: where the jobs run (`CLUSTER_TARGETS`).
      parameters: submitit executor parameters for the jobs (e.g. `{"account": "lab", "time": 600}` for Slurm;
        `setup`: shell lines run before each job).
      devices: the driver's devices (default: every local device); each worker splits its batch over as many.
      target_chunks: evaluation periods per batch run in about this many chunks (as `LocalExecutor`'s).
      checkpoint_every_s: the workers' seconds between checkpoints (as `LocalExecutor`'s).
    """

    def __init__(
        self,
        target: str,
        parameters: Mapping[str, Any] | None = None,
        *,
        devices: Sequence[Any] | None = None,
        target_chunks: int = 10,
        checkpoint_every_s: float = 60.0,
    ):
        self.target = parse_cluster(target)
        self.parameters = dict(parameters or {})
        self.devices = tuple(devices or sweep_devices())
        self.target_chunks = target_chunks
        self.checkpoint_every_s = checkpoint_every_s

    def check(self) -> None:
        check_engine()
        check_parameters(self.target, self.parameters)

    def run(self, work: Any) -> tuple[pd.DataFrame | None, pd.DataFrame | None]:
        def on_rows(rows: pd.DataFrame, results: pd.DataFrame) -> None:  # a batch folded in
            work.wall_time.save()
            for logger in work.loggers:
                logger.log(rows)
            if work.on_chunk is not None:
                work.on_chunk(results)

        options = {
            "target_chunks": self.target_chunks,
            "checkpoint_every_s": self.checkpoint_every_s,
            "save_policies": work.save_policies,
        }
        return drive(
            work.spec,
            work.out,
            work.batches,
            work.results,
            work.rescored,
            self.target,
            work.max_batch,
            len(self.devices),
            options,
            work.bar,
            parameters=self.parameters,
            on_rows=on_rows,
            record=work.record or (lambda name, where: None),
        )
