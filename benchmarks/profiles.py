"""Where a compiled program's time goes: one run traced with `jax.profiler`, its kernels' time summed per HLO op,
per source line and per kernel (the accelerator's kernels, or on a CPU the thunks XLA runs). Used by
`gpu_profile.py` and by `harness.time_training_batch(..., profile_top=N)` (`pqn_speed.py --profile N`).

On a CPU the trace keeps part of a long run's events (a 40,960-step PQN run kept about 60% of its gradient steps'
kernels), so the shares are a sample: read them as proportions, not totals."""

from __future__ import annotations

import gzip
import json
import re
import shutil
import tempfile
from collections import defaultdict
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from benchmarks import harness

_INSTRUCTION = re.compile(r"^\s*(?:ROOT\s+)?%?([\w.\-]+)\s*=\s*.*?metadata=\{([^}]*)\}")
_FIELD = re.compile(r'(\w+)=(?:"((?:[^"\\]|\\.)*)"|(\S+))')
_TABLE_ROW = re.compile(r"^(\d+) (?:\"(.*)\"|\{(.*)\})$")
_CONTROL_FLOW = re.compile(r"^(while|cond|conditional|call)(\.\d+)?$")


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
    """The trace's op events on the accelerator (or, with none, every event naming an HLO op but a loop or branch)."""
    trace = next(trace_dir.rglob("perfetto_trace.json.gz"))
    with gzip.open(trace) as f:
        events = json.load(f)
    events = events["traceEvents"] if isinstance(events, dict) else events
    names = {e["pid"]: e["args"]["name"] for e in events if e.get("ph") == "M" and e.get("name") == "process_name"}
    gpu_pids = {pid for pid, name in names.items() if "/device:" in name and "CPU" not in name.upper()}
    ops = [e for e in events if e.get("ph") == "X" and "hlo_op" in e.get("args", {})]
    on_device = [e for e in ops if e["pid"] in gpu_pids]
    # A CPU's thunks include its loops and branches, whose time is their body's kernels' again.
    return on_device or [e for e in ops if not _CONTROL_FLOW.match(e["args"]["hlo_op"])]


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


def profile_call(run: Callable[[], Any], hlo_texts: Sequence[str], top: int) -> dict[str, Any]:
    """`run()` (which runs the compiled programs whose optimised HLO texts are `hlo_texts` to the end) traced once,
    summarised by `summarise` with its `top` rankings; the trace itself is deleted (hundreds of MB for a long run)."""
    import jax

    trace_dir = Path(tempfile.mkdtemp(prefix="amjax_trace_"))
    try:
        with jax.profiler.trace(str(trace_dir), create_perfetto_trace=True):
            run()
        sources: dict[str, str] = {}
        for text in hlo_texts:
            sources.update(hlo_sources(text))
        return summarise(device_events(trace_dir), sources, top)
    finally:
        shutil.rmtree(trace_dir, ignore_errors=True)


def top_table(rows: list[dict[str, Any]], title: str) -> str:
    """One of `summarise`'s rankings as a markdown table."""
    return harness.markdown_table(
        rows,
        [
            (title, lambda t: t["name"]),
            ("kernels", lambda t: t["count"]),
            ("ms", lambda t: f"{t['ms']:.1f}"),
            ("share", lambda t: f"{t['share']:.1%}"),
        ],
    )
