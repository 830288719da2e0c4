"""Sweeps: grids of configurations trained in compiled vmapped batches, with results, summaries and resume."""

from amjax.files import FolderBusyError
from amjax.sweep.grid import RunConfig, SweepSpec, expand, group_runs
from amjax.sweep.runner import (
    CompileQueue,
    SweepMismatchError,
    SweepResult,
    SweepTooLargeError,
    load_sweep_policy,
    policy_path,
    run_sweep,
)

__all__ = [
    "CompileQueue",
    "FolderBusyError",
    "RunConfig",
    "SweepMismatchError",
    "SweepResult",
    "SweepSpec",
    "SweepTooLargeError",
    "expand",
    "group_runs",
    "load_sweep_policy",
    "policy_path",
    "run_sweep",
]
