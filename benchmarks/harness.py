"""The one way a benchmark runs its cases and records them.

- Each case runs in a child process of its own (`run_child`): its peak resident memory is its own (the child
  reports the kernel's high-water mark of its own address space, `child_result`), and one case's compiled programs
  and allocator state cannot slow the next.
- Every record is one JSON line in `benchmarks/results/<bench>_<date>_<machine>.jsonl` (`Recorder`): first a "run"
  line naming the machine (CPU model, cores, memory, the JAX backend and device, jax version, commit, the command
  and the 1-minute load average at the start), then one "case" line per case, then an "end" line with the load at
  the end. A rerun on the same day and machine appends to the same file (each run has its own `run` id), so
  results files carry no ad-hoc suffixes: what differs between runs (settings, commit, options) is in the lines.
- The markdown tables the docs include are rendered from those lines (`markdown_table`; each benchmark's
  `render(records)`, rerun with `python -m benchmarks.harness render FILE.jsonl`), never written by hand.

A child is the benchmark's own script run again with `--child CASE_JSON`; it prints its measurements as the last
line of its output, `RESULT {json}` (`child_result`).
"""

from __future__ import annotations

import datetime
import importlib
import json
import os
import platform
import re
import resource
import shlex
import subprocess
import sys
import time
import uuid
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]  # the repository: children run there, with it importable
RESULTS = ROOT / "benchmarks" / "results"
RESULT_PREFIX = "RESULT "
PROGRESS_PREFIX = "PROGRESS "  # a child's measurements so far, kept if it runs out of time


# -- the machine ------------------------------------------------------------------------------------


def cpu_model() -> str:
    """The CPU's model name (/proc/cpuinfo; the platform's processor name elsewhere)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return re.sub(r"\s+", " ", line.split(":", 1)[1]).strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def memory_gib() -> float:
    return round(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30, 1)


def accelerator() -> dict[str, str]:
    """The default JAX backend and its first device, asked of a child process so this one never starts JAX (a
    benchmark's parent must not hold the device or the CPU device count its children set)."""
    code = "import jax; d = jax.devices()[0]; print(jax.default_backend(), jax.__version__, d.device_kind, sep='|')"
    try:
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT)
        backend, version, kind = out.stdout.strip().splitlines()[-1].split("|")
    except (subprocess.SubprocessError, ValueError, IndexError):
        return {"backend": "unknown", "jax": "unknown", "device": "unknown"}
    return {"backend": backend, "jax": version, "device": kind}


def commit() -> str:
    try:
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=ROOT)
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], capture_output=True, cwd=ROOT)
        return out.stdout.strip() + ("+changes" if dirty.stdout.strip() else "") if out.returncode == 0 else "unknown"
    except OSError:
        return "unknown"


def machine() -> dict[str, Any]:
    """What the numbers were taken on."""
    from amjax.cores import cpu_vector_isa  # imports JAX without starting it

    return {
        "host": platform.node(),
        "cpu": cpu_model(),
        "cpu_vector_isa": cpu_vector_isa(),  # rounding differed between two "AMD EPYC" with and without AVX-512
        "cpus": os.cpu_count(),
        "affinity": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "memory_gib": memory_gib(),
        "python": platform.python_version(),
        **accelerator(),
    }


def machine_slug(info: dict[str, Any]) -> str:
    """A short file-name part naming the machine: the device on an accelerator (e.g. "nvidia-h100-80gb-hbm3"),
    else the CPU's maker and family, its widest vector extension where known, and the usable cores (e.g.
    "amd-epyc-avx2-2c", "intel-xeon-avx-512-2c"). Two 2-core "AMD EPYC" machines, with and without AVX-512,
    compiled 2x apart (docs/results/benchmarks.md), so their runs go to different files."""
    if info.get("backend") not in ("cpu", "unknown", None):
        name = str(info["device"])
    else:
        words = re.sub(r"\(R\)|\(TM\)|CPU|Processor|@.*", " ", str(info["cpu"])).split()
        name = " ".join([*words[:2], info.get("cpu_vector_isa") or "", f"{info['affinity']}c"])
    return re.sub(r"[^a-z0-9]+", "-", name.lower()).strip("-") or "machine"


def results_path(bench: str, info: dict[str, Any], when: datetime.date | None = None) -> Path:
    """`benchmarks/results/<bench>_<date>_<machine>.jsonl`."""
    return RESULTS / f"{bench}_{(when or datetime.date.today()).isoformat()}_{machine_slug(info)}.jsonl"


# -- recording --------------------------------------------------------------------------------------


def command_line() -> str:
    """The command that is running, as a user would type it from the repository: `python -m PACKAGE ...` for a
    package's `__main__.py`, else `python benchmarks/SCRIPT.py ...` (arguments quoted as a shell needs)."""
    script = Path(sys.argv[0]).resolve()
    if script.name == "__main__.py":  # an installed package's (`python -m pytest`): its name alone
        parts = script.parent.relative_to(ROOT).parts if script.is_relative_to(ROOT) else (script.parent.name,)
        head = ["python", "-m", ".".join(parts)]
    else:
        head = ["python", str(script.relative_to(ROOT)) if script.is_relative_to(ROOT) else script.name]
    return shlex.join([*head, *sys.argv[1:]])


class Recorder:
    """Appends one benchmark run's records to its JSON-lines file (see the module docstring)."""

    def __init__(self, bench: str, settings: dict[str, Any], out: str | Path | None = None):
        self.bench = bench
        self.info = machine()
        self.path = Path(out) if out else results_path(bench, self.info)
        self.run = uuid.uuid4().hex[:8]
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._write(
            {
                "kind": "run",
                "bench": bench,
                "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
                "commit": commit(),
                "command": command_line(),
                "settings": settings,
                "machine": self.info,
                "load_start": round(os.getloadavg()[0], 2),
            }
        )

    def _write(self, record: dict[str, Any]) -> None:
        with open(self.path, "a") as f:
            f.write(json.dumps({**record, "run": self.run}, default=str) + "\n")

    def case(self, record: dict[str, Any]) -> dict[str, Any]:
        """Record one case's measurements (and print them); returns the record."""
        self._write({"kind": "case", **record})
        print(json.dumps(record, default=str), flush=True)
        return record

    def end(self) -> None:
        self._write({"kind": "end", "load_end": round(os.getloadavg()[0], 2)})


def read_runs(path: str | Path) -> list[dict[str, Any]]:
    """Every run of a results file: its "run" record with its `cases` (a list) and `load_end` added."""
    runs: dict[str, dict[str, Any]] = {}
    for line in Path(path).read_text().splitlines():
        if not line.strip():
            continue
        record = json.loads(line)
        if record["kind"] == "run":
            runs[record["run"]] = {**record, "cases": [], "load_end": None}
        elif record["run"] in runs:
            if record["kind"] == "case":
                runs[record["run"]]["cases"].append(record)
            else:
                runs[record["run"]]["load_end"] = record.get("load_end")
    return list(runs.values())


def describe(run: dict[str, Any]) -> str:
    """One sentence naming where and when a run was taken."""
    m = run["machine"]
    device = f"{m['device']} ({m['backend']})" if m["backend"] != "cpu" else f"{m['affinity']} usable cores"
    ended = f" -> {run['load_end']}" if run["load_end"] is not None else " (the run stopped before its end)"
    load = f"load average {run['load_start']}{ended}"
    cpu = f"{m['cpu']} ({m['cpu_vector_isa']})" if m.get("cpu_vector_isa") else m["cpu"]  # two EPYCs differ 2x
    return (
        f"{run['date'][:16].replace('T', ' ')} UTC, commit {run['commit']}, `{run['command']}`; {cpu}, "
        f"{device}, {m['memory_gib']} GiB, jax {m['jax']}; {load}."
    )


def markdown_table(rows: Sequence[dict[str, Any]], columns: Sequence[tuple[str, Callable[[dict], Any]]]) -> str:
    """A markdown table: one row per record, `columns` = (header, value of a record) pairs; columns of numbers
    (with "-" or blanks where a row has none) right-aligned, integers with thousands separators."""

    def cell(value: Any) -> str:
        if isinstance(value, bool) or value is None:
            return "" if value is None else str(value)
        if isinstance(value, int):
            return f"{value:,}"
        return str(value)

    values = [[f(row) for _, f in columns] for row in rows]

    def is_number(value: Any) -> bool:
        return isinstance(value, int | float) and not isinstance(value, bool)

    def right_aligned(i: int) -> bool:  # numbers, with "-" or blanks where a row has none
        cells = [row[i] for row in values]
        return any(map(is_number, cells)) and all(is_number(v) or v in ("-", "", None) for v in cells)

    numeric = [right_aligned(i) for i in range(len(columns))]
    lines = [
        "| " + " | ".join(header for header, _ in columns) + " |",
        "|" + "|".join("---:" if is_number else "---" for is_number in numeric) + "|",
    ]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in values]
    return "\n".join(lines) + "\n"


def write_markdown(path: str | Path, render: Callable[[list[dict[str, Any]]], str]) -> Path:
    """Render a results file's runs with `render` into the .md beside it (what the docs include)."""
    target = Path(path).with_suffix(".md")
    target.write_text(render(read_runs(path)))
    return target


# -- children ---------------------------------------------------------------------------------------


def run_child(
    script: str | Path, case: dict[str, Any], timeout: float | None = None, env: dict[str, str] | None = None
) -> dict[str, Any]:
    """Run `python SCRIPT --child CASE_JSON` in the repository; the child's `RESULT` record with `peak_rss_mib` (the
    child's own, from the kernel), `wall_s` and `status` "ok" added, or the case with a `status` saying why there
    are no measurements (a timeout, or the child's last line of errors) and, after a timeout, the last record the
    child printed with `child_progress` as `partial`."""
    pythonpath = os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))
    command = [sys.executable, str(script), "--child", json.dumps(case)]
    start = time.perf_counter()
    proc = subprocess.Popen(
        command,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": pythonpath, **(env or {})},
    )
    try:
        stdout, stderr = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        stdout, _ = proc.communicate()
        stopped = {**case, "status": f"timeout after {timeout:.0f} s"}
        for line in reversed((stdout or "").splitlines()):
            if line.startswith(PROGRESS_PREFIX):
                return {**stopped, "partial": json.loads(line[len(PROGRESS_PREFIX) :])}
        return stopped
    wall = time.perf_counter() - start
    for line in reversed(stdout.splitlines()):
        if line.startswith(RESULT_PREFIX):
            result = json.loads(line[len(RESULT_PREFIX) :])
            return {**case, **result, "wall_s": round(wall, 3), "status": "ok"}
    tail = (stderr or stdout).strip().splitlines()[-1:] or [f"exit {proc.returncode}"]
    return {**case, "status": f"failed: {tail[0][:300]}"}


def peak_rss_mib() -> float:
    """This process's peak resident memory so far: the kernel's high-water mark of its own address space (VmHWM).
    Not `getrusage`'s ru_maxrss, which on Linux starts a child at its parent's peak (the parent's is carried over
    at fork and exec), so a small case under a large parent would report the parent's memory."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024  # kB
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # elsewhere (KiB on Linux, bytes on macOS)


def settings_of(args: Any) -> dict[str, Any]:
    """A command line's arguments (an argparse namespace) as a run's settings, without the internal `--child`."""
    return {name: value for name, value in vars(args).items() if name != "child"}


def run_cases(
    bench: str,
    settings: dict[str, Any],
    out: str | Path | None,
    script: str | Path,
    cases: Iterable[dict[str, Any]],
    render: Callable[[list[dict[str, Any]]], str],
    timeout: float | None = None,
) -> Path:
    """A whole benchmark run: each case in its own child (`run_child`), recorded as it finishes, the markdown
    rendered again after each case (a run cut short keeps the rows it has); prints this run's tables and returns
    the results file."""
    recorder = Recorder(bench, settings, out)
    for case in cases:
        recorder.case(run_child(script, case, timeout=timeout))
        write_markdown(recorder.path, render)
    recorder.end()
    markdown = write_markdown(recorder.path, render)
    print(render([run for run in read_runs(recorder.path) if run["run"] == recorder.run]))
    print(f"written to {recorder.path} and {markdown}")
    return recorder.path


def time_training_batch(algo: Any, items: Sequence[Any], keys: Any, profile_top: int = 0) -> dict[str, Any]:
    """Compile and run validated configs `items` (one static key) of `algo` with `keys` as one vmapped training
    program split over this process's CPU devices, as a sweep runs a batch; the compile and run seconds, the env
    steps per second of the run (all configurations together, evaluations included) and the median final test
    costed return. With `profile_top` > 0, one more run is traced (`profiles.profile_call`, under "profile": its
    `profile_top` costliest source lines, ops and kernels). JAX is imported here, so a child can set its device count
    before."""
    import jax
    import jax.numpy as jnp

    from amjax.agents import stack_configs
    from amjax.agents.training import init_run, run_evals
    from amjax.sweep.devices import config_sharding, sharded_jit

    config, num_evals, total = stack_configs(list(items)), items[0].num_evals, items[0].total_timesteps
    cpus = jax.devices("cpu")

    def eval_returns(c: Any, k: Any) -> Any:
        return run_evals(algo, c, init_run(algo, c, k), num_evals)[1].test.costed_return

    train = sharded_jit(jax.vmap(eval_returns), cpus, in_shardings=config_sharding(cpus))
    config, keys = jax.device_put((config, keys), config_sharding(cpus))
    start = time.perf_counter()
    compiled = train.lower(config, keys).compile()
    compile_s = time.perf_counter() - start
    start = time.perf_counter()
    returns = jax.block_until_ready(compiled(config, keys))
    run_s = time.perf_counter() - start
    timing = {
        "steps_per_config": total,
        "compile_s": round(compile_s, 1),
        "run_s": round(run_s, 1),
        "env_steps_per_s": round(len(items) * total / run_s),
        "final_eval_return_median": round(float(jnp.median(returns[:, -1])), 1),
    }
    if profile_top > 0:
        from benchmarks.profiles import profile_call

        run = lambda: jax.block_until_ready(compiled(config, keys))  # noqa: E731
        timing["profile"] = profile_call(run, [compiled.as_text()], profile_top)
    return timing


def child_progress(measurements: dict[str, Any]) -> None:
    """In a child: print the measurements so far, which `run_child` keeps (as `partial`) if the child runs out of
    time before `child_result`."""
    print(PROGRESS_PREFIX + json.dumps(measurements, default=str), flush=True)


def child_result(measurements: dict[str, Any]) -> None:
    """In a child: print the measurements, with the child's own peak memory (`peak_rss_mib`), as the record
    `run_child` reads."""
    record = {**measurements, "peak_rss_mib": round(peak_rss_mib())}
    print(RESULT_PREFIX + json.dumps(record, default=str), flush=True)


def main(argv: list[str] | None = None) -> int:
    """`python -m benchmarks.harness render FILE.jsonl ...`: re-render each file's markdown with its benchmark's
    `render` (the module named by the file's "bench" field)."""
    args = list(sys.argv[1:] if argv is None else argv)
    if len(args) < 2 or args[0] != "render":
        print("usage: python -m benchmarks.harness render FILE.jsonl [FILE.jsonl ...]", file=sys.stderr)
        return 2
    for path in args[1:]:
        bench = read_runs(path)[0]["bench"]
        module = importlib.import_module(f"benchmarks.{bench}")
        print(write_markdown(path, module.render))
    return 0


if __name__ == "__main__":
    sys.exit(main())
