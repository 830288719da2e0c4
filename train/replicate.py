"""`amjax replicate`: the paper's whole grid, then its report.

The paper's grid (default): Dueling DQN and PPO on CartPole-v0, Acrobot-v1 and LunarLander-v3, and DRQN on
CartPole-v0 (where the paper ran it), each x costs 0, 0.1, 0.2, 0.3 plus vanilla x 10 seeds: 350 configurations.
`--extended` runs DRQN, recurrent PPO, PQN and recurrent PQN on every environment too: 900 configurations. One sweep per
environment in `OUT/<env>/` (each resumable: rerun the same command after an interruption), each with its report in
`OUT/<env>/report/`, and `OUT/report.md` joining their tables with wall times.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import pandas as pd

from amjax.files import COMPILE_CACHE, atomic_write, folder_lock, remove_partial_writes, use_compile_cache
from train.flags import add_cluster_arguments, add_logging_arguments, cluster_from_args, executor_for, make_loggers
from train.presets import REPLICATE_BUDGETS, replicate_specs

# The paper ran its recurrent agent (DRQN) on CartPole only; the default grid follows it.
PAPER_AGENTS: dict[str, tuple[str, ...]] = {
    "CartPole-v0": ("dqn", "ppo", "drqn"),
    "Acrobot-v1": ("dqn", "ppo"),
    "LunarLander-v3": ("dqn", "ppo"),
}
EXTENDED_AGENTS = ("dqn", "ppo", "drqn", "ppo-rnn", "pqn", "pqn-rnn")  # --extended: on every environment


def replicate_grid(
    envs: tuple[str, ...], agents: tuple[str, ...] = (), extended: bool = False, seeds: int = 10, quick: bool = False
) -> dict[str, Any]:
    """One sweep spec per environment: `agents` on every env if given, else the paper's grid (`extended`: the
    recurrent agents and PQN on every env too)."""
    specs: dict[str, Any] = {}
    for env in envs:
        chosen = agents or (EXTENDED_AGENTS if extended else PAPER_AGENTS.get(env, ("dqn", "ppo")))
        specs |= replicate_specs((env,), chosen, seeds, quick)
    return specs


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    parser = subparsers.add_parser(
        "replicate",
        help="run the paper's grid (350 configurations; --extended: 900) and write its report",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--out", default="runs/replicate", help="output folder (rerun to resume)")
    parser.add_argument(
        "--env",
        nargs="+",
        default=list(REPLICATE_BUDGETS),
        metavar="ENV",
        help=f"a subset of {', '.join(REPLICATE_BUDGETS)}",
    )
    parser.add_argument(
        "--agent",
        nargs="+",
        metavar="AGENT",
        help="these agents on every env (default: the paper's: dqn and ppo everywhere, drqn on "
        "CartPole-v0); agents: ppo, dqn (Dueling Double DQN with n-step returns), drqn, ppo-rnn, pqn, pqn-rnn",
    )
    parser.add_argument(
        "--extended", action="store_true", help=f"the extended grid: {', '.join(EXTENDED_AGENTS)} on every env"
    )
    parser.add_argument("--seeds", type=int, help="seeds per setting (default: 10; 2 with --quick)")
    parser.add_argument(
        "--quick",
        action="store_true",
        help="a smoke run of the same grid: 40,960 steps per configuration (default 2 seeds)",
    )
    parser.add_argument("--max-batch", type=int, default=1024, help="most configurations per compiled batch")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    parser.add_argument("--no-maps", action="store_true", help="skip the reports' measurement maps")
    add_cluster_arguments(parser)
    add_logging_arguments(parser)
    return parser


def _index(out: Path, timings: dict[str, float], reports: dict[str, Path]) -> Path:
    """OUT/report.md: every environment's results table and wall time, with links to the full reports."""
    from amjax.analysis.report import format_paper_table
    from amjax.analysis.tables import to_markdown

    lines = [
        "# Replication report",
        "",
        "Bellinger et al. (Canadian AI 2022), replicated with amjax: per environment, the median over seeds of "
        "the best test costed return and the measured fraction at that evaluation; the full reports (figures, "
        "measurement maps, per-configuration tables) are linked below.",
        "",
    ]
    tables = []
    for env, report in reports.items():
        table = pd.read_csv(report.parent / "paper_table.csv")
        tables.append(table)
        link = report.relative_to(out)
        lines += [
            f"## {env}",
            "",
            f"Report: [{link}]({link}); wall time (all invocations together): {timings[env] / 60:.1f} min.",
            "",
            to_markdown(format_paper_table(table)),
            "",
        ]
    if tables:
        pd.concat(tables, ignore_index=True).to_csv(out / "paper_table.csv", index=False)
    path = out / "report.md"
    path.write_text("\n".join(lines))
    return path


def run(args: argparse.Namespace, error: Any) -> int:
    """Run the replication `args` describe; `error(message)` reports bad flags (exits 2)."""
    from amjax.sweep import FolderBusyError, SweepMismatchError, SweepTooLargeError
    from amjax.sweep.cluster import ClusterError
    from amjax.sweep.grid import expand
    from amjax.sweep.storage import UnreadableFileError

    seeds = (2 if args.quick else 10) if args.seeds is None else args.seeds
    try:
        if seeds < 1:
            raise ValueError(f"--seeds: got {seeds}; allowed values: integers >= 1")
        if args.max_batch < 1:
            raise ValueError(f"--max-batch: got {args.max_batch}; allowed values: integers >= 1")
        specs = replicate_grid(tuple(args.env), tuple(args.agent or ()), args.extended, seeds, args.quick)
        for spec in specs.values():
            expand(spec)  # every check before anything is written
        make_loggers(args, str(args.out))  # a missing package fails here, before anything is written
        cluster = cluster_from_args(args)
    except (ValueError, TypeError, ImportError) as problem:
        error(str(problem))
    out = Path(args.out)
    try:
        with folder_lock(out):
            remove_partial_writes(out, recursive=False)  # each sweep folder cleans its own
            remove_partial_writes(out / COMPILE_CACHE)
            use_compile_cache(out)  # a resumed replication loads its programs instead of compiling them again
            index = _replicate(specs, out, args, *cluster)
    except (SweepMismatchError, FolderBusyError, SweepTooLargeError, UnreadableFileError, ClusterError) as problem:
        print(f"replicate: error: {problem}", file=sys.stderr)
        return 2
    print(f"\nReplication report: {index}")
    return 0


def _replicate(
    specs: dict[str, Any], out: Path, args: argparse.Namespace, cluster: str | None, cluster_parameters: dict[str, Any]
) -> Path:
    """Run (or resume) each environment's sweep (its batches on `cluster` if given) and report, then write the
    joint report; returns its path."""
    from amjax.analysis import write_report
    from amjax.sweep import CompileQueue, run_sweep
    from amjax.sweep.batches import COMPILE_LOCK
    from amjax.sweep.storage import WallTime

    timings: dict[str, float] = {}
    reports: dict[str, Path] = {}
    # One compile queue for every environment's batches, in the order they train; the next environment's are
    # queued when one starts, so its first batch compiles while this one trains (a LunarLander-v3 Dueling DQN batch
    # compiles for about 2.5 min) and, on the paper's grid, is done before this one's report.
    compiler = CompileQueue() if cluster is None else None
    envs = list(specs)

    def queue(env: str) -> None:
        if compiler is not None:
            compiler.queue_sweep(specs[env], out / env, max_batch=args.max_batch)

    try:
        if envs:
            queue(envs[0])  # before the next environment's, which run_sweep's own queueing would come after
        for i, (env, spec) in enumerate(specs.items()):
            if i + 1 < len(envs):
                queue(envs[i + 1])
            run_sweep(
                spec,
                out / env,
                executor_for(cluster, cluster_parameters, compile_queue=compiler),
                max_batch=args.max_batch,
                progress=not args.no_progress,
                loggers=make_loggers(args, str(out / env)),
            )
            wall_time = WallTime(out / env / "wall_time.json", new_invocation=False)
            with COMPILE_LOCK:  # the report's measurement maps compile; never beside the queue's compiles
                reports[env] = write_report(out / env, maps=not args.no_maps)
            # The folder's account: training over every invocation (killed ones included) + reports.
            timings[env] = wall_time.save()
            print(f"{env}: {timings[env] / 60:.1f} min in all; report {reports[env]}")
            path = out / "wall_times.json"
            text = json.dumps({**(json.loads(path.read_text()) if path.exists() else {}), **timings}, indent=2)
            atomic_write(path, lambda tmp, text=text: Path(tmp).write_text(text + "\n"))
    finally:
        if compiler is not None:
            compiler.cancel()
    return _index(out, timings, reports)
