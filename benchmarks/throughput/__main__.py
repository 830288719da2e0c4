"""The command line: `python -m benchmarks.throughput` from the repository root, or `python benchmarks/throughput`.
The parent builds the cases and runs each in a child process (this file run with --child CASE_JSON, through
`benchmarks.harness.run_child`), records each as a JSON line (`harness.Recorder`), then renders the report from them."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

if not __package__:  # run as `python benchmarks/throughput`: import the package by its full name, from the repository
    _HERE, _ROOT = Path(__file__).resolve().parent, Path(__file__).resolve().parents[2]
    # The package's own directory (sys.path[0] here) would make its modules top-level ones: put the repository there.
    sys.path[:1] = [str(_ROOT)] if sys.path and Path(sys.path[0]).resolve() == _HERE else [str(_ROOT), *sys.path[:1]]

import benchmarks.throughput as package  # noqa: E402
from benchmarks import harness  # noqa: E402
from benchmarks.throughput import cases, report, runners, timing  # noqa: E402


def _add_case_arguments(parser: argparse.ArgumentParser) -> None:
    """Which cases run, and how each is timed."""
    parser.add_argument("--child", help=argparse.SUPPRESS)
    parser.add_argument("--agents", default="ppo,dqn", help="comma-separated: ppo, dqn (default: both)")
    parser.add_argument("--sizes", default=None, help="configurations per case (default 1,16,256,1024; quick 1,4)")
    parser.add_argument(
        "--impls",
        default="amjax,amjax-vanilla,reference",
        help=f"comma-separated, from {', '.join(cases.IMPLS)} (default: the first three)",
    )
    parser.add_argument(
        "--steps",
        default=None,
        help="env steps per config: one number for every size, or size:steps pairs "
        "(1:204800,16:51200); rounded to a multiple of evals x steps per update "
        "(default: min(max, max(min, budget / configs)), see STEP_RULES)",
    )
    parser.add_argument(
        "--cores",
        type=int,
        default=None,
        help="CPU devices amjax spreads its configurations over (default: one per usable core, "
        "as amjax does; the plain reference always runs as written, on one device)",
    )
    parser.add_argument("--evals", type=int, default=5, help="evaluations per run (default 5)")
    parser.add_argument("--eval-episodes", type=int, default=10, help="test episodes per evaluation (default 10)")
    parser.add_argument("--target-chunks", type=int, default=10, help="the sweep runner's target_chunks (default 10)")
    parser.add_argument("--no-reference-eval", action="store_true", help="the plain reference skips evaluation")
    parser.add_argument(
        "--repeats",
        type=int,
        default=1,
        help="run each compiled case this many times and keep the fastest (default 1; use 3 on a busy machine)",
    )
    parser.add_argument(
        "--buffer",
        type=int,
        default=None,
        help="DQN buffer per config for every size (default: min(DQNConfig's buffer_size, steps per config))",
    )


def _add_sb3_arguments(parser: argparse.ArgumentParser) -> None:
    """The Stable-Baselines3 rows."""
    parser.add_argument(
        "--sb3",
        dest="sb3",
        action="store_true",
        default=None,
        help="SB3 rows (default: if stable_baselines3 is importable)",
    )
    parser.add_argument("--no-sb3", dest="sb3", action="store_false")
    parser.add_argument("--sb3-steps", type=int, default=None, help="env steps for the SB3 rows (default 20,000)")
    parser.add_argument(
        "--sb3-configs", type=int, default=None, help="amjax configs with SB3's DQN hyperparameters (default 64)"
    )
    parser.add_argument(
        "--sb3-threads",
        type=int,
        default=1,
        help="torch threads for SB3 (default 1: faster for these small networks; 2 threads on a "
        "busy 2-core machine ran 20x slower)",
    )
    parser.add_argument(
        "--sb3-buffer",
        type=int,
        default=cases.SB3_DQN["buffer_size"],
        help="buffer per config for that case (default SB3's 1,000,000)",
    )


def _add_extra_arguments(parser: argparse.ArgumentParser) -> None:
    """The buffer scan and the interleaved wrapper overhead."""
    parser.add_argument(
        "--buffer-scan",
        default="",
        help="also time amjax DQN at these buffer sizes (e.g. 1000,10000,100000) to see whether the "
        "step cost grows with capacity",
    )
    parser.add_argument("--buffer-scan-configs", type=int, default=16)
    parser.add_argument(
        "--overhead",
        default=None,
        help="configuration counts at which to time the wrapper's overhead with the active-measure "
        "and vanilla programs interleaved in one process, training only (default 256; quick 4; '' "
        "skips)",
    )
    parser.add_argument("--overhead-rounds", type=int, default=6, help="timed runs of each program (default 6)")
    parser.add_argument("--buffer-scan-steps", type=int, default=20_000)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.throughput",
        description=package.__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    _add_case_arguments(parser)
    _add_sb3_arguments(parser)
    _add_extra_arguments(parser)
    parser.add_argument("--timeout", type=float, default=900, help="seconds per case before it is abandoned")
    parser.add_argument(
        "--out",
        default=None,
        help="results file to append the run's JSON lines to (default: "
        "benchmarks/results/throughput_<date>_<machine>.jsonl); the report of all its runs is written beside it (.md)",
    )
    parser.add_argument("--markdown", default=None, help="also write this run's report (markdown) to this path")
    parser.add_argument("--json", default=None, help="also write this run's records as one JSON document to this path")
    parser.add_argument("--quick", action="store_true", help="smoke run: tiny sizes and budgets")
    return parser


def _sb3_importable() -> bool:
    try:
        import stable_baselines3  # noqa: F401
    except ImportError:
        return False
    return True


def resolve(parser: argparse.ArgumentParser, args: argparse.Namespace) -> argparse.Namespace:
    """The parent's arguments as lists and numbers, with --quick's defaults; errors for unknown names."""
    args.agents = [a for a in args.agents.split(",") if a]
    args.impls = [i for i in args.impls.split(",") if i]
    for impl in args.impls:
        if impl not in cases.IMPLS:
            parser.error(f"--impls: unknown {impl!r}; allowed: {', '.join(cases.IMPLS)}")
    for agent in args.agents:
        if agent not in ("ppo", "dqn"):
            parser.error(f"--agents: unknown {agent!r}; allowed: ppo, dqn")
    args.sizes = [int(s) for s in (args.sizes or ("1,4" if args.quick else "1,16,256,1024")).split(",")]
    args.buffer_scan = [int(b) for b in args.buffer_scan.split(",") if b]
    overhead = ("4" if args.quick else "256") if args.overhead is None else args.overhead
    args.overhead = [int(s) for s in overhead.split(",") if s]
    if args.sb3 is None:
        args.sb3 = _sb3_importable()
    args.sb3_steps = args.sb3_steps or (2_000 if args.quick else 20_000)
    args.sb3_configs = args.sb3_configs or (4 if args.quick else 64)
    return args


def run_cases(todo: list[dict[str, Any]], timeout: float, recorder: harness.Recorder) -> None:
    """Each case in a fresh process, one after another, with a progress line each; each recorded."""
    print(f"{len(todo)} cases, each in a fresh process:", flush=True)
    for i, case in enumerate(todo, 1):
        print(report.case_line(i, len(todo), case), end="", flush=True)
        result = timing.run_case(case, timeout)
        print(report.result_line(result), flush=True)
        recorder.case(result)


def main(argv: list[str] | None = None) -> None:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.child:
        runners.run_child(json.loads(args.child))
        return
    resolve(parser, args)
    settings = {key: value for key, value in vars(args).items() if key != "child"}
    recorder = harness.Recorder("throughput", {**settings, "software": report.software()}, args.out)
    print(f"recording to {recorder.path}", flush=True)
    run_cases(cases.build_cases(args), args.timeout, recorder)
    recorder.end()
    run = next(r for r in harness.read_runs(recorder.path) if r["run"] == recorder.run)
    text = report.render([run])
    print("\n" + text)
    print(f"written to {recorder.path} and {harness.write_markdown(recorder.path, report.render)}")
    if args.markdown:
        Path(args.markdown).write_text(text)
        print(f"markdown written to {args.markdown}")
    if args.json:
        report.write_json(args.json, run)


if __name__ == "__main__":
    main()
