"""JAX's persistent compilation cache as amjax leaves it (`amjax.files.write_compile_cache_whole`): an entry is
there whole or not at all, whatever instant its writer is killed at."""

from __future__ import annotations

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
