"""Optional per-configuration logging of a sweep's evaluation rows to TensorBoard or Weights & Biases.

Off by default; the sweep's own files (results, summaries, checkpoints) are always written. The runner calls
`log(rows)` with each chunk's new rows (one per configuration x evaluation point, the columns of `results`) and
`close()` at the end. Each configuration is its own run, named by its `config_id`; its env, agent, cost, seed and
swept hyperparameters are the run's config / tags. A resumed sweep logs again the evaluation points recomputed after
its last checkpoint.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Protocol

import pandas as pd

from amjax.sweep.storage import METRIC_COLUMNS

# Results columns logged as scalars (tag = column name with its first "_" turned into "/": eval/return, ...).
METRICS = METRIC_COLUMNS
_NOT_CONFIG = {*METRICS, "env_steps", "diverged", "config_id"}


class RunLogger(Protocol):
    def log(self, rows: pd.DataFrame) -> None: ...

    def close(self) -> None: ...


def _tag(column: str) -> str:
    return column.replace("_", "/", 1)


def _scalars(row: Any) -> dict[str, float]:
    values = {_tag(c): float(getattr(row, c)) for c in METRICS if hasattr(row, c)}
    values = {k: v for k, v in values.items() if math.isfinite(v)}  # no training episode ended: nothing to log
    values["diverged"] = float(bool(row.diverged))
    return values


def _run_config(rows: pd.DataFrame) -> dict[str, Any]:
    first = rows.iloc[0]
    return {c: (v.item() if hasattr(v, "item") else v) for c, v in first.items() if c not in _NOT_CONFIG}


def _missing(package: str) -> ImportError:
    return ImportError(f"{package} is not installed: pip install 'amjax-rl[logging]' (or pip install {package})")


class TensorBoardLogger:
    """One TensorBoard run per configuration in `logdir/<config_id>/` (tensorboardX event files)."""

    def __init__(self, logdir: str | Path):
        try:
            from tensorboardX import SummaryWriter
        except ImportError:
            raise _missing("tensorboardX") from None
        self._writer_type = SummaryWriter
        self.logdir = Path(logdir)
        self._writers: dict[str, Any] = {}

    def log(self, rows: pd.DataFrame) -> None:
        for config_id, group in rows.groupby("config_id", sort=False):
            writer = self._writers.get(config_id)
            if writer is None:
                writer = self._writers[config_id] = self._writer_type(str(self.logdir / config_id))
                writer.add_text("config", ", ".join(f"{k}={v}" for k, v in _run_config(group).items()))
            for row in group.itertuples(index=False):
                for tag, value in _scalars(row).items():
                    writer.add_scalar(tag, value, global_step=int(row.env_steps))
            writer.flush()

    def close(self) -> None:
        for writer in self._writers.values():
            writer.close()
        self._writers.clear()


class WandbLogger:
    """One Weights & Biases run per configuration (run id = config_id, grouped by env and agent).

    `mode="offline"` (the default) needs no network or account: runs go to `dir/wandb/` and can be uploaded later
    with `wandb sync`. Runs stay open until `close()`; for sweeps of thousands of configurations prefer TensorBoard.
    `wandb_module` replaces the `wandb` import (for tests).
    """

    def __init__(self, project: str, dir: str | Path, mode: str = "offline", wandb_module: Any = None):
        from amjax.validation import check_choice

        check_choice("mode", mode, ("offline", "online", "disabled"))
        if wandb_module is None:
            try:
                import wandb as wandb_module
            except ImportError:
                raise _missing("wandb") from None
        self._wandb = wandb_module
        self.project, self.dir, self.mode = project, Path(dir), mode
        self._runs: dict[str, Any] = {}

    def log(self, rows: pd.DataFrame) -> None:
        self.dir.mkdir(parents=True, exist_ok=True)
        for config_id, group in rows.groupby("config_id", sort=False):
            run = self._runs.get(config_id)
            if run is None:
                config = _run_config(group)
                run = self._runs[config_id] = self._wandb.init(
                    project=self.project,
                    id=config_id,
                    name=config_id,
                    dir=str(self.dir),
                    mode=self.mode,
                    group=f"{config.get('env')}-{config.get('agent')}",
                    config=config,
                    reinit="create_new",
                    resume="allow",
                )
            for row in group.itertuples(index=False):
                run.log(_scalars(row), step=int(row.env_steps))

    def close(self) -> None:
        for run in self._runs.values():
            run.finish()
        self._runs.clear()


__all__ = ["METRICS", "RunLogger", "TensorBoardLogger", "WandbLogger"]
