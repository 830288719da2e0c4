"""Command line: `amjax sweep ...`, `demo`, `presets`, `report`, `replicate`, `pareto` and `prune` (also
`python -m train ...`).

Bad flags exit with status 2 and a message before anything is written or compiled. A write the disk refuses (no
space, no permission, read-only) also exits with status 2 and a message; what was finished stays on disk.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
from collections.abc import Sequence
from typing import Any, NoReturn

import jax
import pandas as pd

import amjax
from amjax.cores import cpu_description
from amjax.files import use_compile_cache

# The CLI is an application: every core for its sweeps, asked for before gymnax (imported below) starts JAX.
amjax.use_all_cores()

from amjax.agents import ALGORITHMS  # noqa: E402
from amjax.agents.registry import agent_list  # noqa: E402
from amjax.envs.registry import make_env  # noqa: E402
from amjax.presets import ENV_PRESETS  # noqa: E402
from amjax.sweep import FolderBusyError, SweepMismatchError, SweepSpec, SweepTooLargeError, run_sweep  # noqa: E402
from amjax.sweep.cluster import ClusterError  # noqa: E402
from amjax.sweep.devices import sweep_devices  # noqa: E402
from amjax.sweep.grid import MAX_CONFIGS, expand, round_schedule  # noqa: E402
from amjax.sweep.storage import UnreadableFileError  # noqa: E402
from train import pareto, prune, replicate, report  # noqa: E402
from train.flags import (  # noqa: E402
    add_cluster_arguments,
    add_logging_arguments,
    cluster_from_args,
    disk_error_message,
    executor_for,
    make_loggers,
    parse_set_value,
)
from train.presets import PRESETS  # noqa: E402


def _sequence_fields() -> set[str]:
    """Config fields whose single value is itself a tuple (network widths)."""
    return {
        f.name
        for algo in ALGORITHMS.values()
        for f in dataclasses.fields(algo.config_type)
        if isinstance(f.default, tuple)
    }


def _is_instruments(value: Any) -> bool:
    """Whether `value` is one `instruments` value: "default", () or a tuple of index tuples."""
    return value == "default" or (isinstance(value, tuple) and all(isinstance(v, tuple) for v in value))


def _parse_set(items: Sequence[str]) -> dict[str, Any]:
    """`name=v1,v2` -> {name: [v1, v2]} (swept); `name=v` -> {name: v}; `agent.name=v` for one agent only. For a
    tuple-valued field such as `hidden`, `hidden=(128,128)` is one value and `hidden=(64,64),(128,128)` two."""
    hyperparams = {}
    sequence_fields = _sequence_fields()
    for item in items:
        name, sep, text = item.partition("=")
        if not sep or not name:
            raise ValueError(f"--set: expected NAME=VALUE[,VALUE...], got {item!r}")
        value = parse_set_value(text)
        if name.rpartition(".")[2] == "instruments":  # one value is "default" or a tuple of index tuples
            if isinstance(value, tuple) and value and all(_is_instruments(v) for v in value):
                value = list(value)
        elif name.rpartition(".")[2] in sequence_fields:
            if isinstance(value, tuple) and value and all(isinstance(v, tuple) for v in value):
                value = list(value)
        elif isinstance(value, tuple):
            value = list(value)
        hyperparams[name] = value
    return hyperparams


def build_parser(prog: str = "python -m train") -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=prog,
        description="Train active-measure agents over grids of (env, agent, cost, seed, hyperparameters), "
        "all configurations of a group in one compiled program.",
    )
    commands = parser.add_subparsers(dest="command", required=True)

    sweep = commands.add_parser(
        "sweep",
        help="train a grid of configurations",
        description="Train every combination; rerun the same command to resume an interrupted sweep.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    sweep.add_argument("--preset", choices=sorted(PRESETS), help="start from a named sweep; flags override it")
    sweep.add_argument("--env", nargs="+", metavar="ENV", help="environment ids, e.g. CartPole-v0 Acrobot-v1")
    sweep.add_argument("--agent", nargs="+", metavar="AGENT", help=f"agents: {agent_list()}")
    sweep.add_argument("--cost", nargs="+", type=float, metavar="C", help="measurement costs (>= 0)")
    sweep.add_argument("--seeds", type=int, metavar="N", help="number of seeds (0..N-1)")
    sweep.add_argument("--seed-list", nargs="+", type=int, metavar="S", help="explicit seeds instead")
    sweep.add_argument("--steps", type=int, metavar="N", help="env steps per configuration")
    sweep.add_argument("--eval-every", type=int, metavar="N", help="env steps between greedy evaluations")
    sweep.add_argument("--eval-episodes", type=int, metavar="N", help="test episodes per evaluation")
    sweep.add_argument(
        "--vanilla",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="also train on the plain env (always measured, no cost)",
    )
    sweep.add_argument("--mode", choices=("last", "random", "noisy"), help="what an unmeasured step shows")
    sweep.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="NAME=V[,V...]",
        help="a hyperparameter value or list of values, e.g. learning_rate=1e-3,3e-4 or ppo.num_envs=16 "
        "(traced fields are vmapped; static ones such as hidden=(128,128) compile separately; booleans as "
        "True/False or true/false)",
    )
    sweep.add_argument(
        "--env-defaults",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="start each env from its tuned hyperparameters (amjax.presets: "
        f"{', '.join(ENV_PRESETS)}); --set values override them",
    )
    sweep.add_argument("--out", required=True, help="output folder (rerun with the same folder to resume)")
    sweep.add_argument("--max-batch", type=int, default=1024, help="most configurations per compiled batch")
    sweep.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    add_cluster_arguments(sweep)
    add_logging_arguments(sweep)

    demo = commands.add_parser("demo", help="the quick-start sweep (a few minutes on 2 cores)")
    demo.add_argument("--out", default="runs/demo", help="output folder")
    demo.add_argument("--no-progress", action="store_true", help="hide the progress bar")

    commands.add_parser("presets", help="list the named sweeps and each environment's tuned settings")
    report.add_parser(commands)
    replicate.add_parser(commands)
    pareto.add_parser(commands)
    prune.add_parser(commands)
    return parser


def spec_from_args(args: argparse.Namespace) -> SweepSpec:
    """The sweep the flags describe (preset first, flags on top)."""
    spec = PRESETS[args.preset] if args.preset else SweepSpec()
    changes: dict[str, Any] = {}
    if args.env:
        changes["envs"] = tuple(args.env)
    if args.agent:
        changes["agents"] = tuple(args.agent)
    if args.cost:
        changes["costs"] = tuple(args.cost)
    if args.seeds is not None and args.seed_list:
        raise ValueError("--seeds and --seed-list: give one of them")
    if args.seeds is not None:
        if not 1 <= args.seeds <= MAX_CONFIGS:
            raise ValueError(f"--seeds: got {args.seeds}; allowed values: integers in [1, {MAX_CONFIGS:,}]")
        changes["seeds"] = tuple(range(args.seeds))
    if args.seed_list:
        changes["seeds"] = tuple(args.seed_list)
    for flag, name in (
        ("steps", "total_timesteps"),
        ("eval_every", "eval_every"),
        ("eval_episodes", "eval_episodes"),
        ("vanilla", "vanilla"),
        ("mode", "mode"),
    ):
        if getattr(args, flag) is not None:
            changes[name] = getattr(args, flag)
    if args.set:
        changes["hyperparams"] = {**spec.hyperparams, **_parse_set(args.set)}
    for agent in changes.get("agents", ()):
        if agent not in ALGORITHMS:
            raise ValueError(f"--agent: unknown agent {agent!r}; allowed values: {agent_list()}")
    for env in changes.get("envs", ()):
        try:
            make_env(env)  # cheap; a brax id ("brax:<env_name>[:<backend>]") loads its model, about a second
        except (ValueError, ImportError) as error:
            raise type(error)(f"--env: {str(error).removeprefix('env_id: ')}") from None
    spec = dataclasses.replace(spec, **changes)
    # Each env's tuned presets (amjax.presets) unless --no-env-defaults, as `SweepSpec` applies them from Python.
    return dataclasses.replace(spec, env_defaults=None if args.env_defaults else {})


def describe_presets(spec: SweepSpec) -> list[str]:
    """One line per env and agent of the sweep that starts from tuned presets: which values."""
    lines = []
    for env, values in spec.resolved_env_defaults().items():
        for agent in spec.agents:
            fields = ALGORITHMS[agent].config_type.__dataclass_fields__
            mine = {
                k.removeprefix(f"{agent}."): v
                for k, v in values.items()
                if k.startswith(f"{agent}.") or ("." not in k and k in fields)
            }
            if mine:
                lines.append(
                    f"{env} {agent} starts from its presets (amjax.presets; --no-env-defaults: none, --set "
                    "overrides one): " + ", ".join(f"{k}={_value_text(v)}" for k, v in mine.items())
                )
    return lines


def _value_text(value: Any) -> str:
    return "x".join(map(str, value)) if isinstance(value, tuple) else str(value)


def describe_devices() -> str:
    """What a sweep's configurations are split over, e.g. "2 CPU devices (AMD EPYC, AVX-512)": results are
    bit-identical only on the same count, CPU model and vector extensions (XLA's float rounding depends on all
    three, and training amplifies it)."""
    devices = sweep_devices()
    kind = devices[0].platform.upper()
    model = cpu_description() if kind == "CPU" else devices[0].device_kind
    return f"{len(devices)} {kind} device{'s' if len(devices) > 1 else ''} ({model})"


def format_table(table: pd.DataFrame) -> str:
    """The seed table as text: median [q25, q75] of best costed reward and measured fraction, and the median
    re-scored costed reward of the best policies on fresh episodes with its measured fraction."""
    if table.empty:
        return "(no results)"
    shown = table.copy()
    shown["cost"] = [("vanilla" if v else f"{c:g}") for v, c in zip(shown.vanilla, shown.cost, strict=True)]
    shown["best costed reward"] = [
        f"{m:7.2f} [{a:.2f}, {b:.2f}]"
        for m, a, b in zip(shown.best_return_median, shown.best_return_q25, shown.best_return_q75, strict=True)
    ]
    shown["measured fraction"] = [
        f"{m:.3f} [{a:.3f}, {b:.3f}]"
        for m, a, b in zip(
            shown.measured_fraction_median, shown.measured_fraction_q25, shown.measured_fraction_q75, strict=True
        )
    ]
    shown["re-scored"] = [
        f"{m:7.2f} [{a:.2f}, {b:.2f}]"
        for m, a, b in zip(
            shown.best_policy_return_median, shown.best_policy_return_q25, shown.best_policy_return_q75, strict=True
        )
    ]
    shown["re-scored measured"] = [f"{m:.3f}" for m in shown.best_policy_measured_fraction_median]
    extra = [c for c in table.columns if c not in _SEED_TABLE_COLUMNS]
    columns = [
        "env",
        "agent",
        "cost",
        *extra,
        "seeds",
        "diverged",
        "best costed reward",
        "measured fraction",
        "re-scored",
        "re-scored measured",
    ]
    return shown[columns].to_string(index=False)


_SEED_TABLE_COLUMNS = {
    "env",
    "agent",
    "vanilla",
    "cost",
    "seeds",
    "diverged",
    "best_return_median",
    "best_return_q25",
    "best_return_q75",
    "measured_fraction_median",
    "measured_fraction_q25",
    "measured_fraction_q75",
    "best_policy_return_median",
    "best_policy_return_q25",
    "best_policy_return_q75",
    "best_policy_measured_fraction_median",
}


def main(argv: Sequence[str] | None = None, prog: str = "python -m train") -> int:
    parser = build_parser(prog)
    args = parser.parse_args(argv)
    try:
        return _run(parser, args)
    except OSError as error:  # a full or read-only disk: a message and status 2, never a traceback
        message = disk_error_message(error, _output_folder(args))
        if message is None:
            raise
        print(f"{parser.prog}: error: {message}", file=sys.stderr)
        return 2


def _output_folder(args: argparse.Namespace) -> str | None:
    """The folder the command writes in: --out, or prune's FOLDER."""
    return getattr(args, "out", None) or getattr(args, "folder", None)


def _run(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    if args.command == "report":
        return report.run(args)
    if args.command == "replicate":
        return replicate.run(args, parser.error)
    if args.command == "pareto":
        return pareto.run(args, parser.error)
    if args.command == "prune":
        return prune.run(args, parser.error)
    if args.command == "presets":
        for name, spec in PRESETS.items():
            runs = len(expand(spec))
            print(f"{name}: {runs} configurations x {spec.total_timesteps:,} steps — {spec}")
        print("\nEach environment's tuned settings (amjax.presets), applied by every command and SweepSpec:")
        for env, values in ENV_PRESETS.items():
            print(f"{env}: " + ", ".join(f"{key}={_value_text(value)}" for key, value in values.items()))
        return 0
    metadata: dict[str, Any] = {}
    try:
        if args.command == "demo":
            spec, max_batch = PRESETS["demo"], 1024
        else:
            spec, max_batch = spec_from_args(args), args.max_batch
            if max_batch < 1:
                raise ValueError(f"--max-batch: got {max_batch}; allowed values: integers >= 1")
            for flag, value in (("--steps", spec.total_timesteps), ("--eval-every", spec.eval_every)):
                if value < 1:
                    raise ValueError(f"{flag}: got {value}; allowed values: integers >= 1")
            requested = {"total_timesteps": spec.total_timesteps, "eval_every": spec.eval_every}
            spec, note = round_schedule(spec)  # any budget: whole updates and evaluation periods
            if note:
                print(f"{parser.prog}: {note}")
                metadata["requested_schedule"] = requested
        expand(spec)  # every check, before anything is written
        cluster, cluster_parameters = cluster_from_args(args) if args.command == "sweep" else (None, {})
        loggers = make_loggers(args, args.out)
    except (ValueError, TypeError, ImportError) as error:
        parser.error(str(error))  # exits with status 2
    for line in describe_presets(spec):
        print(f"{parser.prog}: {line}")
    print(f"{parser.prog}: {describe_devices()}")
    use_compile_cache(args.out)  # a resumed sweep loads its programs instead of compiling them again
    try:
        result = run_sweep(
            spec,
            args.out,
            executor_for(cluster, cluster_parameters),
            max_batch=max_batch,
            progress=not args.no_progress,
            loggers=loggers,
            metadata=metadata,
        )
    except (SweepMismatchError, FolderBusyError, SweepTooLargeError, UnreadableFileError, ClusterError) as error:
        print(f"{parser.prog}: error: {error}", file=sys.stderr)
        return 2
    except jax.errors.JaxRuntimeError as error:  # what the memory check cannot foresee (evaluation batches, XLA)
        if "RESOURCE_EXHAUSTED" not in str(error):
            raise
        print(
            f"{parser.prog}: error: out of memory ({str(error).splitlines()[0][:200]}); results so far are kept "
            f"in {args.out}: lower --max-batch or the sizes (num_envs, buffer_size, --eval-episodes)",
            file=sys.stderr,
        )
        return 2
    print()
    print("Median [interquartile range] over seeds of the best greedy test costed reward (the paper's metric, biased")
    print("upward: the best of many noisy evaluations) and the measured fraction of steps at that evaluation; then")
    print("the same best policies re-scored on fresh test episodes (100 by default) and their measured fraction:")
    print(format_table(result.table))
    print(f"\nResults: {result.out}/results.parquet (.csv), summary.parquet (.csv), seed_summary.csv, metadata.json")
    return 0


def interruptible_main(prog: str) -> int:
    """`main` for a process of its own (the `amjax` command, `python -m train`): Ctrl-C (SIGINT) stops it with a
    line saying what is kept and exit status 130, not a traceback. Python sees the signal once the compiled call
    running in the main thread returns (up to a chunk's time); the finished batches and the checkpointed chunks
    are on disk, so a rerun of the same command resumes from them. The process then ends at once (`os._exit`):
    waiting for the runner's threads, still inside XLA, would abort it ("terminate called ...").

    Python raises the interrupt wherever the main thread is; inside a garbage-collector callback (jax registers
    one) or a `__del__` it would only print "Exception ignored" and training would go on. Such an interrupt reaches
    `sys.unraisablehook`, which here stops the process the same way."""

    def stop() -> NoReturn:
        print(
            f"\n{prog}: interrupted. The finished batches and checkpointed chunks are kept on disk; rerun the "
            "same command to resume",
            file=sys.stderr,
        )
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(130)

    previous_hook = sys.unraisablehook

    def stop_on_swallowed_interrupt(unraisable: Any) -> None:
        if isinstance(unraisable.exc_value, KeyboardInterrupt):
            stop()
        previous_hook(unraisable)

    sys.unraisablehook = stop_on_swallowed_interrupt
    try:
        return main(prog=prog)
    except KeyboardInterrupt:
        stop()
    finally:
        sys.unraisablehook = previous_hook


def console_main() -> int:
    """The `amjax` console command (`[project.scripts]`)."""
    return interruptible_main("amjax")
