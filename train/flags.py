"""Flags that several commands share (sweep, replicate): optional per-configuration logging, cluster targets, the
syntax of a `--set` value (also `benchmarks/pqn_speed.py`'s); and the message for a write the disk refuses, which
every command gives the same way."""

from __future__ import annotations

import argparse
import ast
import errno
import json
from pathlib import Path
from typing import Any

from amjax.sweep.cluster import check_engine, check_parameters, parse_cluster
from amjax.sweep.loggers import TensorBoardLogger, WandbLogger


def parse_set_value(text: str) -> Any:
    """One `--set` value: a Python literal; `true` / `false` in any case as booleans (as YAML and JSON write
    them); else a bare word, or a tuple of values where commas separate bare words (relu,tanh)."""
    try:
        return ast.literal_eval(text)
    except (ValueError, SyntaxError):
        if "," in text:  # bare words among the values, e.g. relu,tanh
            return tuple(parse_set_value(part) for part in text.split(","))
        if text.strip().lower() in ("true", "false"):
            return text.strip().lower() == "true"
        return text  # a bare word, e.g. relu


def add_logging_arguments(parser: argparse.ArgumentParser) -> None:
    """--tensorboard / --wandb flags (optional per-configuration logging; local files are always written)."""
    parser.add_argument(
        "--tensorboard",
        action="store_true",
        help="also log every configuration to TensorBoard (OUT/tensorboard/<config_id>)",
    )
    parser.add_argument(
        "--wandb", metavar="PROJECT", help="also log every configuration to Weights & Biases project PROJECT"
    )
    parser.add_argument(
        "--wandb-mode",
        choices=("offline", "online"),
        default="offline",
        help="offline needs no network (upload later with `wandb sync OUT/wandb/offline-run-*`)",
    )


def make_loggers(args: argparse.Namespace, out: str) -> list[Any]:
    """The loggers the flags ask for; ImportError (with the pip command) when a package is missing."""
    loggers: list[Any] = []
    if getattr(args, "tensorboard", False):
        loggers.append(TensorBoardLogger(Path(out) / "tensorboard"))
    if getattr(args, "wandb", None):
        loggers.append(WandbLogger(args.wandb, out, mode=args.wandb_mode))
    return loggers


def add_cluster_arguments(parser: argparse.ArgumentParser) -> None:
    """--cluster / --cluster-option flags (batches as jobs through submitit; docs/cluster.md)."""
    parser.add_argument(
        "--cluster",
        metavar="TARGET",
        help="run the batches as jobs through submitit (the [cluster] extra): local:N for N worker "
        "processes here, slurm:PARTITION[:JOBS] for Slurm jobs on a whole node each (--out must be "
        "on a filesystem the nodes share; docs/cluster.md)",
    )
    parser.add_argument(
        "--cluster-option",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="a submitit executor parameter for the jobs, e.g. account=lab or time=600 (Slurm "
        "minutes); the value is read as JSON when it parses, else as text",
    )


def cluster_from_args(args: argparse.Namespace) -> tuple[str | None, dict[str, Any]]:
    """`--cluster` and `--cluster-option` read and checked (the target's form, the engine installed, the
    parameters' names); (None, {}) for a local sweep."""
    target, options = getattr(args, "cluster", None), getattr(args, "cluster_option", [])
    if target is None:
        if options:
            raise ValueError("--cluster-option: give --cluster too")
        return None, {}
    parameters: dict[str, Any] = {}
    for option in options:
        name, sep, text = option.partition("=")
        if not sep or not name.isidentifier():
            raise ValueError(
                f"--cluster-option: got {option!r}; allowed values: NAME=VALUE, NAME a submitit "
                "executor parameter (e.g. account=lab, time=600)"
            )
        try:
            parameters[name] = json.loads(text)
        except ValueError:
            parameters[name] = text
    try:
        check_engine()
        check_parameters(parse_cluster(target), parameters)
    except (ValueError, ImportError) as error:
        message = str(error).replace("cluster_parameters: ", "--cluster-option: ").replace("cluster: ", "--cluster: ")
        raise type(error)(message) from None
    return target, parameters


def executor_for(cluster: str | None, parameters: dict[str, Any], compile_queue: Any = None) -> Any:
    """The executor `cluster_from_args`'s values describe: the cluster's jobs, else this process (compiling ahead
    on `compile_queue` if given)."""
    from amjax.sweep import ClusterExecutor, LocalExecutor

    if cluster is not None:
        return ClusterExecutor(cluster, parameters)
    return LocalExecutor(compile_queue=compile_queue)


# What a full or protected disk raises: the command stops with a message, not a traceback.
DISK_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EACCES, errno.EPERM, errno.EROFS}


def disk_error_message(error: OSError, out: str | None) -> str | None:
    """The message for a write the disk refused (None if `error` is not one): what failed, and that a rerun of the
    same command resumes once there is space (or permission), every batch finished before kept."""
    if error.errno not in DISK_ERRNOS:
        return None
    what = error.strerror or str(error)
    if error.filename and str(error.filename) not in what:
        what = f"{what}: {error.filename}"
    kept = f" in {out}" if out else ""
    return (
        f"{what} [{errno.errorcode.get(error.errno, error.errno)}]. Everything finished before it is kept{kept}; "
        "free some space (or fix the permissions) and rerun the same command to resume"
    )
