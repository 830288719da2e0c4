"""The distribution: its name, version and console command (the wheel itself is built and tried by .ci/run)."""

from __future__ import annotations

import subprocess
import sys
import tomllib
from importlib import metadata
from pathlib import Path

import pytest

import amjax
from train import cli

PYPROJECT = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())["project"]


def test_distribution_is_not_the_strangers_name():
    # "amjax" on PyPI is an unrelated project (JAX algebraic multigrid solvers).
    assert PYPROJECT["name"] == "amjax-rl"


def test_version_comes_from_the_installed_metadata():
    assert amjax.__version__ == metadata.version(PYPROJECT["name"]) == PYPROJECT["version"]


def test_console_command_is_the_cli():
    (entry,) = metadata.entry_points(group="console_scripts", name="amjax")
    assert entry.value == PYPROJECT["scripts"]["amjax"] == "train.cli:console_main"
    assert entry.load() is cli.console_main


def test_console_command_names_itself(capsys):
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["demo", "--help"], prog="amjax")
    assert exit_info.value.code == 0
    assert capsys.readouterr().out.startswith("usage: amjax demo")


def test_module_entry_point_still_works(tmp_path):
    done = subprocess.run(
        [sys.executable, "-m", "train", "presets"], capture_output=True, text=True, cwd=tmp_path, timeout=120
    )
    assert done.returncode == 0, done.stderr
    assert "demo:" in done.stdout
