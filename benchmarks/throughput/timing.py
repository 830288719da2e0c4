"""How the benchmark measures: wall and CPU time of repeated or interleaved runs, resident memory before compiling,
and each case in a fresh subprocess (benchmarks/throughput/__main__.py run again with --child, through
`benchmarks.harness.run_child`) so that its peak RSS, which the child reports with `harness.child_result`, is its
own."""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from benchmarks import harness

CHILD = Path(__file__).with_name("__main__.py")  # the script each case runs in: `python CHILD --child CASE_JSON`


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
    """What the child's environment adds to this one's (the harness makes the repository importable): its CPU device
    count where it is not one per core. amjax's cases take one per core in the child (`runners.run_child` calls
    `amjax.use_all_cores()`, which keeps a count set here) unless --cores sets it; every other case (the plain
    reference, the interleaved overhead pair) runs on one."""
    if not case["impl"].startswith("amjax"):
        return {"JAX_NUM_CPU_DEVICES": "1"}
    return {"JAX_NUM_CPU_DEVICES": str(case["cores"])} if case["cores"] else {}


def run_case(case: dict[str, Any], timeout: float) -> dict[str, Any]:
    """Run one case in a fresh process (`harness.run_child`); the case with its measurements (the child's peak RSS
    and the aggregate env-steps/s included) and status "ok", or a status saying why there are none."""
    result = harness.run_child(CHILD, case, timeout=timeout, env=_child_env(case))
    if result["status"] == "ok":
        result["steps_per_s"] = result["configs"] * result["steps"] / result["run_s"]
    return result
