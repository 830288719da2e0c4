"""The sweep runner: every group of configurations that shares a compiled program is trained as one vmapped
batch, in chunks of evaluation periods, with progress, results written after each chunk and train states
checkpointed, so that killing the process at any moment and rerunning the same call resumes where it stopped.

Every file is written atomically (`amjax.files.atomic_write`: a temporary file, flushed, then one durable rename),
results before checkpoints: a rerun recomputes at most the work after the last checkpoint (training is
deterministic), and rows are keyed by (config_id, env_steps) so none is duplicated. A batch is finished when its
commit marker (`finished/<batch>.json`) is there, written last, after its rows, re-scores, policies and final
checkpoint; a rerun that finds a marker without all of those files, or the files without a marker, redoes what is
missing (`_batch_state`), so a kill at any instant loses no finished work (tests/sweep/test_crash_points.py kills
it at every rename).

Batches' programs are compiled ahead of time on a background thread (`CompileQueue`) while batches train;
finished batches are skipped without compiling.
"""

from __future__ import annotations

import collections
import functools
import json
import operator
import os
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax
import numpy as np
import pandas as pd
from tqdm.auto import tqdm

from amjax.agents import EvalRow, init_run
from amjax.agents.saved import SavedPolicy, load_policy, save_policy
from amjax.files import folder_lock, remove_partial_writes
from amjax.sweep import storage
from amjax.sweep.batches import Batch, BatchPrograms, compile_batch, plan_batches
from amjax.sweep.cluster import PARTS, check_engine, check_parameters, drive, merge_parts, parse_cluster
from amjax.sweep.devices import config_sharding, sweep_devices
from amjax.sweep.grid import RunConfig, SweepSpec, expand, group_runs
from amjax.sweep.loggers import RunLogger
from amjax.sweep.storage import policy_path


class SweepMismatchError(ValueError):
    """The output folder holds a different sweep."""


class SweepTooLargeError(ValueError):
    """A batch's train states would not fit in this machine's memory."""


@dataclass(frozen=True)
class SweepResult:
    out: Path
    results: pd.DataFrame  # one row per configuration x evaluation point
    summary: pd.DataFrame  # one row per configuration
    table: pd.DataFrame  # median / IQR over seeds


def _rescored_rows(batch: Batch, configs: Any, states: Any, programs: BatchPrograms) -> pd.DataFrame:
    """Each real configuration's best policy on fresh test episodes (one row per configuration)."""
    scores = jax.device_get(programs.rescore(configs, states))
    real = len(batch.runs)
    return pd.DataFrame(
        {
            "config_id": [r.config_id for r in batch.runs],
            "best_policy_return": np.asarray(scores.costed_return)[:real],
            "best_policy_raw_return": np.asarray(scores.raw_return)[:real],
            "best_policy_measured_fraction": np.asarray(scores.measured_fraction)[:real],
            "best_policy_episodes": [r.config.rescore_episodes for r in batch.runs],
        }
    )


def _check_memory(batches: Sequence[Batch], memory: int) -> None:
    """Refuse, before anything is written or compiled, a batch whose train states would not fit in `memory` bytes
    three times over (the states, the chunk's new states and the checkpoint's copy)."""
    for batch in batches:
        size = _state_shapes(batch)[1]
        if 3 * size > memory:
            raise SweepTooLargeError(
                f"the train states of {batch.size} {batch.algo.name} configurations take "
                f"{size / 2**30:.1f} GiB (3x that while training) and this machine has {memory / 2**30:.1f} "
                "GiB: lower --max-batch (max_batch), or the fields that size them (num_envs, buffer_size, ...)"
            )


_SHAPES: dict[tuple[Any, ...], tuple[Any, int]] = {}  # (agent, static fields, batch size) -> (shapes, bytes)


def _state_shapes(batch: Batch) -> tuple[Any, int]:
    """The shapes of a batch's train states and their bytes, sized without allocating them (`jax.eval_shape`);
    the same for every batch of a compiled group and size, so traced once per process."""
    key = (batch.algo.name, batch.runs[0].config.static_key(), batch.size)
    if key not in _SHAPES:
        configs, keys = batch.stacked()
        shapes = jax.eval_shape(jax.vmap(lambda c, k: init_run(batch.algo, c, k)), configs, keys)
        _SHAPES[key] = shapes, sum(x.size * x.dtype.itemsize for x in jax.tree.leaves(shapes))
    return _SHAPES[key]


def _memory_bytes() -> int:
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def _real(batch: Batch, tree: Any) -> Any:
    """The rows of a batched pytree that belong to real (not padding) configurations."""
    return jax.tree.map(lambda x: x[: len(batch.runs)], tree)


def _rows(batch: Batch, rows: EvalRow, hyper_columns: list[str]) -> pd.DataFrame:
    """The evaluation rows of the real (unpadded) configurations of a batch as a tidy table."""
    arrays = {k: np.asarray(v)[: len(batch.runs)] for k, v in rows.columns().items()}
    num_evals = arrays["env_steps"].shape[1]
    frame = {
        "config_id": np.repeat([r.config_id for r in batch.runs], num_evals),
        "env": np.repeat([r.env for r in batch.runs], num_evals),
        "agent": np.repeat([r.agent for r in batch.runs], num_evals),
        "vanilla": np.repeat([r.vanilla for r in batch.runs], num_evals),
        "cost": np.repeat([r.cost for r in batch.runs], num_evals),
        "seed": np.repeat([r.seed for r in batch.runs], num_evals),
    }
    for name in hyper_columns:
        frame[name] = np.repeat([_cell(r.hyperparams.get(name)) for r in batch.runs], num_evals)
    frame.update({k: v.reshape(-1) for k, v in arrays.items()})
    table = pd.DataFrame(frame)
    table["eval_measured_fraction"] = table.eval_measurements / table.eval_length
    return table


def _group_configs(runs: Sequence[RunConfig]) -> list[dict[str, Any]]:
    """Every field of one configuration per compiled group (traced fields as in its first configuration)."""
    return [{"agent": group[0].agent, **group[0].config.to_dict()} for group in group_runs(runs)]


def load_sweep_policy(out: str | Path, config_id: str) -> SavedPolicy:
    """The best policy a sweep in `out` saved for `config_id` (see its results' config_id column)."""
    path = policy_path(out, config_id)
    if not path.exists():
        saved = sorted(p.stem for p in (Path(out) / "policies").glob("*.msgpack"))
        raise FileNotFoundError(
            f"config_id: no saved policy {config_id!r} in {out}; saved: {', '.join(saved[:10]) or 'none'}"
            + (" ..." if len(saved) > 10 else "")
        )
    return load_policy(path)


def _save_policies(
    out: Path, batch: Batch, states: Any, evals_done: int, results: pd.DataFrame, rescored: pd.DataFrame | None
) -> None:
    """Write each real configuration's best policy so far (parameters of its best evaluation), with its re-scored
    figures (`rescored`: the sweep's re-scoring table) once the configuration has them."""
    best_params, best_return, best_fraction = jax.device_get(
        (states.best_params, states.best_return, states.best_measured_fraction)
    )
    healthy = results[~results.diverged & results.eval_return.notna()]
    best_steps = healthy.loc[healthy.groupby("config_id").eval_return.idxmax()].set_index("config_id").env_steps
    scores = (
        pd.DataFrame()
        if rescored is None
        else rescored.set_index("config_id").drop(columns="best_policy_episodes", errors="ignore")
    )
    for i, run in enumerate(batch.runs):
        info = {
            "config_id": run.config_id,
            "env": run.env,
            "agent": run.agent,
            "vanilla": run.vanilla,
            "cost": run.cost,
            "seed": run.seed,
            "best_return": float(best_return[i]),
            "best_measured_fraction": float(best_fraction[i]),
            "best_env_steps": int(best_steps.get(run.config_id, 0)),
            "trained_env_steps": evals_done * run.config.eval_every,
        }
        if run.config_id in scores.index:
            info.update({k: float(v) for k, v in scores.loc[run.config_id].items()})
        params = jax.tree.map(operator.itemgetter(i), best_params)
        save_policy(policy_path(out, run.config_id), run.config, params, info)


def _cell(value: Any) -> Any:
    return "x".join(map(str, value)) if isinstance(value, list | tuple) else value


def _check_folder(out: Path, spec: SweepSpec, compare: bool = True) -> bool:
    """Whether `out` already holds this sweep (False: a new folder); SweepMismatchError if it holds anything else
    that claims to be a sweep (with `compare=False`, only if it is not a folder or its metadata is unreadable).
    Reads only."""
    if out.exists() and not out.is_dir():
        raise SweepMismatchError(f"out: {out} is a file; give a folder")
    meta_path = out / "metadata.json"
    if not meta_path.exists():
        return False
    try:
        stored = json.loads(meta_path.read_text()).get("spec")
        stored = SweepSpec.from_json(stored) if stored is not None else None
    except (ValueError, TypeError, AttributeError) as error:
        raise SweepMismatchError(
            f"out: {meta_path} is not a sweep's metadata ({error}); choose another folder"
        ) from None
    if compare and (stored is None or stored.to_json() != spec.to_json()):  # older files: defaults filled
        raise SweepMismatchError(f"out: {out} holds a different sweep (see its metadata.json); choose another folder")
    return True


def _claim_folder(out: Path, spec: SweepSpec, runs: Sequence[RunConfig], extra: Mapping[str, Any]) -> None:
    """Write the sweep's metadata to a new folder, or check that an existing folder holds the same sweep."""
    if not _check_folder(out, spec):
        storage.write_json(
            out / "metadata.json",
            {"spec": spec.to_json(), "agent_configs": _group_configs(runs), **storage.environment_info(), **extra},
        )


def _record_batch(out: Path, batch_name: str, where: Mapping[str, Any]) -> None:
    """Note in metadata.json where a cluster job ran a batch (node, pid, devices, seconds, job id, attempts)."""
    meta = json.loads((out / "metadata.json").read_text())
    meta.setdefault("cluster_batches", {})[batch_name] = dict(where)
    storage.write_json(out / "metadata.json", meta)


def _train_batch(
    batch: Batch,
    out: Path,
    results: pd.DataFrame | None,
    hyper_columns: list[str],
    bar: tqdm,
    *,
    target_chunks: int,
    checkpoint_every_s: float,
    save_policies: bool,
    on_chunk: Callable[[pd.DataFrame], None] | None,
    loggers: Sequence[RunLogger],
    devices: tuple[jax.Device, ...],
    wall_time: storage.WallTime,
    rescored: pd.DataFrame | None,
    programs: BatchPrograms | None = None,
) -> tuple[pd.DataFrame | None, pd.DataFrame | None]:
    """Train (or resume) one batch chunk by chunk, writing rows after every chunk, then re-score its best policies
    and commit it (`_finish_batch`); returns the results and re-scoring tables. `programs`: the batch's programs
    compiled ahead (`compile_batch`); compiled here if not given."""
    config0 = batch.runs[0].config
    num_evals = config0.num_evals
    if programs is None:
        programs = compile_batch(batch, target_chunks, devices)
    evals_per_chunk = programs.evals_per_chunk
    ckpt_path = storage.checkpoint_path(out, batch.name)
    configs = programs.configs
    states = programs.init(configs, programs.keys)  # plain (strongly typed) arrays, left on the device
    evals_done = 0
    # A checkpoint is used only if the rows it went past are all on disk (they are written first; a folder whose
    # rows were lost trains the batch again from the start, which reproduces them).
    if ckpt_path.exists() and storage.checkpoint_evals(ckpt_path) <= _evals_with_rows(batch, results):
        real_rows, evals_done = storage.load_checkpoint(ckpt_path, _real(batch, jax.device_get(states)))
        states = batch.pad(real_rows)
    # Fresh or restored, the states are split over the devices as the compiled chunk program expects (a fresh
    # batch's stay on the accelerator: a DQN batch's replay buffers are gigabytes).
    sharding = config_sharding(list(devices))
    configs, states = jax.device_put((configs, states), sharding)
    bar.update(len(batch.runs) * evals_done * config0.eval_every)
    label = f"{batch.runs[0].env} {batch.algo.name} ({len(batch.runs)} configs)"
    bar.set_description(label)
    last_checkpoint = time.monotonic()
    # Checkpoints are written on a thread of their own while the next chunk trains (a LunarLander-v3 Dueling DQN
    # batch's is 340 MB, about 1.3 s); a chunk's rows are always on disk before its checkpoint is started, and the
    # batch is committed only once its last checkpoint is written.
    with ThreadPoolExecutor(1, thread_name_prefix="amjax-checkpoint") as writer:
        pending: Future | None = None
        while evals_done < num_evals:
            start = time.monotonic()
            states, rows = programs.chunk(configs, states)
            rows = jax.device_get(rows)
            evals_done += evals_per_chunk
            new_rows = _rows(batch, rows, hyper_columns)
            results = storage.merge_rows(results, new_rows)
            storage.write_table(out / "results", results)
            wall_time.save()
            for logger in loggers:
                logger.log(new_rows)
            if evals_done == num_evals or time.monotonic() - last_checkpoint >= checkpoint_every_s:
                if save_policies and evals_done < num_evals:  # a finished batch saves them once, re-scored, below
                    _save_policies(out, batch, states, evals_done, results, None)
                # A copy: `states` is donated to the next chunk while the copy is written.
                snapshot = jax.tree.map(np.array, _real(batch, jax.device_get(states)))
                if pending is not None:
                    pending.result()  # one write at a time, in order; a failed write raises here
                pending = writer.submit(storage.save_checkpoint, ckpt_path, snapshot, evals_done)
                last_checkpoint = time.monotonic()
            steps = len(batch.runs) * evals_per_chunk * config0.eval_every
            best = np.nanmedian(np.asarray(states.best_return)[: len(batch.runs)])
            bar.set_postfix({"steps/s": f"{steps / (time.monotonic() - start):.3g}", "median best": f"{best:.1f}"})
            bar.set_description(label)
            bar.update(steps)
            if on_chunk is not None:
                on_chunk(results)

        def rescore() -> pd.DataFrame:
            bar.set_description(f"{label}, re-scoring the best policies")
            return _rescored_rows(batch, configs, states, programs)

        # The re-scoring overlaps the last checkpoint's write; the commit waits for it.
        rescored = _finish_batch(
            out,
            batch,
            _real(batch, states),
            results,
            rescored,
            save_policies,
            rescore,
            wait=lambda: pending is None or pending.result(),
        )
        bar.set_description(label)
    return results, rescored


def _finish_batch(
    out: Path,
    batch: Batch,
    states: Any,
    results: pd.DataFrame,
    rescored: pd.DataFrame | None,
    save_policies: bool,
    rescore: Callable[[], pd.DataFrame] | None,
    wait: Callable[[], Any] = lambda: None,
) -> pd.DataFrame | None:
    """Complete a trained batch in `out` and commit it: its re-scores (`rescore()`, unless the table has them from
    before a kill), its final policies (`states`: the real configurations' final train states), then, after
    `wait()` (its last checkpoint's write), its marker, the one file that says the batch is finished. Returns the
    re-scoring table."""
    ids = [run.config_id for run in batch.runs]
    if not storage.all_rescored(rescored, ids):
        rescored = storage.merge_by_config(rescored, rescore())
        storage.write_table(out / "rescored", rescored)
    config0 = batch.runs[0].config
    if save_policies:
        _save_policies(out, batch, states, config0.num_evals, results, rescored[rescored.config_id.isin(ids)])
    wait()
    storage.write_marker(
        out, storage.batch_marker(batch.name, ids, config0.num_evals, config0.eval_every, save_policies)
    )
    return rescored


def _evals_with_rows(batch: Batch, results: pd.DataFrame | None) -> int:
    return storage.evals_with_rows(results, (run.config_id for run in batch.runs), batch.runs[0].config.eval_every)


# What a rerun has left to do for a batch (`_batch_state`).
DONE = "done"  # committed, every file there: nothing
COMMIT = "commit"  # trained, checkpointed and re-scored (killed before its commit): policies and marker, no compile
TRAIN = "train"  # train (or resume), re-score and commit: its programs are compiled


def _batch_state(
    out: Path, batch: Batch, results: pd.DataFrame | None, rescored: pd.DataFrame | None, save_policies: bool
) -> str:
    """DONE, COMMIT or TRAIN for `batch` in `out`; a marker whose files are not all there counts as none."""
    if storage.batch_complete(out, batch.name, results, rescored, save_policies):
        return DONE
    num_evals = batch.runs[0].config.num_evals
    if (
        storage.checkpoint_evals(storage.checkpoint_path(out, batch.name)) == num_evals
        and _evals_with_rows(batch, results) >= num_evals
        and storage.all_rescored(rescored, (run.config_id for run in batch.runs))
    ):
        return COMMIT
    return TRAIN


def _commit_trained(
    out: Path, batch: Batch, results: pd.DataFrame, rescored: pd.DataFrame, save_policies: bool
) -> None:
    """Commit a COMMIT batch from its final checkpoint (sized with `jax.eval_shape`: nothing compiles)."""
    shapes = _state_shapes(batch)[0]
    real = jax.tree.map(lambda x: jax.ShapeDtypeStruct((len(batch.runs), *x.shape[1:]), x.dtype), shapes)
    states, _ = storage.load_checkpoint(storage.checkpoint_path(out, batch.name), real)
    _finish_batch(out, batch, states, results, rescored, save_policies, rescore=None)


class CompileQueue:
    """Compiles batches' programs ahead of time, one after another in the order they were queued, on one
    background daemon thread (an interrupted process does not wait for it) while batches train.

    `run_sweep` queues each of its unfinished batches in training order and takes each one's programs when it
    reaches it. A caller running sweeps one after another (`amjax replicate`) passes them one queue and queues the
    next sweep's batches (`queue_sweep`) when one starts, so that they compile while this one trains.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._jobs: collections.deque = collections.deque()
        self._futures: dict[tuple, Future] = {}
        self._worker: threading.Thread | None = None

    def submit(self, batch: Batch, target_chunks: int, devices: tuple[jax.Device, ...]) -> None:
        """Queue `batch`'s compile (nothing if it is queued already)."""
        key = (batch.name, target_chunks, devices)
        with self._lock:
            if key in self._futures:
                return
            self._futures[key] = future = Future()
            self._jobs.append((future, batch, target_chunks, devices))
            if self._worker is None:
                self._worker = threading.Thread(target=self._work, name="amjax-compile-ahead", daemon=True)
                self._worker.start()

    def take(self, batch: Batch, target_chunks: int, devices: tuple[jax.Device, ...]) -> BatchPrograms:
        """`batch`'s programs once compiled (queued now if they were not); a failed compile raises its error."""
        self.submit(batch, target_chunks, devices)
        with self._lock:
            future = self._futures.pop((batch.name, target_chunks, devices))
        return future.result()

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
            if _batch_state(out, batch, results, rescored, save_policies=True) == TRAIN:
                self.submit(batch, target_chunks, devices)

    def cancel(self) -> None:
        """Drop the compiles not started yet (the one under way finishes on its own)."""
        with self._lock:
            for future, *_ in self._jobs:
                future.cancel()
            self._jobs.clear()
            self._futures.clear()

    def _work(self) -> None:
        while True:
            with self._lock:
                if not self._jobs:
                    self._worker = None
                    return
                future, *args = self._jobs.popleft()
            if future.set_running_or_notify_cancel():
                try:
                    future.set_result(compile_batch(*args))
                except BaseException as error:  # re-raised by take() in the sweep's thread
                    future.set_exception(error)


def run_sweep(
    spec: SweepSpec,
    out: str | Path,
    *,
    max_batch: int = 1024,
    target_chunks: int = 10,
    checkpoint_every_s: float = 60.0,
    progress: bool = True,
    on_chunk: Callable[[pd.DataFrame], None] | None = None,
    save_policies: bool = True,
    loggers: Sequence[RunLogger] = (),
    devices: Sequence[jax.Device] | None = None,
    metadata: Mapping[str, Any] | None = None,
    cluster: str | None = None,
    cluster_parameters: Mapping[str, Any] | None = None,
    compile_queue: CompileQueue | None = None,
) -> SweepResult:
    """Train every configuration of `spec`, writing results under `out`; resumes a sweep already there.

    Args:
      max_batch: most configurations compiled into one vmapped batch (bounds memory; DQN's replay buffers
        take configurations x buffer_size x transition size).
      target_chunks: evaluation periods are run in about this many jitted chunks per batch; results are
        written after each chunk.
      checkpoint_every_s: train states are checkpointed after a chunk when this many seconds have passed
        since the last checkpoint (and always at the end of a batch).
      on_chunk: called with the full results table after every chunk (e.g. to draw live plots); on a cluster,
        after each batch is folded in.
      save_policies: keep each configuration's best policy in `out/policies/<config_id>.msgpack` (written with
        every checkpoint, and with its re-scores before its batch is committed; load one with
        `load_sweep_policy(out, config_id)`).
      loggers: also send each chunk's new rows to these (e.g. `TensorBoardLogger(out / "tensorboard")`,
        `WandbLogger(project, out)`); they are closed when the sweep ends or stops.
      devices: the devices each batch's configurations are split over (default: `sweep_devices()`, every local
        device: one per CPU core after `amjax.use_all_cores()`, else one). Results agree across device counts to
        float rounding (XLA's rounding can depend on a shard's size, so the same count keeps them closest); a
        sweep may resume on another count.
      metadata: extra entries for a new folder's metadata.json (e.g. the budget a command line asked for before
        `round_schedule`).
      cluster: run the batches as jobs through submitit: "local:N" (N worker processes here) or
        "slurm:PARTITION[:JOBS]" (a whole node per job); `out` must be on a filesystem the workers share. Results
        are the same as a local run's, and either may resume the other (`amjax.sweep.cluster`, docs/cluster.md).
      cluster_parameters: submitit executor parameters for the jobs (e.g. `{"account": "lab", "time": 600}` for
        Slurm).
      compile_queue: compiles the batches ahead of time (default: a queue of this sweep's own); pass one queue to
        consecutive sweeps, each queued beforehand with `CompileQueue.queue_sweep`, to compile a sweep's first
        batch while the sweep before it trains (not used with `cluster`).

    Raises:
      WriteError (an OSError): the disk refused a write (no space, permissions); what was committed stays, and
        the same call resumes once the disk accepts writes again.
      SweepMismatchError: `out` holds a different sweep.
      SweepTooLargeError: a batch's train states would not fit in memory (checked before anything is written).
      FolderBusyError: another running process is writing to `out`.
    """
    runs = expand(spec)  # validates everything before touching the disk
    target = None
    if cluster is not None:
        target = parse_cluster(cluster)
        check_engine()
        check_parameters(target, cluster_parameters)
    out = Path(out)
    hyper_columns = sorted({k for r in runs for k in r.hyperparams})
    devices = tuple(devices or sweep_devices())
    batches = plan_batches(runs, max_batch, len(devices))
    _check_memory(batches, _memory_bytes())
    _check_folder(out, spec, compare=False)  # before the lock file: a foreign folder is left as it was
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise SweepMismatchError(f"out: cannot create the folder {out} ({error.strerror})") from None
    with folder_lock(out):  # one writer per folder; the lock dies with the process, however it dies
        # Temporary files of writes that a killed run left unfinished (a cluster's parts are their workers' own).
        remove_partial_writes(out, skip=(PARTS,))
        _claim_folder(out, spec, runs, metadata or {})
        wall_time = storage.WallTime(out / "wall_time.json")
        # Parts a cluster run left (stopped before it folded them in): their rows and checkpoints, so either
        # runner resumes where the other stopped.
        results, rescored = merge_parts(
            out, storage.read_table(out / "results"), storage.read_table(out / "rescored"), save_policies
        )
        total_steps = len(runs) * spec.total_timesteps
        bar = tqdm(total=total_steps, unit="step", unit_scale=True, disable=not progress, desc="sweep")
        try:
            states = [_batch_state(out, batch, results, rescored, save_policies) for batch in batches]
            for batch, state in zip(batches, states, strict=True):
                if state == COMMIT:  # killed between its re-scoring and its commit
                    _commit_trained(out, batch, results, rescored, save_policies)
            todo = [batch for batch, state in zip(batches, states, strict=True) if state == TRAIN]
            bar.update(
                sum(
                    len(b.runs) * b.runs[0].config.num_evals * b.runs[0].config.eval_every
                    for b in batches
                    if b not in todo
                )
            )
            if target is None:
                # Every batch's programs compile in turn on a background thread while batches train (a compile
                # keeps about one core busy); the training thread compiles nothing meanwhile.
                compiler = compile_queue or CompileQueue()
                for batch in todo:
                    compiler.submit(batch, target_chunks, devices)
                try:
                    for batch in todo:
                        bar.set_description(
                            f"{batch.runs[0].env} {batch.algo.name} ({len(batch.runs)} configs), compiling"
                        )
                        results, rescored = _train_batch(
                            batch,
                            out,
                            results,
                            hyper_columns,
                            bar,
                            target_chunks=target_chunks,
                            checkpoint_every_s=checkpoint_every_s,
                            save_policies=save_policies,
                            on_chunk=on_chunk,
                            loggers=loggers,
                            devices=devices,
                            wall_time=wall_time,
                            rescored=rescored,
                            programs=compiler.take(batch, target_chunks, devices),
                        )
                finally:
                    if compile_queue is None:
                        compiler.cancel()
            else:

                def on_rows(rows: pd.DataFrame, results: pd.DataFrame) -> None:  # a batch folded in
                    wall_time.save()
                    for logger in loggers:
                        logger.log(rows)
                    if on_chunk is not None:
                        on_chunk(results)

                options = {
                    "target_chunks": target_chunks,
                    "checkpoint_every_s": checkpoint_every_s,
                    "save_policies": save_policies,
                }
                results, rescored = drive(
                    spec,
                    out,
                    todo,
                    results,
                    rescored,
                    target,
                    max_batch,
                    len(devices),
                    options,
                    bar,
                    parameters=cluster_parameters,
                    on_rows=on_rows,
                    record=functools.partial(_record_batch, out),
                )
        finally:
            bar.close()
            for logger in loggers:
                logger.close()
        if results is None:
            results = pd.DataFrame()
        summary = storage.summarize(results, hyper_columns, rescored)
        table = storage.seed_table(summary, hyper_columns)
        storage.write_table(out / "summary", summary)
        storage.write_table(out / "seed_summary", table)
        wall_time.save()
    return SweepResult(out, results, summary, table)
