"""`amjax prune FOLDER`: delete the final checkpoints of a sweep's finished batches (train states, replay buffers),
so that the folder can be copied to another machine, archived or committed, and resumed there. Rows, re-scores,
policies and commit markers stay; unfinished batches keep their checkpoints, and so do batches finished without
policies (a rerun that saves them builds them from the checkpoint). Once pruned, a batch whose policies or rows are
lost later is trained again. FOLDER is the --out of `amjax sweep` or of `amjax replicate` (every env's sweep in it).
`--compile-cache` also deletes the compiled programs the commands keep there, which only save a rerun its compiling.
"""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING, Any

from amjax.files import FolderBusyError

if TYPE_CHECKING:
    from amjax.sweep.prune import PruneResult


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
    return f"{count / 1e6:,.1f} MB"


def _line(result: PruneResult, verb: str) -> str:
    """One folder's line: what went (checkpoints, compiled programs, leftover temporary files) and what stayed."""
    gone = []
    if result.pruned:
        gone.append(f"{len(result.pruned)} finished batches' checkpoints ({_megabytes(result.checkpoint_bytes)})")
    if result.cache_bytes:
        gone.append(f"the compile cache ({_megabytes(result.cache_bytes)})")
    if result.partial_files:
        gone.append(f"{result.partial_files} temporary files of interrupted writes")
    line = f"{result.folder}: {verb} " + (", ".join(gone) or "nothing")
    if result.kept:
        line += f"; kept {len(result.kept)} checkpoints: " + "; ".join(f"{b} ({why})" for b, why in result.kept.items())
    return line


def run(args: argparse.Namespace, error: Any) -> int:
    """Prune the folder `args` names; `error(message)` reports a bad argument (exits 2)."""
    from amjax.sweep.prune import prune_folder

    try:
        done = prune_folder(args.folder, compile_cache=args.compile_cache, dry_run=args.dry_run)
    except (ValueError, FolderBusyError) as problem:
        error(str(problem))
    verb = "would delete" if args.dry_run else "deleted"
    for result in done:
        print(_line(result, verb))
    print(f"{verb} {_megabytes(sum(r.freed_bytes for r in done))} in all")
    return 0
