"""Files of a sweep: atomic writes, msgpack checkpoints of train states, the tidy results table and summaries.

Layout of an output folder:
  metadata.json        the sweep spec, package versions, git revision, CPU (written once; identifies the sweep)
  results.parquet/.csv one row per configuration x evaluation point
  summary.parquet/.csv one row per configuration: best costed reward, final values, measurement reduction
  rescored.parquet/.csv one row per finished configuration: its best policy on fresh test episodes
  checkpoints/*.msgpack  train states of each compiled batch (for resuming), no pickle
  policies/<config_id>.msgpack  the best policy of each configuration (`amjax.load_policy`)
  finished/<batch>.json  a batch's commit marker: written last, once everything above is on disk for it
                       (`amjax prune` later deletes a finished batch's checkpoint and says so in its marker)
  compile_cache/<machine>/ the compiled programs, for a rerun (`amjax.files.use_compile_cache`; the CLI's)

Crash consistency: every file appears through one durable rename (`amjax.files.commit`), and a batch counts as
finished only when its marker is there *and* the files it vouches for are (`batch_complete`); a rerun redoes
whatever is missing.
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import time
from collections.abc import Callable, Iterable
from importlib import metadata
from pathlib import Path
from typing import Any

import jax
import numpy as np
import pandas as pd
from flax import serialization

import amjax
from amjax.batching import shared_disagreements
from amjax.cores import cpu_description
from amjax.files import atomic_write

KEY_COLUMNS = ["config_id", "env_steps"]


def write_json(path: Path, data: Any) -> None:
    atomic_write(path, lambda tmp: Path(tmp).write_text(json.dumps(data, indent=2, default=str) + "\n"))


def write_table(path_stem: Path, table: pd.DataFrame) -> None:
    """Write `table` as Parquet and CSV, each atomically."""
    atomic_write(path_stem.with_suffix(".parquet"), lambda tmp: table.to_parquet(tmp, index=False))
    atomic_write(path_stem.with_suffix(".csv"), lambda tmp: table.to_csv(tmp, index=False))


class UnreadableFileError(ValueError):
    """A file of a sweep folder that is corrupt, truncated or of another format; nothing is overwritten."""


def read_table(path_stem: Path) -> pd.DataFrame | None:
    """The Parquet table `path_stem`.parquet, or None if there is none; UnreadableFileError if it is corrupt.

    Read through one open file: given a path, pyarrow may open it twice (its size, then its pages), and a writer's
    atomic replace in between (a cluster worker's part, read by the driver for progress) gives a torn read."""
    path = path_stem.with_suffix(".parquet")
    try:
        with open(path, "rb") as file:
            return pd.read_parquet(file)
    except FileNotFoundError:
        return None
    except Exception as error:  # truncated or foreign: pyarrow raises several kinds
        raise UnreadableFileError(
            f"{path} is unreadable ({type(error).__name__}: {str(error)[:200]}); restore it from the CSV beside it "
            "or a backup, or choose another folder (nothing was overwritten)"
        ) from None


def merge_rows(old: pd.DataFrame | None, new: pd.DataFrame) -> pd.DataFrame:
    """Append `new` rows; a (config_id, env_steps) already present is replaced, never duplicated."""
    table = new if old is None else pd.concat([old, new], ignore_index=True)
    table = table.drop_duplicates(KEY_COLUMNS, keep="last")
    return table.sort_values(KEY_COLUMNS, kind="stable").reset_index(drop=True)


def merge_by_config(old: pd.DataFrame | None, new: pd.DataFrame) -> pd.DataFrame:
    """Append per-configuration rows; a config_id already present is replaced, never duplicated."""
    table = new if old is None else pd.concat([old, new], ignore_index=True)
    return table.drop_duplicates("config_id", keep="last").sort_values("config_id").reset_index(drop=True)


# -- checkpoints -----------------------------------------------------------------------------------------


class WallTime:
    """Seconds spent on a sweep folder over all its invocations, kept in `path` (JSON). `save()` after each
    chunk, so a killed invocation counts up to its last chunk; `new_invocation=False` adds to the same count (e.g.
    the time of writing its report)."""

    def __init__(self, path: Path, new_invocation: bool = True):
        self.path = path
        stored = json.loads(path.read_text()) if path.exists() else {}
        self.before = float(stored.get("seconds", 0.0))
        self.invocations = int(stored.get("invocations", 0)) + int(new_invocation)
        self.start = time.monotonic()

    @property
    def seconds(self) -> float:
        return self.before + time.monotonic() - self.start

    def save(self) -> float:
        """Write the total so far; returns it (seconds, as written)."""
        seconds = round(self.seconds, 1)
        write_json(self.path, {"seconds": seconds, "invocations": self.invocations})
        return seconds


def all_rescored(rescored: pd.DataFrame | None, config_ids: Iterable[str]) -> bool:
    """Whether every configuration in `config_ids` has its re-scored row in `rescored` (its batch is finished)."""
    return rescored is not None and set(config_ids) <= set(rescored.config_id)


def evals_with_rows(results: pd.DataFrame | None, config_ids: Iterable[str], eval_every: int) -> int:
    """How many leading evaluation periods every configuration in `config_ids` has its rows for."""
    config_ids = list(config_ids)
    if results is None or not config_ids:
        return 0
    mine = results[results.config_id.isin(config_ids)]
    done = 0
    steps = {c: set(s) for c, s in mine.groupby("config_id").env_steps}
    while all((done + 1) * eval_every in steps.get(c, ()) for c in config_ids):
        done += 1
    return done


# A commit marker's key saying the batch's final checkpoint was deleted on purpose (absent in older markers: kept).
CHECKPOINT_PRUNED = "checkpoint_pruned"


def marker_path(folder: Path, batch_name: str) -> Path:
    """Where a sweep folder (or a cluster part) keeps the commit marker of batch `batch_name`."""
    return Path(folder) / "finished" / f"{batch_name}.json"


def batch_marker(
    batch_name: str, config_ids: Iterable[str], evals: int, eval_every: int, policies: bool
) -> dict[str, Any]:
    """What a batch's commit marker records: the batch, its configurations and evaluations, whether its policies
    were saved."""
    return {
        "batch": batch_name,
        "config_ids": sorted(config_ids),
        "evals": int(evals),
        "eval_every": int(eval_every),
        "policies": bool(policies),
    }


def write_marker(folder: Path, marker: dict[str, Any]) -> None:
    """Commit a batch as finished in `folder` (`batch_marker`): call only once its rows, re-scores, final
    checkpoint (and policies, if it says so) are on disk there."""
    write_json(marker_path(folder, marker["batch"]), marker)


def read_marker(folder: Path, batch_name: str) -> dict[str, Any] | None:
    """The commit marker of `batch_name` in `folder`, or None if there is none (or it is unreadable)."""
    try:
        return json.loads(marker_path(folder, batch_name).read_text())
    except (OSError, ValueError):
        return None


def batch_complete(
    folder: Path, batch_name: str, results: pd.DataFrame | None, rescored: pd.DataFrame | None, policies: bool
) -> bool:
    """Whether `folder` holds batch `batch_name` finished: its marker, and every file the marker vouches for
    (`marker_files_present`)."""
    marker = read_marker(folder, batch_name)
    return marker is not None and marker_files_present(folder, marker, results, rescored, policies)


def marker_files_present(
    folder: Path, marker: dict[str, Any], results: pd.DataFrame | None, rescored: pd.DataFrame | None, policies: bool
) -> bool:
    """Whether `folder` has everything a batch's marker vouches for: the rows of every evaluation, the re-scores,
    the final checkpoint (unless the marker says it was pruned: `amjax.sweep.prune_sweep`) and (with `policies`,
    which the marker must also say were saved) each configuration's policy."""
    config_ids = marker["config_ids"]
    return (
        (marker["policies"] or not policies)
        and evals_with_rows(results, config_ids, marker["eval_every"]) >= marker["evals"]
        and all_rescored(rescored, config_ids)
        and (
            marker.get(CHECKPOINT_PRUNED, False)
            or checkpoint_evals(checkpoint_path(folder, marker["batch"])) == marker["evals"]
        )
        and (not policies or all(policy_path(folder, c).exists() for c in config_ids))
    )


def policy_path(folder: str | Path, config_id: str) -> Path:
    """Where a sweep keeps the best policy of configuration `config_id`."""
    return Path(folder) / "policies" / f"{config_id}.msgpack"


def checkpoint_path(folder: Path, batch_name: str) -> Path:
    """Where a sweep folder (or a cluster part) keeps the checkpoint of batch `batch_name`."""
    return Path(folder) / "checkpoints" / f"{batch_name}.msgpack"


def save_checkpoint(path: Path, state: Any, evals_done: int) -> None:
    """Save a pytree of arrays (any structure) with msgpack; restore it with `load_checkpoint`."""
    leaves = [np.asarray(x) for x in jax.tree.leaves(state)]
    payload = {"evals_done": evals_done, "leaves": {str(i): x for i, x in enumerate(leaves)}}
    atomic_write(path, lambda tmp: Path(tmp).write_bytes(serialization.msgpack_serialize(payload)))


def checkpoint_evals(path: Path) -> int:
    """The evaluation periods a checkpoint holds, read from its head without loading its arrays (-1 if there is
    no readable checkpoint at `path`)."""
    import msgpack

    try:
        with open(path, "rb") as handle:
            unpacker = msgpack.Unpacker(handle, raw=False)
            for _ in range(unpacker.read_map_header()):  # save_checkpoint writes evals_done first
                key = unpacker.unpack()
                if key == "evals_done":
                    return int(unpacker.unpack())
                unpacker.skip()
    except (OSError, ValueError, msgpack.UnpackException):
        pass
    return -1


def load_checkpoint(path: Path, like: Any) -> tuple[Any, int]:
    """Restore a checkpoint into the structure of `like`; raise ValueError if it does not fit."""
    try:
        payload = serialization.msgpack_restore(path.read_bytes())
        stored = [payload["leaves"][str(i)] for i in range(len(payload["leaves"]))]
        evals_done = int(payload["evals_done"])
    except Exception as error:  # corrupt or truncated file
        raise UnreadableFileError(
            f"checkpoint {path} is unreadable ({error}); delete it to restart that batch"
        ) from None
    leaves, treedef = jax.tree.flatten(like)  # arrays, or their shapes (`jax.eval_shape`)
    if len(stored) != len(leaves) or any(
        s.shape != np.shape(x) or s.dtype != (x.dtype if hasattr(x, "dtype") else np.asarray(x).dtype)
        for s, x in zip(stored, leaves, strict=True)
    ):
        raise UnreadableFileError(f"checkpoint {path} does not match this sweep's train state; delete it to restart")
    restored = jax.tree.unflatten(treedef, stored)
    # The chunk program takes the step counters from the first configuration (`batching.take_shared`).
    if differ := shared_disagreements(restored):
        raise UnreadableFileError(
            f"checkpoint {path} holds step counters that differ between its configurations ({', '.join(differ)}); "
            "delete it to restart that batch"
        )
    return restored, evals_done


# -- metadata ----------------------------------------------------------------------------------------------


def environment_info() -> dict[str, Any]:
    """Package versions, git revision and machine, for the metadata file."""
    versions = {"amjax": amjax.__version__}
    for name in ("jax", "jaxlib", "flax", "optax", "gymnax", "numpy", "pandas"):
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    try:
        revision = (
            subprocess.run(
                ["git", "rev-parse", "HEAD"],
                capture_output=True,
                text=True,
                cwd=Path(__file__).parent,
                timeout=5,
            ).stdout.strip()
            or None
        )
    except (OSError, subprocess.SubprocessError):
        revision = None
    return {
        "versions": versions,
        "git_revision": revision,
        "python": platform.python_version(),
        "machine": f"{platform.machine()}, {os.cpu_count()} cores",
        "cpu": cpu_description(),  # rows are bit for bit the same only on this CPU (and device count)
        "jax_backend": jax.default_backend(),
        "jax_devices": len(jax.local_devices()),  # the sweep's configurations are spread over these
    }


# -- summaries -----------------------------------------------------------------------------------------------

ID_COLUMNS = ["config_id", "env", "agent", "vanilla", "cost", "seed"]
# The metrics a results table holds per evaluation (`EvalRow.columns`, and the measured fraction the runner derives
# from them); with ID_COLUMNS, "env_steps", "diverged" and the swept hyperparameters they are the whole table.
METRIC_COLUMNS = (
    "eval_return",
    "eval_raw_return",
    "eval_measured_fraction",
    "eval_length",
    "eval_measurements",
    "train_return",
    "train_raw_return",
    "train_length",
    "train_measurements",
    "loss",
)


RESCORED_COLUMNS = [
    "best_policy_return",
    "best_policy_raw_return",
    "best_policy_measured_fraction",
    "best_policy_episodes",
]


def summarize(results: pd.DataFrame, hyper_columns: list[str], rescored: pd.DataFrame | None = None) -> pd.DataFrame:
    """Per configuration: best greedy costed reward (the paper's metric; diverged points excluded), the
    measured fraction at that point, final values, the reduction in measurements vs always measuring, and (from
    `rescored`, NaN until a configuration has finished) its best policy re-scored on fresh test episodes."""
    rows = []
    results = results.assign(measured_fraction=results.eval_measurements / results.eval_length)
    for _, runs in results.groupby("config_id", sort=False):
        runs = runs.sort_values("env_steps")
        healthy = runs[~runs.diverged & runs.eval_return.notna()]
        final = runs.iloc[-1]
        best = healthy.loc[healthy.eval_return.idxmax()] if len(healthy) else None
        row = {c: final[c] for c in ID_COLUMNS + hyper_columns}
        row.update(
            env_steps=int(final.env_steps),
            best_return=np.nan if best is None else best.eval_return,
            best_raw_return=np.nan if best is None else best.eval_raw_return,
            best_measured_fraction=np.nan if best is None else best.measured_fraction,
            best_env_steps=np.nan if best is None else best.env_steps,
            final_return=final.eval_return,
            final_raw_return=final.eval_raw_return,
            final_measured_fraction=final.measured_fraction,
            measurement_reduction=np.nan if best is None else 1.0 - best.measured_fraction,
            diverged=bool(runs.diverged.any()),
        )
        rows.append(row)
    summary = pd.DataFrame(rows)
    if summary.empty:
        return summary
    if rescored is None:
        rescored = pd.DataFrame(columns=["config_id", *RESCORED_COLUMNS])
    return summary.merge(rescored[["config_id", *RESCORED_COLUMNS]], on="config_id", how="left")


def seed_table(summary: pd.DataFrame, hyper_columns: list[str]) -> pd.DataFrame:
    """Median and interquartile range over seeds of best costed reward and measured fraction, per env x agent x
    vanilla x cost (x swept hyperparameters)."""
    keys = ["env", "agent", "vanilla", "cost", *hyper_columns]

    def q(p: float) -> Callable[[pd.Series], float]:
        return lambda s: s.quantile(p)

    table = summary.groupby(keys, dropna=False, sort=True).agg(
        seeds=("seed", "count"),
        diverged=("diverged", "sum"),
        best_return_median=("best_return", "median"),
        best_return_q25=("best_return", q(0.25)),
        best_return_q75=("best_return", q(0.75)),
        measured_fraction_median=("best_measured_fraction", "median"),
        measured_fraction_q25=("best_measured_fraction", q(0.25)),
        measured_fraction_q75=("best_measured_fraction", q(0.75)),
        best_policy_return_median=("best_policy_return", "median"),
        best_policy_return_q25=("best_policy_return", q(0.25)),
        best_policy_return_q75=("best_policy_return", q(0.75)),
        best_policy_measured_fraction_median=("best_policy_measured_fraction", "median"),
    )
    return table.reset_index()
