"""How the benchmark measures: memory from the kernel, wall and CPU time of repeated or interleaved runs, and each
case in a fresh subprocess (this package run again with --child) so that its peak RSS is its own."""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]  # the repository: the child's working directory and import root


def peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def current_rss_mib() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def timed(run: Callable[..., Any], repeats: int, prepare: Callable[[], Any] | None = None) -> dict[str, Any]:
    """Run `run` `repeats` times (on `prepare()`'s result, made before the clock starts, if given); the fastest
    run's wall and CPU seconds, every run's wall time, and the fastest run's output."""
    times = []
    for _ in range(repeats):
        args = () if prepare is None else (prepare(),)
        start, cpu = time.perf_counter(), time.process_time()
        out = run(*args)
        times.append((time.perf_counter() - start, time.process_time() - cpu, out))
    best = min(times, key=lambda t: t[0])
    return {"run_s": best[0], "run_cpu_s": best[1], "run_all_s": [t[0] for t in times], "out": best[2]}


def interleaved(runs: dict[Any, Callable[[], Any]], rounds: int) -> dict[Any, list[float]]:
    """Wall times of each run, in alternation (a, b, b, a, ...), after one untimed run of each."""
    times: dict[Any, list[float]] = {key: [] for key in runs}
    for run in runs.values():
        run()  # warm-up: first-run allocations stay out of the timings
    for round_ in range(rounds):
        for key in list(runs) if round_ % 2 == 0 else list(runs)[::-1]:
            start = time.perf_counter()
            runs[key]()
            times[key].append(time.perf_counter() - start)
    return times


def overhead_figures(active: list[float], vanilla: list[float]) -> dict[str, Any]:
    """The active-measure program's extra time over the vanilla one, fastest vs fastest and median vs median."""
    import numpy as np

    active_s, vanilla_s = np.asarray(active), np.asarray(vanilla)
    return {
        "min": float(active_s.min() / vanilla_s.min() - 1),
        "median": float(np.median(active_s) / np.median(vanilla_s) - 1),
        # Paired by round: the spread of the per-round ratio says how far to trust the two figures above.
        "rounds": (active_s / vanilla_s - 1).tolist(),
        "active_s": active,
        "vanilla_s": vanilla,
    }


def _child_env(case: dict[str, Any]) -> dict[str, str]:
    """The child's environment: the repository importable, and its CPU device count. amjax takes one device per
    core on import unless told (--cores); the plain reference runs on one."""
    pythonpath = os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))
    if not case["impl"].startswith("amjax"):
        devices = {"JAX_NUM_CPU_DEVICES": "1"}
    else:
        devices = {"JAX_NUM_CPU_DEVICES": str(case["cores"])} if case["cores"] else {}
    return dict(os.environ, PYTHONPATH=pythonpath, **devices)


def run_case(case: dict[str, Any], timeout: float) -> dict[str, Any]:
    """Run one case in a fresh process (`python -m benchmarks.throughput --child CASE`); the case with its
    measurements and status "ok", or a status saying why there are none."""
    start = time.perf_counter()
    try:
        proc = subprocess.run(
            [sys.executable, "-m", "benchmarks.throughput", "--child", json.dumps(case)],
            capture_output=True,
            text=True,
            timeout=timeout,
            env=_child_env(case),
            cwd=str(ROOT),
        )
    except subprocess.TimeoutExpired:
        return {**case, "status": f"timeout after {timeout:.0f} s"}
    wall = time.perf_counter() - start
    for line in proc.stdout.splitlines():
        if line.startswith("RESULT "):
            result = {**case, **json.loads(line[len("RESULT ") :]), "status": "ok", "wall_s": wall}
            result["steps_per_s"] = result["configs"] * result["steps"] / result["run_s"]
            return result
    tail = (proc.stderr or proc.stdout).strip().splitlines()[-1:] or [f"exit {proc.returncode}"]
    return {**case, "status": f"failed: {tail[0][:200]}"}
