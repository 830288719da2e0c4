"""`amjax prune FOLDER`: delete the final checkpoints of a sweep's finished batches (train states, replay buffers),
which nothing reads once a batch is committed, so that the folder can be copied to another machine, archived or
committed, and resumed there. Rows, re-scores, policies and commit markers stay; unfinished batches keep their
checkpoints. FOLDER is the --out of `amjax sweep` or of `amjax replicate` (every env's sweep in it).
`--compile-cache` also deletes the compiled programs the commands keep there, which only save a rerun its compiling.
"""

from __future__ import annotations

import argparse
from typing import Any

from amjax.files import FolderBusyError


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    parser = subparsers.add_parser(
        "prune",
        help="delete what finished batches no longer need (final checkpoints), keeping a resumable folder",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("folder", help="a sweep's or a replication's output folder (its --out)")
    parser.add_argument("--compile-cache", action="store_true", help="also delete the folder's compiled programs")
    parser.add_argument("--dry-run", action="store_true", help="change nothing; print what would be deleted")
    return parser


def _megabytes(count: int) -> str:
    return f"{count / 2**20:,.1f} MiB"


def run(args: argparse.Namespace, error: Any) -> int:
    """Prune the folder `args` names; `error(message)` reports a bad argument (exits 2)."""
    from amjax.sweep.prune import prune_folder

    try:
        done = prune_folder(args.folder, compile_cache=args.compile_cache, dry_run=args.dry_run)
    except (ValueError, FolderBusyError) as problem:
        error(str(problem))
    verb = "would delete" if args.dry_run else "deleted"
    for result in done:
        line = f"{result.folder}: {verb} {len(result.pruned)} finished batches' checkpoints"
        if not result.pruned and not result.kept and result.freed_bytes:  # a replication's own compile cache
            line = f"{result.folder}: {verb} the compile cache"
        line += f" ({_megabytes(result.freed_bytes)})"
        if result.kept:
            line += f"; kept {len(result.kept)} that a rerun resumes from: {', '.join(result.kept)}"
        print(line)
    print(f"{verb} {_megabytes(sum(r.freed_bytes for r in done))} in all")
    return 0
