"""Sweep folders written by an older amjax (committed under tests/data/old_sweep, written at commit 3043e65 by its
`make.py`, before `MeasureSpec`) still load, score and resume with today's code.

- `full/`: a finished sweep (PPO and Dueling DQN, costs 0.1 / 0.3 and vanilla, with `extra_obs`); its tables load,
  rerunning the sweep trains nothing, and its saved policies score on fixed keys exactly what the old code's did
  (`expected.json`).
- `interrupted/`: the same sweep as a kill right after its first checkpoint left it; resumed today (by make.py's
  `resume`, on one CPU device as it was written), it ends with the old code's finished tables and policies: bit
  for bit on the machine that wrote them (`machine.json`), to float rounding (1e-5) on another CPU, which rounds
  the training it resumes differently.
"""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pandas as pd
import pytest

from amjax.analysis import load_results
from amjax.sweep import SweepSpec, load_sweep_policy, run_sweep

DATA = Path(__file__).parents[1] / "data" / "old_sweep"
TABLES = {"results": ["config_id", "env_steps"], "rescored": ["config_id"], "summary": ["config_id"]}


def _make_module():
    """tests/data/old_sweep/make.py: the spec and options the folders were written with (what a user reruns)."""
    spec = importlib.util.spec_from_file_location("old_sweep_make", DATA / "make.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


MAKE = _make_module()
SPEC, OPTIONS = MAKE.SPEC, MAKE.OPTIONS


def test_the_stored_spec_reads_back_as_the_spec_that_wrote_it():
    stored = json.loads((DATA / "full" / "metadata.json").read_text())["spec"]
    assert SweepSpec.from_json(stored).to_json() == stored
    # The same sweep as today's spec: presets added since for other agents (PQN's on CartPole) are not its own.
    assert SweepSpec.from_json(stored).identity() == SPEC.identity()
    assert SweepSpec.from_json(stored).hyperparams == SPEC.hyperparams  # tuples restored: ("since_measured",)


def _on_the_writing_machine() -> bool:
    return json.loads((DATA / "machine.json").read_text()) == MAKE.machine()


def _assert_same_tables(out: Path, reference: Path, exact: bool = True) -> None:
    for name, keys in TABLES.items():
        got = pd.read_parquet(out / f"{name}.parquet").sort_values(keys).reset_index(drop=True)
        want = pd.read_parquet(reference / f"{name}.parquet").sort_values(keys).reset_index(drop=True)
        pd.testing.assert_frame_equal(got, want, check_exact=exact, rtol=1e-5, atol=1e-5, obj=name)


def _assert_same_policies(out: Path, reference: Path, exact: bool = True) -> None:
    names = sorted(p.stem for p in (reference / "policies").glob("*.msgpack"))
    assert sorted(p.stem for p in (out / "policies").glob("*.msgpack")) == names and len(names) == 6

    def same(a, b) -> bool:
        a, b = np.asarray(a), np.asarray(b)
        return np.array_equal(a, b) if exact else np.allclose(a, b, rtol=1e-5, atol=1e-5)

    for name in names:
        got, want = load_sweep_policy(out, name), load_sweep_policy(reference, name)
        assert got.config == want.config and got.agent == want.agent and got.info == want.info
        assert all(jax.tree.leaves(jax.tree.map(same, got.params, want.params))), name


@pytest.fixture
def copied(tmp_path):
    def copy(name: str) -> Path:
        return shutil.copytree(DATA / name, tmp_path / name)

    return copy


def test_an_old_finished_sweep_loads_and_has_nothing_left_to_train(copied):
    out = copied("full")
    results = load_results(out)
    assert len(results.summary) == 6 and set(results.summary.agent) == {"ppo", "dqn"}
    assert results.summary.extra_obs.notna().sum() == 4  # the costed runs carry the option, the vanilla ones not
    stamps = {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file() and p.name != ".lock"}
    run_sweep(SPEC, out, **OPTIONS)
    _assert_same_tables(out, DATA / "full")
    changed = [p.relative_to(out) for p, stamp in stamps.items() if p.stat().st_mtime_ns != stamp]
    assert all(p.parts[0] not in ("checkpoints", "policies", "finished") for p in changed), changed


def test_old_saved_policies_score_as_the_old_code_scored_them():
    expected = json.loads((DATA / "expected.json").read_text())
    assert len(expected) == 6
    for config_id, scores in expected.items():
        saved = load_sweep_policy(DATA / "full", config_id)
        assert saved.config.measure_spec().extra_obs == (() if saved.config.vanilla else ("since_measured",))
        got = saved.evaluate(jax.random.PRNGKey(MAKE.EVAL_KEY), MAKE.EVAL_EPISODES)
        assert got == pytest.approx(scores, rel=1e-6, abs=1e-6), config_id


@pytest.mark.slow
def test_an_old_interrupted_sweep_resumes_to_the_old_result(copied):
    """Resumed in a process with one CPU device, as the folder was written (across device counts results agree
    only to float rounding)."""
    out = copied("interrupted")
    assert len(list((out / "finished").glob("*.json"))) < 2  # it was stopped before its last batch finished
    env = {**os.environ, "JAX_NUM_CPU_DEVICES": "1", "PYTHONPATH": str(Path(__file__).parents[2])}
    subprocess.run([sys.executable, str(DATA / "make.py"), "resume", str(out)], env=env, check=True, timeout=900)
    exact = _on_the_writing_machine()
    _assert_same_tables(out, DATA / "full", exact)
    _assert_same_policies(out, DATA / "full", exact)
