"""Flags that several commands share (sweep, replicate): optional per-configuration logging."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from amjax.sweep.loggers import TensorBoardLogger, WandbLogger


def add_logging_arguments(parser: argparse.ArgumentParser) -> None:
    """--tensorboard / --wandb flags (optional per-configuration logging; local files are always written)."""
    parser.add_argument("--tensorboard", action="store_true",
                        help="also log every configuration to TensorBoard (OUT/tensorboard/<config_id>)")
    parser.add_argument("--wandb", metavar="PROJECT",
                        help="also log every configuration to Weights & Biases project PROJECT")
    parser.add_argument("--wandb-mode", choices=("offline", "online"), default="offline",
                        help="offline needs no network (upload later with `wandb sync OUT/wandb/offline-run-*`)")


def make_loggers(args: argparse.Namespace, out: str) -> list[Any]:
    """The loggers the flags ask for; ImportError (with the pip command) when a package is missing."""
    loggers: list[Any] = []
    if getattr(args, "tensorboard", False):
        loggers.append(TensorBoardLogger(Path(out) / "tensorboard"))
    if getattr(args, "wandb", None):
        loggers.append(WandbLogger(args.wandb, out, mode=args.wandb_mode))
    return loggers
