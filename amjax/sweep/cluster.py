"""Sweeps on a cluster (issue 18, work in progress on the `cluster` branch): the driver plans the batches as a local
sweep does and sends each unfinished batch to a worker through submitit (Slurm job arrays on a cluster, local
subprocesses with `local:N`). A worker trains its batch into `out/parts/<batch>/` (results, re-scoring, checkpoint
and policies, all atomic); the driver merges a finished part into `out/` exactly as a local sweep writes it, so a
sweep may resume locally after a cluster run and vice versa. A worker that dies has its batch submitted again and
resumes from its part's checkpoint.

Shared: `out` must be on a filesystem that the driver and every worker see (the cluster's shared home or scratch).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import socket
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

CLUSTER_TARGETS = "local:N (N worker processes on this machine) or slurm:PARTITION"
POLL_S = 2.0
MAX_ATTEMPTS = 3  # submissions of one batch before the sweep stops with an error


@dataclass(frozen=True)
class ClusterTarget:
    kind: str  # "local" or "slurm"
    workers: int  # local: worker processes; slurm: jobs running at once (array parallelism)
    partition: str | None = None


def parse_cluster(target: str) -> ClusterTarget:
    """`local:N` or `slurm:PARTITION[:N]`; ValueError naming `cluster` otherwise."""
    match = re.fullmatch(r"local:(\d+)|slurm:([\w.-]+)(?::(\d+))?", str(target))
    if not match or (match.group(1) is not None and int(match.group(1)) < 1):
        raise ValueError(f"cluster: got {target!r}; allowed values: {CLUSTER_TARGETS}")
    if match.group(1) is not None:
        return ClusterTarget("local", int(match.group(1)))
    return ClusterTarget("slurm", int(match.group(3) or 64), match.group(2))


def make_executor(target: ClusterTarget, folder: Path) -> Any:
    """A submitit executor for `target`, its logs in `folder`."""
    import submitit

    if target.kind == "local":
        executor = submitit.LocalExecutor(folder=folder)
        executor.update_parameters(timeout_min=24 * 60)
    else:
        executor = submitit.AutoExecutor(folder=folder, cluster="slurm")
        executor.update_parameters(slurm_partition=target.partition, timeout_min=24 * 60,
                                   slurm_array_parallelism=target.workers, cpus_per_task=os.cpu_count())
    return executor


def part_folder(out: Path, batch_name: str) -> Path:
    return Path(out) / "parts" / batch_name


def train_part(spec_json: dict[str, Any], out: str, batch_name: str, max_batch: int, num_devices: int,
               options: dict[str, Any], cores: int | None = None) -> dict[str, Any]:
    """The worker's job: train batch `batch_name` of the sweep `spec_json` into its part folder (resuming from the
    part's checkpoint if an earlier attempt died). Returns where it ran."""
    if cores:
        os.environ.setdefault("JAX_NUM_CPU_DEVICES", str(cores))
    from amjax.sweep import runner, storage
    from amjax.sweep.batches import plan_batches
    from amjax.sweep.devices import sweep_devices
    from amjax.sweep.grid import SweepSpec, expand

    spec = SweepSpec.from_json(spec_json)
    runs = expand(spec)
    batch = next(b for b in plan_batches(runs, max_batch, num_devices) if b.name == batch_name)
    part = part_folder(Path(out), batch_name)
    part.mkdir(parents=True, exist_ok=True)
    storage.write_json(part / "worker.json", {"node": socket.gethostname(), "pid": os.getpid()})
    hyper_columns = sorted({k for r in runs for k in r.hyperparams})
    start = time.monotonic()
    from tqdm.auto import tqdm

    with tqdm(disable=True) as bar:
        runner._train_batch(
            batch, part, storage.read_table(part / "results"), hyper_columns, bar,
            devices=tuple(sweep_devices()), wall_time=storage.WallTime(part / "wall_time.json"),
            rescored=storage.read_table(part / "rescored"), loggers=(), on_chunk=None, **options)
    return {"batch": batch_name, "node": socket.gethostname(), "pid": os.getpid(),
            "seconds": round(time.monotonic() - start, 1)}


def merge_part(out: Path, batch_name: str, results: Any, rescored: Any) -> tuple[Any, Any]:
    """Fold a finished part into `out`: its rows into results / rescored (keyed, never duplicated), its policies
    and checkpoint into their usual places; then the part is removed."""
    from amjax.sweep import storage

    part = part_folder(out, batch_name)
    results = storage.merge_rows(results, storage.read_table(part / "results"))
    rescored = storage.merge_by_config(rescored, storage.read_table(part / "rescored"))
    storage.write_table(out / "results", results)
    storage.write_table(out / "rescored", rescored)
    for sub in ("policies", "checkpoints"):
        if (part / sub).exists():
            (out / sub).mkdir(exist_ok=True)
            for path in (part / sub).iterdir():
                os.replace(path, out / sub / path.name)
    shutil.rmtree(part)
    return results, rescored


def drive(spec: Any, out: Path, batches: list[Any], results: Any, rescored: Any, target: ClusterTarget,
          max_batch: int, num_devices: int, options: dict[str, Any], bar: Any) -> tuple[Any, Any]:
    """Send every unfinished batch to the cluster, at most `target.workers` at once, and merge each finished part
    into `out`; a batch whose job dies is submitted again (up to MAX_ATTEMPTS times)."""
    from amjax.cores import usable_cores
    from amjax.sweep import storage

    done = set() if rescored is None else set(rescored.config_id)
    queue = [b for b in batches if any(r.config_id not in done for r in b.runs)]
    for batch in batches:  # steps of batches already merged
        if batch not in queue:
            bar.update(len(batch.runs) * spec.total_timesteps)
    executor = make_executor(target, out / "cluster" / "logs")
    cores = max(1, usable_cores() // target.workers) if target.kind == "local" else None
    log_path = out / "cluster.json"
    log = json.loads(log_path.read_text()) if log_path.exists() else {}
    running: dict[str, tuple[Any, Any]] = {}
    attempts: dict[str, int] = {}
    counted: dict[str, int] = {}
    while queue or running:
        while queue and len(running) < target.workers:
            batch = queue.pop(0)
            attempts[batch.name] = attempts.get(batch.name, 0) + 1
            job = executor.submit(train_part, spec.to_json(), str(out), batch.name, max_batch, num_devices, options,
                                  cores)
            running[batch.name] = (batch, job)
        time.sleep(POLL_S)
        for name, (batch, job) in list(running.items()):
            part_rows = storage.read_table(part_folder(out, name) / "results") if job.state != "PENDING" else None
            rows = 0 if part_rows is None else len(part_rows)
            bar.update((rows - counted.get(name, 0)) * spec.eval_every)
            counted[name] = rows
            if not job.done():
                continue
            del running[name]
            try:
                info = job.result()
            except Exception as error:  # the worker died or raised: run the batch again, from its checkpoint
                if attempts[name] >= MAX_ATTEMPTS:
                    raise RuntimeError(f"batch {name} failed {attempts[name]} times on the cluster; last error: "
                                       f"{error}") from None
                queue.insert(0, batch)
                continue
            results, rescored = merge_part(out, name, results, rescored)
            log[name] = {**info, "job_id": str(job.job_id), "attempts": attempts[name]}
            storage.write_json(log_path, log)
    return results, rescored
