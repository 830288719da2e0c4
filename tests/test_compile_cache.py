"""JAX's persistent compilation cache as amjax leaves it (`amjax.files.write_compile_cache_whole`): an entry is
there whole or not at all, whatever instant its writer is killed at; and the cache a command keeps in its output
folder (`amjax.files.use_compile_cache`)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from jax._src import lru_cache

import amjax.envs  # noqa: F401  (applies write_compile_cache_whole)

VALUE = bytes(range(256)) * 4096  # 1 MiB


def _cache(path: Path) -> lru_cache.LRUCache:
    return lru_cache.LRUCache(str(path), max_size=-1)


def test_an_entry_is_written_whole_under_its_name(tmp_path):
    cache = _cache(tmp_path)
    cache.put("key", VALUE)
    assert cache.get("key") == VALUE
    assert [p.name for p in tmp_path.iterdir()] == ["key-cache"]  # no temporary left behind
    cache.put("key", b"other")  # an existing entry is kept, as JAX does
    assert cache.get("key") == VALUE


@pytest.mark.parametrize("moment", ["opened", "half written", "written, not renamed"])
def test_a_writer_killed_at_any_moment_leaves_no_entry(tmp_path, moment):
    """A child process dies (os._exit: no cleanup, as SIGKILL) at each step of writing an entry; the cache then has
    no entry under the key (a reader compiles afresh), never a truncated one."""
    child = textwrap.dedent(
        f"""
        import os, pathlib
        import amjax.envs
        from amjax import files
        from jax._src import lru_cache

        moment = {moment!r}
        write_bytes, commit = pathlib.Path.write_bytes, files.commit

        def dying_write(self, data):
            if moment == "opened":
                os._exit(9)
            if moment == "half written":
                with open(self, "wb") as f:
                    f.write(data[: len(data) // 2])
                os._exit(9)
            return write_bytes(self, data)

        def dying_commit(source, target):
            os._exit(9)

        pathlib.Path.write_bytes = dying_write
        if moment == "written, not renamed":
            files.commit = dying_commit
        lru_cache.LRUCache({str(tmp_path)!r}, max_size=-1).put("key", bytes(range(256)) * 4096)
        """
    )
    result = subprocess.run([sys.executable, "-c", child], capture_output=True, text=True, timeout=120)
    assert result.returncode == 9, result.stderr
    assert not (tmp_path / "key-cache").exists()
    assert _cache(tmp_path).get("key") is None
    _cache(tmp_path).put("key", VALUE)  # the next writer's entry is whole
    assert _cache(tmp_path).get("key") == VALUE


FOLDER_CACHE = textwrap.dedent(
    """
    import json, sys
    import jax, jax.numpy as jnp
    from jax import monitoring
    from amjax.files import use_compile_cache

    hits = []
    monitoring.register_event_listener(lambda event, **_: hits.append(event) if event.endswith("cache_hits") else None)
    jnp.zeros(3).sum()  # JAX has compiled (and decided whether it caches) before the call
    folder = use_compile_cache(sys.argv[1])
    jax.jit(lambda x: jnp.sin(x) @ x)(jnp.ones((8, 8))).block_until_ready()
    print(json.dumps({"folder": None if folder is None else str(folder), "hits": len(hits)}))
    """
)


def _folder_cache_run(out: Path, **env: str) -> dict:
    environment = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
    environment.update(JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0", **env)
    result = subprocess.run(
        [sys.executable, "-c", FOLDER_CACHE, str(out)], capture_output=True, text=True, timeout=120, env=environment
    )
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout.splitlines()[-1])


def test_a_command_keeps_its_programs_in_its_folder_per_machine(tmp_path):
    """`use_compile_cache(out)` (the CLI's sweep, demo, replicate and pareto call it after checking their input):
    the programs compiled after it go to out/compile_cache/<backend and CPU>, even when JAX compiled something
    before; a second process there loads them; a cache the user set is kept and the folder is left alone."""
    from amjax.cores import cpu_vector_isa

    first = _folder_cache_run(tmp_path / "out")
    folder = Path(first["folder"])
    assert folder.parent == tmp_path / "out" / "compile_cache" and folder.name.startswith("cpu-")
    assert cpu_vector_isa().lower().replace("-", "") in folder.name.replace("-", "")
    assert any(folder.glob("jit_*-cache")) and first["hits"] == 0
    assert _folder_cache_run(tmp_path / "out")["hits"] >= 1  # the program loaded, not compiled again
    own = _folder_cache_run(tmp_path / "other", JAX_COMPILATION_CACHE_DIR=str(tmp_path / "mine"))
    assert own["folder"] is None and not (tmp_path / "other").exists() and any((tmp_path / "mine").glob("*-cache"))
