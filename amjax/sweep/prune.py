"""Pruning a sweep folder: delete what its finished batches no longer need, so that the folder is small enough to
copy, archive or commit, and still resumes as it would have (`amjax prune`).

A finished batch's final checkpoint holds its train states (a Dueling DQN batch's holds every replay buffer: 340 MB
for 40 LunarLander-v3 configurations). A rerun reads it only to redo, without training, a file the batch's marker
vouches for that has gone missing (a row, a re-score, a policy) or that was never written (a batch killed after its
re-scores and before its marker). Pruning rewrites the marker first, saying the checkpoint is gone on purpose
(`storage.CHECKPOINT_PRUNED`, the one commit point per batch), then deletes the checkpoint. A kill between the two
leaves a marker that no longer needs the file and the file still there, which the next prune deletes. Rows,
re-scores, policies and markers stay, so a rerun of the sweep, on this machine or on another one (the batches' names
do not depend on the machine), counts every pruned batch finished and trains only the rest. Once pruned, a batch
whose policy or rows are later lost is trained again.

Kept (`PruneResult.kept` says why): unfinished batches' checkpoints (a rerun resumes from them), batches whose
marker vouches for a file that is missing, and batches finished without saving policies (a rerun that saves them
builds them from the checkpoint); a cluster run's parts are left as they were.
"""

from __future__ import annotations

import contextlib
import shutil
from dataclasses import dataclass, field
from pathlib import Path

from amjax.files import COMPILE_CACHE, FolderBusyError, folder_lock, partial_writes, remove_partial_writes
from amjax.sweep import storage
from amjax.sweep.cluster import PARTS

# Why `prune_sweep` keeps a batch's checkpoint (`PruneResult.kept`).
NOT_FINISHED = "not finished"
MISSING_FILE = "its marker vouches for a file that is missing: a rerun rebuilds it from the checkpoint"
NO_POLICIES = "finished without saving policies: a rerun that saves them builds them from the checkpoint"


@dataclass(frozen=True)
class PruneResult:
    """What `prune_sweep` did (or, with `dry_run`, would do) to one sweep folder (or, from `prune_folder`, to a
    replication's own compile cache)."""

    folder: Path
    pruned: tuple[str, ...]  # finished batches whose final checkpoints were deleted
    kept: dict[str, str] = field(default_factory=dict)  # batch -> why its checkpoint stays
    checkpoint_bytes: int = 0  # the checkpoints deleted
    cache_bytes: int = 0  # the compiled programs deleted (`compile_cache`)
    partial_files: int = 0  # temporary files of interrupted writes deleted

    @property
    def freed_bytes(self) -> int:
        return self.checkpoint_bytes + self.cache_bytes


def _size(path: Path) -> int:
    """Bytes of the regular files at or under `path`; links are not followed (deleting a link frees nothing)."""
    if path.is_symlink() or not path.exists():
        return 0
    if path.is_file():
        return path.lstat().st_size
    return sum(p.lstat().st_size for p in path.rglob("*") if p.is_file() and not p.is_symlink())


def _delete_compile_cache(folder: Path, dry_run: bool) -> int:
    """Delete `folder`'s compile cache (a link to one: the link only); returns the bytes freed."""
    cache = folder / COMPILE_CACHE
    size = _size(cache)
    if not dry_run:
        if cache.is_symlink():
            cache.unlink()
        elif cache.is_dir():
            shutil.rmtree(cache)
    return size


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


def _lock(folder: Path, dry_run: bool) -> contextlib.AbstractContextManager:
    """The folder's lock, or none for a dry run (which writes nothing, so it also works on a read-only copy)."""
    return contextlib.nullcontext() if dry_run else folder_lock(folder, argument="folder")


def prune_sweep(out: str | Path, *, compile_cache: bool = False, dry_run: bool = False) -> PruneResult:
    """Delete the final checkpoints of `out`'s finished batches (and with `compile_cache` its compiled programs,
    which only spare a rerun its compiling) and the temporary files of interrupted writes, keeping everything a
    rerun, a report or `load_sweep_policy` reads.

    `dry_run`: change nothing, take no lock, report what would go. Raises ValueError if `out` is not a sweep folder
    and FolderBusyError if a running sweep holds it."""
    out = Path(out)
    if not is_sweep_folder(out):
        raise ValueError(f"folder: {out} is not a sweep folder (no metadata.json)")
    with _lock(out, dry_run):
        results, rescored = storage.read_table(out / "results"), storage.read_table(out / "rescored")
        pruned, kept, checkpoint_bytes = [], {}, 0
        for marker_file in sorted((out / "finished").glob("*.json")):
            marker = storage.read_marker(out, marker_file.stem)
            if marker is None:
                continue  # unreadable: counted as unfinished below
            checkpoint = storage.checkpoint_path(out, marker["batch"])
            if not storage.marker_files_present(out, marker, results, rescored, marker["policies"]):
                kept[marker["batch"]] = MISSING_FILE
                continue
            if marker.get(storage.CHECKPOINT_PRUNED) and not checkpoint.exists():
                continue  # pruned before
            if not marker["policies"]:
                kept[marker["batch"]] = NO_POLICIES
                continue
            pruned.append(marker["batch"])
            checkpoint_bytes += _size(checkpoint)
            if dry_run:
                continue
            if not marker.get(storage.CHECKPOINT_PRUNED):
                storage.write_marker(out, {**marker, storage.CHECKPOINT_PRUNED: True})  # the commit point
            checkpoint.unlink(missing_ok=True)
        for checkpoint in sorted((out / "checkpoints").glob("*.msgpack")):
            if checkpoint.stem not in pruned and checkpoint.stem not in kept:
                kept[checkpoint.stem] = NOT_FINISHED
        kept = {batch: kept[batch] for batch in sorted(kept) if storage.checkpoint_path(out, batch).exists()}
        partial = (partial_writes if dry_run else remove_partial_writes)(out, skip=(PARTS,))
        cache = _delete_compile_cache(out, dry_run) if compile_cache else 0
    return PruneResult(out, tuple(pruned), kept, checkpoint_bytes, cache, len(partial))


def prune_folder(folder: str | Path, *, compile_cache: bool = False, dry_run: bool = False) -> list[PruneResult]:
    """`prune_sweep` on every sweep folder under `folder` (`sweep_folders`): a sweep's, or a replication's with
    one sweep per env, whose own compile cache (`OUT/compile_cache`) goes too with `compile_cache` (its result
    is the last, with the replication's folder and no batches); the replication's folder is locked meanwhile, as
    `amjax replicate` locks it. A sweep folder held by a running sweep stops it with FolderBusyError, which names
    the folders already pruned (their pruning stands)."""
    folder = Path(folder)
    sweeps = sweep_folders(folder)
    if sweeps == [folder]:
        return [prune_sweep(folder, compile_cache=compile_cache, dry_run=dry_run)]
    done: list[PruneResult] = []
    with _lock(folder, dry_run):
        for sweep in sweeps:
            try:
                done.append(prune_sweep(sweep, compile_cache=compile_cache, dry_run=dry_run))
            except FolderBusyError as busy:
                finished = ", ".join(r.folder.name for r in done) or "none"
                raise FolderBusyError(f"{busy} (already pruned: {finished})") from None
        if compile_cache and (folder / COMPILE_CACHE).exists():
            done.append(PruneResult(folder, (), cache_bytes=_delete_compile_cache(folder, dry_run)))
    return done


__all__ = [
    "MISSING_FILE",
    "NOT_FINISHED",
    "NO_POLICIES",
    "PruneResult",
    "is_sweep_folder",
    "prune_folder",
    "prune_sweep",
    "sweep_folders",
]
