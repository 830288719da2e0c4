"""The README's quick-start table is what `amjax demo` prints, number for number.

The demo is deterministic on one machine: the same programs on the same CPU model, vector extensions and device
count give the same bits. Another machine rounds floats differently, and training amplifies that (two 2-core "AMD
EPYC" machines, one with AVX-512, differ by up to 10 points in a PPO row), so the README names the machine that
printed its table (the demo's own first line, `describe_devices`). This test runs the demo: on that machine the
table must be the README's number for number; on another, the same rows and columns with the numbers every machine
should reach (CartPole solved at cost 0, nothing diverged, costed rows between 100 and 200). When results change on
purpose, or CI's machine does, rewrite the table from a run there:
`AMJAX_UPDATE_README=1 python -m pytest tests/test_readme_demo.py`.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest

from train.cli import describe_devices, main

README = Path(__file__).parents[1] / "README.md"
START, END = "<!-- demo-table:start -->", "<!-- demo-table:end -->"
NOTE = (
    "Printed by `amjax demo` on {devices}. Another CPU model, vector extension (with or without AVX-512) or "
    "device count rounds floats differently and training amplifies it, so there the same command prints other numbers. "
    "`tests/test_readme_demo.py` runs the demo and checks this table in CI on this machine (elsewhere: the same rows, "
    "CartPole solved at cost 0)."
)

# The README's table until 2026-11-29: the same command on another 2-core "AMD EPYC" (its vector extensions were not
# recorded; it rounds differently from the AVX-512 one), for the check a machine other than the README's gets.
OTHER_MACHINE = Path(__file__).parent / "data" / "demo_table_other_machine.txt"


def printed_table(stdout: str) -> str:
    """The results table in the demo's output: from its header line to the blank line after it."""
    lines = stdout.splitlines()
    start = next(i for i, line in enumerate(lines) if "best costed reward" in line and line.lstrip().startswith("env"))
    end = next((i for i in range(start, len(lines)) if not lines[i].strip()), len(lines))
    return "\n".join(lines[start:end])


def readme_block(table: str, devices: str) -> str:
    return f"\n```\n{table}\n```\n\n{NOTE.format(devices=devices)}\n"


def block_table(block: str) -> str:
    """The table inside a README block (`readme_block`'s)."""
    return block.split("```")[1].strip("\n")


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
    stdout, devices = capsys.readouterr().out, describe_devices()
    assert devices in stdout  # the demo says what it ran on
    block = readme_block(printed_table(stdout), devices)
    text = README.read_text()
    assert text.count(START) == 1 and text.count(END) == 1, f"README.md needs one {START} ... {END} block"
    head, rest = text.split(START)
    shown, tail = rest.split(END)
    if os.environ.get("AMJAX_UPDATE_README") == "1":
        README.write_text(head + START + block + END + tail)
        return
    named = re.search(r"Printed by `amjax demo` on (.+?)\. ", shown)
    if named is None or named.group(1) == devices:  # the machine the README names: number for number
        assert shown == block, (
            "README.md's demo table is not what `amjax demo` printed on the machine it names (above: this run's). "
            "If results changed on purpose, rewrite it: AMJAX_UPDATE_README=1 python -m pytest "
            "tests/test_readme_demo.py\n" + block
        )
    else:
        assert_same_rows_and_reachable_numbers(printed_table(stdout), block_table(shown))


def _rows(table: str) -> list[list[str]]:
    return [line.split() for line in table.splitlines()]


def assert_same_rows_and_reachable_numbers(printed: str, readme: str) -> None:
    """Another machine's demo table against the README's: the same header and rows (env, agent, cost, seeds),
    nothing diverged, the cost-0 rows solved (best costed reward 200 in median) and the costed rows' medians
    between 100 and 200."""
    got, want = _rows(printed), _rows(readme)
    assert got[0] == want[0] and len(got) == len(want), (printed, readme)
    for row, readme_row in zip(got[1:], want[1:], strict=True):
        assert row[:4] == readme_row[:4], (row, readme_row)  # env, agent, cost, seeds
        diverged, best = int(row[4]), float(row[5])
        assert diverged == 0, row
        assert best >= 195 if row[2] == "0" else 100 <= best <= 200, row


def test_another_machines_table_passes_the_row_check_and_a_broken_one_does_not():
    """The check a machine other than the README's gets: it passes a real other machine's table (numbers up to 10
    points apart) and fails one with a row missing, a divergence, or cost 0 unsolved."""
    readme = block_table(README.read_text().split(START)[1].split(END)[0])
    other = OTHER_MACHINE.read_text().strip("\n")
    assert_same_rows_and_reachable_numbers(other, readme)
    lines = other.splitlines()
    unsolved = lines[1].replace("200.00 [200.00", "150.00 [150.00", 1)
    diverged = lines[2].replace("      3         0  ", "      3         1  ", 1)
    for broken in (lines[:-1], [lines[0], unsolved, *lines[2:]], [*lines[:2], diverged, *lines[3:]]):
        with pytest.raises(AssertionError):
            assert_same_rows_and_reachable_numbers("\n".join(broken), readme)
