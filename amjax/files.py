"""File helpers shared by every layer that writes results."""

from __future__ import annotations

import contextlib
import os
import re
import tempfile
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

try:
    import fcntl
except ImportError:  # Windows: no advisory locks; folders are then not guarded against a second writer
    fcntl = None

PARTIAL_SUFFIX = ".partial"


class FolderBusyError(RuntimeError):
    """Another live process is writing to the same output folder."""


class WriteError(OSError):
    """The disk refused a write (no space, quota, permissions, read-only): names the file; whatever was on disk
    before the write is unchanged."""

    def __init__(self, path: Path, error: OSError):
        reason = error.strerror or str(error)
        super().__init__(error.errno, f"cannot write {path}: {reason}")
        self.path = Path(path)


def _sync(path: str | Path) -> None:
    """Flush a file's (or a folder's entries') data to the disk."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def commit(source: Path, target: Path) -> None:
    """Rename `source` over `target` (same filesystem) and make the rename durable: the one step that makes a
    write visible. Every file of a sweep folder appears through it (`atomic_write`, the cluster's merges)."""
    os.replace(source, target)
    with contextlib.suppress(OSError):  # some filesystems cannot sync a folder; the rename itself is atomic
        _sync(Path(target).parent)


def atomic_write(path: Path, write: Callable[[str], None]) -> None:
    """Call `write(tmp_path)`, flush it to disk, then rename it over `path` (`commit`): readers see the old file or
    the new one, never half, and a file that is there after a crash is whole.

    The temporary file is `.<name>.<random>.partial` beside `path`; a process killed mid-write (SIGKILL, power
    loss) leaves it behind, and `remove_partial_writes` clears it on the next run. A write the disk refuses
    (OSError: no space, permissions, ...) raises `WriteError` naming `path` and leaves the old file as it was.
    """
    path = Path(path)
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=PARTIAL_SUFFIX, dir=path.parent)
        os.close(fd)
        write(tmp)
        _sync(tmp)
        commit(Path(tmp), path)
    except OSError as error:
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)
        if isinstance(error, WriteError):
            raise
        raise WriteError(path, error) from error
    except BaseException:
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)
        raise


def write_compile_cache_whole() -> None:
    """Make JAX's persistent compilation cache write each entry whole (`atomic_write`).

    JAX 0.10 writes an entry in place, so a process killed mid-write (a preempted cluster worker: the cluster
    runner gives its workers one cache) leaves a truncated entry, and a process that reads an entry while another
    writes it sees half of one; loading either aborts the reader (a C++ abort, not an exception). Applied when
    `amjax.envs` is imported (every amjax program starts there); idempotent. A cache with a size limit keeps JAX's
    own locked writes."""
    try:
        from jax._src import lru_cache
    except ImportError:  # a JAX without this private module: left as it is
        return
    put = lru_cache.LRUCache.put
    if getattr(put, "writes_whole", False):
        return

    def put_whole(self, key: str, value: bytes) -> None:
        if not key or self.eviction_enabled:
            return put(self, key, value)
        path = Path(str(self.path)) / f"{key}{lru_cache._CACHE_SUFFIX}"
        if not path.exists():
            atomic_write(path, lambda tmp: Path(tmp).write_bytes(value))

    put_whole.writes_whole = True
    lru_cache.LRUCache.put = put_whole


COMPILE_CACHE = "compile_cache"  # a command's persistent compilation cache, under its output folder


def use_compile_cache(folder: str | Path) -> Path | None:
    """Keep the programs this process compiles from now on in ``folder/compile_cache/<machine>`` (JAX's persistent
    compilation cache; entries written whole, `write_compile_cache_whole`), so that a command run there again (a
    killed sweep resumed) loads them instead of compiling them again: minutes per batch on LunarLander-v3.

    The subfolder names the backend and the CPU (e.g. ``cpu-amd-epyc-avx-512``): JAX's cache key does not, and a
    program built for one CPU's vector extension must not load on another (a folder copied to another machine).
    Programs that take under JAX's `jax_persistent_cache_min_compile_time_secs` (1 s) to compile are not kept. A
    cache the user set (``JAX_COMPILATION_CACHE_DIR`` or JAX's config) is kept: then this returns None, else the
    folder. Call it before the work it should cover; programs already compiled in this process are not added."""
    import jax
    from jax.experimental.compilation_cache import compilation_cache

    from amjax.cores import cpu_description

    if jax.config.jax_compilation_cache_dir:
        return None
    machine = "-".join(filter(None, re.split(r"[^a-z0-9]+", f"{jax.default_backend()} {cpu_description()}".lower())))
    path = Path(folder) / COMPILE_CACHE / machine
    jax.config.update("jax_compilation_cache_dir", str(path))
    compilation_cache.reset_cache()  # JAX decides once per process whether it caches: at its first compile
    return path


def partial_writes(folder: Path, recursive: bool = True, skip: Sequence[str] = ()) -> list[Path]:
    """The temporary files that interrupted `atomic_write` calls left in `folder` (and its subfolders if
    `recursive`, bar those named in `skip`), sorted."""
    pattern = f".*{PARTIAL_SUFFIX}"
    folder = Path(folder)
    leftovers = sorted(folder.rglob(pattern) if recursive else folder.glob(pattern)) if folder.is_dir() else []
    return [p for p in leftovers if p.relative_to(folder).parts[0] not in skip]


def remove_partial_writes(folder: Path, recursive: bool = True, skip: Sequence[str] = ()) -> list[Path]:
    """Delete the `partial_writes` in `folder` (subfolders named in `skip` are other processes'); returns them.
    Only safe while no other process writes there (hold `folder_lock`)."""
    leftovers = partial_writes(folder, recursive, skip)
    for leftover in leftovers:
        leftover.unlink(missing_ok=True)
    return leftovers


@contextlib.contextmanager
def folder_lock(folder: Path, argument: str = "out", wait: bool = False) -> Iterator[None]:
    """Hold an exclusive lock on `folder` (created if needed) for the block; the operating system releases it
    when the process ends, however it ends. If another process holds it: wait for it with `wait`, else raise
    FolderBusyError naming `argument`."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    if fcntl is None:
        yield
        return
    with open(folder / ".lock", "a+") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX if wait else fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise FolderBusyError(
                f"{argument}: {folder} is being written by another running process; wait for it to finish "
                "or choose another folder"
            ) from None
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)
