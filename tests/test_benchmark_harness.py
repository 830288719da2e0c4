"""The benchmark harness (benchmarks/harness.py): children, JSON-lines records, file names and rendered tables."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import pytest

from benchmarks import harness

CHILD = textwrap.dedent(
    """
    import json, sys, time
    from benchmarks import harness

    case = json.loads(sys.argv[sys.argv.index("--child") + 1])
    if case.get("fail"):
        raise RuntimeError("the case broke")
    if case.get("progress"):
        harness.child_progress({"done": 1})
        harness.child_progress({"done": 2})
    if case.get("sleep"):
        time.sleep(case["sleep"])
    block = b"x" * (case.get("mib", 0) * 2**20)  # written, so resident: counted in the child's peak RSS
    print("noise before the result")
    harness.child_result({"answer": case["x"] * 2})
    """
)


@pytest.fixture
def child(tmp_path):
    path = tmp_path / "child.py"
    path.write_text(CHILD)
    return path


def test_a_child_reports_its_measurements_and_its_own_memory(child):
    small = harness.run_child(child, {"x": 21})
    large = harness.run_child(child, {"x": 1, "mib": 300})
    assert small["status"] == "ok" and small["answer"] == 42 and small["x"] == 21 and small["wall_s"] > 0
    # each child's peak memory is its own: the allocation shows in its record only, and neither carries the memory
    # of this (pytest) process, which getrusage's ru_maxrss would pass on to a child
    assert large["peak_rss_mib"] >= 300 and small["peak_rss_mib"] < 100


def test_a_failing_or_slow_child_gets_a_status_not_numbers(child):
    failed = harness.run_child(child, {"x": 1, "fail": True})
    assert failed["status"].startswith("failed: RuntimeError: the case broke") and "answer" not in failed
    slow = harness.run_child(child, {"x": 1, "sleep": 30}, timeout=3)
    assert slow["status"] == "timeout after 3 s" and "partial" not in slow
    # what a slow child reported before its time ran out is kept (its last report), but is no result
    # (8 s: the child starts Python and prints twice before its time runs out, on a loaded machine too)
    partly = harness.run_child(child, {"x": 1, "sleep": 30, "progress": True}, timeout=8)
    assert partly["status"] == "timeout after 8 s" and partly["partial"] == {"done": 2} and "answer" not in partly
    done = harness.run_child(child, {"x": 1, "progress": True})
    assert done["status"] == "ok" and done["answer"] == 2 and "partial" not in done


def test_runs_append_to_one_file_per_day_and_machine(tmp_path, monkeypatch):
    info = {"backend": "cpu", "cpu": "AMD EPYC 7B13 64-Core Processor", "affinity": 2, "device": "cpu"}
    monkeypatch.setattr(harness, "machine", lambda: {**info, "cpus": 2, "memory_gib": 24.0, "python": "3", "jax": "x"})
    assert harness.machine_slug(info) == "amd-epyc-2c"  # /proc/cpuinfo named no vector extension
    # the same model with and without AVX-512 compiles 2x apart: its runs go to another file
    assert harness.machine_slug({**info, "cpu_vector_isa": "AVX2"}) == "amd-epyc-avx2-2c"
    assert harness.machine_slug({**info, "cpu_vector_isa": "AVX-512"}) == "amd-epyc-avx-512-2c"
    assert harness.machine_slug({**info, "cpu": "Intel(R) Xeon(R) CPU @ 2.20GHz"}) == "intel-xeon-2c"
    assert harness.machine_slug({"backend": "gpu", "device": "NVIDIA H100 80GB HBM3"}) == "nvidia-h100-80gb-hbm3"
    monkeypatch.setattr(harness, "RESULTS", tmp_path)
    first = harness.Recorder("demo", {"size": 1})
    first.case({"case": "a", "status": "ok", "speed": 1000})
    first.end()
    second = harness.Recorder("demo", {"size": 2})
    second.case({"case": "a", "status": "ok", "speed": 2000})
    assert first.path == second.path and first.path.name.startswith("demo_") and first.path.suffix == ".jsonl"
    assert first.path.name.endswith("_amd-epyc-2c.jsonl")
    runs = harness.read_runs(first.path)
    assert [r["settings"]["size"] for r in runs] == [1, 2] and runs[0]["load_end"] is not None
    assert [[c["speed"] for c in r["cases"]] for r in runs] == [[1000], [2000]]
    assert all(json.loads(line)["run"] in (first.run, second.run) for line in first.path.read_text().splitlines())


def test_markdown_table():
    rows = [{"case": "a", "speed": 12345, "ratio": 1.5}, {"case": "b", "speed": 7, "ratio": 0.25}]
    table = harness.markdown_table(
        rows, [("case", lambda r: r["case"]), ("speed", lambda r: r["speed"]), ("ratio", lambda r: r["ratio"])]
    )
    assert table.splitlines() == [
        "| case | speed | ratio |",
        "|---|---:|---:|",
        "| a | 12,345 | 1.5 |",
        "| b | 7 | 0.25 |",
    ]


def test_run_cases_records_every_case_and_renders_the_table(child, tmp_path, capsys):
    def render(runs):
        rows = [case for run in runs for case in run["cases"]]
        return harness.markdown_table(rows, [("x", lambda r: r["x"]), ("status", lambda r: r["status"][:6])])

    out = tmp_path / "bench.jsonl"
    path = harness.run_cases("bench", {"n": 2}, out, child, [{"x": 1}, {"x": 2, "fail": True}], render)
    assert path == out and [r["settings"] for r in harness.read_runs(out)] == [{"n": 2}]
    assert out.with_suffix(".md").read_text().splitlines()[2:] == ["| 1 | ok |", "| 2 | failed |"]
    assert "| 2 | failed |" in capsys.readouterr().out


def test_the_suite_profile_counts_each_tests_programs(tmp_path):
    """`benchmarks/suite_compile.py` as a pytest plugin: each test's programs compiled (an empty compile cache),
    summed per file; a test that compiles nothing has none."""
    from benchmarks import suite_compile

    (tmp_path / "test_two.py").write_text(
        textwrap.dedent(
            """
            import jax, jax.numpy as jnp

            def test_compiles_two():
                jax.jit(lambda x: x * 2)(jnp.ones(3)).block_until_ready()
                jax.jit(lambda x: jnp.sin(x).sum())(jnp.ones(5)).block_until_ready()

            def test_compiles_none():
                assert 1 + 1 == 2
            """
        )
    )
    records = tmp_path / "records"
    records.mkdir()
    env = {
        **os.environ,
        suite_compile.RECORDS_ENV: str(records),
        "JAX_COMPILATION_CACHE_DIR": str(tmp_path / "cache"),
        "PYTHONPATH": os.pathsep.join(filter(None, [str(harness.ROOT), os.environ.get("PYTHONPATH")])),
    }
    command = [sys.executable, "-m", "pytest", "-q", "-p", "benchmarks.suite_compile", "test_two.py"]
    assert subprocess.run(command, cwd=tmp_path, env=env, capture_output=True).returncode == 0
    tests = {r["test"]: r for r in suite_compile.read_records(records)}
    assert tests["test_two.py::test_compiles_two"]["programs"] >= 2
    assert tests["test_two.py::test_compiles_two"]["compile_s"] > 0
    assert tests["test_two.py::test_compiles_none"].get("programs", 0) == 0
    (row,) = [r for r in suite_compile.by_file(list(tests.values())) if r["file"] == "test_two.py"]
    assert row["tests"] == 2 and row["programs"] == tests["test_two.py::test_compiles_two"]["programs"]


def test_the_suite_profile_names_its_cache_empty_or_warm(tmp_path):
    """A run's compile cache: a new folder (empty), a kept folder that is empty or holds entries, or the suite's own
    (warm); only an empty one counts the default tier's tests over the slow tier's bound."""
    from benchmarks.suite_compile import compile_cache

    assert compile_cache(False, None, tmp_path) == (str(tmp_path / "cache"), "empty")
    kept = tmp_path / "kept"
    assert compile_cache(False, str(kept), tmp_path) == (str(kept), "empty")  # not made yet
    kept.mkdir()
    assert compile_cache(False, str(kept), tmp_path)[1] == "empty"
    (kept / "jit_f-cache").write_bytes(b"x")
    assert compile_cache(False, str(kept), tmp_path) == (str(kept), "warm")
    assert compile_cache(True, None, tmp_path) == (None, "warm")
