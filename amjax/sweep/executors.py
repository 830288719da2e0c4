"""Executors: what runs a sweep's unfinished batches once the runner has opened its folder.

`run_sweep(spec, out, executor)` plans the batches, opens and locks the folder, commits what a kill left trained,
and hands the batches still to train to its executor (`Executor.run`), which returns the results and re-scoring
tables. Two exist:
- `LocalExecutor(devices=None, ...)`: this process, each batch's configurations split over `devices` (every local
  device by default: one per CPU core after `amjax.use_all_cores()`, so sharded over the cores; one device: not
  sharded), the next batches compiling on a background thread while one trains.
- `ClusterExecutor("local:N" | "slurm:PARTITION[:JOBS]", ...)` (`amjax.sweep.cluster`): each batch as a submitit job
  on a worker, merged back into the folder.
Both run a batch through `amjax.sweep.batch_run`, so they write the same files and either may resume the other.
"""

from __future__ import annotations

import collections
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import jax
import pandas as pd
from tqdm.auto import tqdm

from amjax import strategy
from amjax.cores import maps_past_half
from amjax.sweep import storage
from amjax.sweep.batch_run import TRAIN, batch_state, train_batch
from amjax.sweep.batches import Batch, BatchPrograms, compile_batch, plan_batches, release_programs
from amjax.sweep.devices import sweep_devices
from amjax.sweep.grid import SweepSpec, expand
from amjax.sweep.loggers import RunLogger


@dataclass
class SweepWork:
    """What the runner hands an executor: the batches to train (in order) and everything they write with."""

    spec: SweepSpec
    out: Path
    batches: list[Batch]  # planned for `Executor.devices`, none of them finished
    results: pd.DataFrame | None
    rescored: pd.DataFrame | None
    hyper_columns: list[str]
    max_batch: int
    save_policies: bool
    bar: tqdm
    wall_time: storage.WallTime
    loggers: Sequence[RunLogger] = ()
    on_chunk: Callable[[pd.DataFrame], None] | None = None
    record: Callable[[str, dict[str, Any]], None] | None = None  # where a batch ran (cluster jobs)


class Executor(Protocol):
    """Runs a sweep's unfinished batches (`SweepWork`); `devices`: what the batches are planned for."""

    devices: tuple[jax.Device, ...]

    def check(self) -> None:
        """Refuse (ValueError, ImportError) what cannot run, before anything is written."""

    def run(self, work: SweepWork) -> tuple[pd.DataFrame | None, pd.DataFrame | None]:
        """Train `work.batches` into `work.out`; returns the results and re-scoring tables."""


class CompileQueue:
    """Compiles batches' programs ahead of time, in the order they were queued, on one background daemon thread (an
    interrupted process does not wait for it) while batches train.

    `LocalExecutor` queues each of its batches in training order and takes each one's programs when it reaches it.
    A caller running sweeps one after another (`amjax replicate`) gives their executors one queue and queues the
    next sweep's batches (`queue_sweep`) when one starts, so that they compile while this one trains.

    At most `ahead` batches wait compiled and not yet taken, and none is compiled ahead while this process uses
    over half the kernel's memory mappings (`amjax.cores.maps_past_half`): every compiled program stays loaded until
    taken and trained, and a LunarLander-v3 sweep of 12 batches compiled all ahead passed Linux's limit and died
    (2026-11-29). A batch taken before its turn is compiled next.
    """

    def __init__(self, ahead: int = 2) -> None:
        if ahead < 0:
            raise ValueError(f"ahead: got {ahead}; allowed values: integers >= 0")
        self.ahead = ahead
        self._lock = threading.Condition()
        self._jobs: collections.deque = collections.deque()
        self._futures: dict[tuple, Future] = {}
        self._waiting: set[Future] = set()  # compiled (or compiling) ahead, not taken yet
        self._wanted: set[Future] = set()  # a take waits for them
        self._worker: threading.Thread | None = None

    def submit(self, batch: Batch, target_chunks: int, devices: tuple[jax.Device, ...]) -> None:
        """Queue `batch`'s compile (nothing if it is queued already), for the strategy current in this thread."""
        key = (batch.name, target_chunks, devices, strategy.current())
        with self._lock:
            if key in self._futures:
                return
            self._futures[key] = future = Future()
            self._jobs.append((future, batch, *key[1:]))
            if self._worker is None:
                self._worker = threading.Thread(target=self._work, name="amjax-compile-ahead", daemon=True)
                self._worker.start()
            self._lock.notify_all()

    def take(self, batch: Batch, target_chunks: int, devices: tuple[jax.Device, ...]) -> BatchPrograms:
        """`batch`'s programs once compiled (next, whatever is ahead of it, if its compile has not started); a failed
        compile raises its error."""
        self.submit(batch, target_chunks, devices)
        with self._lock:
            future = self._futures.pop((batch.name, target_chunks, devices, strategy.current()))
            self._wanted.add(future)
            self._lock.notify_all()
        try:
            return future.result()
        finally:
            with self._lock:
                self._wanted.discard(future)
                self._waiting.discard(future)
                self._lock.notify_all()

    def queue_sweep(
        self,
        spec: SweepSpec,
        out: str | Path,
        *,
        max_batch: int = 1024,
        target_chunks: int = 10,
        devices: Sequence[jax.Device] | None = None,
    ) -> None:
        """Queue the batches `run_sweep(spec, out, ...)` with these arguments would train (those not finished in
        `out`), in its order."""
        devices = tuple(devices or sweep_devices())
        out = Path(out)
        results, rescored = (
            (storage.read_table(out / "results"), storage.read_table(out / "rescored"))
            if out.is_dir()
            else (None, None)
        )
        for batch in plan_batches(expand(spec), max_batch, len(devices)):
            if batch_state(out, batch, results, rescored, save_policies=True) == TRAIN:
                self.submit(batch, target_chunks, devices)

    def cancel(self) -> None:
        """Drop the compiles not started yet and the programs not taken (the compile under way finishes on its
        own)."""
        with self._lock:
            for future, *_ in self._jobs:
                future.cancel()
            self._jobs.clear()
            self._futures.clear()
            self._waiting.clear()
            self._wanted.clear()
            self._lock.notify_all()

    def _next_job(self) -> tuple | None:
        """The job to compile now: one a `take` waits for, else the first in line if it may be compiled ahead."""
        wanted = next((job for job in self._jobs if job[0] in self._wanted), None)
        if wanted is not None:
            self._jobs.remove(wanted)
            return wanted
        if self._jobs and len(self._waiting) < self.ahead and not maps_past_half():
            self._waiting.add(self._jobs[0][0])  # before its result is set: its take always finds it here
            return self._jobs.popleft()
        return None

    def _work(self) -> None:
        while True:
            with self._lock:
                job = None
                while self._jobs and (job := self._next_job()) is None:
                    self._lock.wait(timeout=5.0)  # a take, a cancel or freed mappings (checked again)
                if job is None:
                    self._worker = None
                    return
            future, *args = job
            if future.set_running_or_notify_cancel():
                try:
                    future.set_result(compile_batch(*args))
                except BaseException as error:  # re-raised by take() in the sweep's thread
                    future.set_exception(error)
            del job, future, args  # the programs are the taker's: not kept loaded while this thread waits


class LocalExecutor:
    """Trains the batches in this process, one after another, each split over `devices` (default: every local
    device, `sweep_devices()`), the next ones compiling on `compile_queue`'s thread (default: a queue of this
    sweep's own) while one trains.

    Args:
      devices: the devices each batch's configurations are split over. Results agree across device counts to float
        rounding (XLA's rounding can depend on a shard's size, so the same count keeps them closest); a sweep may
        resume on another count.
      target_chunks: evaluation periods are run in about this many jitted chunks per batch; results are written
        after each chunk.
      checkpoint_every_s: train states are checkpointed after a chunk when this many seconds have passed since the
        last checkpoint (and always at the end of a batch).
      compile_queue: one queue for consecutive sweeps, each queued beforehand with `CompileQueue.queue_sweep`, so
        that a sweep's first batch compiles while the sweep before it trains.
    """

    def __init__(
        self,
        devices: Sequence[jax.Device] | None = None,
        *,
        target_chunks: int = 10,
        checkpoint_every_s: float = 60.0,
        compile_queue: CompileQueue | None = None,
    ):
        self.devices = tuple(devices or sweep_devices())
        self.target_chunks = target_chunks
        self.checkpoint_every_s = checkpoint_every_s
        self.compile_queue = compile_queue

    def check(self) -> None:
        pass

    def run(self, work: SweepWork) -> tuple[pd.DataFrame | None, pd.DataFrame | None]:
        results, rescored = work.results, work.rescored
        # Every batch's programs compile in turn on a background thread while batches train (a compile keeps about
        # one core busy); the training thread compiles nothing meanwhile.
        compiler = self.compile_queue or CompileQueue()
        for batch in work.batches:
            compiler.submit(batch, self.target_chunks, self.devices)
        try:
            for batch in work.batches:
                work.bar.set_description(
                    f"{batch.runs[0].env} {batch.algo.name} ({len(batch.runs)} configs), compiling"
                )
                results, rescored = train_batch(
                    batch,
                    work.out,
                    results,
                    work.hyper_columns,
                    work.bar,
                    target_chunks=self.target_chunks,
                    checkpoint_every_s=self.checkpoint_every_s,
                    save_policies=work.save_policies,
                    on_chunk=work.on_chunk,
                    loggers=work.loggers,
                    devices=self.devices,
                    wall_time=work.wall_time,
                    rescored=rescored,
                    programs=compiler.take(batch, self.target_chunks, self.devices),
                )
                release_programs()  # near the memory-map limit: the finished batch's programs unloaded
        finally:
            if self.compile_queue is None:
                compiler.cancel()
        return results, rescored


__all__ = ["CompileQueue", "Executor", "LocalExecutor", "SweepWork"]
