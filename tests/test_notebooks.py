"""Every notebook runs top to bottom with tiny budgets: the cell tagged `parameters` is followed by an injected cell
that overrides its values (as papermill does), and the notebook is executed in a fresh kernel in a temporary
folder (so `runs/...` outputs land there). The kernels share a persistent JAX compilation cache in a temporary
folder: the notebooks compile some of the same programs, and compiling, not training, dominates these runs.
Deselect with `-m "not slow"`."""

from __future__ import annotations

import ast
import re
import tomllib
from pathlib import Path
from typing import Any

import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")
pytest.importorskip("ipykernel")

NOTEBOOKS = Path(__file__).resolve().parents[1] / "notebooks"
DISTRIBUTION = tomllib.loads((NOTEBOOKS.parent / "pyproject.toml").read_text())["project"]["name"]

# The smallest PPO that compiles quickly: compile time, not training, dominates these runs.
TINY_PPO = {"num_envs": 4, "num_steps": 32, "update_epochs": 1, "num_minibatches": 1, "hidden": (16,)}
TINY_BUDGET = {"TOTAL_TIMESTEPS": 2048, "EVAL_EVERY": 1024, "EVAL_EPISODES": 2}

PARAMETERS: dict[str, dict[str, Any]] = {
    "quickstart.ipynb": {**TINY_BUDGET, "COSTS": (0.0, 0.2), "SEEDS": (0, 1), "PPO_STATIC": TINY_PPO},
    "env_library.ipynb": {
        "NUM_COSTS": 16,
        "NUM_KEYS": 2,
        "TRAIN_TIMESTEPS": 2048,
        "EVAL_EVERY": 1024,
        "PPO_STATIC": TINY_PPO,
    },
    "paper_replication.ipynb": {
        **TINY_BUDGET,
        "AGENTS": ("ppo",),
        "COSTS": (0.0, 0.2),
        "SEEDS": (0, 1),
        "HYPERPARAMS": TINY_PPO,
        "MAP_AGENT": "ppo",
        "MAP_COSTS": (0.0, 0.2),
    },
}


def _parameters_cell(notebook: Any) -> int:
    tagged = [i for i, cell in enumerate(notebook.cells) if "parameters" in cell.metadata.get("tags", [])]
    assert len(tagged) == 1, "a notebook needs exactly one cell tagged 'parameters'"
    return tagged[0]


def test_every_notebook_is_tested_and_clean():
    assert sorted(p.name for p in NOTEBOOKS.glob("*.ipynb")) == sorted(PARAMETERS)
    for name, overrides in PARAMETERS.items():
        notebook = nbformat.read(NOTEBOOKS / name, as_version=4)
        nbformat.validate(notebook)
        cell = notebook.cells[_parameters_cell(notebook)]
        defined = {t.id for node in ast.parse(cell.source).body if isinstance(node, ast.Assign) for t in node.targets}
        assert set(overrides) <= defined, f"{name}: overrides {set(overrides) - defined} are not parameters"
        assert not any(c.get("outputs") for c in notebook.cells if c.cell_type == "code"), f"{name}: stored outputs"


def test_install_cells_install_this_project():
    """The name `amjax` on PyPI is a stranger's package: every install names this project's distribution, and the
    cell checks that the `amjax` it imported is this project."""
    assert DISTRIBUTION != "amjax"
    for path in sorted(NOTEBOOKS.glob("*.ipynb")):
        notebook = nbformat.read(path, as_version=4)
        installs = [c.source for c in notebook.cells if c.cell_type == "code" and "pip install" in c.source]
        assert len(installs) == 1, f"{path.name}: expected one install cell"
        cell = installs[0]
        assert f'AMJAX_SOURCE = "{DISTRIBUTION}[plots]"' in cell, f"{path.name}: installs no {DISTRIBUTION}"
        assert f'name = "{DISTRIBUTION}"' in cell, f"{path.name}: does not recognise its own clone"
        assert not re.search(r"%pip install[^\n]*[\"' ]amjax(\[|[\"' ]|$)", cell), f"{path.name}: installs bare amjax"
        identity = 'name in dir(amjax) for name in ("make", "ActiveMeasure", "use_all_cores")'
        assert identity in cell, f"{path.name}: no identity check"
        assert "amjax.use_all_cores()" in cell, f"{path.name}: does not ask for every core"


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(PARAMETERS))
def test_notebook_runs(name, tmp_path, monkeypatch):
    # Read by JAX in the kernel process, which inherits this environment and the suite's compilation cache
    # (tests/conftest.py); every compiled program is kept, however quick.
    monkeypatch.setenv("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
    monkeypatch.setenv("JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES", "0")
    notebook = nbformat.read(NOTEBOOKS / name, as_version=4)
    source = "# Injected by tests/test_notebooks.py\n" + "\n".join(
        f"{key} = {value!r}" for key, value in PARAMETERS[name].items()
    )
    injected = nbformat.v4.new_code_cell(source)
    injected.metadata["tags"] = ["injected-parameters"]
    notebook.cells.insert(_parameters_cell(notebook) + 1, injected)
    client = nbclient.NotebookClient(
        notebook, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}
    )
    client.execute()  # raises CellExecutionError, with the failing cell and traceback, on any error
    images = sum(
        "image/png" in output.get("data", {})
        for cell in notebook.cells
        if cell.cell_type == "code"
        for output in cell.outputs
    )
    assert images >= 2, f"{name}: expected figures in the outputs, found {images}"
