"""How amjax's programs are laid out for the hardware they compile for: the ``"cpu"`` or the ``"gpu"`` strategy.

The two compute the same arithmetic (the same results to float rounding; tests/test_strategy.py checks it) and
differ only in how a batch is scheduled:

- ``"cpu"`` (a few cores): a vmapped batch runs in cache-sized groups one after another
  (`amjax.batching.in_groups`: PPO's epochs and value passes, DRQN's ``train_group``, LunarLander's 512-env step
  groups), and LunarLander's Gauss-Seidel solves sit behind always-taken conditionals that stop XLA's CPU fusion
  from recomputing them (`amjax.envs.lunar_lander.fusion.materialized`). On two cores these are 10-40% faster.
- ``"gpu"`` (an accelerator): every batch runs at once, as one wide kernel per operation, and nothing is hidden
  behind a conditional: on a GPU each group is a serial step and each conditional a host round trip to read its
  predicate, which left a sweep at 0.11-0.65x a plain PureJaxRL-style script and the LunarLander port at 156 k
  env-steps/s on an H200 (docs/gpu.md).

The strategy follows `jax.default_backend()` (``"cpu"`` on CPU, ``"gpu"`` on GPU and TPU). Override it with the
environment variable ``AMJAX_STRATEGY=cpu|gpu``, `set_default`, or for a block of code `use`. It is read when a
program is traced: amjax's trainers and sweep programs key their compiled programs on it, but a function you
``jax.jit`` yourself keeps the strategy of its first trace.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from contextvars import ContextVar

import jax

STRATEGIES = ("cpu", "gpu")
ENV_VAR = "AMJAX_STRATEGY"

_in_block: ContextVar[str | None] = ContextVar("amjax_strategy", default=None)
_default: str | None = None  # set_default's choice


def _checked(name: str, where: str) -> str:
    if name not in STRATEGIES:
        raise ValueError(f"{where}: unknown strategy {name!r}; allowed values: {', '.join(STRATEGIES)}")
    return name


def for_backend(backend: str) -> str:
    """The strategy a JAX backend gets by default: ``"cpu"`` for the CPU, ``"gpu"`` for any accelerator."""
    return "cpu" if backend == "cpu" else "gpu"


def default() -> str:
    """The strategy outside any `use` block: `set_default`'s, else ``$AMJAX_STRATEGY``, else the backend's."""
    if _default is not None:
        return _default
    if os.environ.get(ENV_VAR):
        return _checked(os.environ[ENV_VAR].strip().lower(), ENV_VAR)
    return for_backend(jax.default_backend())


def current() -> str:
    """The strategy programs traced now take (the innermost `use` block's, else `default()`)."""
    return _in_block.get() or default()


def set_default(name: str | None) -> None:
    """Make ``name`` (``"cpu"`` or ``"gpu"``) the default strategy of this process; None restores the automatic
    choice. Programs already compiled keep theirs."""
    global _default
    _default = None if name is None else _checked(name, "set_default")


@contextlib.contextmanager
def use(name: str | None) -> Iterator[str]:
    """Trace with strategy ``name`` inside the block (None: `current()`, unchanged); yields the strategy."""
    name = current() if name is None else _checked(name, "use")
    token = _in_block.set(name)
    try:
        yield name
    finally:
        _in_block.reset(token)


def is_gpu() -> bool:
    """Whether programs traced now take the ``"gpu"`` strategy."""
    return current() == "gpu"


__all__ = ["ENV_VAR", "STRATEGIES", "current", "default", "for_backend", "is_gpu", "set_default", "use"]
