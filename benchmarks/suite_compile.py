"""Where the test suite's time goes: per test file, the programs XLA compiled, the seconds spent compiling, tracing
and lowering them, and the hits of the persistent compile cache (JAX's monitoring events), beside the tests' wall
time. What a fresh machine pays (issue 52) is the cold run, with an empty compile cache.

    python benchmarks/suite_compile.py                      # the default tier, cache empty (~11 min on 2 cores)
    python benchmarks/suite_compile.py --cache DIR          # the same, filling DIR (kept) with what it compiles
    python benchmarks/suite_compile.py --tier slow --cache DIR   # then the slow tier on it, as CI runs (~54 min)
    python benchmarks/suite_compile.py --warm               # with the suite's own cache: what a second run pays
    python benchmarks/suite_compile.py -- tests/agents/test_algorithms.py   # pytest's arguments after `--`
    python benchmarks/suite_compile.py --per-test tests.jsonl              # also every test's record, appended

The run is `python -m pytest -q -p benchmarks.suite_compile ...` (this module is also the pytest plugin that
listens to JAX's events, in each xdist worker) with `JAX_COMPILATION_CACHE_DIR` set to a new empty folder unless
`--warm` or `--cache`. Its records go through the harness into `results/suite_compile_<date>_<machine>.jsonl`: one
case per test file, then the tier's totals with its 20 slowest tests (and, for the default tier with an empty
cache, how many tests took over the slow tier's 20 s); the `.md` beside it is rendered from them. Programs compiled
in a process a test starts (the command line, notebook kernels, killed children) are in the wall time, not in the
program counts.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import pytest

if not __package__:  # run as a file: the repository importable, for `benchmarks.harness`
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks import harness  # noqa: E402

RECORDS_ENV = "AMJAX_SUITE_COMPILE_RECORDS"  # the folder each pytest process writes its tests' records to
_EVENTS = {  # JAX's duration events (jax/_src/dispatch.py, compiler.py) -> the record's field
    "/jax/core/compile/backend_compile_duration": "compile_s",
    "/jax/core/compile/jaxpr_trace_duration": "trace_s",
    "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower_s",
    "/jax/compilation_cache/cache_retrieval_time_sec": "cache_load_s",
}
SLOW_S = 20  # a test over this many seconds with an empty cache belongs in the slow tier (tests/conftest.py)
FIELDS = ("tests", "wall_s", "programs", "compile_s", "trace_s", "lower_s", "cache_hits", "cache_load_s")


# -- the pytest plugin (loaded in each pytest process by `-p benchmarks.suite_compile`) -----------------------------


class _Listener:
    """Sums JAX's compile events per test while the test runs (setup, call and teardown)."""

    def __init__(self) -> None:
        self.current = "<collection>"
        self.records: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)

    def duration(self, event: str, seconds: float, **_: Any) -> None:
        field = _EVENTS.get(event)
        if field:
            self.records[self.current][field] += seconds
            if field == "compile_s":
                self.records[self.current]["programs"] += 1

    def event(self, event: str, **_: Any) -> None:
        if event == "/jax/compilation_cache/cache_hits":
            self.records[self.current]["cache_hits"] += 1


_listener: _Listener | None = None


def pytest_configure(config: Any) -> None:
    global _listener
    if os.environ.get(RECORDS_ENV) and _listener is None:
        import jax.monitoring

        _listener = _Listener()
        jax.monitoring.register_event_duration_secs_listener(_listener.duration)
        jax.monitoring.register_event_listener(_listener.event)


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_protocol(item: Any, nextitem: Any) -> None:
    if _listener is not None:
        _listener.current = item.nodeid
        _listener.records[item.nodeid]["tests"] = 1


def pytest_runtest_logreport(report: Any) -> None:
    if _listener is not None and report.nodeid in _listener.records:
        _listener.records[report.nodeid]["wall_s"] += report.duration


def pytest_unconfigure(config: Any) -> None:
    folder = os.environ.get(RECORDS_ENV)
    if _listener is None or not folder:
        return
    worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
    with open(Path(folder) / f"{worker}-{os.getpid()}.jsonl", "w") as out:
        for test, counts in _listener.records.items():
            out.write(json.dumps({"test": test, **{k: round(v, 3) for k, v in counts.items()}}) + "\n")


# -- the run and its records -----------------------------------------------------------------------------------------


def read_records(folder: str | Path) -> list[dict[str, Any]]:
    """Every test's record that the pytest processes wrote into `folder`."""
    return [json.loads(line) for path in sorted(Path(folder).glob("*.jsonl")) for line in path.read_text().splitlines()]


def by_file(records: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The records summed per test file (work outside any test, such as collection, under its own name), most
    worker-seconds first."""
    files: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
    for record in records:
        name = record["test"].split("::")[0]
        files[name].update({field: record.get(field, 0) for field in FIELDS})
    counted = ("tests", "programs", "cache_hits")
    rows = [
        {"file": name, **{f: int(counts[f]) if f in counted else round(counts[f], 1) for f in FIELDS}}
        for name, counts in files.items()
    ]
    return sorted(rows, key=lambda row: (-row["wall_s"], -row["compile_s"]))


def compile_cache(warm: bool, cache: str | None, scratch: Path) -> tuple[str | None, str]:
    """The compile cache folder a run sets (None: the suite's own, tests/conftest.py) and its state, "empty" or
    "warm": `cache` (kept after the run) or a new folder under `scratch`, empty unless `cache` holds entries."""
    if warm:
        return None, "warm"
    folder = Path(cache) if cache else scratch / "cache"
    return str(folder), "warm" if folder.is_dir() and any(folder.iterdir()) else "empty"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tier", choices=("default", "slow", "all"), default="default", help="the suite's tier")
    caches = parser.add_mutually_exclusive_group()
    caches.add_argument("--warm", action="store_true", help="use the suite's own compile cache instead of an empty one")
    caches.add_argument("--cache", help="use this compile cache folder and keep what the run compiles into it")
    parser.add_argument("--out", help="the results file (default: results/suite_compile_<date>_<machine>.jsonl)")
    parser.add_argument("--per-test", help="also append every test's record, with its run's id, to this file")
    parser.add_argument("pytest_args", nargs="*", help="test paths or pytest options (after --)")
    args = parser.parse_args(argv)

    with tempfile.TemporaryDirectory(prefix="suite-compile-") as scratch:
        env = {**os.environ, RECORDS_ENV: str(Path(scratch) / "records")}
        Path(env[RECORDS_ENV]).mkdir()
        folder, state = compile_cache(args.warm, args.cache, Path(scratch))
        if folder:
            env["JAX_COMPILATION_CACHE_DIR"] = folder
        command = [sys.executable, "-m", "pytest", "-q", "-p", "benchmarks.suite_compile", "--tier", args.tier]
        settings = {"tier": args.tier, "cache": state, "pytest": args.pytest_args}
        recorder = harness.Recorder("suite_compile", settings, args.out)
        start = time.perf_counter()
        status = subprocess.run([*command, *args.pytest_args], cwd=harness.ROOT, env=env).returncode
        wall = time.perf_counter() - start
        records = read_records(env[RECORDS_ENV])
    if args.per_test:  # appended, each record with its run's id, as the harness appends runs to one file
        with open(args.per_test, "a") as out:
            out.writelines(json.dumps({"run": recorder.run, **record}) + "\n" for record in records)
    for row in by_file(records):
        recorder.case({"case": row["file"], "status": "ok", **row})
    totals = {f: round(sum(r.get(f, 0) for r in records), 1) for f in FIELDS}
    slowest = sorted(records, key=lambda r: -r.get("wall_s", 0))[:20]
    over = [r for r in records if r["test"] != "<collection>" and r.get("wall_s", 0) > SLOW_S]
    recorder.case(
        {
            "case": "total",
            "status": "ok" if status == 0 else f"pytest exited {status}",
            "wall_clock_s": round(wall, 1),
            **totals,
            "slowest": [{k: r.get(k, 0) for k in ("test", "wall_s", "programs", "compile_s")} for r in slowest],
            "over_slow_s": len(over) if args.tier == "default" and state == "empty" else None,
        }
    )
    recorder.end()
    print(f"\n{harness.write_markdown(recorder.path, render)}")
    return status


def render(runs: list[dict[str, Any]]) -> str:
    """Per run: the totals, the files by worker-seconds and the slowest tests."""
    out = ["# Where the test suite's time goes\n"]
    for run in runs:
        cases = [c for c in run["cases"] if c["case"] != "total"]
        total = next((c for c in run["cases"] if c["case"] == "total"), None)
        settings = run["settings"]
        out.append(f"\n## {settings['tier']} tier, compile cache {settings['cache']}\n\n{harness.describe(run)}\n")
        if total:
            out.append(
                f"\n{total['tests']:,.0f} tests in {total['wall_clock_s'] / 60:.1f} min ({total['status']}): "
                f"{total['programs']:,.0f} programs compiled in {total['compile_s']:,.0f} s, tracing "
                f"{total['trace_s']:,.0f} s, lowering {total['lower_s']:,.0f} s, {total['cache_hits']:,.0f} loaded "
                f"from the cache; the tests' own time {total['wall_s']:,.0f} worker-seconds.\n"
            )
            if total.get("over_slow_s") is not None:
                out.append(f"Default-tier tests over the slow tier's {SLOW_S} s: {total['over_slow_s']}.\n")
        columns = [("file", lambda c: c["case"])] + [(f, lambda c, f=f: c[f]) for f in FIELDS]
        out.append("\n" + harness.markdown_table(cases, columns))
        if total:
            slow = [("test", lambda t: t["test"]), ("wall_s", lambda t: round(t["wall_s"], 1))]
            slow += [("programs", lambda t: int(t["programs"])), ("compile_s", lambda t: round(t["compile_s"], 1))]
            out.append("\nThe slowest tests:\n\n" + harness.markdown_table(total["slowest"], slow))
    return "".join(out)


if __name__ == "__main__":
    sys.exit(main())
