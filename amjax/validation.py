"""Argument checks shared by every layer: each error names the argument and the allowed values."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import jax
import numpy as np


def is_traced(value: Any) -> bool:
    """Whether any leaf of `value` is a tracer (under jit / vmap: its caller checked the concrete values)."""
    return any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves(value))


def check_choice(name: str, value: Any, allowed: Iterable[Any]) -> None:
    """Raise ValueError unless `value` is one of `allowed`."""
    allowed = list(allowed)
    if value not in allowed:
        raise ValueError(f"{name}: got {value!r}; allowed values: {', '.join(map(repr, allowed))}")


def check_bool(name: str, value: Any) -> bool:
    """Raise ValueError unless `value` is exactly True or False (1, 0 and 1.0 are refused)."""
    if not isinstance(value, bool | np.bool_):
        raise ValueError(f"{name}: got {value!r}; allowed values: True, False")
    return bool(value)


def check_real(
    name: str,
    value: Any,
    *,
    low: float = -np.inf,
    high: float = np.inf,
    low_inclusive: bool = True,
    high_inclusive: bool = True,
) -> np.ndarray:
    """Check that `value` (a number or array of numbers) is finite and in [low, high] (either end open if told).

    Returns it as a float64 NumPy array. Runs on concrete values, before anything is compiled.
    """
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"{name}: expected a real number, got {value!r}") from None
    allowed = f"finite numbers in {'[' if low_inclusive else '('}{low}, {high}{']' if high_inclusive else ')'}"
    if array.size == 0 or not np.all(np.isfinite(array)):
        raise ValueError(f"{name}: got {value!r}; allowed values: {allowed}")
    below = array < low if low_inclusive else array <= low
    above = array > high if high_inclusive else array >= high
    if np.any(below) or np.any(above):
        raise ValueError(f"{name}: got {value!r}; allowed values: {allowed}")
    return array


def check_positive_int(name: str, value: Any, minimum: int = 1, maximum: int | None = None) -> int:
    """Check that `value` is an integer >= `minimum` (and <= `maximum` if given; bools are refused)."""
    if (
        isinstance(value, bool)
        or not isinstance(value, int | np.integer)
        or value < minimum
        or (maximum is not None and value > maximum)
    ):
        allowed = f"integers >= {minimum}" if maximum is None else f"integers in [{minimum}, {maximum:,}]"
        raise ValueError(f"{name}: got {value!r}; allowed values: {allowed}")
    return int(value)


def check_whole_number(name: str, value: Any, *, low: float = 0.0) -> np.ndarray:
    """Check that `value` (a number or array of numbers, for vmap) holds finite whole numbers >= `low`, as ints or
    floats (a count that a traced float field carries, e.g. 3.0). Returns it as a float64 NumPy array."""
    array = check_real(name, value, low=low)
    if np.any(array != np.floor(array)):
        raise ValueError(f"{name}: got {value!r}; allowed values: whole numbers >= {low:g} (a count)")
    return array
