"""What the benchmark prints and writes: the progress lines, and the report rendered from a results file's JSON lines
(`render`, what `python -m benchmarks.harness render FILE.jsonl` calls): the table, the ratio lines, and the notes
(the prose lives in notes.md, a string.Template this module fills with the run's figures)."""

from __future__ import annotations

import argparse
import contextlib
import json
import math
from collections.abc import Callable
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from string import Template
from typing import Any

from benchmarks import harness

from .cases import COSTS, ENV_ID, IMPL_LABELS, IMPLS, MAX_EPISODE_STEPS, TRANSITION_BYTES

NOTES = Path(__file__).with_name("notes.md")
SOFTWARE = ("jaxlib", "flax", "optax", "gymnax", "stable_baselines3", "torch")  # besides Python and jax (the harness's)


def software() -> dict[str, str]:
    """The installed versions of the libraries the cases run on (SB3 and torch where installed), read from the
    package metadata, so the parent never imports jax: recorded in the run's settings."""
    versions = {}
    for name in SOFTWARE:
        with contextlib.suppress(PackageNotFoundError):
            versions[name.replace("_", "-")] = version(name)
    return versions


def _fmt(value: Any, spec: str = ".1f") -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    return format(value, spec)


def _rate(value: float | None) -> str:
    if value is None:
        return "-"
    if value >= 1e6:
        return f"{value / 1e6:.2f} M"
    if value >= 1e3:
        return f"{value / 1e3:.1f} k"
    return f"{value:.0f}"


def case_line(i: int, total: int, case: dict[str, Any]) -> str:
    """The progress line's start, printed before a case runs."""
    extra = f", buffer {case['buffer']:,}" if case.get("buffer") else ""
    return (
        f"[{i}/{total}] {IMPL_LABELS[case['impl']]} {case['agent']} x {case['configs']} "
        f"({case['steps']:,} steps/config{extra}) ... "
    )


def result_line(result: dict[str, Any]) -> str:
    """The progress line's end, once the case has run."""
    if result["status"] != "ok":
        return result["status"]
    if result["impl"] == "overhead":
        train, env = result["train"], result["env_only"]
        return (
            f"training {train['min'] * 100:+.1f}% (fastest) {train['median'] * 100:+.1f}% (median); env alone "
            f"{env['min'] * 100:+.1f}% {env['median'] * 100:+.1f}%"
        )
    return (
        f"compile {result['compile_s']:.1f} s, run {result['run_s']:.1f} s "
        f"(CPU {result['run_cpu_s']:.1f} s), {_rate(result['steps_per_s'])} steps/s, "
        f"peak {result['peak_rss_mib']:.0f} MiB"
    )


def _env_label(r: dict[str, Any]) -> str:
    if r["impl"] == "sb3":
        return "Gymnasium CartPole-v1"
    return f"{ENV_ID} vanilla" if r["vanilla"] else f"{ENV_ID} active-measure"


def _eval_ratio(r: dict[str, Any]) -> float | None:
    """Evaluation env steps (each evaluation scans MAX_EPISODE_STEPS) per training env step."""
    if r["impl"] == "sb3" or (r["impl"].startswith("reference") and not r["reference_eval"]):
        return None
    return r["evals"] * r["eval_episodes"] * MAX_EPISODE_STEPS / r["steps"]


def _ok(r: dict[str, Any]) -> bool:
    return r.get("status") == "ok"


def _label(r: dict[str, Any]) -> str:
    return f"SB3 {r['agent'].upper()} (defaults)" if r["impl"] == "sb3" else IMPL_LABELS[r["impl"]]


def _seconds(key: str) -> Callable[[dict[str, Any]], Any]:
    """A column of seconds to 0.1 s, "-" for a failed case."""

    def value(r: dict[str, Any]) -> Any:
        return round(r[key], 1) if _ok(r) and r.get(key) is not None else "-"

    return value


# The table's columns: (header, value of a case record), for `harness.markdown_table`. A failed case keeps its row,
# its status in the env-steps/s column.
COLUMNS: list[tuple[str, Callable[[dict[str, Any]], Any]]] = [
    ("implementation", _label),
    ("agent", lambda r: r["agent"].upper()),
    ("env", _env_label),
    ("configs", lambda r: r["configs"]),
    ("steps/config", lambda r: r["steps"]),
    ("buffer/config", lambda r: r.get("buffer") or "-"),
    ("eval/train steps", lambda r: _fmt(_eval_ratio(r), ".2f")),
    ("compile (s)", _seconds("compile_s")),
    ("run (s)", _seconds("run_s")),
    ("run CPU (s)", _seconds("run_cpu_s")),
    ("env-steps/s", lambda r: _rate(r.get("steps_per_s")) if _ok(r) else r.get("status", "?")),
    ("peak RSS (MiB)", lambda r: r.get("peak_rss_mib", "-") if _ok(r) else "-"),
    ("eval return", lambda r: _fmt(r.get("eval_return")) if _ok(r) else "-"),
]


def table_rows(results: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The cases that are table rows. The overhead cases are reported as ratios: their run times are paired, not a
    throughput."""
    return [r for r in results if r["impl"] != "overhead"]


def table(results: list[dict[str, Any]]) -> str:
    """The markdown table of a run's cases (its header even without rows)."""
    return harness.markdown_table(table_rows(results), COLUMNS)


def _find(results: list[dict[str, Any]], impl: str, agent: str, configs: int | None = None) -> dict | None:
    for r in results:
        ok = r.get("status") == "ok"
        if ok and r["impl"] == impl and r["agent"] == agent and configs in (None, r["configs"]):
            return r
    return None


def _pair_ratios(results: list[dict[str, Any]], agent: str, size: int) -> list[str]:
    """amjax vs the plain reference, and active vs vanilla env, at one agent and size."""
    am, van = _find(results, "amjax", agent, size), _find(results, "amjax-vanilla", agent, size)
    ref, ref_van = _find(results, "reference", agent, size), _find(results, "reference-vanilla", agent, size)
    parts = []
    if am and ref:
        parts.append(
            f"amjax / plain reference = {am['steps_per_s'] / ref['steps_per_s']:.2f}x "
            f"(by CPU seconds: {ref['run_cpu_s'] / am['run_cpu_s']:.2f}x)"
        )
    if am and van:
        parts.append(
            f"active-measure wrapper overhead (amjax) = {(van['steps_per_s'] / am['steps_per_s'] - 1) * 100:+.0f}%"
        )
    if ref and ref_van:
        parts.append(f"wrapper overhead (reference) = {(ref_van['steps_per_s'] / ref['steps_per_s'] - 1) * 100:+.0f}%")
    if am and ref:
        parts.append(f"compile amjax / reference = {am['compile_s'] / ref['compile_s']:.2f}x")
    return parts


def _overhead_line(r: dict[str, Any]) -> str:
    train, env = r["train"], r["env_only"]
    return (
        f"{r['agent'].upper()} x {r['configs']}: active-measure overhead, interleaved in one process "
        f"({len(train['rounds'])} runs each): training {train['min'] * 100:+.1f}% (fastest vs fastest), "
        f"{train['median'] * 100:+.1f}% (median vs median), per round {min(train['rounds']) * 100:+.1f}% to "
        f"{max(train['rounds']) * 100:+.1f}%; the env alone ({env['envs']:,} envs x {env['steps']} random "
        f"steps: {_rate(env['active_steps_per_s'])} vs {_rate(env['vanilla_steps_per_s'])} steps/s) "
        f"{env['min'] * 100:+.1f}% / {env['median'] * 100:+.1f}%"
    )


def _sb3_lines(results: list[dict[str, Any]], sizes: list[int]) -> list[str]:
    """amjax's speed-up over SB3's DQN (with SB3's hyperparameters) and over SB3's PPO."""
    lines = []
    sb3_dqn, amjax_sb3 = _find(results, "sb3", "dqn"), _find(results, "amjax-sb3", "dqn")
    if sb3_dqn and amjax_sb3:
        n = amjax_sb3["configs"]
        sequential = n * sb3_dqn["run_s"] * amjax_sb3["steps"] / sb3_dqn["steps"]
        lines.append(
            f"DQN with SB3's default hyperparameters: amjax x {n} configs {_rate(amjax_sb3['steps_per_s'])} "
            f"env-steps/s vs SB3 DQN {_rate(sb3_dqn['steps_per_s'])}/s: speed-up "
            f"{amjax_sb3['steps_per_s'] / sb3_dqn['steps_per_s']:.1f}x ({n} runs: amjax "
            f"{amjax_sb3['compile_s'] + amjax_sb3['run_s']:.0f} s including compile, SB3 {sequential:.0f} s one "
            "after another)"
        )
    sb3_ppo = _find(results, "sb3", "ppo")
    for size in sizes:
        am = _find(results, "amjax", "ppo", size)
        if am and sb3_ppo:
            lines.append(
                f"PPO: amjax x {size} configs / SB3 PPO (1 env) = "
                f"{am['steps_per_s'] / sb3_ppo['steps_per_s']:.1f}x aggregate env-steps/s"
            )
    return lines


def _buffer_scan_line(results: list[dict[str, Any]]) -> list[str]:
    scan = sorted(
        (r for r in results if r["impl"] == "amjax-buffer" and r.get("status") == "ok"), key=lambda r: r["buffer"]
    )
    if len(scan) < 2:
        return []
    return [
        f"DQN step cost vs replay capacity (amjax, {scan[0]['configs']} configs, {scan[0]['steps']:,} steps each): "
        + ", ".join(
            f"{r['buffer']:,} slots {_rate(r['steps_per_s'])}/s "
            f"({r['steps_per_s'] / scan[0]['steps_per_s']:.2f}x, CPU {r['run_cpu_s']:.1f} s, "
            f"RSS {r['peak_rss_mib']:.0f} MiB)"
            for r in scan
        )
    ]


def ratio_lines(results: list[dict[str, Any]]) -> list[str]:
    """The ratios between cases the run has both of, one line each."""
    lines = []
    sizes = sorted({r["configs"] for r in results if r["impl"] in IMPLS})
    for agent in ("ppo", "dqn"):
        for size in sizes:
            parts = _pair_ratios(results, agent, size)
            if parts:
                lines.append(f"{agent.upper()} x {size}: " + "; ".join(parts))
    lines += [_overhead_line(r) for r in results if r["impl"] == "overhead" and r.get("status") == "ok"]
    return lines + _sb3_lines(results, sizes) + _buffer_scan_line(results)


# ---------------------------------------------------------------------------------------------------------------
# The notes: notes.md's sections, filled with the run's figures.
# ---------------------------------------------------------------------------------------------------------------

Applies = Callable[[argparse.Namespace, list[dict[str, Any]]], bool]
NOTE_APPLIES: dict[str, Applies] = {  # notes that only some runs print; the others always appear
    "dqn-warmup": lambda args, results: bool(_dqn_steps(results)) and "reference" in args.impls,
    "overhead": lambda args, results: any(r["impl"] == "overhead" for r in results),
    "sb3": lambda args, results: any(r["impl"] == "sb3" for r in results),
}


def read_notes(path: Path = NOTES) -> tuple[dict[str, str], dict[str, str]]:
    """notes.md's `## note` and `### fragment` sections (name -> text, each joined into one line), in order."""
    notes: dict[str, str] = {}
    fragments: dict[str, str] = {}
    section: tuple[dict[str, str], str] | None = None
    for line in path.read_text().splitlines():
        if line.startswith(("## ", "### ")):
            level, name = line.split(" ", 1)
            section = (notes if level == "##" else fragments, name.strip())
            section[0][section[1]] = ""
        elif section and line.strip():
            section[0][section[1]] = f"{section[0][section[1]]} {line.strip()}".lstrip()
    return notes, fragments


def _dqn_steps(results: list[dict[str, Any]]) -> list[int]:
    return sorted({r["steps"] for r in results if r["agent"] == "dqn" and r["impl"] in IMPLS})


def _run_figures(args: argparse.Namespace, results: list[dict[str, Any]]) -> dict[str, Any]:
    """The placeholders that come from the arguments and the results."""
    chunks = sorted({r["chunks"] for r in results if r.get("chunks")})
    baselines = [r["baseline_rss_mib"] for r in results if r.get("baseline_rss_mib") and r["impl"] != "sb3"]
    replay = [
        f"{r['configs']} x {r['buffer']:,} = {r['configs'] * r['buffer'] * TRANSITION_BYTES / 2**20:,.1f} MiB"
        for r in results
        if r["impl"] in ("amjax", "amjax-sb3") and r["agent"] == "dqn"
    ]
    return {
        "repeats": args.repeats,
        "evals": args.evals,
        "eval_episodes": args.eval_episodes,
        "sb3_threads": args.sb3_threads,
        "chunks": ", ".join(map(str, chunks)) or "?",
        "replay_memory": ", ".join(replay) or "no DQN case in this run",
        "rss_low": f"{min(baselines):.0f}" if baselines else "?",
        "rss_high": f"{max(baselines):.0f}" if baselines else "?",
        "has_baselines": bool(baselines),
    }


def note_values(args: argparse.Namespace, results: list[dict[str, Any]], fragments: dict[str, str]) -> dict[str, Any]:
    """Every placeholder of notes.md, the fragments that apply included."""
    from amjax.agents import DQNConfig

    default = DQNConfig()
    values = {
        **_run_figures(args, results),
        "max_episode_steps": MAX_EPISODE_STEPS,
        "costs": ", ".join(map(str, COSTS)),
        "transition_bytes": TRANSITION_BYTES,
        "default_buffer": f"{default.buffer_size:,}",
        "default_buffer_1024_gib": f"{default.buffer_size * 1024 * TRANSITION_BYTES / 2**30:.1f}",
        "learning_starts": f"{default.learning_starts:,}",
        "warmup_shares": ", ".join(
            f"({min(default.learning_starts / s, 1):.0%} of the run at {s:,} steps)" for s in _dqn_steps(results)
        ),
    }

    def fragment(name: str, applies: bool = True) -> str:
        return Template(fragments[name]).substitute(values) if applies else ""

    values["fastest_of"] = fragment("fastest-of", args.repeats > 1)
    values["reference_evaluation"] = fragment(
        "reference-skips-evaluation" if args.no_reference_eval else "reference-evaluates"
    )
    values["rss_before_compile"] = fragment("rss-before-compile", values["has_baselines"])
    return values


def note_lines(args: argparse.Namespace, results: list[dict[str, Any]]) -> list[str]:
    """The notes that apply to the run, in notes.md's order, one line each."""
    notes, fragments = read_notes()
    values = note_values(args, results, fragments)
    return [
        Template(text).substitute(values)
        for name, text in notes.items()
        if name not in NOTE_APPLIES or NOTE_APPLIES[name](args, results)
    ]


# ---------------------------------------------------------------------------------------------------------------
# The report of a results file.
# ---------------------------------------------------------------------------------------------------------------


def _software_line(run: dict[str, Any]) -> str:
    m, versions = run["machine"], run["settings"].get("software", {})
    libraries = "".join(f", {name} {v}" for name, v in versions.items())  # jax's version is in `describe`'s line
    return f"Python {m['python']}{libraries}, backend {m['backend']}"


def render_run(run: dict[str, Any]) -> str:
    """One run's report: where and when, the table, the ratios and the notes."""
    args, results = argparse.Namespace(**run["settings"]), run["cases"]
    ratios, notes = ratio_lines(results), note_lines(args, results)
    md = [
        f"- Run: {harness.describe(run)}",
        f"- Software: {_software_line(run)}",
        "- A load average above ~0.5 (1 min) makes the timings noisy",
        "",
        table(results),
    ]
    if ratios:
        md += ["Ratios (env-steps/s):", "", *(f"- {line}" for line in ratios), ""]
    md += ["Notes:", "", *(f"- {line}" for line in notes)]
    return "\n".join(md) + "\n"


def render(runs: list[dict[str, Any]]) -> str:
    """The markdown of a results file (`harness.read_runs`): each run's report, a rule between runs."""
    return "\n---\n\n".join(render_run(run) for run in runs)


def write_json(path: str | Path, run: dict[str, Any]) -> None:
    """--json: the run's records (its "run" line with its `cases` and `load_end`) as one JSON document."""
    Path(path).write_text(json.dumps(run, indent=1, default=str))
    print(f"raw results written to {path}")
