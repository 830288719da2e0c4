"""Where a sweep's time goes on an accelerator: amjax's sweep programs and the plain reference compiled in one
process, timed in alternation, then each profiled for one run; device time is summed per HLO op and per source line.

    python benchmarks/gpu_profile.py --agent ppo --configs 1024 --steps 51200 --out DIR

Writes DIR/profile_<agent>_<configs>.md (the wall times, kernel counts, device busy time, and the ops and source
lines that take the most device time in each implementation) and the same as JSON. On a CPU it runs too (the
figures are then the CPU's thunks), which is how the script is checked before a GPU session.
"""

from __future__ import annotations

import argparse
import gzip
import json
import re
import shutil
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import jax  # noqa: E402

from benchmarks.throughput import runners  # noqa: E402
from benchmarks.throughput.cases import _default_buffer, _round_steps, _steps_per_update  # noqa: E402
from benchmarks.throughput.timing import interleaved  # noqa: E402

_INSTRUCTION = re.compile(r"^\s*(?:ROOT\s+)?%?([\w.\-]+)\s*=\s*.*?metadata=\{([^}]*)\}")
_FIELD = re.compile(r'(\w+)=(?:"((?:[^"\\]|\\.)*)"|(\S+))')
_TABLE_ROW = re.compile(r"^(\d+) (?:\"(.*)\"|\{(.*)\})$")


def _tables(hlo_text: str) -> dict[str, dict[int, Any]]:
    """The module's FileNames, FunctionNames, FileLocations and StackFrames tables."""
    tables: dict[str, dict[int, Any]] = {}
    current = None
    for line in hlo_text.splitlines():
        if line in ("FileNames", "FunctionNames", "FileLocations", "StackFrames"):
            current = tables.setdefault(line, {})
            continue
        match = _TABLE_ROW.match(line) if current is not None else None
        if not match:
            current = None if not line.strip() else current
            continue
        value = (
            match.group(2)
            if match.group(2) is not None
            else dict((k, int(v)) for k, v in re.findall(r"(\w+)=(-?\d+)", match.group(3)))
        )
        current[int(match.group(1))] = value
    return tables


def hlo_sources(hlo_text: str, depth: int = 2) -> dict[str, str]:
    """Instruction name -> its innermost `depth` source frames ('file:line function < ...') and the primitive,
    from an optimised HLO module's metadata."""
    tables = _tables(hlo_text)
    files, functions = tables.get("FileNames", {}), tables.get("FunctionNames", {})
    locations, frames = tables.get("FileLocations", {}), tables.get("StackFrames", {})

    def where(frame_id: int) -> str:
        parts = []
        while frame_id in frames and len(parts) < depth:
            location = locations.get(frames[frame_id]["file_location_id"], {})
            file = Path(files.get(location.get("file_name_id"), "?")).name
            parts.append(f"{file}:{location.get('line', '?')} {functions.get(location.get('function_name_id'), '?')}")
            parent = frames[frame_id].get("parent_frame_id", frame_id)
            frame_id = -1 if parent == frame_id else parent
        return " < ".join(parts) or "?"

    sources = {}
    for line in hlo_text.splitlines():
        match = _INSTRUCTION.match(line)
        if not match:
            continue
        fields = {k: a or b for k, a, b in _FIELD.findall(match.group(2))}
        op = fields.get("op_name", "").split("/")[-1]
        frame = int(fields["stack_frame_id"]) if "stack_frame_id" in fields else -1
        sources[match.group(1)] = f"{where(frame)} ({op})"
    return sources


def device_events(trace_dir: Path) -> list[dict[str, Any]]:
    """The trace's op events on the accelerator (or, with none, every event naming an HLO op)."""
    trace = next(trace_dir.rglob("perfetto_trace.json.gz"))
    with gzip.open(trace) as f:
        events = json.load(f)
    events = events["traceEvents"] if isinstance(events, dict) else events
    names = {e["pid"]: e["args"]["name"] for e in events if e.get("ph") == "M" and e.get("name") == "process_name"}
    gpu_pids = {pid for pid, name in names.items() if "/device:" in name and "CPU" not in name.upper()}
    ops = [e for e in events if e.get("ph") == "X" and "hlo_op" in e.get("args", {})]
    on_device = [e for e in ops if e["pid"] in gpu_pids]
    return on_device or ops


def summarise(events: list[dict[str, Any]], sources: dict[str, str], top: int) -> dict[str, Any]:
    by_op: dict[str, list[float]] = defaultdict(lambda: [0, 0.0])
    by_source: dict[str, list[float]] = defaultdict(lambda: [0, 0.0])
    by_kernel: dict[str, list[float]] = defaultdict(lambda: [0, 0.0])
    # A kernel inside a command buffer (a CUDA graph) names the buffer as its op; its own name is the fusion's,
    # with "_" for "." (the HLO name).
    underscored = {name.replace(".", "_"): source for name, source in sources.items()}
    for e in events:
        op = e["args"]["hlo_op"]
        source = sources.get(op) or underscored.get(e["name"], "?")
        kernel = f"{e['name'][:60]} in {op}: {underscored.get(e['name'], '')}"
        for table, key in ((by_op, op), (by_source, source), (by_kernel, kernel)):
            table[key][0] += 1
            table[key][1] += e["dur"]
    busy_us = sum(e["dur"] for e in events)
    span_us = (max(e["ts"] + e["dur"] for e in events) - min(e["ts"] for e in events)) if events else 0.0

    def rows(table):
        ranked = sorted(table.items(), key=lambda kv: -kv[1][1])[:top]
        share = 1.0 / busy_us if busy_us else 0.0
        return [{"name": k, "count": int(c), "ms": t / 1e3, "share": t * share} for k, (c, t) in ranked]

    return {
        "kernels": len(events),
        "busy_ms": busy_us / 1e3,
        "span_ms": span_us / 1e3,
        "top_ops": rows(by_op),
        "top_sources": rows(by_source),
        "top_kernels": rows(by_kernel),
    }


def _kernel_figures(summary: dict[str, Any]) -> str:
    if "kernels" not in summary:
        return ""
    return f"; {summary['kernels']} kernels; busy {summary['busy_ms']:.0f} ms of a {summary['span_ms']:.0f} ms span"


def build(case: dict[str, Any]) -> dict[str, Any]:
    """impl -> (run, optimised HLO texts) for amjax and the reference, compiled as the throughput benchmark does."""
    programs = runners._compile_amjax({**case, "impl": "amjax"})
    reference, run_reference, _ = runners.compile_reference(case)
    return {
        "amjax": (runners.sweep_run(programs), [programs.chunk.as_text(), programs.init.as_text()]),
        "reference": (run_reference, [reference.as_text()]),
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--agent", choices=("ppo", "dqn"), default="ppo")
    parser.add_argument("--configs", type=int, default=1024)
    parser.add_argument("--steps", type=int, default=51_200)
    parser.add_argument("--rounds", type=int, default=3, help="timed runs of each implementation, alternating")
    parser.add_argument("--top", type=int, default=25, help="ops and source lines listed per implementation")
    parser.add_argument("--out", default="/tmp/gpu_profile")
    parser.add_argument("--no-profile", dest="profile", action="store_false", help="time only, no trace")
    args = parser.parse_args(argv)

    case = {
        "agent": args.agent,
        "configs": args.configs,
        "vanilla": False,
        "evals": 5,
        "eval_episodes": 10,
        "reference_eval": True,
        "target_chunks": 10,
        "sb3_threads": 1,
        "repeats": 1,
        "cores": None,
    }
    case["steps"] = _round_steps(args.steps, case["evals"] * _steps_per_update(args.agent))
    if args.agent == "dqn":
        case["buffer"] = _default_buffer(case["steps"], _steps_per_update("dqn"))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    device = jax.devices()[0]
    print(f"{device.device_kind} ({jax.default_backend()}), {args.agent} {args.configs} x {case['steps']}", flush=True)

    start = time.perf_counter()
    built = build(case)
    print(f"compiled both in {time.perf_counter() - start:.1f} s", flush=True)
    walls = interleaved({impl: run for impl, (run, _) in built.items()}, args.rounds)
    env_steps = case["configs"] * case["steps"]
    result: dict[str, Any] = {"device": f"{device.device_kind} ({jax.default_backend()})", "case": case, "impls": {}}
    for impl, (run, texts) in built.items():
        if not args.profile:
            wall = min(walls[impl])
            result["impls"][impl] = {"wall_s": walls[impl], "env_steps_per_s": env_steps / wall, "top_sources": []}
            print(f"{impl}: {wall:.3f} s ({env_steps / wall / 1e6:.2f} M env-steps/s)", flush=True)
            continue
        trace_dir = Path(tempfile.mkdtemp(prefix=f"trace_{args.agent}_{args.configs}_{impl}_"))
        with jax.profiler.trace(str(trace_dir), create_perfetto_trace=True):
            run()
        sources: dict[str, str] = {}
        for text in texts:
            sources.update(hlo_sources(text))
        summary = summarise(device_events(trace_dir), sources, args.top)
        shutil.rmtree(trace_dir)  # hundreds of MB for a long run; the summary is what is kept
        summary["wall_s"] = walls[impl]
        summary["env_steps_per_s"] = env_steps / min(walls[impl])
        result["impls"][impl] = summary
        print(
            f"{impl}: {min(walls[impl]):.3f} s ({summary['env_steps_per_s'] / 1e6:.2f} M env-steps/s), "
            f"{summary['kernels']} kernels, device busy {summary['busy_ms']:.0f} ms of {summary['span_ms']:.0f}",
            flush=True,
        )
    name = f"profile_{args.agent}_{args.configs}"
    (out / f"{name}.json").write_text(json.dumps(result, indent=1))
    lines = [f"# {args.agent} {args.configs} x {case['steps']} on {result['device']}", ""]
    for impl, s in result["impls"].items():
        lines += [
            f"## {impl}: best {min(s['wall_s']):.3f} s of {', '.join(f'{w:.3f}' for w in s['wall_s'])}; "
            f"{s['env_steps_per_s'] / 1e6:.2f} M env-steps/s{_kernel_figures(s)}",
            "",
            "| source (op) | kernels | ms | share |",
            "|---|---|---|---|",
        ]
        lines += [f"| {r['name']} | {r['count']} | {r['ms']:.1f} | {r['share']:.1%} |" for r in s["top_sources"]]
        for title, key in (("HLO op", "top_ops"), ("kernel in op: source", "top_kernels")):
            lines += ["", f"| {title} | kernels | ms | share |", "|---|---|---|---|"]
            lines += [f"| {r['name']} | {r['count']} | {r['ms']:.1f} | {r['share']:.1%} |" for r in s.get(key, [])]
        lines.append("")
    (out / f"{name}.md").write_text("\n".join(lines))
    print((out / f"{name}.md").read_text())


if __name__ == "__main__":
    main()
