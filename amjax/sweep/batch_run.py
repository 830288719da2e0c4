"""One batch of a sweep, from its first chunk to its commit, in one folder (a sweep's, or a cluster worker's part):
train (or resume) chunk by chunk writing rows and checkpoints, re-score the best policies, save them, then write the
batch's commit marker; and what a rerun has left to do for a batch it finds (`batch_state`). Every executor runs
batches through these (`amjax.sweep.executors`, `amjax.sweep.cluster`).

Every file is written atomically (`amjax.files.atomic_write`: a temporary file, flushed, then one durable rename),
results before checkpoints: a rerun recomputes at most the work after the last checkpoint (training is
deterministic), and rows are keyed by (config_id, env_steps) so none is duplicated. A batch is finished when its
commit marker (`finished/<batch>.json`) is there, written last, after its rows, re-scores, policies and final
checkpoint (`amjax.sweep.prune` may delete that checkpoint later, saying so in the marker); a rerun that finds a
marker without all of those files, or the files without a marker, redoes what is missing, so a kill at any instant
loses no finished work (tests/sweep/test_crash_points.py stops it at every rename).
"""

from __future__ import annotations

import operator
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
from tqdm.auto import tqdm

from amjax.agents import EvalRow, init_run
from amjax.agents.saved import save_policy
from amjax.sweep import storage
from amjax.sweep.batches import Batch, BatchPrograms, compile_batch
from amjax.sweep.devices import config_sharding
from amjax.sweep.loggers import RunLogger
from amjax.sweep.storage import policy_path


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


_SHAPES: dict[tuple[Any, ...], tuple[Any, int]] = {}  # (agent, static fields, batch size) -> (shapes, bytes)


def state_shapes(batch: Batch) -> tuple[Any, int]:
    """The shapes of a batch's train states and their bytes, sized without allocating them (`jax.eval_shape`);
    the same for every batch of a compiled group and size, so traced once per process."""
    key = (batch.algo.name, batch.runs[0].config.static_key(), batch.size)
    if key not in _SHAPES:
        configs, keys = batch.stacked()
        shapes = jax.eval_shape(jax.vmap(lambda c, k: init_run(batch.algo, c, k)), configs, keys)
        _SHAPES[key] = shapes, sum(x.size * x.dtype.itemsize for x in jax.tree.leaves(shapes))
    return _SHAPES[key]


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


def _cell(value: Any) -> Any:
    return "x".join(map(str, value)) if isinstance(value, list | tuple) else value


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


def train_batch(
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
    and commit it (`finish_batch`); returns the results and re-scoring tables. `programs`: the batch's programs
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
    # The next chunk is queued before this one's rows are fetched and written, so an accelerator never waits for
    # the host between chunks; only a chunk that checkpoints (or saves policies) holds the next one back until its
    # states are copied (they are donated to the next chunk).
    with ThreadPoolExecutor(1, thread_name_prefix="amjax-checkpoint") as writer:
        pending: Future | None = None
        queued = programs.chunk(configs, states) if evals_done < num_evals else None
        while queued is not None:
            start = time.monotonic()
            states, rows = queued
            evals_done += evals_per_chunk
            checkpoint = evals_done == num_evals or time.monotonic() - last_checkpoint >= checkpoint_every_s
            best_return = jnp.copy(states.best_return)  # read below, after `states` may have been donated
            queued = None if checkpoint else programs.chunk(configs, states)
            rows = jax.device_get(rows)
            new_rows = _rows(batch, rows, hyper_columns)
            results = storage.merge_rows(results, new_rows)
            storage.write_table(out / "results", results)
            wall_time.save()
            for logger in loggers:
                logger.log(new_rows)
            if checkpoint:
                if save_policies and evals_done < num_evals:  # a finished batch saves them once, re-scored, below
                    _save_policies(out, batch, states, evals_done, results, None)
                # A copy: `states` is donated to the next chunk while the copy is written.
                snapshot = jax.tree.map(np.array, _real(batch, jax.device_get(states)))
                if pending is not None:
                    pending.result()  # one write at a time, in order; a failed write raises here
                pending = writer.submit(storage.save_checkpoint, ckpt_path, snapshot, evals_done)
                last_checkpoint = time.monotonic()
                queued = programs.chunk(configs, states) if evals_done < num_evals else None
            steps = len(batch.runs) * evals_per_chunk * config0.eval_every
            best = np.nanmedian(np.asarray(best_return)[: len(batch.runs)])
            bar.set_postfix({"steps/s": f"{steps / (time.monotonic() - start):.3g}", "median best": f"{best:.1f}"})
            bar.set_description(label)
            bar.update(steps)
            if on_chunk is not None:
                on_chunk(results)

        def rescore() -> pd.DataFrame:
            bar.set_description(f"{label}, re-scoring the best policies")
            return _rescored_rows(batch, configs, states, programs)

        # The re-scoring overlaps the last checkpoint's write; the commit waits for it.
        rescored = finish_batch(
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


def finish_batch(
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


# What a rerun has left to do for a batch (`batch_state`).
DONE = "done"  # committed, every file there: nothing

COMMIT = "commit"  # trained, checkpointed and re-scored (killed before its commit): policies and marker, no compile

TRAIN = "train"  # train (or resume), re-score and commit: its programs are compiled


def batch_state(
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


def commit_trained(out: Path, batch: Batch, results: pd.DataFrame, rescored: pd.DataFrame, save_policies: bool) -> None:
    """Commit a COMMIT batch from its final checkpoint (sized with `jax.eval_shape`: nothing compiles)."""
    shapes = state_shapes(batch)[0]
    real = jax.tree.map(lambda x: jax.ShapeDtypeStruct((len(batch.runs), *x.shape[1:]), x.dtype), shapes)
    states, _ = storage.load_checkpoint(storage.checkpoint_path(out, batch.name), real)
    finish_batch(out, batch, states, results, rescored, save_policies, rescore=None)


__all__ = ["COMMIT", "DONE", "TRAIN", "batch_state", "commit_trained", "finish_batch", "state_shapes", "train_batch"]
