"""A sweep on a local submitit cluster against the local runner, in one invocation (issue 18).

Times the same 64-configuration PPO + Dueling DQN sweep on CartPole-v0 (costs 0 / 0.1 / 0.2 / 0.3 x 8 seeds per
agent) three ways, each in its own child process started the way a user starts it (`amjax.use_all_cores()` first):
the local runner (one batch per agent, each spread over both cores), and `cluster="local:N"` for each N of
`--workers` (a batch per worker process, the cores split between them). It checks that every cluster run's rows
equal the local run's, and measures the engine's own cost per task: a no-op job's round trip through submitit's
LocalExecutor, and a worker's start (Python, JAX and amjax imported) before its batch begins.

    python benchmarks/cluster_overhead.py                 # writes benchmarks/results/cluster_overhead_<date>.md
    python benchmarks/cluster_overhead.py --steps 8192 --workers 2 --out /tmp/cl   # a smoke run
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the benchmarks are not installed

COSTS = (0.0, 0.1, 0.2, 0.3)


def run_child(steps: int, seeds: int, out: str, cluster: str | None) -> None:
    """One timed sweep in this (child) process; prints a JSON line."""
    import amjax

    amjax.use_all_cores()
    from amjax.sweep import SweepSpec, run_sweep

    spec = SweepSpec(
        envs=("CartPole-v0",),
        agents=("ppo", "dqn"),
        costs=COSTS,
        seeds=tuple(range(seeds)),
        total_timesteps=steps,
        eval_every=steps // 10,
    )
    start = time.perf_counter()
    run_sweep(spec, out, progress=False, cluster=cluster)
    print(json.dumps({"seconds": time.perf_counter() - start}))


def _noop() -> int:
    return 0


def job_round_trip(folder: Path, repeats: int) -> list[float]:
    """Seconds from submitting a no-op job to holding its result, through submitit's LocalExecutor."""
    import submitit

    executor = submitit.LocalExecutor(folder=folder)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        executor.submit(_noop).result()
        times.append(time.perf_counter() - start)
    return times


def worker_start(repeats: int) -> list[float]:
    """Seconds for a fresh Python to import what a worker imports before its batch starts."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        subprocess.run([sys.executable, "-c", "import amjax.sweep.runner"], check=True)
        times.append(time.perf_counter() - start)
    return times


def timed(args: argparse.Namespace, name: str, cluster: str | None) -> tuple[float, Path]:
    out = Path(args.out) / name
    command = [
        sys.executable,
        __file__,
        "--child",
        "--steps",
        str(args.steps),
        "--seeds",
        str(args.seeds),
        "--out",
        str(out),
    ] + (["--cluster", cluster] if cluster else [])
    child = subprocess.run(command, capture_output=True, text=True)
    if child.returncode != 0:
        raise SystemExit(f"{name}: the sweep failed (exit {child.returncode}):\n{child.stderr[-4000:]}")
    seconds = json.loads(child.stdout.strip().splitlines()[-1])["seconds"]
    print(f"{name}: {seconds:.1f} s", flush=True)
    return seconds, out


def same_rows(a: Path, b: Path) -> bool:
    key = ["config_id", "env_steps"]
    ra = pd.read_parquet(a / "results.parquet").sort_values(key).reset_index(drop=True)
    rb = pd.read_parquet(b / "results.parquet").sort_values(key).reset_index(drop=True)
    values = ["eval_return", "eval_measurements", "train_return", "loss"]
    return ra[key].equals(rb[key]) and np.allclose(
        ra[values].to_numpy(float), rb[values].to_numpy(float), rtol=1e-5, equal_nan=True
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=153_600, help="env steps per configuration")
    parser.add_argument("--seeds", type=int, default=8, help="seeds per (agent, cost): 8 gives 64 configurations")
    parser.add_argument("--workers", type=int, nargs="+", default=[2], help="local cluster sizes to time")
    parser.add_argument("--repeats", type=int, default=5, help="repeats of the per-task overhead probes")
    parser.add_argument("--out", default=None, help="scratch folder (default: a temporary one)")
    parser.add_argument("--markdown", default=None, help="where to write the table")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--cluster", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        run_child(args.steps, args.seeds, args.out, args.cluster)
        return
    from benchmarks.throughput.report import machine_info

    args.out = args.out or tempfile.mkdtemp(prefix="amjax_cluster_")
    load = os.getloadavg()[0]
    local_s, local_out = timed(args, "local", None)
    rows = [("local runner (both cores per batch)", local_s, None, True)]
    for workers in args.workers:
        seconds, out = timed(args, f"local_{workers}", f"local:{workers}")
        ran = json.loads((out / "metadata.json").read_text())["cluster_batches"]
        rows.append((f"cluster local:{workers}", seconds, ran, same_rows(local_out, out)))
    round_trip = job_round_trip(Path(args.out) / "noop_logs", args.repeats)
    start = worker_start(args.repeats)
    configs = 2 * len(COSTS) * args.seeds
    lines = [
        f"# Sweeps on a local cluster vs the local runner ({datetime.date.today()})",
        "",
        f"Machine: {machine_info()['cpu']}; load average "
        f"{load:.2f} at the start, {os.getloadavg()[0]:.2f} at the end. Sweep: PPO + Dueling DQN on CartPole-v0, "
        f"costs {', '.join(map(str, COSTS))} x {args.seeds} seeds = {configs} configurations x {args.steps:,} "
        "steps (one batch per agent).",
        "",
        "| run | wall s | vs local | same rows | where the batches ran (seconds of training per batch) |",
        "|---|---|---|---|---|",
    ]
    for name, seconds, ran, same in rows:
        where = (
            "-"
            if ran is None
            else "; ".join(
                f"{b.split('-')[0]}: {v['node']} pid {v['pid']}, {v['devices']} device(s), {v['seconds']} s"
                for b, v in sorted(ran.items())
            )
        )
        lines.append(f"| {name} | {seconds:.1f} | {seconds / local_s:.2f}x | {'yes' if same else 'NO'} | {where} |")
    lines += [
        "",
        f"Per-task overhead: a no-op job's round trip through submitit's LocalExecutor "
        f"{statistics.median(round_trip):.2f} s (median of {args.repeats}); a worker's start (Python + JAX + "
        f"amjax imports) {statistics.median(start):.2f} s.",
    ]
    text = "\n".join(lines) + "\n"
    print(text)
    path = Path(args.markdown or Path(__file__).parent / "results" / f"cluster_overhead_{datetime.date.today()}.md")
    path.write_text(text)
    print(f"written: {path}")


if __name__ == "__main__":
    main()
