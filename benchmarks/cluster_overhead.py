"""A sweep on a local submitit cluster against the local runner, in one invocation (issue 18).

Times the same 64-configuration PPO + Dueling DQN sweep on CartPole-v0 (costs 0 / 0.1 / 0.2 / 0.3 x 8 seeds per
agent) three ways, each in its own child process started the way a user starts it (`amjax.use_all_cores()` first):
the local runner (one batch per agent, each spread over both cores), and `cluster="local:N"` for each N of
`--workers` (a batch per worker process, the cores split between them). It checks that every cluster run's rows
equal the local run's, and measures the engine's own cost per task: a no-op job's round trip through submitit's
LocalExecutor, and a worker's start (Python, JAX and amjax imported) before its batch begins.

Each sweep and each probe runs in a child process of `benchmarks.harness` (`run_child`), one after the other, as
before; the parent compares the sweeps' rows (in the `--scratch` folder) once they are written. The cluster runs'
workers are the children's own children (submitit's LocalExecutor), so a record's `peak_rss_mib` is the launching
process's alone. The records go to benchmarks/results/cluster_overhead_<date>_<machine>.jsonl (or `--out`) and the
markdown table is rendered beside it.

    python benchmarks/cluster_overhead.py    # benchmarks/results/cluster_overhead_<date>_<machine>.jsonl / .md
    python benchmarks/cluster_overhead.py --steps 10240 --seeds 1 --workers 2 --repeats 1 --out /tmp/cl.jsonl  # smoke
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

if not __package__:  # run as a file: the repository importable, for `benchmarks.harness`
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks import harness  # noqa: E402

COSTS = (0.0, 0.1, 0.2, 0.3)


def run_sweep_case(steps: int, seeds: int, out: str, cluster: str | None) -> dict[str, Any]:
    """One timed sweep in this (child) process: its seconds, and where a cluster run's batches ran."""
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
    result: dict[str, Any] = {"seconds": round(time.perf_counter() - start, 2)}
    if cluster:
        result["cluster_batches"] = json.loads((Path(out) / "metadata.json").read_text())["cluster_batches"]
    return result


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


def run_case(case: dict[str, Any]) -> dict[str, Any]:
    """One case in this (child) process: a sweep, or one of the per-task overhead probes."""
    if case["case"] == "job_round_trip":
        return {"seconds": [round(t, 3) for t in job_round_trip(Path(case["folder"]), case["repeats"])]}
    if case["case"] == "worker_start":
        return {"seconds": [round(t, 3) for t in worker_start(case["repeats"])]}
    return run_sweep_case(case["steps"], case["seeds"], case["folder"], case["cluster"])


def same_rows(a: Path, b: Path) -> bool:
    import numpy as np
    import pandas as pd

    key = ["config_id", "env_steps"]
    ra = pd.read_parquet(a / "results.parquet").sort_values(key).reset_index(drop=True)
    rb = pd.read_parquet(b / "results.parquet").sort_values(key).reset_index(drop=True)
    values = ["eval_return", "eval_measurements", "train_return", "loss"]
    return ra[key].equals(rb[key]) and np.allclose(
        ra[values].to_numpy(float), rb[values].to_numpy(float), rtol=1e-5, equal_nan=True
    )


def _where(r: dict[str, Any]) -> str:
    """Where a cluster run's batches ran (seconds of training per batch)."""
    if not r.get("cluster_batches"):
        return "-"
    return "; ".join(
        f"{b.split('-')[0]}: {v['node']} pid {v['pid']}, {v['devices']} device(s), {v['seconds']} s"
        for b, v in sorted(r["cluster_batches"].items())
    )


def render(runs: list[dict[str, Any]]) -> str:
    """The markdown of a results file: one table per run, each sweep's seconds against the local runner's of the
    same run, and the per-task overhead probes' medians."""
    parts = []
    for run in runs:
        settings, cases = run["settings"], run["cases"]
        ok = [r for r in cases if r["status"] == "ok"]
        sweeps = [r for r in ok if r["case"] not in ("job_round_trip", "worker_start")]
        local = next((r["seconds"] for r in sweeps if r["cluster"] is None), None)
        probes = {r["case"]: r["seconds"] for r in ok if r["case"] in ("job_round_trip", "worker_start")}
        configs = 2 * len(COSTS) * settings["seeds"]
        overhead = []
        if "job_round_trip" in probes:
            overhead.append(
                "a no-op job's round trip through submitit's LocalExecutor "
                f"{statistics.median(probes['job_round_trip']):.2f} s (median of {len(probes['job_round_trip'])})"
            )
        if "worker_start" in probes:
            overhead.append(
                f"a worker's start (Python + JAX + amjax imports) {statistics.median(probes['worker_start']):.2f} s"
            )
        parts.append(
            f"# Sweeps on a local cluster vs the local runner ({run['date'][:10]})\n\n"
            f"Sweep: PPO + Dueling DQN on CartPole-v0, costs {', '.join(map(str, COSTS))} x {settings['seeds']} "
            f"seeds = {configs} configurations x {settings['steps']:,} steps (one batch per agent). Each run in its "
            f"own process, one after the other. {harness.describe(run)}\n\n"
            + harness.markdown_table(
                sweeps,
                [
                    (
                        "run",
                        lambda r: (
                            "local runner (both cores per batch)" if r["cluster"] is None else f"cluster {r['cluster']}"
                        ),
                    ),
                    ("wall s", lambda r: f"{r['seconds']:.1f}"),
                    ("vs local", lambda r, local=local: f"{r['seconds'] / local:.2f}x" if local else ""),
                    (
                        "same rows",
                        lambda r: (
                            "yes" if r["cluster"] is None else {True: "yes", False: "NO"}.get(r.get("same_rows"), "-")
                        ),
                    ),
                    ("where the batches ran (seconds of training per batch)", _where),
                ],
            )
            + (f"\nPer-task overhead: {'; '.join(overhead)}.\n" if overhead else "")
            + "".join(f"\n{r['case']}: {r['status']}\n" for r in cases if r["status"] != "ok")
        )
    return "\n".join(parts)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=153_600, help="env steps per configuration")
    parser.add_argument("--seeds", type=int, default=8, help="seeds per (agent, cost): 8 gives 64 configurations")
    parser.add_argument("--workers", type=int, nargs="+", default=[2], help="local cluster sizes to time")
    parser.add_argument("--repeats", type=int, default=5, help="repeats of the per-task overhead probes")
    parser.add_argument(
        "--out",
        help="results file to append to (default: benchmarks/results/cluster_overhead_<date>_<machine>.jsonl; the "
        "markdown table is written beside it)",
    )
    parser.add_argument("--scratch", default=None, help="folder for the sweeps' outputs (default: a temporary one)")
    parser.add_argument("--markdown", default=None, help="also write the rendered table here")
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        harness.child_result(run_case(json.loads(args.child)))
        return 0

    scratch = Path(args.scratch or tempfile.mkdtemp(prefix="amjax_cluster_"))
    settings = harness.settings_of(args)
    recorder = harness.Recorder("cluster_overhead", {**settings, "scratch": str(scratch)}, args.out)
    sweep = {"steps": args.steps, "seeds": args.seeds}
    local = recorder.case(
        harness.run_child(__file__, {"case": "local", **sweep, "folder": str(scratch / "local"), "cluster": None})
    )
    for workers in args.workers:
        name = f"local_{workers}"
        case = {"case": name, **sweep, "folder": str(scratch / name), "cluster": f"local:{workers}"}
        record = harness.run_child(__file__, case)
        if record["status"] == "ok" and local["status"] == "ok":
            record["same_rows"] = bool(same_rows(scratch / "local", scratch / name))
        recorder.case(record)
    recorder.case(
        harness.run_child(
            __file__, {"case": "job_round_trip", "repeats": args.repeats, "folder": str(scratch / "noop_logs")}
        )
    )
    recorder.case(harness.run_child(__file__, {"case": "worker_start", "repeats": args.repeats}))
    recorder.end()
    markdown = harness.write_markdown(recorder.path, render)
    if args.markdown:
        Path(args.markdown).write_text(markdown.read_text())
    print(f"written to {recorder.path} and {markdown}" + (f" (and {args.markdown})" if args.markdown else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
