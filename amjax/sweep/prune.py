"""Pruning a sweep folder: delete what its finished batches no longer need, so that the folder is small enough to
copy, archive or commit, and still resumes as it would have (`amjax prune`).

A finished batch's final checkpoint holds its train states (a Dueling DQN batch's holds every replay buffer: 340 MB
for 40 LunarLander-v3 configurations). Only a rerun killed after the batch's re-scores and before its commit marker
reads it; once the marker is written nothing does. Pruning rewrites the marker first, saying the checkpoint is gone
on purpose (`storage.CHECKPOINT_PRUNED`, the one commit point per batch), then deletes the checkpoint. A kill
between the two leaves a marker that no longer needs the file and the file still there, which the next prune
deletes. Rows, re-scores, policies and markers stay, so a rerun of the sweep, on this machine or on another one
(the batches' names do not depend on the machine), counts every pruned batch finished and trains only the rest.

Left as they were: unfinished batches' checkpoints (a rerun resumes from them), batches whose marker vouches for a
file that is missing (a rerun needs the checkpoint to redo the file without training), and a cluster run's parts.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

from amjax.files import COMPILE_CACHE, folder_lock
from amjax.sweep import storage


@dataclass(frozen=True)
class PruneResult:
    """What `prune_sweep` did (or, with `dry_run`, would do) to one sweep folder."""

    folder: Path
    pruned: tuple[str, ...]  # finished batches whose final checkpoints were deleted
    kept: tuple[str, ...]  # batches whose checkpoints stay: unfinished (or missing a file), a rerun needs them
    freed_bytes: int  # checkpoints deleted, plus the compile cache with `compile_cache`


def _size(path: Path) -> int:
    if path.is_file():
        return path.stat().st_size
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def is_sweep_folder(folder: Path) -> bool:
    """Whether `folder` holds a sweep (its metadata.json), as `run_sweep` writes it."""
    return (Path(folder) / "metadata.json").is_file()


def sweep_folders(folder: str | Path) -> list[Path]:
    """The sweep folders under `folder`: itself if it is one, else its subfolders that are (`amjax replicate`'s
    `OUT/<env>/`). ValueError, naming the argument, if there are none."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ValueError(f"folder: {folder} is not a folder; give a sweep's or a replication's output folder")
    if is_sweep_folder(folder):
        return [folder]
    found = sorted(p for p in folder.iterdir() if p.is_dir() and is_sweep_folder(p))
    if not found:
        raise ValueError(
            f"folder: {folder} holds no sweep (no metadata.json in it or in its subfolders); give the --out of "
            "`amjax sweep` or `amjax replicate`"
        )
    return found


def prune_sweep(out: str | Path, *, compile_cache: bool = False, dry_run: bool = False) -> PruneResult:
    """Delete the final checkpoints of `out`'s finished batches (and with `compile_cache` its compiled programs,
    which only spare a rerun its compiling), keeping everything a rerun, a report or `load_sweep_policy` reads.

    `dry_run`: change nothing, report what would go. Raises ValueError if `out` is not a sweep folder and
    FolderBusyError if a running sweep holds it."""
    out = Path(out)
    if not is_sweep_folder(out):
        raise ValueError(f"folder: {out} is not a sweep folder (no metadata.json)")
    with folder_lock(out, argument="folder"):
        results, rescored = storage.read_table(out / "results"), storage.read_table(out / "rescored")
        pruned, freed = [], 0
        for marker_file in sorted((out / "finished").glob("*.json")):
            marker = storage.read_marker(out, marker_file.stem)
            if marker is None or not storage.marker_files_present(out, marker, results, rescored, marker["policies"]):
                continue
            checkpoint = storage.checkpoint_path(out, marker["batch"])
            if marker.get(storage.CHECKPOINT_PRUNED) and not checkpoint.exists():
                continue  # pruned before
            pruned.append(marker["batch"])
            freed += _size(checkpoint) if checkpoint.exists() else 0
            if dry_run:
                continue
            if not marker.get(storage.CHECKPOINT_PRUNED):
                storage.write_marker(out, {**marker, storage.CHECKPOINT_PRUNED: True})  # the commit point
            checkpoint.unlink(missing_ok=True)
        kept = tuple(sorted(p.stem for p in (out / "checkpoints").glob("*.msgpack") if p.stem not in pruned))
        cache = out / COMPILE_CACHE
        if compile_cache and cache.is_dir():
            freed += _size(cache)
            if not dry_run:
                shutil.rmtree(cache)
    return PruneResult(out, tuple(pruned), kept, freed)


def prune_folder(folder: str | Path, *, compile_cache: bool = False, dry_run: bool = False) -> list[PruneResult]:
    """`prune_sweep` on every sweep folder under `folder` (`sweep_folders`): a sweep's, or a replication's with
    one sweep per env, whose own compile cache (`OUT/compile_cache`) goes too with `compile_cache`; the
    replication's folder is locked meanwhile, as `amjax replicate` locks it."""
    folder = Path(folder)
    sweeps = sweep_folders(folder)
    if sweeps == [folder]:
        return [prune_sweep(folder, compile_cache=compile_cache, dry_run=dry_run)]
    with folder_lock(folder, argument="folder"):
        done = [prune_sweep(sweep, compile_cache=compile_cache, dry_run=dry_run) for sweep in sweeps]
        cache = folder / COMPILE_CACHE
        if compile_cache and cache.is_dir():
            done.append(PruneResult(folder, (), (), _size(cache)))
            if not dry_run:
                shutil.rmtree(cache)
    return done


__all__ = ["PruneResult", "is_sweep_folder", "prune_folder", "prune_sweep", "sweep_folders"]
