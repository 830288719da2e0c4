"""The sweep runner: `run_sweep(spec, out, executor)` plans the batches (every group of configurations that shares
a compiled program, trained as one vmapped batch), opens and locks the folder, finishes what a kill left trained,
and hands the batches still to train to an executor (`amjax.sweep.executors`: this process, or a cluster's jobs),
which trains each in chunks of evaluation periods with progress, results written after each chunk and train states
checkpointed (`amjax.sweep.batch_run`). Killing the process at any moment and rerunning the same call resumes where
it stopped and loses no finished work: a batch is finished only once its commit marker is written, last
(tests/sweep/test_crash_points.py stops it at every rename). Finished batches are skipped without compiling.
"""

from __future__ import annotations

import functools
import json
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd
from tqdm.auto import tqdm

from amjax.agents.saved import SavedPolicy, load_policy
from amjax.files import folder_lock, remove_partial_writes
from amjax.sweep import storage
from amjax.sweep.batch_run import COMMIT, TRAIN, batch_state, commit_trained, state_shapes
from amjax.sweep.batches import Batch, plan_batches
from amjax.sweep.cluster import PARTS, ClusterExecutor, merge_parts
from amjax.sweep.executors import Executor, LocalExecutor, SweepWork
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


def _check_memory(batches: Sequence[Batch], memory: int) -> None:
    """Refuse, before anything is written or compiled, a batch whose train states would not fit in `memory` bytes
    three times over (the states, the chunk's new states and the checkpoint's copy)."""
    for batch in batches:
        size = state_shapes(batch)[1]
        if 3 * size > memory:
            raise SweepTooLargeError(
                f"the train states of {batch.size} {batch.algo.name} configurations take "
                f"{size / 2**30:.1f} GiB (3x that while training) and this machine has {memory / 2**30:.1f} "
                "GiB: lower --max-batch (max_batch), or the fields that size them (num_envs, buffer_size, ...)"
            )


def _memory_bytes() -> int:
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


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
    if compare and (stored is None or stored.identity() != spec.identity()):  # older files: defaults filled
        differences = (
            identity_differences(stored.identity(), spec.identity())
            if stored is not None
            else ["its metadata.json names no sweep spec"]
        )
        raise SweepMismatchError(
            f"out: {out} holds a different sweep; {'; '.join(differences)}. Rerun with the folder's settings to resume "
            "it (its metadata.json has them), or choose another folder"
        )
    return True


def identity_differences(stored: Mapping[str, Any], new: Mapping[str, Any], limit: int = 6) -> list[str]:
    """What differs between a folder's sweep identity (`SweepSpec.identity`) and this call's, one phrase per
    differing entry (nested dicts followed down: `env_defaults["Acrobot-v1"]["drqn.reward_scale"]`), at most
    `limit` of them and a count of the rest."""
    found = []

    def walk(a: Any, b: Any, path: str) -> None:
        if isinstance(a, Mapping) or isinstance(b, Mapping):  # a dict on one side only: against an empty one
            a, b = ({} if x is _UNSET else x for x in (a, b))
        if isinstance(a, Mapping) and isinstance(b, Mapping):
            for key in [*a, *(k for k in b if k not in a)]:
                walk(a.get(key, _UNSET), b.get(key, _UNSET), f"{path}[{json.dumps(key)}]" if path else str(key))
        elif a != b:
            found.append(f"{path}: the folder has {_shown(a)}, this sweep {_shown(b)}")

    walk(stored, new, "")
    shown = found[:limit] + ([f"and {len(found) - limit} more"] if len(found) > limit else [])
    if any(phrase.startswith("env_defaults") for phrase in found):
        shown.append("env_defaults are the library's presets (amjax.presets): one changed since the folder was made")
    return shown


_UNSET = object()


def _shown(value: Any) -> str:
    return "none" if value is _UNSET else json.dumps(value, default=str)


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


def run_sweep(
    spec: SweepSpec,
    out: str | Path,
    executor: Executor | None = None,
    *,
    max_batch: int = 1024,
    progress: bool = True,
    on_chunk: Callable[[pd.DataFrame], None] | None = None,
    save_policies: bool = True,
    loggers: Sequence[RunLogger] = (),
    metadata: Mapping[str, Any] | None = None,
    **executor_options: Any,
) -> SweepResult:
    """Train every configuration of `spec`, writing results under `out`; resumes a sweep already there.

    Args:
      executor: what runs the batches (`amjax.sweep.executors`): `LocalExecutor()` (the default: this process,
        split over every local device) or `ClusterExecutor("local:N" | "slurm:PARTITION[:JOBS]")`.
      max_batch: most configurations compiled into one vmapped batch (bounds memory; DQN's replay buffers
        take configurations x buffer_size x transition size).
      on_chunk: called with the full results table after every chunk (e.g. to draw live plots); on a cluster,
        after each batch is folded in.
      save_policies: keep each configuration's best policy in `out/policies/<config_id>.msgpack` (written with
        every checkpoint, and with its re-scores before its batch is committed; load one with
        `load_sweep_policy(out, config_id)`).
      loggers: also send each chunk's new rows to these (e.g. `TensorBoardLogger(out / "tensorboard")`,
        `WandbLogger(project, out)`); they are closed when the sweep ends or stops.
      metadata: extra entries for a new folder's metadata.json (e.g. the budget a command line asked for before
        `round_schedule`).
      executor_options: without `executor`, the options that build it, as before executors existed: `devices`,
        `target_chunks`, `checkpoint_every_s`, `compile_queue` (`LocalExecutor`'s), or `cluster` (a target) with
        `cluster_parameters` (`ClusterExecutor`'s).

    Raises:
      WriteError (an OSError): the disk refused a write (no space, permissions); what was committed stays, and
        the same call resumes once the disk accepts writes again.
      SweepMismatchError: `out` holds a different sweep.
      SweepTooLargeError: a batch's train states would not fit in memory (checked before anything is written).
      FolderBusyError: another running process is writing to `out`.
    """
    runs = expand(spec)  # validates everything before touching the disk
    executor = _executor(executor, executor_options)
    executor.check()
    out = Path(out)
    hyper_columns = sorted({k for r in runs for k in r.hyperparams})
    batches = plan_batches(runs, max_batch, len(executor.devices))
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
        # executor resumes where the other stopped.
        results, rescored = merge_parts(
            out, storage.read_table(out / "results"), storage.read_table(out / "rescored"), save_policies
        )
        bar = tqdm(
            total=len(runs) * spec.total_timesteps, unit="step", unit_scale=True, disable=not progress, desc="sweep"
        )
        try:
            states = [batch_state(out, batch, results, rescored, save_policies) for batch in batches]
            for batch, state in zip(batches, states, strict=True):
                if state == COMMIT:  # killed between its re-scoring and its commit
                    commit_trained(out, batch, results, rescored, save_policies)
            todo = [batch for batch, state in zip(batches, states, strict=True) if state == TRAIN]
            bar.update(
                sum(
                    len(b.runs) * b.runs[0].config.num_evals * b.runs[0].config.eval_every
                    for b, state in zip(batches, states, strict=True)
                    if state != TRAIN
                )
            )
            work = SweepWork(
                spec,
                out,
                todo,
                results,
                rescored,
                hyper_columns,
                max_batch,
                save_policies,
                bar,
                wall_time,
                loggers,
                on_chunk,
                record=functools.partial(_record_batch, out),
            )
            results, rescored = executor.run(work)
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


LOCAL_OPTIONS = ("devices", "target_chunks", "checkpoint_every_s", "compile_queue")
CLUSTER_OPTIONS = ("devices", "target_chunks", "checkpoint_every_s", "cluster", "cluster_parameters")


def _executor(executor: Executor | None, options: Mapping[str, Any]) -> Executor:
    """`executor`, or the one `options` describe (`run_sweep`'s keywords from before executors); TypeError naming
    what does not fit."""
    if executor is not None:
        if options:
            raise TypeError(f"run_sweep: give the executor its options ({', '.join(options)}), not run_sweep")
        return executor
    options = {name: value for name, value in options.items() if value is not None}
    cluster = options.pop("cluster", None)
    allowed = CLUSTER_OPTIONS if cluster is not None else LOCAL_OPTIONS
    unknown = sorted(set(options) - set(allowed))
    if unknown:
        raise TypeError(
            f"run_sweep: unexpected keyword argument(s) {', '.join(unknown)}; allowed: "
            f"{', '.join(sorted(set(LOCAL_OPTIONS) | set(CLUSTER_OPTIONS)))}"
        )
    if cluster is not None:
        parameters = options.pop("cluster_parameters", None)
        return ClusterExecutor(cluster, parameters, **options)
    return LocalExecutor(**options)
