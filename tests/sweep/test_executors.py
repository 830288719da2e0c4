"""The compile-ahead queue (`amjax.sweep.executors.CompileQueue`): how far ahead it compiles, in which thread, and
what stops it (a bounded number of waiting programs, the kernel's memory-map limit); and the release of finished
batches' programs near that limit (`amjax.sweep.batches.release_programs`)."""

from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor
from types import SimpleNamespace

import pytest

from amjax import cores
from amjax.sweep import SweepSpec, batches, executors, run_sweep

DEVICES = ("cpu:0",)


@pytest.fixture
def compiles(monkeypatch):
    """Batches' compiles recorded (name, thread) instead of run; each returns "programs of NAME"."""
    calls: list[tuple[str, str]] = []

    def fake_compile(batch, target_chunks, devices, strategy_name):
        calls.append((batch.name, threading.current_thread().name))
        return f"programs of {batch.name}"

    monkeypatch.setattr(executors, "compile_batch", fake_compile)
    monkeypatch.setattr(executors, "maps_past_half", lambda: False)
    return calls


def _settled(calls: list, count: int) -> list[str]:
    """The compiled names once `count` compiles happened (within 30 s: the queue's worker rechecks the map limit
    every 5 s, and a loaded machine starves threads) and no more follow for a moment."""
    deadline = time.monotonic() + 30
    while len(calls) < count and time.monotonic() < deadline:
        time.sleep(0.01)
    time.sleep(0.3)  # a queue that compiles too far ahead does it now
    return [name for name, _ in calls]


def _take(queue: executors.CompileQueue, name: str) -> str:
    with ThreadPoolExecutor(1) as pool:  # a queue that never delivers fails the test instead of hanging it
        return pool.submit(queue.take, SimpleNamespace(name=name), 10, DEVICES).result(timeout=10)


@pytest.mark.parametrize("ahead", [1, 2])
def test_the_queue_compiles_at_most_ahead_batches_beyond_those_taken(compiles, ahead):
    queue = executors.CompileQueue(ahead=ahead)
    names = [f"b{i}" for i in range(5)]
    for name in names:
        queue.submit(SimpleNamespace(name=name), 10, DEVICES)
    assert _settled(compiles, ahead) == names[:ahead]
    assert _take(queue, "b0") == "programs of b0"
    assert _settled(compiles, ahead + 1) == names[: ahead + 1]  # one taken: one more compiled
    # A batch taken out of turn is compiled next, whatever waits ahead of it.
    assert _take(queue, "b4") == "programs of b4"
    assert _settled(compiles, ahead + 2) == [*names[: ahead + 1], "b4"]
    assert {thread for _, thread in compiles} == {"amjax-compile-ahead"}
    queue.cancel()


def test_nothing_is_compiled_ahead_near_the_memory_map_limit(compiles, monkeypatch):
    """Past half of the kernel's limit on memory mappings (every loaded program holds thousands) the queue compiles
    only what a take waits for; under it, it compiles ahead again."""
    monkeypatch.setattr(executors, "maps_past_half", lambda: True)
    queue = executors.CompileQueue(ahead=2)
    for name in ("b0", "b1", "b2"):
        queue.submit(SimpleNamespace(name=name), 10, DEVICES)
    assert _settled(compiles, 0) == []
    assert _take(queue, "b0") == "programs of b0"
    assert _settled(compiles, 1) == ["b0"]
    monkeypatch.setattr(executors, "maps_past_half", lambda: False)  # programs freed
    assert _settled(compiles, 3) == ["b0", "b1", "b2"]  # seen again within the worker's wait
    queue.cancel()


def test_a_failed_compile_is_raised_by_its_take(compiles, monkeypatch):
    def broken(batch, *args):
        raise RuntimeError(f"cannot compile {batch.name}")

    monkeypatch.setattr(executors, "compile_batch", broken)
    queue = executors.CompileQueue()
    with pytest.raises(RuntimeError, match="cannot compile b0"):
        _take(queue, "b0")
    with pytest.raises(ValueError, match="ahead: got -1"):
        executors.CompileQueue(ahead=-1)


def test_memory_maps_reads_this_process_and_the_kernels_limit():
    maps = cores.memory_maps()
    if maps is None:
        pytest.skip("this OS does not say (not Linux)")
    used, limit = maps
    assert 0 < used < limit


@pytest.mark.slow
def test_finished_batches_programs_are_unloaded_near_the_memory_map_limit(tmp_path, monkeypatch):
    """Each batch's programs stay loaded while the runner's jitted functions live (their mappings counted by the
    kernel); near the limit the runner drops them after each batch, and the mappings they held are returned."""
    spec = SweepSpec(
        envs=("CartPole-v0",),
        agents=("ppo",),
        costs=(0.1,),
        seeds=(0,),
        total_timesteps=2048,
        eval_every=1024,
        eval_episodes=2,
        hyperparams={"num_envs": 4, "num_steps": 32, "hidden": [(5,), (6,), (7,)]},  # 3 batches, 3 programs each
    )
    released = []
    monkeypatch.setattr(batches, "maps_past_half", lambda: True)
    release = batches.release_programs
    monkeypatch.setattr(executors, "release_programs", lambda: released.append(cores.memory_maps()[0]) or release())
    before = cores.memory_maps()[0]
    run_sweep(spec, tmp_path / "sweep", progress=False, target_chunks=1)
    assert len(released) == 3  # after each batch
    assert batches._compiled_programs.cache_info().currsize == 0
    held_by_one_batch = released[0] - before  # its programs, loaded (or read from the suite's compile cache)
    assert held_by_one_batch > 500
    # Unloaded: the mappings after the last release are about those before the sweep, not three batches' worth.
    assert cores.memory_maps()[0] - before < held_by_one_batch
