"""Crash consistency at every commit point: a sweep stopped at any rename of any of its files, then rerun with the
same call, ends exactly as the uninterrupted sweep (rows, re-scores, summaries, every policy and checkpoint byte
for byte, every batch's commit marker), locally and on a `local:2` cluster; a write the disk refuses stops the
command with a message and exit status 2, and a rerun completes it.

Every file of a sweep folder appears through one rename (`amjax.files.commit`, which calls `os.replace`), so the
renames are the only instants at which what a crash leaves on disk changes. `CommitPoints` wraps `os.replace` and
copies the folder just before and just after each rename into it: each copy is exactly what a process killed at
that instant (SIGKILL, power cut after the rename was flushed) leaves, temporary files included. Renames wait
while a copy is taken, so a copy is one instant's state even with the checkpoint thread writing. One run gives
every commit point; each distinct state is then rerun. `test_a_real_kill_leaves_what_the_copy_shows` kills a child
process (`os._exit`) at one such point and checks that it leaves the same files as the copy.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import jax
import pandas as pd
import pytest

from amjax.files import PARTIAL_SUFFIX
from amjax.sweep import SweepSpec, run_sweep
from amjax.sweep.cluster import LOGS
from train.cli import main

SPEC = SweepSpec(
    envs=("CartPole-v0",),
    agents=("ppo", "dqn"),  # two batches: one per agent
    costs=(0.1, 0.2),
    seeds=(0,),
    vanilla=False,
    total_timesteps=2048,
    eval_every=1024,
    eval_episodes=2,
    hyperparams={"ppo.num_envs": 4, "ppo.num_steps": 32, "rescore_episodes": 4},
)
# One chunk per evaluation, a checkpoint (and the policies so far) after every chunk: every kind of write, twice.
OPTIONS = {"progress": False, "target_chunks": 2, "checkpoint_every_s": 0.0}
TABLES = {
    "results": ["config_id", "env_steps"],
    "rescored": ["config_id"],
    "summary": ["config_id"],
    "seed_summary": ["agent", "cost"],
}
BYTE_EXACT = ("checkpoints", "policies", "finished")  # folders whose files must equal the uninterrupted run's
IGNORED = {".lock", "wall_time.json"}  # the lock file, and seconds that differ by run


class CommitPoints:
    """`os.replace` wrapped: before and after each rename into `root`, `on_point(k, when, target)` is called (k
    counts those renames from 1; when is "before" or "after"). One lock orders the renames and the callbacks."""

    def __init__(self, root: Path, on_point: Callable[[int, str, Path], None]):
        self.root, self.on_point = Path(root).resolve(), on_point
        self.count = 0
        self.lock = threading.RLock()
        self.original = os.replace

    def __call__(self, source, target, *args, **kwargs):
        if not Path(target).resolve().is_relative_to(self.root):
            return self.original(source, target, *args, **kwargs)
        with self.lock:
            self.count += 1
            self.on_point(self.count, "before", Path(target))
            self.original(source, target, *args, **kwargs)
            self.on_point(self.count, "after", Path(target))
        return None


def _digest(folder: Path, skip: str | None = None) -> str:
    """A folder's files and their contents, bar temporary files (a rerun deletes them before it reads anything)
    and the subfolder `skip`."""
    digest = hashlib.sha256()
    for path in sorted(p for p in folder.rglob("*") if p.is_file() and p.name not in IGNORED):
        name = str(path.relative_to(folder))
        if name.endswith(PARTIAL_SUFFIX) or (skip is not None and name.startswith(skip + os.sep)):
            continue
        digest.update(name.encode() + b"\0" + path.read_bytes())
    return digest.hexdigest()


def record_commit_points(
    run: Callable[[], object], out: Path, copies: Path, monkeypatch, before_first: Callable[[Path], None] | None = None
) -> dict[str, Path]:
    """Run `run()` (writing `out`) with every rename into `out` wrapped; returns {"<k>-<when>-<file>": copy of `out`
    at that instant}, one copy per distinct state. States that differ only in temporary files count as one: a
    rerun's first act is to delete those (`remove_partial_writes`), so the copy just before rename k (the file
    about to be renamed still temporary) is the state just after rename k - 1 once a rerun starts."""
    seen: dict[str, str] = {}
    points: dict[str, Path] = {}

    def on_point(k: int, when: str, target: Path) -> None:
        if before_first is not None:
            before_first(target)
        state = _digest(out)
        if state in seen:
            return
        seen[state] = name = f"{k:03d}-{when}-{target.name}"
        points[name] = shutil.copytree(out, copies / name)

    wrapper = CommitPoints(out, on_point)
    monkeypatch.setattr(os, "replace", wrapper)
    try:
        run()
    finally:
        monkeypatch.setattr(os, "replace", wrapper.original)
    assert wrapper.count > 20  # metadata, rows, wall time, checkpoints, policies, re-scores, markers, summaries
    return points


def assert_same_sweep(out: Path, reference: Path, where: str = "") -> None:
    """`out` ends as the uninterrupted sweep `reference`: the same tables, byte-identical checkpoints, policies and
    markers (no file more or less), no temporary file, no cluster part left."""
    for name, keys in TABLES.items():
        got = pd.read_parquet(out / f"{name}.parquet").sort_values(keys).reset_index(drop=True)
        want = pd.read_parquet(reference / f"{name}.parquet").sort_values(keys).reset_index(drop=True)
        pd.testing.assert_frame_equal(got, want, check_exact=True, obj=f"{where} {name}")
    for folder in BYTE_EXACT:
        got = {p.name: p.read_bytes() for p in (out / folder).iterdir()}
        want = {p.name: p.read_bytes() for p in (reference / folder).iterdir()}
        assert sorted(got) == sorted(want), f"{where}: {folder}/ holds {sorted(got)}, expected {sorted(want)}"
        assert got == want, f"{where}: {folder}/ files differ from the uninterrupted run's"
    assert not list(out.rglob(f"*{PARTIAL_SUFFIX}")), where
    assert not (out / "parts").exists(), where


@pytest.fixture(scope="module")
def local_points(tmp_path_factory) -> tuple[Path, dict[str, Path]]:
    """The uninterrupted local sweep and a copy of its folder at every commit point."""
    root = tmp_path_factory.mktemp("local")
    with pytest.MonkeyPatch.context() as monkeypatch:
        points = record_commit_points(
            lambda: run_sweep(SPEC, root / "full", **OPTIONS), root / "full", root / "points", monkeypatch
        )
    return root / "full", points


@pytest.mark.slow
def test_every_local_commit_point_recovers(local_points, tmp_path):
    """Stopped just before or just after any rename, the same `run_sweep` call finishes the sweep exactly as the
    uninterrupted one; the reruns of the states just after a batch's re-scores and just before its marker are
    what issue 51 found losing policies."""
    reference, points = local_points
    kinds = {name.split("-", 2)[2] for name in points}
    assert {"metadata.json", "results.parquet", "rescored.csv", "summary.csv"} <= kinds
    assert any(k.startswith("ppo-") for k in kinds) and any(k.startswith("dqn-") for k in kinds)
    assert any(k.endswith(".msgpack") for k in kinds)
    for name, copy in points.items():
        out = shutil.copytree(copy, tmp_path / name)
        run_sweep(SPEC, out, **OPTIONS)
        assert_same_sweep(out, reference, where=f"stopped at {name}")


@pytest.mark.slow
def test_a_marker_without_its_files_is_redone(local_points, tmp_path):
    """A finished folder that lost a policy, a checkpoint or its rows: the rerun redoes what is missing (the
    policy without training; the checkpoint and rows by training the batch again) instead of trusting the
    marker."""
    reference, _ = local_points
    policy = next((reference / "policies").iterdir()).name
    checkpoint = next((reference / "checkpoints").glob("dqn-*")).name
    for lost in (f"policies/{policy}", f"checkpoints/{checkpoint}", "rescored.parquet", "results.parquet"):
        out = shutil.copytree(reference, tmp_path / lost.replace("/", "_"))
        (out / lost).unlink()
        run_sweep(SPEC, out, **OPTIONS)
        assert_same_sweep(out, reference, where=f"without {lost}")


def _cli_sweep(out: Path) -> list[str]:
    return [
        "sweep",
        "--env",
        "CartPole-v0",
        "--agent",
        "ppo",
        "dqn",
        "--cost",
        "0.1",
        "0.2",
        "--seeds",
        "1",
        "--no-vanilla",
        "--steps",
        "2048",
        "--eval-every",
        "1024",
        "--eval-episodes",
        "2",
        "--set",
        "ppo.num_envs=4",
        "--set",
        "ppo.num_steps=32",
        "--set",
        "rescore_episodes=4",
        "--no-env-defaults",
        "--out",
        str(out),
        "--no-progress",
    ]


@pytest.fixture(scope="module")
def cli_run(tmp_path_factory) -> Path:
    """The uninterrupted command-line sweep."""
    out = tmp_path_factory.mktemp("cli") / "full"
    assert main(_cli_sweep(out)) == 0
    return out


# The first write of each kind (the checkpoint's on the checkpoint thread).
WRITES = [
    "metadata.json",
    "results.parquet",
    "results.csv",
    "wall_time.json",
    "checkpoints/",
    "rescored.parquet",
    "policies/",
    "finished/",
    "summary.parquet",
]


@pytest.mark.parametrize(
    ("code", "write"), [*(("ENOSPC", w) for w in WRITES), ("EACCES", "policies/"), ("EROFS", "finished/")]
)
@pytest.mark.slow
def test_a_refused_write_stops_with_a_message_and_a_rerun_completes(
    cli_run, tmp_path, capsys, monkeypatch, code, write
):
    """The disk refuses the first write of a kind (no space, no permission, read-only): the command prints one
    message naming the file and what to do, exits 2 with no traceback, leaves no temporary file, and the same
    command run again once the disk accepts writes ends as the uninterrupted run."""
    out = tmp_path / "run"
    original = os.replace
    refused = []

    def refuse(source, target, *args, **kwargs):
        inside = Path(target).resolve().is_relative_to(out.resolve())
        if inside and not refused and str(Path(target).resolve().relative_to(out.resolve())).startswith(write):
            refused.append(Path(target))
            raise OSError(getattr(errno, code), os.strerror(getattr(errno, code)), str(target))
        return original(source, target, *args, **kwargs)

    monkeypatch.setattr(os, "replace", refuse)
    capsys.readouterr()
    assert main(_cli_sweep(out)) == 2
    err = capsys.readouterr().err
    assert refused and f"[{code}]" in err and "rerun the same command" in err and str(refused[0]) in err, err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert not list(out.rglob(f"*{PARTIAL_SUFFIX}"))  # the refused write's temporary file is gone
    monkeypatch.setattr(os, "replace", original)
    assert main(_cli_sweep(out)) == 0
    assert_same_sweep(out, cli_run, where=f"{code} at {write}")


@pytest.mark.slow
def test_a_real_kill_leaves_what_the_copy_shows(local_points, tmp_path):
    """A child process running the same sweep, `os._exit`ed just after its first batch's re-scores are renamed
    into place (before its policies and marker: the instant issue 51 found), leaves the files that the copy taken
    at that point holds (checkpoints aside: their thread may have renamed the last one or not yet, in either run);
    the rerun completes it."""
    reference, points = local_points
    name = next(n for n in points if n.split("-", 2)[1:] == ["after", "rescored.csv"])
    out = tmp_path / "killed"
    child = f"""
import json, os
import jax
jax.config.update("jax_num_cpu_devices", {len(jax.devices())})
from amjax.sweep import SweepSpec, run_sweep
out, original = os.path.realpath({str(out)!r}), os.replace
def replace(source, target, *args, **kwargs):
    original(source, target, *args, **kwargs)
    if os.path.realpath(target) == os.path.join(out, "rescored.csv"):
        os._exit(9)
os.replace = replace
run_sweep(SweepSpec.from_json(json.loads({json.dumps(SPEC.to_json())!r})), out, **{OPTIONS!r})
"""
    # The suite's compilation cache, read only (no entry written under 1e9 s of compiling): the kill must not cut
    # one of its entries short (tests/conftest.py).
    read_only = {"JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "1e9"}
    env = {**os.environ, **read_only, "PYTHONPATH": str(Path(__file__).parents[2])}
    done = subprocess.run([sys.executable, "-c", child], env=env, capture_output=True, text=True, timeout=900)
    assert done.returncode == 9, done.stderr[-3000:]
    assert _digest(out, skip="checkpoints") == _digest(points[name], skip="checkpoints"), (
        "the kill left other files than the copy at that point"
    )
    run_sweep(SPEC, out, **OPTIONS)
    assert_same_sweep(out, reference, where="after a real kill")


@pytest.mark.slow
def test_every_cluster_driver_commit_point_recovers(tmp_path_factory, monkeypatch):
    """The `local:2` driver stopped just before or just after each of its renames (its merges of the workers'
    parts, its summaries), then the same call rerun: the same rows, re-scores, policies, checkpoints and markers
    as the uninterrupted cluster run, and no part left. Issue 51 found a merge stopped between its rows and its
    moves deleting the batch's checkpoint and policies."""
    root = tmp_path_factory.mktemp("cluster")
    full = root / "full"
    options = {**OPTIONS, "cluster": "local:2"}

    waited = []

    def both_parts_finished(target: Path) -> None:
        """The driver's first merge waits for both workers, their parts finished and submitit's result pickles
        written (a worker renames its `.save_tmp` after its part's marker: a copy of `out` then could race it):
        every later copy needs no job to finish it."""
        if target.name == "metadata.json" or waited:
            return
        deadline = time.monotonic() + 900
        logs = full / LOGS
        while (
            len(list((full / "parts").glob("*/finished/*.json"))) < 2
            or len(list(logs.glob("*_result.pkl"))) < 2
            or any(logs.glob("*.save_tmp"))
        ):
            assert time.monotonic() < deadline, "the workers did not finish"
            time.sleep(0.2)
        waited.append(True)

    points = record_commit_points(
        lambda: run_sweep(SPEC, full, **options), full, root / "points", monkeypatch, before_first=both_parts_finished
    )
    kinds = {name.split("-", 2)[2] for name in points}
    assert {"results.parquet", "rescored.csv", "metadata.json", "summary.csv"} <= kinds
    assert any(k.startswith("ppo-") and k.endswith(".json") for k in kinds)  # a marker moved into out
    for name, copy in points.items():
        out = shutil.copytree(copy, root / "reruns" / name)
        run_sweep(SPEC, out, **options)
        assert_same_sweep(out, full, where=f"driver stopped at {name}")
