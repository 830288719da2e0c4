"""Instruments: measuring parts of the observation, each part with its own cost and noise.

The paper's agent measures everything or nothing. With instruments, the observation's features are split into
`k` disjoint groups (an instrument each: a thermocouple, an assay, a camera), and each step the agent chooses a
control action and which instruments to read. Only the features of the instruments read are refreshed; each
instrument has its own fresh/stale flag, price and reading noise.

Action encoding (`ActiveMeasure(instruments=...)`):
- Discrete(n) control: Discrete(n * 2^k), `action = control + n * mask`, where bit j of `mask` reads instrument j
  (with k = 1 this is the paper's `control + n * measure`);
- Box(d) control: Box(k + d), `[read_1, ..., read_k, control...]`, instrument j read iff `read_j >= 0.5`.

An instrument is a tuple of observation indices (entries of a vector observation; channels of an image, which an
instrument reads at every pixel, e.g. one MinAtar object type per channel); `instruments` is a tuple of
instruments that together hold every feature exactly once. `DEFAULT_INSTRUMENTS` names a split for the
environments where one is natural; `instruments="default"` picks it.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from amjax.validation import check_real

# Per env id: (name, observation indices) of each default instrument, cheapest first in spirit.
DEFAULT_INSTRUMENTS: dict[str, tuple[tuple[str, tuple[int, ...]], ...]] = {
    # gymnax / Gymnasium CartPole: [x, x_dot, theta, theta_dot]
    "CartPole-v0": (("cart", (0, 1)), ("pole", (2, 3))),
    "CartPole-v1": (("cart", (0, 1)), ("pole", (2, 3))),
    # Acrobot: [cos t1, sin t1, cos t2, sin t2, dt1, dt2]: one sensor per link
    "Acrobot-v1": (("link 1", (0, 1, 4)), ("link 2", (2, 3, 5))),
    # The stirred-tank reactor (amjax/envs/reactor.py): [concentration, temperature]
    "CSTR-v0": (("thermocouple", (1,)), ("assay", (0,))),
}
MAX_INSTRUMENTS = 8  # the joint Discrete space grows as 2^k


def default_instruments(env_id: str) -> tuple[tuple[int, ...], ...]:
    """The env's default instruments (observation indices); ValueError naming the envs that have some."""
    if env_id not in DEFAULT_INSTRUMENTS:
        raise ValueError(
            f"instruments: {env_id} has no default instruments; allowed: 'default' for "
            f"{', '.join(DEFAULT_INSTRUMENTS)}, or a tuple of index tuples such as ((0, 1), (2, 3))"
        )
    return tuple(features for _, features in DEFAULT_INSTRUMENTS[env_id])


def instrument_names(env_id: str, instruments: tuple[tuple[int, ...], ...]) -> tuple[str, ...]:
    """Display names: the default instruments' names where they match, else the indices ("obs 0,1")."""
    named = {features: name for name, features in DEFAULT_INSTRUMENTS.get(env_id, ())}
    return tuple(named.get(tuple(f), "obs " + ",".join(map(str, f))) for f in instruments)


def resolve_instruments(env_id: str, instruments: Any) -> tuple[tuple[int, ...], ...]:
    """`instruments` with "default" replaced by the env's default split (unchecked otherwise)."""
    return default_instruments(env_id) if instruments == "default" else instruments


def check_instruments(instruments: Any, obs_size: int) -> tuple[tuple[int, ...], ...]:
    """`instruments` as a tuple of int tuples that together hold each of `obs_size` features exactly once, or ()
    (the paper's single switch); ValueError naming the problem otherwise."""
    example = "e.g. ((0, 1), (2, 3)) for CartPole's cart and pole, 'default', or () for the paper's single switch"
    if isinstance(instruments, str) or not isinstance(instruments, tuple | list):
        raise ValueError(
            f"instruments: got {instruments!r}; allowed values: a tuple of tuples of observation indices, {example}"
        )
    if not instruments:
        return ()
    if len(instruments) > MAX_INSTRUMENTS:
        raise ValueError(
            f"instruments: {len(instruments)} instruments; at most {MAX_INSTRUMENTS} (the joint "
            "action space grows as 2^k)"
        )
    result = []
    for group in instruments:
        if (
            not isinstance(group, tuple | list)
            or not group
            or not all(isinstance(i, int | np.integer) and not isinstance(i, bool) for i in group)
        ):
            raise ValueError(
                f"instruments: each instrument is a non-empty tuple of observation indices, got {group!r}; {example}"
            )
        result.append(tuple(int(i) for i in group))
    flat = sorted(i for group in result for i in group)
    if flat != list(range(obs_size)):
        raise ValueError(
            f"instruments: {tuple(result)} must hold each observation index 0..{obs_size - 1} exactly "
            f"once (the observation has {obs_size} features: a vector's entries, an image's channels)"
        )
    return tuple(result)


def check_instrument_values(name: str, value: Any, num_instruments: int, batched: bool = False) -> np.ndarray:
    """`value` as one number >= 0 per instrument (instrument_costs, instrument_noise); with `batched`, leading axes
    to vmap over are allowed. ValueError naming `name` otherwise."""
    if not num_instruments:
        raise ValueError(f"{name}: only with instruments (there are none; set instruments first)")
    array = check_real(name, value, low=0.0)
    if (array.shape[-1:] if batched else array.shape) != (num_instruments,):
        vmap = " (a last axis of that length; leading axes to vmap over)" if batched else ""
        raise ValueError(
            f"{name}: got shape {array.shape}; allowed: one number per instrument, {num_instruments} of them{vmap}"
        )
    return array


def feature_owner(instruments: tuple[tuple[int, ...], ...]) -> np.ndarray:
    """[features]: the index of the instrument that reads each feature."""
    owner = np.zeros(sum(len(g) for g in instruments), np.int32)
    for j, group in enumerate(instruments):
        owner[list(group)] = j
    return owner


def decode_mask(mask: jax.Array, num_instruments: int) -> jax.Array:
    """[..., k] booleans: bit j of an integer `mask` reads instrument j."""
    bits = jnp.arange(num_instruments, dtype=jnp.int32)
    return (jnp.asarray(mask, jnp.int32)[..., None] >> bits) & 1 == 1


def encode_mask(readings: jax.Array) -> jax.Array:
    """The integer mask of [..., k] booleans (inverse of `decode_mask`)."""
    readings = jnp.asarray(readings, jnp.int32)
    return (readings << jnp.arange(readings.shape[-1], dtype=jnp.int32)).sum(-1)


def served_readings(requested: jax.Array, used: jax.Array, budget: jax.Array) -> jax.Array:
    """The requested readings a budget allows: instruments are served in their order while the readings made
    before each (this episode's `used` plus earlier instruments this step) are below `budget` (whole readings: a
    fraction counts as its floor)."""
    before = used + jnp.cumsum(requested.astype(jnp.int32)) - requested.astype(jnp.int32)
    return requested & (before < jnp.floor(budget))
