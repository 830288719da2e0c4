"""The README's quick-start table is what `amjax demo` prints, number for number.

The demo is deterministic on one machine: the same programs on the same CPU model and device count give the same
bits. Another CPU model or device count rounds floats differently, and training amplifies that, so the README says
which machine printed its table, and this test runs the demo and compares. When results change on purpose (or the
machine does), rewrite the table from a run: `AMJAX_UPDATE_README=1 python -m pytest tests/test_readme_demo.py`.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from train.cli import describe_devices, main

README = Path(__file__).parents[1] / "README.md"
START, END = "<!-- demo-table:start -->", "<!-- demo-table:end -->"
NOTE = (
    "Printed by `amjax demo` on {devices}. Another CPU model or device count rounds floats differently and "
    "training amplifies it, so there the same command prints other numbers. `tests/test_readme_demo.py` runs the "
    "demo and checks this table in CI."
)


def printed_table(stdout: str) -> str:
    """The results table in the demo's output: from its header line to the blank line after it."""
    lines = stdout.splitlines()
    start = next(i for i, line in enumerate(lines) if "best costed reward" in line and line.lstrip().startswith("env"))
    end = next((i for i in range(start, len(lines)) if not lines[i].strip()), len(lines))
    return "\n".join(lines[start:end])


def readme_block(table: str, devices: str) -> str:
    return f"\n```\n{table}\n```\n\n{NOTE.format(devices=devices)}\n"


def test_printed_table_is_found_in_the_demo_output():
    stdout = (
        "python -m train: 2 CPU devices (X)\n\nMedian [interquartile range] ...\n"
        "        env agent cost  seeds  best costed reward\nCartPole-v0   dqn    0      3  200.00\n\n"
        "Results: runs/demo/results.parquet\n"
    )
    assert printed_table(stdout) == (
        "        env agent cost  seeds  best costed reward\nCartPole-v0   dqn    0      3  200.00"
    )


@pytest.mark.slow
def test_readme_shows_what_the_demo_prints(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path / "demo"), "--no-progress"]) == 0
    stdout = capsys.readouterr().out
    assert describe_devices() in stdout  # the demo says what it ran on
    block = readme_block(printed_table(stdout), describe_devices())
    text = README.read_text()
    assert text.count(START) == 1 and text.count(END) == 1, f"README.md needs one {START} ... {END} block"
    head, rest = text.split(START)
    shown, tail = rest.split(END)
    if os.environ.get("AMJAX_UPDATE_README") == "1":
        README.write_text(head + START + block + END + tail)
        return
    assert shown == block, (
        "README.md's demo table is not what `amjax demo` printed here (above: this run's). If results changed on "
        "purpose, or this is another CPU model or device count than the README names, rewrite it: "
        "AMJAX_UPDATE_README=1 python -m pytest tests/test_readme_demo.py\n" + block
    )
