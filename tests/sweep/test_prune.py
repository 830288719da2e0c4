"""`amjax prune`: a pruned folder loses only its finished batches' final checkpoints, resumes without training
anything again, on its machine or copied elsewhere, and a prune killed at any of its commit points (each marker's
rename, each checkpoint's deletion) leaves a folder that a rerun of either command completes."""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import shutil
from pathlib import Path

import pandas as pd
import pytest

from amjax.files import PARTIAL_SUFFIX, FolderBusyError, folder_lock
from amjax.sweep import SweepSpec, prune_folder, prune_sweep, run_sweep
from amjax.sweep.prune import MISSING_FILE, NO_POLICIES, NOT_FINISHED
from amjax.sweep.storage import CHECKPOINT_PRUNED
from train.cli import main

SPEC = SweepSpec(
    envs=("CartPole-v0",),
    agents=("ppo", "dqn"),  # two batches: one per agent
    costs=(0.1,),
    seeds=(0,),
    vanilla=False,
    total_timesteps=2048,
    eval_every=1024,
    eval_episodes=2,
    hyperparams={"ppo.num_envs": 4, "ppo.num_steps": 32, "rescore_episodes": 4},
)
OPTIONS = {"progress": False}
KEPT = ("results.parquet", "rescored.parquet", "summary.parquet", "policies")  # what a pruned folder still holds


def _files(folder: Path, under: str = "") -> dict[str, bytes]:
    root = folder / under
    return {
        str(p.relative_to(folder)): p.read_bytes()
        for p in sorted(root.rglob("*") if root.is_dir() else [root])
        if p.is_file() and p.name != ".lock" and not p.name.endswith(PARTIAL_SUFFIX)
    }


def _digest(folder: Path) -> str:
    digest = hashlib.sha256()
    for name, data in _files(folder).items():
        if name != "wall_time.json":
            digest.update(name.encode() + b"\0" + data)
    return digest.hexdigest()


@pytest.fixture(scope="module")
def finished(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("prune") / "full"
    run_sweep(SPEC, out, **OPTIONS)
    return out


def _assert_pruned_and_resumable(out: Path, reference: Path, where: str) -> None:
    """`out` is `reference` pruned: no checkpoint, markers that say so, everything else byte for byte; and a rerun
    of the sweep trains nothing (it would write checkpoints) and ends with the same tables."""
    assert not list((out / "checkpoints").glob("*.msgpack")), where
    for marker in (out / "finished").glob("*.json"):
        assert json.loads(marker.read_text())[CHECKPOINT_PRUNED] is True, where
    for name in KEPT:
        assert _files(out, name) == _files(reference, name), f"{where}: {name}"
    run_sweep(SPEC, out, **OPTIONS)
    assert not list((out / "checkpoints").glob("*.msgpack")), f"{where}: the rerun trained a batch again"
    for name, keys in {"results": ["config_id", "env_steps"], "rescored": ["config_id"]}.items():
        got = pd.read_parquet(out / f"{name}.parquet").sort_values(keys).reset_index(drop=True)
        want = pd.read_parquet(reference / f"{name}.parquet").sort_values(keys).reset_index(drop=True)
        pd.testing.assert_frame_equal(got, want, check_exact=True, obj=f"{where} {name}")


def test_a_pruned_folder_moves_and_resumes_without_training(finished, tmp_path):
    """Pruned, then copied elsewhere (another machine's disk): both batches' checkpoints are gone, the rest is
    untouched, and the sweep rerun there counts both batches finished. Pruning again deletes nothing more."""
    out = shutil.copytree(finished, tmp_path / "here")
    before = sum(p.stat().st_size for p in (out / "checkpoints").glob("*.msgpack"))
    result = prune_sweep(out)
    assert len(result.pruned) == 2 and result.kept == {} and result.checkpoint_bytes == before > 0
    assert result.freed_bytes == before and result.cache_bytes == 0
    moved = shutil.copytree(out, tmp_path / "elsewhere")
    _assert_pruned_and_resumable(moved, finished, "moved")
    again = prune_sweep(moved)
    assert again.pruned == () and again.freed_bytes == 0


def test_every_prune_commit_point_recovers(finished, tmp_path, monkeypatch):
    """A copy of the folder just before and after each rename (a marker) and each deletion (a checkpoint) of a
    prune: from each, a rerun of the sweep trains nothing, and prune then sweep ends as the uninterrupted prune."""
    out = shutil.copytree(finished, tmp_path / "full")
    copies: dict[str, Path] = {}
    original_replace, original_unlink = os.replace, Path.unlink

    def point(name: str) -> None:
        state = _digest(out)
        if all(_digest(c) != state for c in copies.values()):
            copies[name] = shutil.copytree(out, tmp_path / "points" / name)

    def replace(source, target, *args, **kwargs):
        point(f"{len(copies):02d}-before-{Path(target).name}")
        original_replace(source, target, *args, **kwargs)
        point(f"{len(copies):02d}-after-{Path(target).name}")

    def unlink(path, *args, **kwargs):
        point(f"{len(copies):02d}-before-unlink-{path.name}")
        original_unlink(path, *args, **kwargs)
        point(f"{len(copies):02d}-after-unlink-{path.name}")

    monkeypatch.setattr(os, "replace", replace)
    monkeypatch.setattr(Path, "unlink", unlink)
    prune_sweep(out)
    monkeypatch.undo()
    assert len(copies) == 5  # the folder as it was, then marker, checkpoint, marker, checkpoint
    for name, copy in copies.items():
        checkpoints = _files(copy, "checkpoints")
        run_sweep(SPEC, copy, **OPTIONS)  # a kill mid-prune: the sweep still finds both batches finished
        assert _files(copy, "checkpoints") == checkpoints, f"stopped at {name}: the rerun trained a batch again"
        prune_sweep(copy)
        _assert_pruned_and_resumable(copy, finished, f"stopped at {name}")


def test_unfinished_batches_keep_their_checkpoints(finished, tmp_path):
    """A batch killed before its marker (its final checkpoint is what commits it without training) and a batch
    whose marker vouches for a policy that is gone keep their checkpoints; the rerun completes both from them."""
    out = shutil.copytree(finished, tmp_path / "partial")
    markers = sorted((out / "finished").glob("*.json"))
    markers[0].unlink()  # killed before its commit
    second = json.loads(markers[1].read_text())
    (out / "policies" / f"{second['config_ids'][0]}.msgpack").unlink()
    result = prune_sweep(out)
    assert result.pruned == () and result.kept == {markers[0].stem: NOT_FINISHED, markers[1].stem: MISSING_FILE}
    run_sweep(SPEC, out, **OPTIONS)
    assert _files(out, "policies") == _files(finished, "policies")
    assert _files(out, "checkpoints") == _files(finished, "checkpoints")  # committed from them, not retrained
    assert len(prune_sweep(out).pruned) == 2


def test_dry_run_changes_nothing_and_a_replication_folder_prunes_each_env(finished, tmp_path, capsys):
    root = tmp_path / "replication"
    for env in ("CartPole-v0", "Acrobot-v1"):  # two copies stand for a replication's sweep per env
        shutil.copytree(finished, root / env)
        (root / env / ".lock").unlink()  # the sweep's, copied with the folder
    (root / "compile_cache" / "cpu-x").mkdir(parents=True)
    (root / "compile_cache" / "cpu-x" / "entry").write_bytes(b"x" * 1000)
    state = {p: _digest(p) for p in (root / "CartPole-v0", root / "Acrobot-v1")}
    assert main(["prune", str(root), "--compile-cache", "--dry-run"]) == 0
    printed = capsys.readouterr().out
    assert "would delete 2 finished batches' checkpoints" in printed and "the compile cache (0.0 MB)" in printed
    assert {p: _digest(p) for p in state} == state and (root / "compile_cache").exists()
    assert not list(root.rglob(".lock"))  # a dry run writes nothing, not even a lock (a read-only copy works)
    done = prune_folder(root, compile_cache=True)
    assert [len(r.pruned) for r in done] == [2, 2, 0] and not (root / "compile_cache").exists()
    assert done[-1].folder == root and done[-1].cache_bytes == 1000 and done[-1].checkpoint_bytes == 0
    for env in ("CartPole-v0", "Acrobot-v1"):
        _assert_pruned_and_resumable(root / env, finished, env)


def test_bad_folders_and_busy_folders_get_a_clear_error(finished, tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    for folder, message in (
        (tmp_path / "missing", "is not a folder"),
        (tmp_path / "empty", "holds no sweep"),
    ):
        with pytest.raises(SystemExit) as exit_info:
            main(["prune", str(folder)])
        assert exit_info.value.code == 2 and message in capsys.readouterr().err
    out = shutil.copytree(finished, tmp_path / "busy")
    with open(out / ".lock", "a+") as handle:  # another process's running sweep holds the folder
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        with pytest.raises(SystemExit) as exit_info:
            main(["prune", str(out)])
    assert exit_info.value.code == 2 and "being written by another running process" in capsys.readouterr().err
    assert _files(out, "checkpoints") == _files(finished, "checkpoints")


def test_a_batch_finished_without_policies_keeps_its_checkpoint(tmp_path, capsys):
    """A sweep run without saving policies: prune keeps its checkpoints and says why, so that a rerun that saves
    policies builds them from those without training (pruned, it would have to train every batch again)."""
    out = tmp_path / "no-policies"
    run_sweep(SPEC, out, save_policies=False, **OPTIONS)
    checkpoints = _files(out, "checkpoints")
    assert main(["prune", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "deleted nothing; kept 2 checkpoints" in printed and "finished batches' checkpoints" not in printed
    assert printed.count("finished without saving policies") == 2
    result = prune_sweep(out, dry_run=True)
    assert result.pruned == () and set(result.kept.values()) == {NO_POLICIES} and len(result.kept) == 2
    assert _files(out, "checkpoints") == checkpoints
    run_sweep(SPEC, out, **OPTIONS)
    assert len(list((out / "policies").glob("*.msgpack"))) == 2
    assert _files(out, "checkpoints") == checkpoints  # the policies came from the checkpoints, not from training
    assert len(prune_sweep(out).pruned) == 2


def test_leftover_temporary_files_and_a_linked_compile_cache_go(finished, tmp_path):
    """An interrupted write's temporary file is deleted (a cluster run's parts are left alone), and a compile cache
    that is a link to another disk loses the link only: its target stays."""
    out = shutil.copytree(finished, tmp_path / "leftovers")
    leftovers = [out / f".results.parquet.k9x2{PARTIAL_SUFFIX}", out / "policies" / f".x.msgpack.a1{PARTIAL_SUFFIX}"]
    theirs = out / "parts" / "batch" / f".results.parquet.b2{PARTIAL_SUFFIX}"
    for leftover in [*leftovers, theirs]:
        leftover.parent.mkdir(parents=True, exist_ok=True)
        leftover.write_bytes(b"half")
    target = tmp_path / "elsewhere" / "cache"
    target.mkdir(parents=True)
    (target / "entry").write_bytes(b"x" * 100)
    (out / "compile_cache").symlink_to(target)
    assert prune_sweep(out, dry_run=True).partial_files == 2 and all(p.exists() for p in leftovers)
    result = prune_sweep(out, compile_cache=True)
    assert result.partial_files == 2 and not any(p.exists() for p in leftovers) and theirs.exists()
    assert not (out / "compile_cache").is_symlink() and (target / "entry").exists() and result.cache_bytes == 0


def test_a_busy_env_in_a_replication_names_what_was_already_pruned(finished, tmp_path):
    root = tmp_path / "replication"
    for env in ("Acrobot-v1", "CartPole-v0"):
        shutil.copytree(finished, root / env)
    # CartPole-v0's folder held as a sweep of that env running in another process would hold it
    with folder_lock(root / "CartPole-v0"), pytest.raises(FolderBusyError, match=r"already pruned: Acrobot-v1\)"):
        prune_folder(root)
    assert not list((root / "Acrobot-v1" / "checkpoints").glob("*.msgpack"))
    assert _files(root / "CartPole-v0", "checkpoints") == _files(finished, "checkpoints")
