"""Sweeps: grids of configurations trained in compiled vmapped batches, with results, summaries and resume.

Layers, bottom to top: `grid` (the configurations) -> `batches` (compiled groups) -> `storage` (files) ->
`batch_run` (one batch, first chunk to commit) -> `executors` / `cluster` (what runs the batches) -> `runner`
(`run_sweep`); `prune` (what a finished folder no longer needs).
"""

from amjax.files import FolderBusyError
from amjax.sweep.cluster import ClusterExecutor
from amjax.sweep.executors import CompileQueue, Executor, LocalExecutor
from amjax.sweep.grid import RunConfig, SweepSpec, expand, group_runs
from amjax.sweep.prune import PruneResult, prune_folder, prune_sweep
from amjax.sweep.runner import (
    SweepMismatchError,
    SweepResult,
    SweepTooLargeError,
    load_sweep_policy,
    policy_path,
    run_sweep,
)

__all__ = [
    "ClusterExecutor",
    "CompileQueue",
    "Executor",
    "FolderBusyError",
    "LocalExecutor",
    "PruneResult",
    "RunConfig",
    "SweepMismatchError",
    "SweepResult",
    "SweepSpec",
    "SweepTooLargeError",
    "expand",
    "group_runs",
    "load_sweep_policy",
    "policy_path",
    "prune_folder",
    "prune_sweep",
    "run_sweep",
]
