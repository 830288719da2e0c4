"""``EnvParams`` (Gymnasium's constructor arguments, traced) and ``EnvState`` (the Box2D world)."""

from __future__ import annotations

import jax
import numpy as np
from flax import struct
from gymnax.environments import environment


@struct.dataclass
class EnvParams(environment.EnvParams):
    """Gymnasium constructor arguments (all traced: vmappable, not baked into the program)."""

    gravity: float = -10.0
    enable_wind: bool = False
    wind_power: float = 15.0
    turbulence_power: float = 1.5
    max_steps_in_episode: int = 1000


@struct.dataclass
class EnvState(environment.EnvState):
    """Box2D world state. Body axis: [hull, legs[0], legs[1]]; edge axis: 10 terrain edges."""

    pos: jax.Array  # (3, 2) centres of mass (b2Sweep.c)
    angle: jax.Array  # (3,)
    vel: jax.Array  # (3, 2) centre-of-mass velocities
    omega: jax.Array  # (3,)
    joint_impulse: jax.Array  # (2, 3) revolute warm-start impulse (point x, point y, limit)
    motor_impulse: jax.Array  # (2,)
    limit_state: jax.Array  # (2,) int32, b2LimitState
    sleep_time: jax.Array  # (3,)
    contact_edge: jax.Array  # (3, 2) int32 the two edges under each body (-1: none)
    touching: jax.Array  # (3, 2) bool, b2Contact touching flag of those (body, edge) pairs
    contact_key: jax.Array  # (3, 2, 2) int32 manifold point ids (b2ContactID.key)
    normal_impulse: jax.Array  # (3, 2, 2) warm-start impulses per manifold point
    tangent_impulse: jax.Array  # (3, 2, 2)
    leg_contact: jax.Array  # (2,) bool, Gymnasium's leg.ground_contact
    game_over: jax.Array  # bool
    awake: jax.Array  # bool
    terrain_y: jax.Array  # (11,) smooth_y
    prev_shaping: jax.Array
    wind_idx: jax.Array  # int32
    torque_idx: jax.Array  # int32
    time: int


def validate_params(params: EnvParams) -> None:
    """Raise ValueError for arguments Gymnasium rejects or warns about (concrete values only)."""
    checks = (
        ("gravity", params.gravity, -12.0, 0.0, "the open interval (-12, 0)"),
        ("wind_power", params.wind_power, 0.0, 20.0, "[0, 20]"),
        ("turbulence_power", params.turbulence_power, 0.0, 2.0, "[0, 2]"),
    )
    for name, value, lo, hi, allowed in checks:
        try:
            arr = np.asarray(value, dtype=np.float64)
        except jax.errors.TracerArrayConversionError as err:
            raise ValueError(f"validate_params needs concrete values, {name} is traced") from err
        bad = ~np.isfinite(arr)
        if name == "gravity":
            bad |= (arr <= lo) | (arr >= hi)
        else:
            bad |= (arr < lo) | (arr > hi)
        if np.any(bad):
            raise ValueError(f"LunarLander {name}={value!r} is outside {allowed}")
    if int(np.min(np.asarray(params.max_steps_in_episode))) < 1:
        raise ValueError("LunarLander max_steps_in_episode must be >= 1")
